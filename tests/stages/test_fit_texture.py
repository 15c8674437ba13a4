"""Stage fit_texture on a small synthetic bird, with a fit small enough for a test."""

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.core.errors import ConfigError
from pipeline.synthetic.score import score_heldout
from tests.support.tiny_fits import TINY_FIT, TINY_TEXTURE

pytestmark = pytest.mark.slow


def test_fit_texture_lowers_the_held_out_error_and_the_scene_loads_it(run_stages, small_bird, mi):
    """From the constant, coarse to fine."""
    texture = (*TINY_TEXTURE, "fit_texture.texture=on", "fit_texture.start=constant")
    outputs = run_stages(small_bird, "fit_texture", *TINY_FIT, *texture)
    folder = outputs["fit_texture"]["textured_dir"]
    report = json.loads((folder / "params.json").read_text())
    assert report["kept"] and report["kind"] == "bitmap" and report["parameter"] == "base_color"
    assert [level["resolution"] for level in report["levels"]] == [[16, 16], [32, 32]]
    # The blotchy bird is what a texture is for.
    assert report["validation_mse_texture"] < 0.9 * report["validation_mse_constant"]
    assert {"base_color.exr", "base_color.png"} <= {p.name for p in folder.iterdir()}
    scene = mi.traverse(mi.load_file(str(folder / "scene.xml")))
    texture = scene["specimen.bsdf.base_color.data"]
    assert texture.shape == (32, 32, 3) and 0.0 <= np.min(texture) and np.max(texture) <= 1.0
    # The other constants were fitted again along with the texture, within
    # fit_material's bounds, and the scene carries the new values.
    constants = json.loads(outputs["fit_material"]["params"].read_text())["params"]
    for name in ("roughness", "spec_trans", "eta"):
        value = report["params"][name][0]
        assert value != constants[name][0], name
        assert report["bounds"][name][0] <= value <= report["bounds"][name][1], name
        assert np.ravel(scene[f"specimen.bsdf.{name}" + ("" if name == "eta" else ".value")])[0] == pytest.approx(
            value, rel=1e-5
        )
    np.testing.assert_allclose(report["params"]["base_color"], np.mean(texture, axis=(0, 1)), atol=1e-4)
    assert sorted(p.name for p in (folder / "heldout").glob("*.render.exr")) == [
        f"{n}.render.exr" for n in report["held_out"]
    ]


def test_a_texture_baked_from_the_photos_starts_far_below_the_constant(run_stages, small_bird, mi):
    """start = photos: the bake alone (before any step) more than halves the constant's
    held-out error on the blotchy bird; only the finest level is fitted, from it."""
    outputs = run_stages(small_bird, "fit_texture", *TINY_FIT, *TINY_TEXTURE, "fit_texture.start=photos")
    report = json.loads((outputs["fit_texture"]["textured_dir"] / "params.json").read_text())
    assert report["kept"] and [level["resolution"] for level in report["levels"]] == [[32, 32]]
    # six training views from two rings above the table leave the underside unseen
    assert report["baked"]["max_size"] == 96 and 0.4 < report["baked"]["texels_seen"] < 1.0
    assert report["levels"][0]["start_validation_mse"] < 0.5 * report["validation_mse_constant"]
    assert report["validation_mse_texture"] <= report["levels"][0]["start_validation_mse"]


def test_a_texture_not_kept_leaves_the_constant_colour_with_the_refitted_constants(run_stages, small_bird, mi):
    """The texture must beat the refitted constants; min_improvement = 1 means it never
    does. The scene then has fit_material's constant colour and the constants that
    fit_texture refitted alone."""
    outputs = run_stages(small_bird, "fit_texture", *TINY_FIT, *TINY_TEXTURE, "fit_texture.min_improvement=1.0")
    folder = outputs["fit_texture"]["textured_dir"]
    report = json.loads((folder / "params.json").read_text())
    constants = json.loads(outputs["fit_material"]["params"].read_text())["params"]
    assert not report["kept"] and not list(folder.glob("base_color.*"))
    assert report["constants_fit"]["iterations"] == 6 and report["params"]["base_color"] == constants["base_color"]
    scene = mi.traverse(mi.load_file(str(folder / "scene.xml")))
    np.testing.assert_allclose(np.ravel(scene["specimen.bsdf.base_color.value"]), constants["base_color"], rtol=1e-5)
    # Six steps may not beat fit_material's values (then the best state is the start):
    # what counts is that the scene holds what params.json says.
    for name in ("roughness", "spec_trans"):
        assert np.ravel(scene[f"specimen.bsdf.{name}.value"])[0] == pytest.approx(report["params"][name][0], rel=1e-5)
    assert np.ravel(scene["specimen.bsdf.eta"])[0] == pytest.approx(report["params"]["eta"][0], rel=1e-5)
    assert score_heldout(folder / "heldout")["views"] == 2


def test_a_guessed_light_too_dim_for_the_texture_is_raised_in_every_scene_file(run_stages, small_bird, mi):
    """Without the board's print the light's level is a guess (measured on the specimen
    as if grey); with colours bounded at 0.3 the bird's baked texels cannot reach the
    photos under it. The bake raises the light until all but 1 % of them fit, and the
    scene files carry the raised light with the texture (params.json says by how much)."""
    light = ("scene.board_plane=false", "light.model=constant", 'fit_material.bounds=["base_color=0.001:0.3"]')
    texture = (*TINY_TEXTURE, "fit_texture.start=photos", "fit_texture.texture=on")
    outputs = run_stages(small_bird, "fit_texture", *TINY_FIT, *light, *texture)
    fitted = json.loads(outputs["fit_material"]["params"].read_text())["light"]
    report = json.loads(outputs["fit_texture"]["params"].read_text())
    scale = report["baked"]["light_scale"]
    assert fitted["level_from"] == "specimen (grey)" and scale > 1.2
    assert report["light"]["environment_mean"] == pytest.approx(
        [scale * v for v in fitted["chosen"]["environment_mean"]]
    )
    for name in ("scene.xml", f"view-{Path(report['held_out'][0]).stem}.xml"):
        scene = mi.traverse(mi.load_file(str(outputs["fit_texture"]["textured_dir"] / name)))
        np.testing.assert_allclose(
            np.ravel(scene["environment.radiance.value"]), report["light"]["environment_mean"], rtol=1e-5
        )
    colours = scene["specimen.bsdf.base_color.data"]
    assert np.max(colours) <= 0.3 and np.mean(np.max(colours, axis=-1) >= 0.2999) < 0.1


def test_a_texture_too_large_for_the_machines_memory_is_refused_before_anything_runs(tmp_path):
    from pipeline.cli.registry import registered_stages
    from pipeline.core.config import load_config
    from pipeline.core.sections import schema

    load_config(schema(registered_stages()), tmp_path, "standard", ["fit_texture.max_resolution=1024"])
    for override in ("fit_texture.max_resolution=100000", "fit_texture.max_grid_resolution=5000"):
        with pytest.raises(ConfigError, match=r"needs about \d+ GiB for the texture's fit, more than 80% of this"):
            load_config(schema(registered_stages()), tmp_path, "standard", [override])
