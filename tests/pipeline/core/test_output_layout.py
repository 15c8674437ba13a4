"""output/: each stage's exports in stages/STAGE/, the last result of each role on top."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import pytest

from pipeline import output_guide
from pipeline.core.config import load_config
from pipeline.core.runner import Runner, check_contract
from pipeline.core.sections import schema
from pipeline.core.stage import Stage, StageInputs, StageResult


@dataclass(frozen=True)
class FitConfig:
    """A fit that can be switched off."""

    enabled: bool = True
    """Run the stage."""


def scene_folder(label: str):
    def main(conf: FitConfig, inputs: StageInputs, out_dir: Path) -> StageResult:
        folder = out_dir / "scene"
        (folder / "heldout").mkdir(parents=True)
        (folder / "scene.xml").write_text(f"<scene>{label}</scene>")
        (folder / "params.json").write_text(json.dumps({"by": label}))
        (folder / "heldout" / "a.render.png").write_text(label)
        if label == "first":
            (folder / "only_first.txt").write_text("first")
        return StageResult({"scene_dir": folder, "params": folder / "params.json"})

    return main


def model(conf: FitConfig, inputs: StageInputs, out_dir: Path) -> StageResult:
    (out_dir / "specimen.glb").write_text("glb")
    return StageResult({"glb": out_dir / "specimen.glb"})


STAGES = (
    Stage(
        "first",
        1,
        FitConfig,
        scene_folder("first"),
        outputs=("scene_dir", "params"),
        exports=("scene_dir", "params"),
        result=("scene", "scene_dir"),
    ),
    Stage(
        "second",
        1,
        FitConfig,
        scene_folder("second"),
        needs=("first.params",),
        outputs=("scene_dir", "params"),
        exports=("scene_dir",),
        result=("scene", "scene_dir"),
        enabled=lambda conf: conf.enabled,
    ),
    Stage(
        "model",
        1,
        FitConfig,
        model,
        needs=("first.params",),
        outputs=("glb",),
        exports=("glb",),
        result=("model", "glb"),
    ),
)


def run(capture: Path, *overrides: str) -> Path:
    presets_dir = capture.parent / "presets"
    presets_dir.mkdir(exist_ok=True)
    (presets_dir / "standard.toml").write_text("")
    Runner(capture, STAGES, load_config(schema(STAGES), capture, "standard", list(overrides), presets_dir)).run()
    return capture / "output"


def test_the_last_result_of_each_role_is_on_top_and_every_stage_in_its_folder(tmp_path):
    capture = tmp_path / "capture"
    capture.mkdir()
    output = run(capture)
    assert (output / "scene.xml").read_text() == "<scene>second</scene>"
    assert json.loads((output / "params.json").read_text()) == {"by": "second"}
    assert (output / "heldout" / "a.render.png").read_text() == "second"
    assert (output / "specimen.glb").read_text() == "glb"
    assert not (output / "only_first.txt").exists()  # the top is one stage's result, not a mixture
    # each stage's own: a folder export laid out in stages/STAGE/, a file inside it once
    assert (output / "stages" / "first" / "scene.xml").read_text() == "<scene>first</scene>"
    assert (output / "stages" / "first" / "only_first.txt").is_file()
    assert (output / "stages" / "second" / "heldout" / "a.render.png").read_text() == "second"
    assert (output / "stages" / "model" / "specimen.glb").is_file()
    manifest = json.loads((output / "manifest.json").read_text())
    assert manifest["scene.xml"]["stage"] == "second" and manifest["stages/first/params.json"]["stage"] == "first"

    guide = output_guide.text(capture)
    assert "scene.xml          second" in guide and "specimen.glb       model" in guide
    assert "stages/first/" in guide and "only_first.txt" in guide

    # With the later stage switched off, the earlier result is the one on top.
    output = run(capture, "second.enabled=false")
    assert (output / "scene.xml").read_text() == "<scene>first</scene>"
    assert (output / "only_first.txt").is_file()
    assert not (output / "stages" / "second").exists()


def test_a_result_must_be_an_export():
    stage = Stage("a", 1, FitConfig, model, outputs=("glb",), exports=(), result=("model", "glb"))
    with pytest.raises(ValueError, match="a's result glb is not one of its exports"):
        check_contract((stage,))
