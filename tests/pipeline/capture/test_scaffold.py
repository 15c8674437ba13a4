import tomllib

from pipeline.cli import main
from pipeline.core.config import load_config
from pipeline.core.sections import schema
from stages import STAGES


def test_new_capture_has_folders_a_documented_toml_and_a_checklist(tmp_path, capsys):
    capture = tmp_path / "captures" / "soap"
    assert main(["new", str(capture), "--description", "lavender soap", "--rig", "turntable"]) == 0
    assert {p.name for p in capture.iterdir()} == {
        "images",
        "calibration",
        "background",
        "masks",
        "capture.toml",
        "README.md",
    }
    text = (capture / "capture.toml").read_text()
    parsed = tomllib.loads(text)
    assert parsed["capture"] == {"description": "lavender soap", "rig": "turntable", "material": "auto"}
    assert set(parsed) == {"capture", "board", "light", "cameras"}  # stage sections are commented out
    for name, cls in schema(STAGES).items():
        assert f"[{name}]" in text, name
        for field in cls.__dataclass_fields__:
            assert f"{field} = " in text, f"{name}.{field}"
    # Every setting carries its documentation: a comment line right above it.
    lines = text.splitlines()
    for i, line in enumerate(lines):
        if " = " in line:
            assert lines[i - 1].startswith("# ("), line
    config = load_config(schema(STAGES), capture)
    assert config["capture"].rig == "turntable"
    readme = (capture / "README.md").read_text()
    for topic in ("overlap", "exposure", "zoom", "board", "Background plate", "Light"):
        assert topic.lower() in readme.lower(), topic


def test_new_refuses_a_folder_with_files(tmp_path, capsys):
    (tmp_path / "bird").mkdir()
    (tmp_path / "bird" / "photo.jpg").write_bytes(b"x")
    assert main(["new", str(tmp_path / "bird")]) == 2
    assert "not empty" in capsys.readouterr().err
