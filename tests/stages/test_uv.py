"""Stage uv: the atlas of the unwrapped mesh (unit tests on a lumpy sphere) and the
stage on the bundled sample bird."""

import json

import numpy as np
import pytest
import trimesh

from pipeline.core.errors import PipelineError
from pipeline.geometry.atlas import overlapping_texels
from stages.uv import Config, unwrap


def _lumpy_sphere() -> trimesh.Trimesh:
    sphere = trimesh.creation.icosphere(subdivisions=3)
    sphere.vertices += 0.05 * np.sin(7 * sphere.vertices)  # uneven: xatlas cuts several charts
    return sphere


@pytest.mark.parametrize("texture_size", [64, 256])
def test_every_chart_lands_on_one_atlas_without_overlap(texture_size):
    # xatlas' first density estimate overflows onto extra atlases at both sizes.
    unwrapped, report = unwrap(_lumpy_sphere(), Config(texture_size=texture_size, padding=2))
    assert report["charts"] > 1 and report["atlas_size"] == [texture_size, texture_size]
    assert report["overlapping_texels"] == 0
    assert overlapping_texels(unwrapped, (texture_size, texture_size)) == 0
    assert unwrapped.visual.uv.min() >= 0 and unwrapped.visual.uv.max() <= 1
    np.testing.assert_allclose(unwrapped.area, _lumpy_sphere().area)


def test_a_texel_density_too_high_for_the_atlas_names_the_key():
    with pytest.raises(PipelineError, match="uv.texel_density"):
        unwrap(_lumpy_sphere(), Config(texture_size=64, texel_density=500.0))


def test_charts_that_fit_no_atlas_name_the_keys_to_change():
    with pytest.raises(PipelineError, match="uv.texture_size = 64 .* uv.padding = 16"):
        unwrap(_lumpy_sphere(), Config(texture_size=64, padding=16))


@pytest.mark.slow
def test_uv_covers_the_mesh_with_little_area_distortion(bird_until_uv):
    _, outputs = bird_until_uv
    report = json.loads(outputs["uv"]["report"].read_text())
    assert report["area_distortion_median"] < 1.2 and report["utilisation"] > 0.5
    assert report["overlapping_texels"] == 0
    obj = trimesh.load(outputs["uv"]["obj"], force="mesh", process=False)
    ply = trimesh.load(outputs["uv"]["mesh"], force="mesh", process=False)
    for mesh in (obj, ply):
        assert mesh.visual.uv is not None and len(mesh.visual.uv) == len(mesh.vertices)
        assert mesh.visual.uv.min() >= 0 and mesh.visual.uv.max() <= 1
    cleaned = trimesh.load(outputs["cleanup"]["mesh"], force="mesh")
    assert abs(ply.area - cleaned.area) < 1e-9 * max(1.0, cleaned.area) + 1e-12


@pytest.mark.slow
def test_the_published_obj_comes_with_its_material_and_texture(bird_until_uv):
    capture, _ = bird_until_uv
    output = capture / "output" / "stages" / "uv"
    (library,) = [
        line.split()[1] for line in (output / "mesh.obj").read_text().splitlines() if line.startswith("mtllib")
    ]
    (texture,) = [line.split()[1] for line in (output / library).read_text().splitlines() if line.startswith("map_Kd")]
    assert (output / texture).is_file()
    assert len(trimesh.load(output / "mesh.obj", force="mesh").visual.material.image.size) == 2
