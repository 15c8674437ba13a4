"""Stage export: the glTF material mapping, model by model, and the stage on a small
synthetic bird."""

import json
import struct
from pathlib import Path

import numpy as np
import pytest
import trimesh

from stages.export import gltf_material
from tests.support.tiny_fits import TINY_FIT, TINY_TEXTURE


def test_volumetric_keeps_absorption_as_attenuation_at_the_mean_chord():
    values = {"alpha": [0.04], "eta": [1.4], "albedo": [0.9, 0.5, 1.0], "sigma_t": [200.0]}
    pbr, extensions = gltf_material("volumetric", values, thickness=0.01)
    assert pbr["roughnessFactor"] == pytest.approx(0.2)  # glTF roughness is sqrt(GGX alpha)
    volume = extensions["KHR_materials_volume"]
    assert volume["attenuationDistance"] == volume["thicknessFactor"] == 0.01
    # sigma_a = sigma_t (1 - albedo): 20, 100 and 0 per metre over 1 cm.
    np.testing.assert_allclose(volume["attenuationColor"], np.exp([-0.2, -1.0, 0.0]), rtol=1e-6)
    assert extensions["KHR_materials_transmission"]["transmissionFactor"] == 1.0


def test_opaque_specular_becomes_the_matching_index_of_refraction():
    values = {"base_color": [0.2, 0.3, 0.4], "roughness": [0.5], "specular": [0.5]}
    pbr, extensions = gltf_material("opaque", values, thickness=0.01)
    # specular 0.5 is F0 = 0.04, the reflectance of ior 1.5.
    assert extensions == {"KHR_materials_ior": {"ior": pytest.approx(1.5)}}
    assert pbr["baseColorFactor"] == [0.2, 0.3, 0.4, 1.0] and pbr["metallicFactor"] == 0.0


@pytest.mark.slow
def test_export_writes_gltf_with_the_models_extensions(run_stages, small_bird):
    outputs = run_stages(small_bird, "export", *TINY_FIT, *TINY_TEXTURE, "fit_geometry.enabled=false")
    data = outputs["export"]["glb"].read_bytes()
    tree = json.loads(data[20 : 20 + struct.unpack("<I", data[12:16])[0]])
    material = tree["materials"][0]
    fitted = json.loads(outputs["fit_geometry"]["params"].read_text())["params"]
    extensions = material["extensions"]
    assert extensions["KHR_materials_transmission"]["transmissionFactor"] == pytest.approx(fitted["spec_trans"][0])
    assert extensions["KHR_materials_ior"]["ior"] == pytest.approx(fitted["eta"][0])
    assert set(tree["extensionsUsed"]) == {"KHR_materials_transmission", "KHR_materials_ior", "KHR_materials_volume"}
    assert fitted["spec_trans"][0] > 0  # the bird is translucent: a clear solid, not a thin wall
    # The vertices and the normals Mitsuba shades with, turned from z up to y up (three.js
    # and Blender shade smooth).
    attributes = tree["meshes"][0]["primitives"][0]["attributes"]
    glb = trimesh.load(outputs["export"]["glb"], force="mesh", process=False)
    ply = trimesh.load(outputs["fit_geometry"]["geometry_dir"] / "mesh.ply", force="mesh", process=False)
    assert "NORMAL" in attributes and len(glb.vertex_normals) == len(ply.vertices)
    np.testing.assert_allclose(glb.vertices, ply.vertices[:, [0, 2, 1]] * [1, 1, -1], atol=1e-6)
    np.testing.assert_allclose(glb.vertex_normals, ply.vertex_normals[:, [0, 2, 1]] * [1, 1, -1], atol=1e-5)


@pytest.mark.slow
def test_no_result_file_holds_a_nan_or_an_infinity(run_stages, small_bird):
    """Every JSON (strictly parsed), scene file, EXR and the glTF's JSON of the fit
    stages and export: the writers refuse non-finite values (pipeline.core.errors)."""
    import re

    from pipeline.synthetic.score import read_linear_image

    outputs = run_stages(small_bird, "export", *TINY_FIT, *TINY_TEXTURE, "fit_geometry.enabled=false")

    def refuse(constant):
        raise AssertionError(f"non-finite constant {constant} in JSON")

    files = [
        path
        for stage in ("scene", "fit_material", "fit_texture", "fit_geometry", "export")
        for output in outputs[stage].values()
        for path in ([output] if output.is_file() else sorted(output.rglob("*")))
        if path.is_file()
    ]
    kinds = {p.suffix for p in files}
    assert {".json", ".xml", ".exr", ".glb"} <= kinds, kinds
    for path in files:
        if path.suffix == ".json":
            json.loads(path.read_text(), parse_constant=refuse)
        elif path.suffix == ".xml":
            assert not re.search(r"\b(nan|inf)\b", path.read_text(), re.IGNORECASE), path
        elif path.suffix == ".exr":
            assert np.all(np.isfinite(read_linear_image(path))), path
        elif path.suffix == ".glb":
            data = path.read_bytes()
            json.loads(data[20 : 20 + struct.unpack("<I", data[12:16])[0]], parse_constant=refuse)


@pytest.mark.parametrize(
    "model, values, volume",
    [
        ("opaque", {"base_color": [0.5, 0.4, 0.3], "roughness": [0.4], "specular": [0.5]}, None),
        ("principled", {"base_color": [0.5, 0.4, 0.3], "roughness": [0.4], "spec_trans": [0.0], "eta": [1.5]}, None),
        ("principled", {"base_color": [0.5, 0.4, 0.3], "roughness": [0.4], "spec_trans": [0.6], "eta": [1.4]}, "clear"),
        ("volumetric", {"alpha": [0.04], "eta": [1.4], "albedo": [0.9, 0.5, 1.0], "sigma_t": [200.0]}, "absorbing"),
    ],
    ids=["opaque", "principled", "principled-transmissive", "volumetric"],
)
def test_every_model_gives_a_glb_the_khronos_validator_passes(tmp_path, model, values, volume):
    from stages.export import specimen_glb
    from tests.support.gltf_viewers import validator_issues

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.02)
    path = tmp_path / "specimen.glb"
    path.write_bytes(specimen_glb(sphere, model, values, None))
    issues = validator_issues(path)
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"]
    data = path.read_bytes()
    extensions = json.loads(data[20 : 20 + struct.unpack("<I", data[12:16])[0]])["materials"][0]["extensions"]
    if volume is None:
        assert "KHR_materials_volume" not in extensions
    else:
        # A solid, not glTF's default thin wall: its thickness is the sphere's mean chord 4 r / 3.
        assert extensions["KHR_materials_volume"]["thicknessFactor"] == pytest.approx(4 * 0.02 / 3, rel=0.02)
        assert ("attenuationColor" in extensions["KHR_materials_volume"]) == (volume == "absorbing")


@pytest.mark.slow
def test_three_js_shows_the_glb_as_mitsuba_renders_the_scene(run_stages, small_bird, tmp_path, mi):
    """The glb, validated, then rendered by three.js in headless Chromium from a held-out
    photo's camera: its outline is the fitted mesh's in that view, and its colour (the
    mean's chromaticity over the specimen; the lights differ) the Mitsuba render's."""
    import shutil
    import xml.etree.ElementTree as ET

    from pipeline.camera.model import mesh_coverage, scaled
    from pipeline.formats.cameras import read_views
    from tests.support.gltf_viewers import three_js_renders, validator_issues

    outputs = run_stages(small_bird, "export", *TINY_FIT, *TINY_TEXTURE, "fit_geometry.enabled=false")
    glb = outputs["export"]["glb"]
    issues = validator_issues(glb)
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"]
    scene_dir = outputs["fit_geometry"]["geometry_dir"]
    name = json.loads(outputs["fit_material"]["params"].read_text())["held_out"][0]
    intrinsics, pose = read_views(outputs["sfm"]["cameras"])[name]
    view = (scaled(intrinsics, 160 / intrinsics.width), pose)
    outline, colour = three_js_renders(glb.read_bytes(), view, ("#ff00ff", "#808080"), tmp_path)
    seen = ~((outline[..., 0] > 0.9) & (outline[..., 1] < 0.05) & (outline[..., 2] > 0.9))
    mesh = trimesh.load(scene_dir / "mesh.ply", force="mesh", process=False)
    coverage = mesh_coverage(mesh.vertices, mesh.faces, *view)
    truth = coverage >= 0.5
    assert (seen & truth).sum() / (seen | truth).sum() > 0.85
    # Mitsuba's render of the same view at the same size.
    work = Path(shutil.copytree(scene_dir, tmp_path / "scene"))
    tree = ET.parse(work / f"view-{Path(name).stem}.xml")
    for entry in tree.iter("integer"):
        if entry.get("name") in ("width", "height"):
            entry.set("value", str(view[0].width if entry.get("name") == "width" else view[0].height))
    tree.write(work / "small.xml")
    rendered = np.asarray(mi.render(mi.load_file(str(work / "small.xml")), spp=32))
    inside = coverage >= 0.99
    three_mean, mitsuba_mean = colour[inside].mean(axis=0), rendered[inside].mean(axis=0)
    np.testing.assert_allclose(three_mean / three_mean.sum(), mitsuba_mean / mitsuba_mean.sum(), atol=0.03)
