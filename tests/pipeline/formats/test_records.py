"""The typed records stages exchange: what is written reads back the same, the file's
other keys survive, and a file without a field names the file, the key and the fix."""

import json

import pytest

from pipeline.core.errors import PipelineError
from pipeline.formats.fit_results import LightChoice, MaterialFit, TexturedFit, read_fitted_scene
from pipeline.formats.scene_description import Ground, Integrator, LightStart, MaterialParameter, ViewFiles
from tests.support.scene_descriptions import scene_description


def _material_fit() -> MaterialFit:
    return MaterialFit(
        model="opaque",
        params={"base_color": [0.5, 0.4, 0.3], "roughness": [0.2]},
        bounds={"base_color": [0.001, 1.0], "roughness": [0.001, 1.0]},
        held_out=["b.jpg"],
        units={"base_color": "linear RGB reflectance", "roughness": "1"},
        integrator=Integrator(type="path", max_depth=16, differentiable="prb"),
        light=LightChoice(
            chosen={"model": "given"}, why="the only light candidate fitted", candidates=[], level=None, level_from=None
        ),
        photo_gains={"a.jpg": [1.0]},
        gain_channels=1,
        heldout_gains={},
        details={"iterations": 12, "stopped": "iterations"},
    )


def test_scene_description_reads_back_what_was_written(tmp_path):
    written = scene_description(
        ground=Ground(radius=0.25, albedo=[0.3, 0.3, 0.3]),
        board_print=[0.1, 0.07],
        parameters={"roughness": MaterialParameter("specimen.bsdf.roughness.value", [0.5], 0.001, 1.0, "1")},
        views={"a.jpg": ViewFiles(xml="view-a.xml", sensor="a")},
        light=LightStart(model="constant", level=[0.5, 0.5, 0.5], level_from="board"),
    )
    path = written.write(tmp_path / "scene.json")
    data = json.loads(path.read_text())
    # the file keeps the layout every reader of scene.json has known
    assert data["integrator"] == {"type": "path", "max_depth": 8, "differentiable": "prb"}
    assert data["views"] == {"a.jpg": {"xml": "view-a.xml", "sensor": "a"}}
    read = type(written).read(path)
    assert read == written
    assert read.view_files() == {"a.jpg": "view-a.xml"} and read.initial_values() == {"roughness": [0.5]}
    deeper = read.fitted_with("opaque", read.integrator.deeper())
    assert (deeper.model, deeper.integrator.max_depth, read.integrator.max_depth) == ("opaque", 16, 8)


def test_a_fit_record_keeps_the_stages_account_beside_its_fields(tmp_path):
    written = _material_fit()
    path = written.write(tmp_path / "params.json")
    data = json.loads(path.read_text())
    assert data["iterations"] == 12 and data["light"]["chosen"] == {"model": "given"}
    read = MaterialFit.read(path)
    assert read == written and not read.light.estimated
    textured = TexturedFit(
        model="opaque", params={}, bounds={}, held_out=[], kept=True, learning_rate=0.03, smoothness=0.05
    )
    assert TexturedFit.read(textured.write(tmp_path / "texture.json")) == textured


def test_a_record_without_a_field_names_the_file_the_key_and_the_fix(tmp_path):
    data = _material_fit().to_json()
    del data["held_out"], data["integrator"]
    path = tmp_path / "params.json"
    path.write_text(json.dumps(data))
    with pytest.raises(PipelineError, match=r"params.json has no held_out, integrator: .*--force"):
        MaterialFit.read(path)


def test_the_fitted_scene_is_the_description_with_fit_materials_model_and_depth(tmp_path):
    description = scene_description().write(tmp_path / "scene.json")
    material = _material_fit().write(tmp_path / "params.json")
    seen, fit = read_fitted_scene(description, material)
    assert (seen.model, seen.integrator.max_depth, fit.model) == ("opaque", 16, "opaque")


def test_an_optional_part_field_left_unset_is_not_written(tmp_path):
    """A given light has no level: its entry stays {"model": "given"}, as the files always had it."""
    path = scene_description(light=LightStart(model="given")).write(tmp_path / "scene.json")
    assert json.loads(path.read_text())["light"] == {"model": "given"}
    assert type(scene_description()).read(path).light == LightStart(model="given")
