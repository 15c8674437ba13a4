"""Stage scene: lined up with the photos on the bundled sample bird (its board frame), and
each model's files on a small synthetic bird (after the geometry stages, shared through
the runner's cache)."""

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.formats.cameras import read_views
from pipeline.formats.scene_description import Integrator, SceneDescription

pytestmark = pytest.mark.slow


def test_scene_loads_renders_and_lines_up_with_the_photos(run_stages, bird_capture, mi):
    outputs = run_stages(bird_capture, "scene")["scene"]
    folder = outputs["scene_dir"]
    description = SceneDescription.read(outputs["description"])
    views = read_views(run_stages(bird_capture, "sfm")["sfm"]["cameras"])
    scene = mi.load_file(str(outputs["scene"]))
    assert len(scene.sensors()) == len(views) == len(description.views)
    root = ET.parse(folder / "specimen.xml").getroot()
    # Every shape, BSDF, medium and emitter has an id; the principled model has no medium.
    for file in [outputs["scene"], folder / "specimen.xml"]:
        for element in ET.parse(file).getroot().iter():
            if element.tag in ("shape", "bsdf", "medium", "emitter", "sensor"):
                assert element.get("id"), f"{file.name}: <{element.tag} type={element.get('type')}> has no id"
    assert root.find(".//medium") is None and description.model == "principled"
    assert description.integrator == Integrator(type="path", max_depth=8, differentiable="prb")
    # The specimen alone, rendered white on black from a photo's view file, covers its mask.
    name = sorted(views)[3]
    view_scene = mi.load_file(str(folder / description.views[name].xml))
    params = mi.traverse(view_scene)
    silhouette = mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "aov", "aovs": "depth:depth"},
            "specimen": {"type": "ply", "filename": str(folder / "mesh.ply")},
        }
    )
    depth = np.asarray(mi.render(silhouette, sensor=view_scene.sensors()[0], spp=4))[..., 0]
    masks_json = run_stages(bird_capture, "masks")["masks"]["masks_json"]
    mask = cv2.imread(str(masks_json.parent / json.loads(masks_json.read_text())["images"][name]["mask"]), 0) > 127
    covered = depth > 0
    assert np.count_nonzero(covered & mask) / np.count_nonzero(covered | mask) > 0.9
    assert "specimen.bsdf.roughness.value" in params.keys()


@pytest.mark.parametrize("model, medium, integrator", [("volumetric", True, "volpath"), ("opaque", False, "path")])
def test_each_model_writes_only_what_it_needs(run_stages, small_bird, mi, model, medium, integrator):
    outputs = run_stages(small_bird, "scene", f"scene.model={model}")["scene"]
    specimen = ET.parse(outputs["scene_dir"] / "specimen.xml").getroot()
    assert (specimen.find(".//medium") is not None) == medium
    names = {e.get("name") for e in specimen.find(".//bsdf").iter()}
    if model == "opaque":
        assert "spec_trans" not in names and "eta" not in names and "specular" in names
    assert json.loads(outputs["description"].read_text())["integrator"]["type"] == integrator
    mi.load_file(str(outputs["scene"]))


def test_the_scene_renders_with_the_mitsuba_command(run_stages, small_bird, mi, tmp_path):
    """The scene files name a render integrator the `mitsuba` command has (prb exists
    only in Python), so a user renders them as they are."""
    import subprocess
    import sys

    from pipeline.imaging.photo_io import read_photo

    folder = run_stages(small_bird, "scene", "scene.spp=1")["scene"]["scene_dir"]
    view = sorted(folder.glob("view-*.xml"))[0]
    command = Path(sys.executable).parent / "mitsuba"
    out = tmp_path / "render.exr"
    variant = mi.variant()
    done = subprocess.run([str(command), "-m", variant, "-o", str(out), str(view)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr + done.stdout
    assert read_photo(out, "linear").pixels.mean() > 0.01
