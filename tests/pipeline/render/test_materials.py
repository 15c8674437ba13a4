"""pipeline.render.materials and the specimen file rewritten with another model."""

import pytest

from pipeline.render import capture_scene, materials


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
