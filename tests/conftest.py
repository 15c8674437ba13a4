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
