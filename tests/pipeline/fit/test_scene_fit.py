"""`pipeline fit` on scenes written the ways users write them: a BSDF declared once
and used through <ref>, objects without ids, an included file, <default> values, IORs
given by name, a render integrator (path) that is swapped for its differentiable one."""

import errno
import json
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from pipeline.cli import main as cli_main
from pipeline.fit import engine
from pipeline.fit.scene_fit import LOCK_FILE, selects
from pipeline.imaging.photo_io import read_photo, write_image

pytestmark = pytest.mark.slow

SENSORS = """<scene version="3.0.0">
{sensors}
</scene>
"""
SENSOR = """  <sensor type="perspective">
    <float name="fov" value="22"/>
    <transform name="to_world"><lookat origin="{x}, {y}, 0.3" target="0, 0, 0" up="0, 0, 1"/></transform>
    <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
    <film type="hdrfilm"><integer name="width" value="48"/><integer name="height" value="36"/></film>
  </sensor>"""
SCENE = """<scene version="3.0.0">
  <default name="spp" value="8"/>
  <default name="rough" value="{rough}"/>
  <!-- lit by hand in Blender -->
  <integrator type="path"><integer name="max_depth" value="4"/></integrator>
  <include filename="parts/sensors.xml"/>
  <bsdf type="principled" id="mat">
    <rgb name="base_color" value="{colour}"/>
    <float name="roughness" value="$rough"/>
    <float name="metallic" value="0.0"/>
  </bsdf>
  <shape type="sphere"><float name="radius" value="0.1"/><ref id="mat"/></shape>
  <shape type="sphere">
    <point name="center" x="0" y="0" z="-0.35"/><float name="radius" value="0.2"/>
    <bsdf type="diffuse"><rgb name="reflectance" value="{floor}"/></bsdf>
  </shape>
  <emitter type="constant"><rgb name="radiance" value="0.4"/></emitter>
  <shape type="rectangle">
    <transform name="to_world">
      <scale value="0.15"/><lookat origin="0.4, 0.4, 0.6" target="0, 0, 0" up="0, 0, 1"/>
    </transform>
    <emitter type="area"><rgb name="radiance" value="8"/></emitter>
  </shape>
</scene>
"""
TRUTH = {"rough": 0.3, "colour": "0.7, 0.4, 0.2", "floor": "0.6, 0.6, 0.6"}


def _write_scene(folder: Path, rough: float, colour: str, floor: str) -> Path:
    (folder / "parts").mkdir(parents=True, exist_ok=True)
    eyes = ((0.6, 0.0), (0.0, 0.6), (-0.5, -0.3))
    sensors = "\n".join(SENSOR.format(x=x, y=y) for x, y in eyes)
    (folder / "parts" / "sensors.xml").write_text(SENSORS.format(sensors=sensors))
    scene = folder / "scene.xml"
    scene.write_text(SCENE.format(rough=rough, colour=colour, floor=floor))
    return scene


@pytest.fixture(scope="module")
def references(mi, tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("user_scene")
    truth = mi.load_file(str(_write_scene(folder / "truth", **TRUTH)), spp=256)
    images = folder / "references"
    images.mkdir()
    for index, sensor in enumerate(truth.sensors()):
        write_image(images / f"ref_{index}.exr", np.asarray(mi.render(truth, sensor=sensor, seed=7), np.float32))
    return images


def _fit(scene: Path, references: Path, out: Path, *params: str) -> int:
    return cli_main(
        [
            "fit",
            str(scene),
            "--references",
            str(references),
            "--params",
            *params,
            "--iterations",
            "20",
            "--batch",
            "3",
            "--spp",
            "4",
            "--still-threshold",
            "0",
            "--out",
            str(out),
        ]
    )


def test_refs_defaults_includes_and_unnamed_objects_fit_and_write_back(mi, references, tmp_path):
    scene = _write_scene(tmp_path / "start", rough=0.7, colour="0.5, 0.5, 0.5", floor="0.3, 0.3, 0.3")
    out = tmp_path / "out"
    assert _fit(scene, references, out, "roughness", "base_color", "reflectance", "--bound", "reflectance=0:1") == 0
    params = json.loads((out / "params.json").read_text())["params"]
    # The BSDF used through <ref> is fitted under its own id, the unnamed floor's BSDF under a stable one.
    assert set(params) == {"mat.roughness.value", "mat.base_color.value", "shape_2.bsdf.reflectance.value"}
    assert abs(params["mat.roughness.value"][0] - 0.3) < 0.7 - 0.3
    assert abs(params["shape_2.bsdf.reflectance.value"][0] - 0.6) < 0.6 - 0.3
    # The written scene loads as it is (includes inlined, files relative to it) with the fitted values.
    written = mi.traverse(mi.load_file(str(out / "scene.xml")))
    for key, value in params.items():
        assert np.ravel(written[key]) == pytest.approx(value, rel=1e-5), key
    assert written["mat.metallic.value"][0] == 0.0
    assert (out / "log.jsonl").read_text().count("\n") == 20
    assert "<!-- lit by hand in Blender -->" in (out / "scene.xml").read_text()  # the user's comments stay
    record = json.loads((out / "params.json").read_text())
    assert record["start"]["mat.roughness.value"] == pytest.approx([0.7]) and record["seconds"] > 0
    # no medium: neither the image memory nor halved steps (pipeline.fit.settings.FitSettings.resolved)
    assert (record["settings"]["image_memory"], record["settings"]["step_halvings"]) == (0, 0)
    assert sorted(Path(p).name for p in record["references"].values()) == ["ref_0.exr", "ref_1.exr", "ref_2.exr"]


def test_a_named_ior_is_fitted_and_written_as_a_number(mi, references, tmp_path):
    scene = _write_scene(tmp_path / "start", rough=0.3, colour="0.7, 0.4, 0.2", floor="0.6, 0.6, 0.6")
    text = scene.read_text().replace(
        '<bsdf type="diffuse"><rgb name="reflectance" value="0.6, 0.6, 0.6"/></bsdf>',
        '<bsdf type="roughdielectric" id="glass"><float name="alpha" value="0.2"/>'
        '<string name="int_ior" value="bk7"/><string name="ext_ior" value="water"/></bsdf>',
    )
    scene.write_text(text)
    out = tmp_path / "out"
    assert _fit(scene, references, out, "eta") == 0
    params = json.loads((out / "params.json").read_text())["params"]
    # The nested BSDF is named by its role under the unnamed shape; the principled BSDF has no eta here.
    assert list(params) == ["shape_2.bsdf.eta"]
    written_xml = (out / "scene.xml").read_text()
    assert "bk7" not in written_xml and "water" not in written_xml
    written = mi.traverse(mi.load_file(str(out / "scene.xml")))
    assert written["shape_2.bsdf.eta"][0] == pytest.approx(params["shape_2.bsdf.eta"][0], rel=1e-5)


def test_a_scene_that_cannot_be_written_keeps_the_fit(mi, references, tmp_path, capsys):
    scene = _write_scene(tmp_path / "start", rough=0.7, colour="0.7, 0.4, 0.2", floor="0.6, 0.6, 0.6")
    out = tmp_path / "out"
    (out / "scene.xml").mkdir(parents=True)  # the scene's file name is taken by a folder
    assert _fit(scene, references, out, "roughness") == 1
    assert json.loads((out / "params.json").read_text())["params"]["mat.roughness.value"]
    assert (out / "log.jsonl").is_file()
    assert "params.json" in capsys.readouterr().err


@pytest.mark.parametrize(
    "pattern, key, selected",
    [
        ("eta", "mat.eta", True),
        ("eta", "mat.metallic.value", False),
        ("base_color", "mat.base_color.value", True),
        ("bsdf.rough.*", "specimen.bsdf.roughness.value", True),
        ("^mat\\.", "mat.eta", True),
        ("^mat\\.", "format.eta", False),
    ],
)
def test_a_word_names_a_property_and_anything_else_is_a_regular_expression(pattern, key, selected):
    assert selects(pattern, key) is selected


def test_a_pattern_that_is_no_regular_expression_is_a_usage_error(mi, references, tmp_path, capsys):
    scene = _write_scene(tmp_path / "start", rough=0.7, colour="0.7, 0.4, 0.2", floor="0.6, 0.6, 0.6")
    assert _fit(scene, references, tmp_path / "out", "(") == 2
    assert "--params '('" in capsys.readouterr().err


def test_films_are_reduced_with_their_crop_windows_and_defaults(mi):
    import xml.etree.ElementTree as ET

    from pipeline.render.user_scene import reduce_films

    tree = ET.ElementTree(
        ET.fromstring(
            '<scene version="3.0.0"><default name="w" value="400"/>'
            '<sensor type="perspective"><film type="hdrfilm"><integer name="width" value="$w"/>'
            '<integer name="height" value="300"/><integer name="crop_offset_x" value="100"/>'
            '<integer name="crop_width" value="200"/></film></sensor>'
            '<sensor type="perspective"/>'
            '<sensor type="perspective"><film type="hdrfilm"><integer name="width" value="32"/>'
            '<integer name="height" value="24"/></film></sensor></scene>'
        )
    )
    assert reduce_films(tree, 100) == [(200, 300), (768, 576), (32, 24)]
    sensors = mi.load_string(ET.tostring(tree.getroot(), encoding="unicode")).sensors()
    assert [tuple(s.film().size()) for s in sensors] == [(100, 75), (100, 75), (32, 24)]
    assert [tuple(s.film().crop_size()) for s in sensors] == [(50, 75), (100, 75), (32, 24)]
    assert tuple(sensors[0].film().crop_offset()) == (25, 0)


def test_a_reduced_film_is_blurred_as_its_reference_averaged_down_to_it(mi):
    """A pixel's square (1/12 px^2) plus the full film's filter scaled: Mitsuba's default
    Gaussian (0.5 px), a box, a tent; another kind and a film kept at its size keep theirs."""
    import xml.etree.ElementTree as ET

    from pipeline.render.user_scene import reduce_films

    def film(rfilter: str, width: int = 400, height: int = 300) -> str:
        return (
            f'<sensor type="perspective"><film type="hdrfilm"><integer name="width" value="{width}"/>'
            f'<integer name="height" value="{height}"/>{rfilter}</film></sensor>'
        )

    tree = ET.ElementTree(
        ET.fromstring(
            '<scene version="3.0.0">'
            + film("")
            + film('<rfilter type="box"/>')
            + film('<rfilter type="tent"><float name="radius" value="2"/></rfilter>')
            + film('<rfilter type="mitchell"/>')
            + film("", width=80, height=60)
            + "</scene>"
        )
    )
    reduce_films(tree, 100)
    filters = [sensor.find("film/rfilter") for sensor in tree.getroot().iter("sensor")]
    stddevs = [float(f.find("float").get("value")) for f in filters[:3]]
    scale = 100 / 400
    expected = [np.sqrt(1 / 12 + v * scale**2) for v in (0.25, 1 / 12, 4 / 6)]
    assert all(f.get("type") == "gaussian" for f in filters[:3])
    assert np.allclose(stddevs, expected)
    assert filters[3].get("type") == "mitchell" and filters[4] is None
    sensors = mi.load_string(ET.tostring(tree.getroot(), encoding="unicode")).sensors()
    assert [round(s.film().rfilter().radius(), 3) for s in sensors[:3]] == [round(4 * v, 3) for v in stddevs]


def test_a_fit_at_reduced_films_writes_the_scene_with_its_own(mi, references, tmp_path):
    scene = _write_scene(tmp_path / "start", rough=0.7, colour="0.5, 0.5, 0.5", floor="0.6, 0.6, 0.6")
    out = tmp_path / "out"
    assert _fit(scene, references, out, "roughness", "--max-size", "24") == 0
    rough = json.loads((out / "params.json").read_text())["params"]["mat.roughness.value"][0]
    assert abs(rough - 0.3) < 0.7 - 0.3
    written = mi.load_file(str(out / "scene.xml"))
    assert [tuple(s.film().size()) for s in written.sensors()] == [(48, 36)] * 3


@pytest.mark.parametrize("where", ["inside-a-file", "the-scene's-folder", "read-only"])
def test_out_is_checked_before_the_fit(mi, references, tmp_path, capsys, monkeypatch, where):
    scene = _write_scene(tmp_path / "start", rough=0.7, colour="0.5, 0.5, 0.5", floor="0.3, 0.3, 0.3")
    before = scene.read_text()
    out, message = {
        "inside-a-file": (scene / "out", "cannot be written (Not a directory)"),
        "the-scene's-folder": (scene.parent, "would overwrite the scene being fitted"),
        "read-only": (tmp_path / "locked", "cannot be written (Read-only file system)"),
    }[where]
    if where == "read-only":  # root ignores permissions: the file system refuses instead
        real = tempfile.TemporaryFile

        def refuse(*args, dir=None, **kwargs):
            if str(dir) == str(out):
                raise OSError(errno.EROFS, "Read-only file system")
            return real(*args, dir=dir, **kwargs)

        monkeypatch.setattr(tempfile, "TemporaryFile", refuse)
    fitted = []
    monkeypatch.setattr(engine, "fit", lambda *args: fitted.append(args))
    assert _fit(scene, references, out, "roughness") == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and fitted == [] and scene.read_text() == before


def test_non_finite_reference_pixels_are_refused_by_file_and_count(mi, references, tmp_path, capsys):
    scene = _write_scene(tmp_path / "start", rough=0.7, colour="0.5, 0.5, 0.5", floor="0.3, 0.3, 0.3")
    spoilt = Path(shutil.copytree(references, tmp_path / "refs"))
    first = sorted(spoilt.iterdir())[0]
    pixels = read_photo(first, "linear").pixels
    pixels[0, :3] = [np.nan, np.inf, -np.inf]
    write_image(first, pixels)
    assert _fit(scene, spoilt, tmp_path / "out", "roughness") == 1
    err = capsys.readouterr().err
    assert (
        f"{first}: 3 pixel(s) in rows 0-" in err
        and "are NaN or infinite" in err
        and not (tmp_path / "out" / "params.json").exists()
    )


def test_negative_reference_pixels_are_refused_by_file_and_count(mi, references, tmp_path, capsys):
    scene = _write_scene(tmp_path / "start", rough=0.7, colour="0.5, 0.5, 0.5", floor="0.3, 0.3, 0.3")
    spoilt = Path(shutil.copytree(references, tmp_path / "refs"))
    first = sorted(spoilt.iterdir())[0]
    pixels = read_photo(first, "linear").pixels
    pixels[2, :5, 1] = -0.25
    write_image(first, pixels)
    assert _fit(scene, spoilt, tmp_path / "out", "roughness") == 1
    err = capsys.readouterr().err
    assert f"{first}: 5 pixel(s) are negative" in err and not (tmp_path / "out" / "params.json").exists()


def test_results_stay_json_when_the_fit_ends_non_finite(tmp_path):
    from pipeline.formats.scene_folder import write_log

    write_log(tmp_path / "log.jsonl", [{"iteration": 1, "loss": float("nan"), "value": [float("inf"), 1.0]}])
    entry = json.loads((tmp_path / "log.jsonl").read_text(), parse_constant=lambda name: pytest.fail(name))
    assert entry == {"iteration": 1, "loss": None, "value": [None, 1.0]}


def test_coarse_to_fine_fits_level_by_level_up_to_the_films_own_size(mi, references, tmp_path):
    """48x36 films from 16 px: levels of 16, 32 and 48 (their own) pixels, each from the
    last one's values; the log says each step's level, the record the levels."""
    from pipeline.fit.scene_fit import FilmSizes

    assert FilmSizes(16, True).levels(48) == [16, 32, 0]
    assert FilmSizes(64, True).levels(48) == [0] and FilmSizes(16).levels(48) == [16] and FilmSizes(0).levels(48) == [0]
    scene = _write_scene(tmp_path / "start", rough=0.7, colour="0.5, 0.5, 0.5", floor="0.6, 0.6, 0.6")
    out = tmp_path / "out"
    arguments = ["--max-size", "16", "--coarse-to-fine", "--iterations", "6", "--batch", "3", "--spp", "4"]
    code = cli_main(
        ["fit", str(scene), "--references", str(references), "--params", "roughness", *arguments, "--out", str(out)]
    )
    assert code == 0
    record = json.loads((out / "params.json").read_text())
    log = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert record["levels"] == [16, 32, "full"] and record["iterations"] == len(log) == 18
    assert [entry["level"] for entry in log] == [0] * 6 + [1] * 6 + [2] * 6
    assert all(a["seconds"] < b["seconds"] for a, b in zip(log, log[1:]))
    # each level starts where the last one ended (one Adam step, 0.1 in log space, apart),
    # not at the file's 0.7
    roughness = [entry["params"]["mat.roughness.value"][0] for entry in log]
    assert abs(np.log(roughness[6] / roughness[5])) < 0.15 and abs(np.log(roughness[12] / roughness[11])) < 0.15
    assert abs(record["params"]["mat.roughness.value"][0] - 0.3) < abs(0.7 - 0.3)


def _fit_process(scene: Path, references: Path, out: Path) -> subprocess.Popen:
    """`pipeline fit` that runs until it is stopped, in a process of its own."""
    argv = ["fit", str(scene), "--references", str(references), "--params", "roughness", "--out", str(out)]
    argv += ["--iterations", "100000", "--still-threshold", "0", "--spp", "2", "--max-size", "16"]
    return subprocess.Popen([sys.executable, "-m", "pipeline", *argv], stderr=subprocess.PIPE, text=True)


def _wait_for_steps(out: Path, process: subprocess.Popen) -> None:
    """Until the fit has taken steps (its lock's holder record is written at the start,
    and a few seconds of steps follow)."""
    deadline = time.monotonic() + 120
    while not (out / LOCK_FILE).is_file() or not (out / LOCK_FILE).read_text():
        assert process.poll() is None and time.monotonic() < deadline, process.stderr.read()
        time.sleep(0.1)
    time.sleep(5)


@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_an_interrupted_fit_writes_its_best_state_marked_interrupted(mi, references, tmp_path, stop):
    scene = _write_scene(tmp_path / "start", rough=0.7, colour="0.5, 0.5, 0.5", floor="0.3, 0.3, 0.3")
    out = tmp_path / "out"
    process = _fit_process(scene, references, out)
    _wait_for_steps(out, process)
    process.send_signal(stop)
    err = process.communicate(timeout=120)[1]
    assert process.returncode == 128 + stop, err
    params = json.loads((out / "params.json").read_text())
    assert params["interrupted"] and params["stopped"].startswith(f"interrupted ({stop.name})")
    assert params["iterations"] > 0 and (out / "scene.xml").is_file() and (out / "log.jsonl").is_file()
    assert "the best state so far is written to" in err and "Traceback" not in err


def test_two_fits_never_share_an_out_folder(mi, references, tmp_path, capsys):
    scene = _write_scene(tmp_path / "start", rough=0.7, colour="0.5, 0.5, 0.5", floor="0.3, 0.3, 0.3")
    out = tmp_path / "out"
    first = _fit_process(scene, references, out)
    try:
        _wait_for_steps(out, first)
        assert _fit(scene, references, out, "roughness") == 1
        err = capsys.readouterr().err
        assert f"{out} is in use by pid {first.pid}" in err and "another --out" in err
    finally:
        first.send_signal(signal.SIGINT)
        first.communicate(timeout=120)
    assert json.loads((out / "params.json").read_text())["interrupted"]  # the first fit's, whole
