"""Stage sfm on the bundled sample bird (30 views, 560x420, the smallest capture on which SIFT
registers every view), a synthetic turntable and, when present, the real porous cube."""

import json
import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import trimesh

from pipeline.camera.model import Intrinsics, Pose, similarity_umeyama
from pipeline.core.errors import PipelineError
from pipeline.formats.cameras import read_cameras, read_views
from pipeline.formats.pinhole import read_camera_settings
from pipeline.synthetic.score import score_cameras
from tests.support.real_captures import SHARED_CAPTURES

pytestmark = pytest.mark.slow


SAMPLE = Path(__file__).parents[2] / "sample_captures" / "bird"


POROUS_CUBE = SHARED_CAPTURES / "porous-cube"
DINO_SPARSE_RING = SHARED_CAPTURES / "dino-sparse-ring"
OXFORD_DINO = SHARED_CAPTURES / "oxford-dino"


def test_sfm_registers_every_photo_in_the_board_frame(bird_until_uv):
    capture, outputs = bird_until_uv
    _, truth = read_cameras(capture / "ground_truth" / "cameras.json")
    views = read_views(outputs["sfm"]["cameras"])
    assert sorted(views) == sorted(truth)  # keyed by the original photo names
    metrics, _ = score_cameras({n: pose for n, (_, pose) in views.items()}, truth)
    assert metrics["rotation_error_deg_median"] <= 0.5
    # Board frame: metric and identical to the synthetic world, without any alignment.
    offsets = [np.linalg.norm(views[n][1].center - truth[n].center) for n in truth]
    assert np.median(offsets) < 0.004
    frame = json.loads(outputs["sfm"]["cameras"].read_text())["frame"]
    assert frame["source"] == "board" and frame["metric"]


def test_sfm_writes_a_colmap_model_in_the_same_frame(bird_until_uv):
    _, outputs = bird_until_uv
    model = pycolmap.Reconstruction(outputs["sfm"]["sparse"])
    views = read_views(outputs["sfm"]["cameras"])
    assert model.num_reg_images() == len(views)
    for image in model.images.values():
        name = image.name.replace(".png", ".jpg")
        np.testing.assert_allclose(image.projection_center(), views[name][1].center, atol=1e-6)
    report = json.loads(outputs["sfm"]["report"].read_text())
    assert report["mean_reprojection_error_px"] < 1.0 and report["mean_track_length"] > 3


def test_too_few_registered_photos_names_them(run_stages, tmp_path):
    capture = Path(shutil.copytree(SAMPLE, tmp_path / "bird", ignore=shutil.ignore_patterns(".pipeline", "output")))
    import cv2

    # Featureless frames (a lens cap, a blue wall) among a few of the bird's photos.
    photos = sorted((capture / "images").glob("*.jpg"))
    for path in photos[12:]:
        path.unlink()
    for index, path in enumerate(photos[:8]):
        cv2.imwrite(str(path), np.full((420, 560, 3), (40 + 8 * index, 90, 160), np.uint8))
    with pytest.raises(PipelineError, match=r"only \d+ of 12 photos registered.*view_000\.jpg"):
        run_stages(capture, "sfm", "undistort.max_size=280", "masks.working_size=280")


@pytest.fixture(scope="module")
def plain_turntable(synth_capture) -> Path:
    """Twelve photos at 384x288 of a plain bird on a hand-turned table (steps 30 degrees
    +-50 %), with board shots."""
    return synth_capture(
        "turntable",
        views=12,
        rings=(30.0,),
        width=384,
        height=288,
        spp=8,
        rig="turntable",
        turn_jitter=0.5,
        texture="plain",
        calibration_shots=12,
        seed=3,
    )


def test_turntable_of_a_plain_specimen_poses_every_photo_within_a_degree(run_stages, plain_turntable):
    """Some steps are too far apart for neighbours to match, and the board's squares match
    themselves from the other side: the board's poses start the circle, features
    place most photos, the rest by board pose or silhouette; none is left out or stacked."""
    capture = plain_turntable
    outputs = run_stages(capture, "sfm")
    # the photos show the board, which turns with the specimen: not the set's colours
    status = json.loads((outputs["masks"]["masks_json"].parent / "status.json").read_text())
    assert status["metrics"]["segmenter"] == "neutral_backdrop"
    _, truth = read_cameras(capture / "ground_truth" / "cameras.json")
    views = read_views(outputs["sfm"]["cameras"])
    assert sorted(views) == sorted(truth)
    metrics, _ = score_cameras({n: pose for n, (_, pose) in views.items()}, truth)
    assert metrics["rotation_error_deg_max"] < 1.0
    report = json.loads(outputs["sfm"]["report"].read_text())["circular"]
    assert sum(len(names) for names in report["pose_source"].values()) == 12
    angles = [report["angle_deg"][n] for n in sorted(truth)]
    assert np.all(np.diff(angles) > 5)  # in turning order, none at another's angle
    # The outlines were fitted with the features, and the report says how well each agreed.
    coherence = report["silhouette_coherence"]
    assert coherence["pairs"] > 0 and 0 < coherence["tangency_sigma_px"] < 2.0


def test_a_turntables_given_intrinsics_are_held_by_sfm(run_stages, plain_turntable):
    """calibrate.known_intrinsics with the focal length 5 % off on purpose: the board shots
    go unused and sfm keeps that focal length (undistort's pinhole of it), where a guessed
    one would have been refined."""
    truth, _ = read_cameras(plain_turntable / "ground_truth" / "cameras.json")
    given = Intrinsics(truth.width, truth.height, 1.05 * truth.fx, 1.05 * truth.fy, truth.cx, truth.cy, truth.dist)
    (plain_turntable / "given.json").write_text(json.dumps(given.to_json()))
    outputs = run_stages(plain_turntable, "sfm", "calibrate.known_intrinsics='given.json'")
    (group,) = json.loads(outputs["calibrate"]["calibration"].read_text())["groups"]
    assert group["source"] == "known"
    (camera,) = read_camera_settings(outputs["undistort"]["pinhole"])
    pinhole = Intrinsics.from_json(camera["intrinsics"])  # the given camera, undistorted
    held, poses = read_cameras(outputs["sfm"]["cameras"])
    assert len(poses) >= 10
    assert held.fx == pytest.approx(pinhole.fx, rel=1e-9) and held.cx == pytest.approx(pinhole.cx, abs=1e-9)
    report = json.loads(outputs["sfm"]["report"].read_text())["circular"]["self_calibration"]
    assert "calibrate.known_intrinsics" in report["skipped"]


@pytest.mark.real_data
@pytest.mark.skipif(not POROUS_CUBE.is_dir(), reason="../shared/captures/porous-cube is not here")
def test_porous_cube_registers_all_but_the_room_shot_and_meshes_a_closed_box(run_stages, tmp_path):
    """Every second photo of the porous cube (white on a white table, no board) plus
    the unrelated room shot: the room shot alone is left out, and the cleaned mesh is
    one closed, box-like surface (a box fills its oriented box; a sphere fills 0.52)."""
    photos = sorted((POROUS_CUBE / "images").glob("*.jpg"))
    room_shot = photos[0]
    (tmp_path / "images").mkdir()
    for photo in [room_shot, *photos[1::2]]:
        (tmp_path / "images" / photo.name).symlink_to(photo)
    (tmp_path / "capture.toml").write_text('[board]\nkind = "none"\n\n[masks]\nsegmenter = "centre_prior"\n')
    outputs = run_stages(tmp_path, "cleanup")
    report = json.loads(outputs["sfm"]["report"].read_text())
    assert set(read_views(outputs["sfm"]["cameras"])) == {p.name for p in photos[1::2]}
    assert report["frame"]["source"] == "ground_plane"
    mesh = trimesh.load(outputs["cleanup"]["mesh"], force="mesh")
    assert mesh.is_watertight and mesh.euler_number == 2
    assert mesh.volume / mesh.bounding_box_oriented.volume > 0.7


@pytest.mark.real_data
@pytest.mark.skipif(not DINO_SPARSE_RING.is_dir(), reason="../shared/captures/dino-sparse-ring is not here")
def test_dino_sparse_ring_closes_its_broken_ring_through_the_arcs_outlines(run_stages, tmp_path):
    """Middlebury's 16 photos of a textureless plaster dinosaur, 23.5 degrees apart: matching
    leaves two arcs of the ring apart, and the smaller is joined to the ring by its outlines
    and solved with it. Turn angles against the calibrated reference, their common offset
    removed."""
    _linked_capture(tmp_path, DINO_SPARSE_RING, "ring")
    outputs = run_stages(tmp_path, "sfm")
    report = json.loads(outputs["sfm"]["report"].read_text())["circular"]
    assert any(group["joined"] and len(group["photos"]) >= 5 for group in report["joined_groups"])
    _, poses = read_cameras(outputs["sfm"]["cameras"])
    assert len(poses) >= 14
    reference = {}
    for line in (DINO_SPARSE_RING / "reference" / "dinoSR_par.txt").read_text().splitlines()[1:]:
        name, *values = line.split()
        R, t = np.array(values[9:18], float).reshape(3, 3), np.array(values[18:21], float)
        reference[name] = -R.T @ t
    errors = _turn_angle_errors_deg(report["angle_deg"], reference)
    assert np.median(errors) < 0.5 and errors.max() < 1.5


def _linked_capture(folder: Path, source: Path, rig: str) -> None:
    """A capture in ``folder`` of ``source``'s photos (linked) on ``rig``, without a board."""
    (folder / "images").mkdir()
    for photo in sorted((source / "images").glob("*.png")):
        (folder / "images" / photo.name).symlink_to(photo)
    (folder / "capture.toml").write_text(f'[capture]\nrig = "{rig}"\n\n[board]\nkind = "none"\n')


def _turn_angle_errors_deg(angles_deg: dict[str, float], reference_centres: dict[str, np.ndarray]) -> np.ndarray:
    """Each placed photo's turn angle (sfm.json's ``angle_deg``) against the reference
    camera centres' angle about their ring's centre, their common offset removed."""
    names = sorted(angles_deg)
    centres = np.array([reference_centres[n] for n in sorted(reference_centres)])
    u, v, _ = np.linalg.svd(centres - centres.mean(axis=0))[2]  # the reference ring's plane
    plane = np.column_stack([(centres - centres.mean(axis=0)) @ u, (centres - centres.mean(axis=0)) @ v])
    # The ring's centre: a least-squares circle (the photos do not cover it evenly).
    a, b, _ = np.linalg.lstsq(np.column_stack([plane, np.ones(len(plane))]), np.sum(plane**2, axis=1), rcond=None)[0]
    true = np.array([reference_centres[n] for n in names]) - centres.mean(axis=0)
    true_angle = np.arctan2(true @ v - b / 2, true @ u - a / 2)
    estimated = np.radians([angles_deg[n] for n in names])
    for sign in (1, -1):  # the reference may turn the other way round
        difference = np.angle(np.exp(1j * (sign * estimated - true_angle)))
        errors = np.degrees(np.abs(np.angle(np.exp(1j * (difference - np.angle(np.mean(np.exp(1j * difference))))))))
        if np.median(errors) < 5:
            break
    return errors


@pytest.mark.real_data
@pytest.mark.skipif(not OXFORD_DINO.is_dir(), reason="../shared/captures/oxford-dino is not here")
def test_oxford_dino_turntable_places_every_photo_at_its_turn_angle_and_centre(run_stages, tmp_path):
    """The Oxford turntable dinosaur, 36 photos 10 degrees apart, no board: every photo
    placed, turn angles and camera centres against its projective turntable reference
    (whose centres lie on an exact circle of radius 1; its viewing directions are good to
    a few degrees only and are not scored here)."""
    _linked_capture(tmp_path, OXFORD_DINO, "turntable")
    outputs = run_stages(tmp_path, "sfm")
    report = json.loads(outputs["sfm"]["report"].read_text())["circular"]
    _, poses = read_cameras(outputs["sfm"]["cameras"])
    assert len(poses) == 36
    reference = {}
    for line in (OXFORD_DINO / "reference" / "cameras.txt").read_text().splitlines():
        name, *values = line.split()
        if name.endswith(".png"):
            R, t = np.array(values[5:14], float).reshape(3, 3), np.array(values[14:17], float)
            reference[name] = -R.T @ t
    errors = _turn_angle_errors_deg(report["angle_deg"], reference)
    assert np.median(errors) < 0.5 and errors.max() < 1.5
    names = sorted(poses)
    estimated, true = np.array([poses[n].center for n in names]), np.array([reference[n] for n in names])
    scale, R, t = similarity_umeyama(estimated, true)
    moved = scale * estimated @ R.T + t
    assert np.sqrt(np.mean(np.sum((moved - true) ** 2, axis=1))) < 0.01  # of the radius, 1


@pytest.mark.real_data
@pytest.mark.skipif(not DINO_SPARSE_RING.is_dir(), reason="../shared/captures/dino-sparse-ring is not here")
def test_dino_sparse_ring_with_its_calibration_given_places_every_viewing_direction_within_a_degree(
    run_stages, tmp_path
):
    """Its principal point sits 40 px above the centre row, which one circular motion cannot
    find; given Middlebury's K as calibrate.known_intrinsics, sfm holds it and every photo's
    viewing direction lands within a degree of the reference (similarity-aligned centres)."""
    _linked_capture(tmp_path, DINO_SPARSE_RING, "ring")
    reference = {}
    for line in (DINO_SPARSE_RING / "reference" / "dinoSR_par.txt").read_text().splitlines()[1:]:
        name, *values = line.split()
        K, R, t = (np.array(values[a:b], float) for a, b in ((0, 9), (9, 18), (18, 21)))
        reference[name] = Pose(R.reshape(3, 3), t)
    K = K.reshape(3, 3)  # every line has the same K
    known = {"width": 640, "height": 480, "fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}
    (tmp_path / "known.json").write_text(json.dumps(known))
    with (tmp_path / "capture.toml").open("a") as settings:
        settings.write('\n[calibrate]\nknown_intrinsics = "known.json"\n')
    outputs = run_stages(tmp_path, "sfm")
    intrinsics, poses = read_cameras(outputs["sfm"]["cameras"])
    assert intrinsics.cx == pytest.approx(K[0, 2]) and intrinsics.cy == pytest.approx(K[1, 2])
    assert len(poses) == 16
    names = sorted(poses)
    _, R, _ = similarity_umeyama(
        np.array([poses[n].center for n in names]), np.array([reference[n].center for n in names])
    )
    directions = [np.degrees(np.arccos(np.clip(reference[n].R[2] @ (R @ poses[n].R[2]), -1, 1))) for n in names]
    assert max(directions) < 1.0


def test_cameras_from_another_tool_replace_calibration_and_sfm(run_stages, tiny_capture, tmp_path):
    from pipeline.camera.model import Similarity
    from pipeline.formats.cameras import read_cameras, read_frame
    from tests.support.byo_capture import byo_capture

    capture = byo_capture(tiny_capture, tmp_path / "byo")
    outputs = run_stages(capture, "sfm", "cameras.source='external'")
    truth_K, truth = read_cameras(capture / "ground_truth" / "cameras.json")
    (group,) = json.loads(outputs["calibrate"]["calibration"].read_text())["groups"]
    assert group["source"] == "external" and group["intrinsics"]["dist"] == truth_K.dist
    assert abs(group["intrinsics"]["cx"] - truth_K.cx) < 1e-9
    _, poses = read_cameras(outputs["sfm"]["cameras"])
    assert set(poses) == set(truth)  # every photo posed, none by SfM
    from_source = Similarity.from_json(read_frame(outputs["sfm"]["cameras"])["from_source"])
    for name, pose in truth.items():
        moved = from_source.pose(pose)
        np.testing.assert_allclose(poses[name].R, moved.R, atol=1e-9)
        np.testing.assert_allclose(poses[name].t, moved.t, atol=1e-6)
    assert json.loads(outputs["sfm"]["report"].read_text())["poses_from"] == "[cameras] source = external"


def test_without_a_board_the_lens_distortion_is_self_calibrated_and_the_principal_point_held(run_stages, tmp_path):
    """The sample bird as if no board had been photographed: focal length from EXIF, the
    lens' barrel distortion left in the photos. Bundle adjustment finds k1 (constrained:
    adjusted) and tries the principal point, which 30 views on two rings constrain only
    to a few pixels: held at the centre, with the reason in sfm.json."""
    capture = Path(shutil.copytree(SAMPLE, tmp_path / "bird", ignore=shutil.ignore_patterns(".pipeline", "output")))
    outputs = run_stages(capture, "sfm", "board.kind='none'")
    report = json.loads(outputs["sfm"]["report"].read_text())
    (calibration,) = report["self_calibration"].values()
    values = calibration["values"]
    true_K, truth = read_cameras(capture / "ground_truth" / "cameras.json")
    assert values["k1"]["adjusted"] and abs(values["k1"]["value"] - true_K.dist[0]) < 0.02
    assert values["k1"]["std"] < 0.02
    assert abs(values["f"]["value"] / true_K.fx - 1) < 0.02
    assert not values["cx"]["adjusted"] and "standard deviation" in calibration["held"]["principal_point"]
    assert report["residual_distortion"]["k1"] == values["k1"]["value"]
    metrics, _ = score_cameras({n: pose for n, (_, pose) in read_views(outputs["sfm"]["cameras"]).items()}, truth)
    assert metrics["registered"] == 30 and metrics["rotation_error_deg_median"] < 1.0
