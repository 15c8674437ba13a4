"""scene and fit_material on the bundled sample bird (after the geometry stages,
shared with test_geometry through the runner's cache)."""

import json
import xml.etree.ElementTree as ET

import cv2
import numpy as np
import pytest
import trimesh
from conftest import run_stages

from pipeline.formats.cameras import read_views
from pipeline.synthetic.score import score_heldout, score_material

pytestmark = pytest.mark.slow
# A fit small enough for a test: windows of 48 px, 4 spp, a few steps.
TINY_FIT = ("fit_material.iterations=8", "fit_material.batch=2", "fit_material.spp=4", "fit_material.max_size=48",
            "fit_material.validate_every=4", "fit_material.validation_spp=8", "fit_material.loss=l2")  # fmt: skip


def test_scene_loads_renders_and_lines_up_with_the_photos(bird_capture, mi):
    outputs = run_stages(bird_capture, "scene")["scene"]
    folder = outputs["scene_dir"]
    description = json.loads(outputs["description"].read_text())
    views = read_views(run_stages(bird_capture, "sfm")["sfm"]["cameras"])
    scene = mi.load_file(str(outputs["scene"]))
    assert len(scene.sensors()) == len(views) == len(description["views"])
    root = ET.parse(folder / "specimen.xml").getroot()
    # Every shape, BSDF, medium and emitter has an id; the principled model has no medium.
    for file in [outputs["scene"], folder / "specimen.xml"]:
        for element in ET.parse(file).getroot().iter():
            if element.tag in ("shape", "bsdf", "medium", "emitter", "sensor"):
                assert element.get("id"), f"{file.name}: <{element.tag} type={element.get('type')}> has no id"
    assert root.find(".//medium") is None and description["model"] == "principled"
    assert description["integrator"] == {"type": "prb", "max_depth": 8}
    # The specimen alone, rendered white on black from a photo's view file, covers its mask.
    name = sorted(views)[3]
    view_scene = mi.load_file(str(folder / description["views"][name]["xml"]))
    params = mi.traverse(view_scene)
    silhouette = mi.load_dict({"type": "scene", "integrator": {"type": "aov", "aovs": "depth:depth"},
                               "specimen": {"type": "ply", "filename": str(folder / "mesh.ply")}})  # fmt: skip
    depth = np.asarray(mi.render(silhouette, sensor=view_scene.sensors()[0], spp=4))[..., 0]
    masks_json = run_stages(bird_capture, "masks")["masks"]["masks_json"]
    mask = cv2.imread(str(masks_json.parent / json.loads(masks_json.read_text())["images"][name]["mask"]), 0) > 127
    covered = depth > 0
    assert np.count_nonzero(covered & mask) / np.count_nonzero(covered | mask) > 0.9
    assert "specimen.bsdf.roughness.value" in params.keys()


@pytest.mark.parametrize("model, medium, integrator", [("volumetric", True, "prbvolpath"), ("opaque", False, "prb")])
def test_each_model_writes_only_what_it_needs(bird_capture, mi, model, medium, integrator):
    outputs = run_stages(bird_capture, "scene", f"scene.model={model}")["scene"]
    specimen = ET.parse(outputs["scene_dir"] / "specimen.xml").getroot()
    assert (specimen.find(".//medium") is not None) == medium
    names = {e.get("name") for e in specimen.find(".//bsdf").iter()}
    if model == "opaque":
        assert "spec_trans" not in names and "eta" not in names and "specular" in names
    assert json.loads(outputs["description"].read_text())["integrator"]["type"] == integrator
    mi.load_file(str(outputs["scene"]))


def test_fit_material_moves_base_colour_toward_the_truth_within_bounds(bird_capture, mi):
    outputs = run_stages(bird_capture, "fit_material", *TINY_FIT)["fit_material"]
    params = json.loads(outputs["params"].read_text())
    truth = json.loads((bird_capture / "ground_truth" / "material.json").read_text())
    start = np.array([0.5, 0.5, 0.5])
    fitted = np.array(params["params"]["base_color"])
    target = np.array(truth["base_color_mean"])  # a constant fit to the textured bird
    assert np.abs(fitted - target).max() < np.abs(start - target).max()
    for name, (lower, upper) in params["bounds"].items():
        assert all(lower - 1e-6 <= v <= upper + 1e-6 for v in params["params"][name])
    assert len(params["held_out"]) == 2 and params["validation_mse"] is not None
    errors = score_material(params, truth)
    assert set(errors) >= {"base_color_abs_error", "roughness_abs_error", "spec_trans_abs_error", "eta_abs_error"}
    heldout = score_heldout(outputs["heldout"])
    assert heldout["views"] == 2 and np.isfinite(heldout["psnr_db_mean"])
    # The fitted scene renders as-is and carries the fitted values.
    fitted_scene = mi.traverse(mi.load_file(str(outputs["scene"])))
    np.testing.assert_allclose(np.ravel(fitted_scene["specimen.bsdf.base_color.value"]), fitted, rtol=1e-5)
    log = [json.loads(line) for line in (outputs["fitted_dir"] / "log.jsonl").read_text().splitlines()]
    assert len(log) == params["iterations"] and "validation_error" in log[3]


def test_fit_material_rejects_bounds_of_unknown_parameters(bird_capture):
    from pipeline.core.errors import PipelineError

    with pytest.raises(PipelineError, match="alpha, not parameters of the principled model"):
        run_stages(bird_capture, "fit_material", *TINY_FIT, 'fit_material.bounds=["alpha=0.1:0.5"]')


TINY_TEXTURE = ("fit_texture.levels=2", "fit_texture.max_resolution=32", "fit_texture.iterations_per_level=6",
                "fit_texture.spp=4", "fit_texture.max_size=48", "fit_texture.validate_every=3",
                "fit_texture.validation_spp=8", "fit_texture.loss=l2")  # fmt: skip


def test_fit_texture_lowers_the_held_out_error_and_the_scene_loads_it(bird_capture, mi):
    outputs = run_stages(bird_capture, "fit_texture", *TINY_FIT, *TINY_TEXTURE, "fit_texture.texture=on")
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
        assert np.ravel(scene[f"specimen.bsdf.{name}" + ("" if name == "eta" else ".value")])[0] == pytest.approx(value, rel=1e-5)
    np.testing.assert_allclose(report["params"]["base_color"], np.mean(texture, axis=(0, 1)), atol=1e-4)
    assert sorted(p.name for p in (folder / "heldout").glob("*.render.exr")) == [f"{n}.render.exr" for n in report["held_out"]]


def test_a_texture_not_kept_leaves_the_constant_colour_with_the_refitted_constants(bird_capture, mi):
    """The texture must beat the refitted constants; min_improvement = 1 means it never
    does. The scene then has fit_material's constant colour and the constants that
    fit_texture refitted alone."""
    outputs = run_stages(bird_capture, "fit_texture", *TINY_FIT, *TINY_TEXTURE, "fit_texture.min_improvement=1.0")
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


TINY_GEOMETRY = ("fit_geometry.iterations=4", "fit_geometry.max_size=32", "fit_geometry.validate_every=4",
                 "fit_geometry.validation_spp=8", "fit_geometry.spp=4", "fit_geometry.material_max_size=48",
                 "fit_geometry.material_spp=4")  # fmt: skip


def test_fit_geometry_pulls_a_sphere_towards_the_silhouettes(bird_capture):
    outputs = run_stages(bird_capture, "fit_geometry", *TINY_FIT, *TINY_TEXTURE, *TINY_GEOMETRY, "fit_geometry.start=sphere",
                         "fit_geometry.loss=silhouette", "fit_geometry.rounds=1", "fit_geometry.material_iterations=0",
                         "fit_geometry.sphere_subdivisions=3", "fit_geometry.step=0.03")  # fmt: skip
    report = json.loads((outputs["fit_geometry"]["geometry_dir"] / "params.json").read_text())
    assert report["loss"] == "silhouette" and report["vertices"] == 642
    assert list(report["rounds"][0]) == ["geometry"]  # no material pass
    # Slow on a CPU (see docs/benchmarks.md): four steps only show the direction.
    assert report["validation_mse"] < report["validation_mse_start"]
    assert report["median_vertex_move_of_diagonal"] > 0
    assert score_heldout(outputs["fit_geometry"]["geometry_dir"] / "heldout")["views"] == len(report["held_out"])


def test_fit_geometry_alternates_shape_and_material_and_the_scene_holds_the_result(bird_capture, mi):
    """Two rounds on the hull with a kept texture: each pass keeps its best held-out
    state (so none ends worse than it started), and the final scene holds the
    refitted constants and texture that params.json reports."""
    outputs = run_stages(bird_capture, "fit_geometry", *TINY_FIT, *TINY_TEXTURE, *TINY_GEOMETRY, "fit_texture.texture=on",
                         "fit_geometry.rounds=2", "fit_geometry.material_iterations=4", "fit_geometry.step=0.01")  # fmt: skip
    folder = outputs["fit_geometry"]["geometry_dir"]
    report = json.loads((folder / "params.json").read_text())
    textured = json.loads((outputs["fit_texture"]["textured_dir"] / "params.json").read_text())
    assert report["loss"] == "photometric" and len(report["rounds"]) == 2
    for done in report["rounds"]:
        for name in ("geometry", "material"):
            assert done[name]["validation"] <= done[name]["validation_start"], name
        material = done["material"]
        assert material["kept"] == (material["validation"] <= 0.98 * material["validation_start"])
    log = [json.loads(line) for line in (folder / "log.jsonl").read_text().splitlines()]
    assert [(e["round"], e["pass"]) for e in log] == [(r, p) for r in (0, 1) for p in ("geometry", "material") for _ in range(4)]
    scene = mi.traverse(mi.load_file(str(folder / "scene.xml")))
    for name in ("roughness", "spec_trans"):
        value = report["params"][name][0]
        assert report["bounds"][name][0] <= value <= report["bounds"][name][1], name
        assert np.ravel(scene[f"specimen.bsdf.{name}.value"])[0] == pytest.approx(value, rel=1e-5)
    assert np.ravel(scene["specimen.bsdf.eta"])[0] == pytest.approx(report["params"]["eta"][0], rel=1e-5)
    texture = np.asarray(scene["specimen.bsdf.base_color.data"])
    np.testing.assert_allclose(report["params"]["base_color"], texture.reshape(-1, 3).mean(axis=0), atol=1e-4)
    assert texture.shape[:2] == (32, 32)
    # The texture and constants were optimised (the best state may still be the start).
    steps = [e["params"] for e in log if e["pass"] == "material"]
    for name in ("base_color", "roughness"):
        assert steps[-1][name] != textured["params"][name], name
    vertices = np.asarray(scene["specimen.vertex_positions"]).reshape(-1, 3)
    hull = trimesh.load(outputs["fit_texture"]["textured_dir"] / "mesh.ply", process=False).vertices
    assert vertices.shape == hull.shape and report["median_vertex_move_of_diagonal"] > 0


def test_a_material_pass_below_the_minimum_gain_leaves_the_material_as_it_was(bird_capture, mi):
    outputs = run_stages(bird_capture, "fit_geometry", *TINY_FIT, *TINY_TEXTURE, *TINY_GEOMETRY, "fit_texture.texture=on",
                         "fit_geometry.rounds=1", "fit_geometry.material_iterations=4",
                         "fit_geometry.material_min_improvement=1")  # fmt: skip
    folder, textured = outputs["fit_geometry"]["geometry_dir"], outputs["fit_texture"]["textured_dir"]
    report = json.loads((folder / "params.json").read_text())
    assert report["rounds"][0]["material"]["kept"] is False
    log = [json.loads(line) for line in (folder / "log.jsonl").read_text().splitlines()]
    steps = [e["params"] for e in log if e["pass"] == "material"]
    before = json.loads((textured / "params.json").read_text())["params"]
    assert steps[-1]["roughness"] != before["roughness"]  # the pass did move it
    assert report["params"] == before
    scene = mi.traverse(mi.load_file(str(folder / "scene.xml")))
    assert np.ravel(scene["specimen.bsdf.roughness.value"])[0] == pytest.approx(before["roughness"][0], rel=1e-5)
    assert (folder / "base_color.exr").read_bytes() == (textured / "base_color.exr").read_bytes()


def test_export_writes_gltf_with_the_models_extensions(bird_capture):
    import struct

    outputs = run_stages(bird_capture, "export", *TINY_FIT, *TINY_TEXTURE, "fit_geometry.enabled=false")
    data = outputs["export"]["glb"].read_bytes()
    tree = json.loads(data[20 : 20 + struct.unpack("<I", data[12:16])[0]])
    material = tree["materials"][0]
    fitted = json.loads((outputs["fit_geometry"]["geometry_dir"] / "params.json").read_text())["params"]
    extensions = material["extensions"]
    assert extensions["KHR_materials_transmission"]["transmissionFactor"] == pytest.approx(fitted["spec_trans"][0])
    assert extensions["KHR_materials_ior"]["ior"] == pytest.approx(fitted["eta"][0])
    assert set(tree["extensionsUsed"]) == {"KHR_materials_transmission", "KHR_materials_ior"}
    # y up: the bird stands on y = 0.
    positions = tree["accessors"][tree["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
    assert positions["min"][1] > -0.005 and positions["max"][1] > 0.05
