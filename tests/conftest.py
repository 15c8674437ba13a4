"""Every fixture of the test suite. Helpers that build test data without being
fixtures (a toy stage graph, views of a sphere) are in tests/support."""

import shutil
from pathlib import Path

import pytest

SAMPLE_CAPTURES = Path(__file__).parents[1] / "sample_captures"


@pytest.fixture(scope="session")
def mi():
    """Mitsuba with the variant the pipeline would pick."""
    from pipeline.render.mitsuba_variant import activate

    activate("auto")
    import mitsuba

    return mitsuba


@pytest.fixture
def presets_dir(tmp_path: Path) -> Path:
    """A presets folder for test-only stage graphs (the real presets name real stages)."""
    folder = tmp_path / "presets"
    folder.mkdir()
    (folder / "standard.toml").write_text("[double]\nfactor = 2\n")
    (folder / "draft.toml").write_text("[double]\nfactor = 3\n")
    return folder


@pytest.fixture
def toy_cli(monkeypatch, presets_dir):
    """The real CLI over the test-only stage graph (tests/support/toy_stages.py) and presets."""
    from pipeline import cli
    from pipeline.cli import registry
    from pipeline.core import config
    from tests.support.toy_stages import RUNS, make_stages

    monkeypatch.setattr(registry, "registered_stages", make_stages)
    monkeypatch.setattr(config, "PRESETS_DIR", presets_dir)
    RUNS.clear()
    return cli.main


@pytest.fixture(scope="session")
def tiny_capture(tmp_path_factory) -> Path:
    """A synthetic capture small enough for tests: 6 views of 96x72 px, 4 spp."""
    from pipeline.synthetic.synth import SynthOptions, synthesize

    out = tmp_path_factory.mktemp("synth") / "bird"
    options = SynthOptions(views=6, width=96, height=72, spp=4, calibration_shots=3, seed=3)
    return synthesize(out, options)


@pytest.fixture(scope="session")
def bird_capture(tmp_path_factory) -> Path:
    """A copy of sample_captures/bird (30 views, 560x420), shared by the tests of SfM, the
    board's frame and what follows from them: the runner's cache lets each module run
    only the stages it adds."""
    return Path(
        shutil.copytree(
            SAMPLE_CAPTURES / "bird",
            tmp_path_factory.mktemp("bird") / "bird",
            ignore=shutil.ignore_patterns(".pipeline", "output"),
        )
    )


def _synth_capture(tmp_path_factory, name: str, **options) -> Path:
    from pipeline.synthetic.synth import SynthOptions, synthesize

    return synthesize(tmp_path_factory.mktemp("synth") / name, SynthOptions(**options))


@pytest.fixture(scope="session")
def synth_capture(tmp_path_factory):
    """``synth_capture(name, **SynthOptions)``: a new synthetic capture."""
    return lambda name, **options: _synth_capture(tmp_path_factory, name, **options)


def _run_stages(capture: Path, until: str, *overrides: str, force: tuple[str, ...] = ()) -> dict[str, dict[str, Path]]:
    from pipeline.core.config import load_config
    from pipeline.core.runner import Runner, Selection
    from pipeline.core.sections import schema
    from stages import STAGES

    config = load_config(schema(STAGES), capture, "standard", list(overrides))
    plan = Runner(capture, STAGES, config).run(Selection(until=until, force=force))
    return {item.stage.name: item.entry.outputs for item in plan if item.entry is not None}


@pytest.fixture(scope="session")
def run_stages():
    """``run_stages(capture, until, *overrides, force=())``: the real stage DAG on
    ``capture`` up to ``until`` (rerunning ``force``); the outputs of each stage."""
    return _run_stages


@pytest.fixture(scope="session")
def small_bird(tmp_path_factory) -> Path:
    """A synthetic bird of 8 close views at 128x96 whose cameras come from its ground
    truth as another tool's (``[cameras] source``): the fit, scene and export stages'
    tests need a specimen, a light and cameras, not SfM, which needs more and larger
    photos (the bundled bird, ``bird_until_uv``). Shared by those tests on one worker."""
    from tests.support.byo_capture import byo_capture

    options = dict(views=8, width=128, height=96, spp=16, distance=0.25, calibration_shots=0, seed=1)
    photos = _synth_capture(tmp_path_factory, "small-bird-photos", **options)
    capture = byo_capture(photos, tmp_path_factory.mktemp("small-bird") / "bird")
    with (capture / "capture.toml").open("a") as settings:
        # A coarse hull and few faces: unwrapping and rendering scale with the faces.
        settings.write('\n[cameras]\nsource = "external"\n\n[mesh]\nresolution = 64\n')
        settings.write("\n[cleanup]\ntarget_faces = 2000\n\n[uv]\ntexture_size = 256\n")
    return capture


@pytest.fixture(scope="session")
def bird_until_uv(bird_capture) -> tuple[Path, dict]:
    """The sample bird through the geometry stages (sfm, mesh, cleanup, uv), and their outputs."""
    return bird_capture, _run_stages(bird_capture, "uv")


@pytest.fixture(scope="session")
def calibration_capture(tmp_path_factory) -> Path:
    """Ten board shots at 320x240 through a strongly distorting lens. ArUco markers need
    about 4 px per bit to decode, which rules out 96-pixel captures for board calibration."""
    return _synth_capture(
        tmp_path_factory,
        "calib",
        views=2,
        width=320,
        height=240,
        spp=4,
        calibration_shots=10,
        distortion=(-0.3, 0.1, 0.001, -0.001, 0.0),
        seed=5,
    )


@pytest.fixture(scope="session")
def mask_capture(tmp_path_factory) -> Path:
    """Six close views at 192x144 with background plates; the bird spans ~100 px. 32 spp:
    photo and plate get independent Monte Carlo noise, which at 8 spp is far above a real
    sensor's and makes plate differencing fail in one view."""
    return _synth_capture(
        tmp_path_factory,
        "masks",
        views=6,
        width=192,
        height=144,
        spp=32,
        distance=0.2,
        calibration_shots=0,
        background_plates=True,
        seed=4,
    )


@pytest.fixture(scope="session")
def orbit_capture(tmp_path_factory) -> Path:
    """Twelve views on one ring at 192x144: neighbours 30 degrees apart share SIFT features."""
    return _synth_capture(
        tmp_path_factory, "orbit", views=12, rings=(30.0,), width=192, height=144, spp=4, calibration_shots=0, seed=6
    )


GROUPED = ("bird_capture", "small_bird", "mask_capture", "calibration_capture", "orbit_capture", "plain_turntable")
"""Fixtures whose tests share one worker: the captures whose stages the tests share
through the runner's cache, and the synthetic captures that take seconds to render
(each worker would render its own)."""


def pytest_itemcollected(item):
    """Under pytest-xdist (``-n 2 --dist loadgroup``, as bin/test runs), the tests of each
    fixture in GROUPED run on one worker; the rest spread over the workers. Marked as
    each test is collected: xdist tags the grouped tests in its own
    pytest_collection_modifyitems, called before this file's."""
    for fixture in GROUPED:
        if fixture in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.xdist_group(fixture))
            return
