import json
import math

import cv2
import numpy as np
import OpenImageIO as oiio
import pytest
import trimesh

from pipeline.camera.board import board_to_world, make_charuco_board
from pipeline.camera.model import mesh_coverage
from pipeline.core.config import load_config
from pipeline.core.errors import PipelineError
from pipeline.core.sections import BoardSection, schema
from pipeline.formats.cameras import read_cameras
from pipeline.synthetic.synth import BIRD_CENTRE, SENSOR_WIDTH_MM, SynthOptions, specimen_poses, synthesize
from stages import STAGES
from tests.support.hard_turntable import hard_turntable_options

pytestmark = pytest.mark.slow


def test_capture_has_photos_calibration_and_ground_truth(tiny_capture):
    photos = sorted((tiny_capture / "images").glob("*.jpg"))
    assert len(photos) == 6
    assert len(list((tiny_capture / "calibration").glob("*.jpg"))) == 3
    truth = tiny_capture / "ground_truth"
    for name in ("cameras.json", "mesh.ply", "material.json", "light.json", "board.json", "synth.json"):
        assert (truth / name).is_file(), name
    assert len(list((truth / "masks").glob("*.png"))) == 6
    image = cv2.imread(str(photos[0]))
    assert image.shape == (72, 96, 3) and image.dtype == np.uint8


def test_capture_toml_is_valid_user_config(tiny_capture):
    config = load_config(schema(STAGES), tiny_capture)
    assert config["capture"].rig == "handheld" and config["capture"].material == "principled"
    assert config["board"] == BoardSection()


def test_photos_carry_exif_focal_length(tiny_capture):
    intrinsics, _ = read_cameras(tiny_capture / "ground_truth" / "cameras.json")
    spec = oiio.ImageInput.open(str(tiny_capture / "images" / "view_000.jpg")).spec()
    assert spec.getattribute("Make") == "pipeline-synth"
    expected_mm = intrinsics.fx * SENSOR_WIDTH_MM / intrinsics.width
    assert spec.getattribute("Exif:FocalLength") == pytest.approx(expected_mm, rel=1e-3)


def test_mesh_projected_with_true_cameras_matches_true_masks(tiny_capture):
    """Poses, intrinsics, distortion, mesh frame and masks agree with each other."""
    intrinsics, poses = read_cameras(tiny_capture / "ground_truth" / "cameras.json")
    mesh = trimesh.load(tiny_capture / "ground_truth" / "mesh.ply")
    assert mesh.is_watertight
    for name, pose in poses.items():
        mask = cv2.imread(str(tiny_capture / "ground_truth" / "masks" / name.replace(".jpg", ".png")), 0) > 0
        silhouette = mesh_coverage(mesh.vertices, mesh.faces, intrinsics, pose) > 0.5
        iou = (mask & silhouette).sum() / (mask | silhouette).sum()
        assert iou > 0.95, f"{name}: IoU {iou:.3f}"  # 0.96-0.98 at 96x72 px; 0.994 at 400x300


def test_photos_are_noisy_srgb_renders_of_a_mottled_specimen(tiny_capture):
    image = cv2.imread(str(tiny_capture / "images" / "view_000.jpg")).astype(float)
    mask = cv2.imread(str(tiny_capture / "ground_truth" / "masks" / "view_000.png"), 0) > 0
    specimen = image[mask]
    assert specimen.std(axis=0).mean() > 8  # blotches, not a flat colour
    assert 40 < image[~mask].mean() < 220  # exposed sensibly


def test_board_pose_from_a_photo_matches_the_ground_truth(tmp_path):
    """ChArUco detection + PnP with the true intrinsics recovers pose @ board_to_world."""
    capture = synthesize(
        tmp_path / "c",
        SynthOptions(views=2, width=480, height=360, spp=8, calibration_shots=0, rings=(40.0,), noise=0.5),
    )
    intrinsics, poses = read_cameras(capture / "ground_truth" / "cameras.json")
    board = BoardSection()
    charuco, B = make_charuco_board(board), board_to_world(board)
    detector = cv2.aruco.CharucoDetector(charuco)
    for name, pose in poses.items():
        corners, ids, _, _ = detector.detectBoard(cv2.imread(str(capture / "images" / name), 0))
        assert ids is not None and len(ids) >= 6, name
        object_points, image_points = charuco.matchImagePoints(corners, ids)
        _, rvec, tvec = cv2.solvePnP(object_points, image_points, intrinsics.K, np.array(intrinsics.dist))
        true_R, true_t = pose.R @ B[:3, :3], pose.R @ B[:3, 3] + pose.t
        angle = math.degrees(np.arccos(np.clip((np.trace(cv2.Rodrigues(rvec)[0].T @ true_R) - 1) / 2, -1, 1)))
        assert angle < 0.5 and np.linalg.norm(tvec.ravel() - true_t) < 0.002
        reprojected, _ = cv2.projectPoints(
            object_points, cv2.Rodrigues(true_R)[0], true_t, intrinsics.K, np.array(intrinsics.dist)
        )
        assert np.linalg.norm(reprojected.reshape(-1, 2) - image_points.reshape(-1, 2), axis=1).mean() < 0.5


def test_turntable_with_uneven_steps_and_volumetric_material(tmp_path):
    capture = synthesize(
        tmp_path / "t",
        SynthOptions(
            views=5,
            width=64,
            height=48,
            spp=2,
            calibration_shots=0,
            rig="turntable",
            turn_jitter=0.5,
            material="volumetric",
            rings=(30.0,),
        ),
    )
    _, poses = read_cameras(capture / "ground_truth" / "cameras.json")
    centres = np.array([p.center for p in poses.values()])
    assert np.ptp(centres[:, 2]) < 1e-9  # one ring around the z axis
    assert np.ptp(np.linalg.norm(centres[:, :2], axis=1)) < 1e-9
    azimuths = np.unwrap(np.arctan2(centres[:, 1], centres[:, 0]))
    steps = np.diff(azimuths)
    assert np.all(steps > 0) and steps.max() / steps.min() > 1.2  # uneven, in file-name order
    config = load_config(schema(STAGES), capture)
    assert config["capture"].rig == "turntable" and config["light"].frame == "camera"
    material = json.loads((capture / "ground_truth" / "material.json").read_text())
    assert material["model"] == "volumetric" and material["sigma_t"] > 0 and material["texture"] is None


def test_refuses_a_non_empty_folder(tmp_path):
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "keep.txt").write_text("mine")
    with pytest.raises(PipelineError, match="is not empty"):
        synthesize(tmp_path / "x", SynthOptions(views=2, width=32, height=32))


def _hard_turntable(tmp_path, backdrop: str):
    """The twin of a hard real turntable, tiny: a glossy plain specimen on a dark plate with
    dots, no board, no EXIF focal length."""
    options = hard_turntable_options(views=4, width=64, height=48, spp=2, backdrop=backdrop, noise=0.0)
    return synthesize(tmp_path / backdrop, SynthOptions(**options))


def test_a_hard_turntable_twin_has_a_room_a_dotted_plate_and_no_board(tmp_path):
    capture = _hard_turntable(tmp_path, "room")
    config = load_config(schema(STAGES), capture)
    assert config["board"].kind == "none" and config["capture"].material == "opaque"
    assert config["light"].environment_map == "ground_truth/room.exr"
    room = oiio.ImageBuf(str(capture / "ground_truth" / "room.exr"))
    assert room.spec().width == 2 * room.spec().height  # an equirectangular map
    spec = oiio.ImageInput.open(str(capture / "images" / "view_000.jpg")).spec()
    assert spec.getattribute("Exif:FocalLength") is None
    material = json.loads((capture / "ground_truth" / "material.json").read_text())
    assert material["model"] == "opaque" and material["roughness"] < 0.2
    # The room is still: a fixed camera sees the same background in every photo.
    first, last = (cv2.imread(str(capture / "images" / f"view_00{i}.jpg")) for i in (0, 3))
    assert np.abs(first[:8].astype(int) - last[:8]).mean() < 3  # the top rows: room only
    assert first[:8].std() > 5  # and it is textured


def test_photos_cut_out_on_white_are_white_off_the_specimen(tmp_path):
    capture = _hard_turntable(tmp_path, "white")
    for photo in sorted((capture / "images").glob("*.jpg")):
        pixels = cv2.imread(str(photo))
        mask = cv2.imread(str(capture / "ground_truth" / "masks" / photo.name.replace(".jpg", ".png")), 0) > 0
        outside = cv2.erode((~mask).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        assert np.percentile(pixels[outside], 1) >= 250 and pixels[mask].mean() < 200  # JPEG rings at edges


def test_a_hand_turned_table_alternates_restarts_goes_round_again_and_wobbles():
    """The turntable's camera path as the randomised pose suite draws it: steps alternating
    short and long, a turn back half-way, part of a second turn, the specimen shifted."""
    options = SynthOptions(
        rig="turntable",
        views=20,
        rings=(30.0,),
        turn_alternation=2.0,
        turn_restart_deg=10.0,
        extra_turn=0.5,
        wobble=0.01,
    )
    poses = specimen_poses(options, np.random.default_rng(0))
    offsets = np.array([pose.center - BIRD_CENTRE for pose in poses])
    steps = np.diff(np.degrees(np.unwrap(np.arctan2(offsets[:, 1], offsets[:, 0]))))
    pairs = np.array([k for k in range(0, 18, 2) if k != 8])  # short then long, but for the restart's
    np.testing.assert_allclose(steps[pairs + 1] / steps[pairs], 2.0)
    assert steps[9] + 10.0 == pytest.approx(2 * steps[8])  # the turn back half-way
    assert steps.sum() + 10.0 > 450.0  # one turn and most of half another
    heights = offsets[:, 2]
    np.testing.assert_allclose(heights[10:] - heights[:10], 0.01 * options.distance, atol=1e-12)


def test_a_turntable_in_sets_moves_the_camera_restarts_and_turns_the_specimen_over(tmp_path):
    """Two sets: the second from higher up and nearer, starting 15 degrees back from
    where the first ended, the specimen turned over. The truth is in the specimen's
    frame: its mesh seen from every true camera covers the true mask, the turned-over
    set's included."""
    options = SynthOptions(
        rig="turntable", views=5, set_views=(3, 2), rings=(20.0, 35.0), set_distances=(1.0, 0.8),
        set_restarts_deg=(0.0, 15.0), sets_turned_over=(2,), width=96, height=96, spp=2,
        calibration_shots=0, table="grey", texture="plain", noise=0.0,
    )  # fmt: skip
    offsets = np.array([pose.center - BIRD_CENTRE for pose in specimen_poses(options, np.random.default_rng(0))])
    distances = np.linalg.norm(offsets, axis=1)
    np.testing.assert_allclose(np.degrees(np.arcsin(offsets[:, 2] / distances)), [20, 20, 20, 35, 35], atol=1e-9)
    np.testing.assert_allclose(distances / options.distance, [1, 1, 1, 0.8, 0.8])
    azimuths = np.degrees(np.arctan2(offsets[:, 1], offsets[:, 0]))
    assert azimuths[3] == pytest.approx(azimuths[2] - 15.0)
    capture = synthesize(tmp_path / "sets", options)
    intrinsics, poses = read_cameras(capture / "ground_truth" / "cameras.json")
    mesh = trimesh.load(capture / "ground_truth" / "mesh.ply", force="mesh")
    for name, pose in poses.items():
        mask = cv2.imread(str(capture / "ground_truth" / "masks" / name.replace(".jpg", ".png")), 0) > 0
        silhouette = mesh_coverage(mesh.vertices, mesh.faces, intrinsics, pose) > 0.5
        assert (mask & silhouette).sum() / (mask | silhouette).sum() > 0.9, name
    # Seen from the turned-over set, the specimen's underside faces up: its cameras look
    # at it from below its own horizon.
    assert all(poses[f"view_{i:03d}.jpg"].center[2] < BIRD_CENTRE[2] for i in (3, 4))


def test_sets_that_do_not_add_up_are_refused(tmp_path):
    with pytest.raises(PipelineError, match="--views 7"):
        synthesize(tmp_path / "x", SynthOptions(rig="turntable", views=6, set_views=(3, 4), width=32, height=32))


def test_a_vase_shows_the_same_outline_from_every_side_of_a_turn():
    from pipeline.synthetic.specimen import vase_mesh

    vase = vase_mesh()
    assert vase.is_watertight and vase.volume > 0
    radius, height = np.hypot(*vase.vertices[:, :2].T), np.round(vase.vertices[:, 2], 9)
    for level in np.unique(height):  # every ring of vertices off the axis lies at one radius
        ring = radius[(height == level) & (radius > 1e-9)]
        assert len(ring) == 0 or np.ptp(ring) < 1e-9
    base, neck = radius[(height > 0) & (height < 0.01)].max(), radius[(height > 0.08) & (height < 0.09)].max()
    assert base > neck + 0.005  # not the same shape upside down
