"""pipeline.render.materials and the specimen file rewritten with another model."""

from dataclasses import replace

import pytest
import trimesh

from pipeline.formats.scene_description import Integrator
from pipeline.render import capture_scene, materials, scene_xml


def test_opaque_from_principled_keeps_colour_and_roughness_and_the_reflectance_of_eta():
    values = materials.opaque_from_principled({"base_color": [0.2, 0.3, 0.4], "roughness": [0.6], "eta": [1.5]})
    # F0 of eta 1.5 is 0.04, Disney's specular 0.5; spec_trans and eta are gone.
    assert values == {"base_color": [0.2, 0.3, 0.4], "roughness": [0.6], "specular": [pytest.approx(0.5)]}
    assert materials.opaque_from_principled({"base_color": [1, 1, 1], "roughness": [1], "eta": [3.0]})["specular"] == [
        1.0
    ]


def test_the_specimen_file_takes_another_models_material_and_keeps_what_it_stands_on(tmp_path):
    path = tmp_path / "specimen.xml"
    principled = materials.initial_values("principled")
    capture_scene.write_specimen_file(path, "principled", principled, None, (0.5, (0.7, 0.7, 0.7)))
    capture_scene.rewrite_specimen_material(path, "volumetric", materials.initial_values("volumetric"))
    text = path.read_text()
    assert "roughdielectric" in text and "homogeneous" in text and "principled" not in text and "ground" in text
    capture_scene.rewrite_specimen_material(path, "opaque", materials.opaque_from_principled(principled))
    text = path.read_text()
    assert "specular" in text and "homogeneous" not in text and "spec_trans" not in text


def test_volumetric_from_principled_keeps_eta_and_colour_and_squares_roughness_inside_the_bounds():
    values = materials.volumetric_from_principled({"base_color": [0.2, 0.0, 0.4], "roughness": [0.5], "eta": [1.4]})
    assert values["eta"] == [1.4] and values["alpha"] == [pytest.approx(0.25)]
    assert values["albedo"] == [0.2, materials.PARAMETERS["albedo"].lower, 0.4]  # 0 would never come back
    assert values["sigma_t"] == list(materials.PARAMETERS["sigma_t"].initial)
    tiny = materials.volumetric_from_principled({"base_color": [0.5] * 3, "roughness": [0.001], "eta": [1.5]})
    assert tiny["alpha"] == [materials.PARAMETERS["alpha"].lower]


def test_scene_files_are_rewritten_to_another_integrator_and_still_load(tmp_path, mi):
    """The scene and view files name the render integrator of the model fit_material
    chose (a medium needs volpath), at its depth; comments and sensors stay."""
    trimesh.creation.icosphere(subdivisions=1, radius=0.05).export(tmp_path / "mesh.ply")
    specimen = tmp_path / "specimen.xml"
    capture_scene.write_specimen_file(specimen, "volumetric", materials.initial_values("volumetric"), None, None)
    root = scene_xml.new_scene()
    scene_xml.plugin(root, "integrator", {"type": "path", "id": "integrator", "max_depth": 8})
    scene_xml.include(root, "specimen.xml")
    scene_xml.write(root, tmp_path / "scene.xml", "the scene stage's note")
    volumetric = materials.model_integrator("volumetric")
    assert volumetric == Integrator(type="volpath", max_depth=32, differentiable="prbvolpath")
    capture_scene.rewrite_integrator(tmp_path, replace(volumetric, max_depth=64))
    text = (tmp_path / "scene.xml").read_text()
    assert "the scene stage's note" in text and text.count("<integrator") == 1
    integrator = mi.load_file(str(tmp_path / "scene.xml")).integrator()
    assert str(integrator).startswith("VolumetricSimplePathIntegrator[") and "max_depth = 64" in str(integrator)
