import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent / "pipeline"))


@pytest.fixture
def presets_dir(tmp_path: Path) -> Path:
    """A presets folder for test-only stage graphs (the real presets name real stages)."""
    folder = tmp_path / "presets"
    folder.mkdir()
    (folder / "standard.toml").write_text("[double]\nfactor = 2\n")
    (folder / "draft.toml").write_text("[double]\nfactor = 3\n")
    return folder


@pytest.fixture(scope="session")
def tiny_capture(tmp_path_factory) -> Path:
    """A synthetic capture small enough for tests: 6 views of 96x72 px, 4 spp."""
    from pipeline.synth import SynthOptions, synthesize

    out = tmp_path_factory.mktemp("synth") / "bird"
    options = SynthOptions(views=6, width=96, height=72, spp=4, calibration_shots=3, seed=3)
    return synthesize(out, options)
