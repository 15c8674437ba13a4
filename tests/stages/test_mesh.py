"""Stage mesh on the bundled sample bird, and reruns of the geometry stages."""

import json

import pytest
import trimesh

from pipeline.camera.model import Similarity
from pipeline.formats.cameras import read_frame
from pipeline.synthetic.score import score_mesh

pytestmark = pytest.mark.slow


def test_mesh_is_a_watertight_specimen_close_to_the_truth(bird_until_uv):
    capture, outputs = bird_until_uv
    truth = trimesh.load(capture / "ground_truth" / "mesh.ply", force="mesh")
    for stage in ("mesh", "cleanup", "uv"):
        mesh = trimesh.load(outputs[stage]["mesh"], force="mesh")
        scores = score_mesh(mesh, truth)
        assert scores["chamfer_pct_of_diagonal"] <= 1.5, (stage, scores)
        assert mesh.bounds[0][2] > -0.002  # cut at the board, nothing of the table below
    cleaned = json.loads(outputs["cleanup"]["report"].read_text())["after"]
    assert cleaned["watertight"] and cleaned["genus"] == 0 and cleaned["components"] == 1
    assert cleaned["faces"] <= 20000


def test_rerun_gives_the_same_poses_and_mesh(run_stages, bird_until_uv):
    """COLMAP's defaults numbered photos in the order extraction threads finished and
    seeded RANSAC from the clock: reruns on bird_volumetric gave rotation errors from
    0.7 to 164 degrees. pymeshlab's Poisson reconstruction ordered its vertices
    differently on every run, and decimation and UV charts follow that order.
    Threaded OpenCV calibration varied the intrinsics in the 11th digit."""
    capture, outputs = bird_until_uv
    first_cameras, first_mesh = outputs["sfm"]["cameras"].read_bytes(), outputs["mesh"]["mesh"].read_bytes()
    # cleanup and uv are functions of the mesh: the same mesh, vertex for vertex, gives them the same input
    rerun = run_stages(capture, "mesh", force=("sfm",))  # calibrate's rerun: tests/stages/test_calibrate.py
    assert rerun["sfm"]["cameras"].read_bytes() == first_cameras
    assert rerun["mesh"]["mesh"].read_bytes() == first_mesh


def test_a_mesh_from_another_tool_follows_its_cameras_or_is_refused(run_stages, tiny_capture, tmp_path):
    import numpy as np
    import trimesh

    from pipeline.camera.model import Similarity
    from pipeline.core.errors import PipelineError
    from pipeline.formats.cameras import read_frame
    from tests.support.byo_capture import byo_capture

    capture = byo_capture(tiny_capture, tmp_path / "byo")
    overrides = ("cameras.source='external'", "mesh.source='ground_truth/mesh.ply'")
    outputs = run_stages(capture, "mesh", *overrides)
    truth = trimesh.load(capture / "ground_truth" / "mesh.ply", process=False)
    from_source = Similarity.from_json(read_frame(outputs["sfm"]["cameras"])["from_source"])
    mesh = trimesh.load(outputs["mesh"]["mesh"], process=False)
    np.testing.assert_allclose(mesh.vertices, from_source.points(truth.vertices), atol=1e-5)
    assert json.loads(outputs["mesh"]["report"].read_text())["silhouette_iou_median"] > 0.8
    truth.apply_translation([0.5 * truth.extents.max(), 0, 0])  # a mesh in some other frame
    truth.export(capture / "moved.ply")
    with pytest.raises(PipelineError, match=r"mesh.source = 'moved.ply': its outline overlaps the masks by 0\.\d\d"):
        run_stages(capture, "mesh", "cameras.source='external'", "mesh.source='moved.ply'")


def test_stereo_carves_the_hull_and_keeps_it_closed(run_stages, synth_capture, tmp_path):
    """The stage's plumbing of stereo (pipeline.geometry.stereo is tested on a dented
    cube): photos read at the cameras' pixels, depths found inside the masks, the
    carved surface still one closed specimen near the truth."""
    from tests.support.byo_capture import byo_capture

    # 12 photos, 30 degrees apart (stereo compares photos 3-45 degrees apart), too
    # small for sfm's features: the true cameras
    photos = synth_capture("stereo", views=12, width=120, height=90, spp=4, calibration_shots=3, seed=3)
    capture = byo_capture(photos, tmp_path / "byo")
    outputs = run_stages(capture, "mesh", "cameras.source='external'", "mesh.refine='stereo'")
    report = json.loads(outputs["mesh"]["report"].read_text())
    assert report["stereo_pixels_kept"] > 0.05  # 14 %: at 120 px, half a window along the outline is much
    assert report["stereo_voxels_carved"] < 0.2 * report["stereo_voxels_in_hull"]
    mesh = trimesh.load(outputs["mesh"]["mesh"], force="mesh")
    truth = trimesh.load(capture / "ground_truth" / "mesh.ply", force="mesh")
    from_source = Similarity.from_json(read_frame(outputs["sfm"]["cameras"])["from_source"])
    truth.apply_transform(from_source.matrix())
    assert mesh.is_watertight and score_mesh(mesh, truth)["chamfer_pct_of_diagonal"] <= 1.5


@pytest.mark.parametrize("damage", ["inf", "flat"])
def test_a_given_mesh_no_step_can_use_is_refused_at_once(run_stages, tiny_capture, tmp_path, damage):
    import numpy as np
    import trimesh

    from pipeline.core.errors import PipelineError
    from tests.support.byo_capture import byo_capture

    capture = byo_capture(tiny_capture, tmp_path / "byo")
    mesh = trimesh.load(capture / "ground_truth" / "mesh.ply", process=False)
    vertices = np.array(mesh.vertices)
    if damage == "flat":
        vertices[:] = vertices[0]
    else:
        vertices[::7] = np.nan if damage == "nan" else np.inf
    trimesh.Trimesh(vertices, mesh.faces, process=False).export(capture / "bad.ply")
    message = "every triangle has zero area" if damage == "flat" else "vertices are NaN or infinite"
    with pytest.raises(PipelineError, match=rf"mesh.source = 'bad.ply': .*bad.ply: .*{message}; repair or re-export"):
        run_stages(capture, "mesh", "cameras.source='external'", "mesh.source='bad.ply'")
