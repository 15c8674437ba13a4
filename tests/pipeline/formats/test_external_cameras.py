"""Cameras from COLMAP and Metashape files, read into the pipeline's conventions.

The Metashape files here are written by this test from its documented conventions
(principal point as an offset from the image centre, pixel centres at +0.5, P1 and
P2 swapped against OpenCV, camera-to-chunk transforms, a chunk transform); no file
exported by Metashape itself is at hand to check against."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.camera.model import Intrinsics, Pose
from pipeline.core.errors import PipelineError
from pipeline.formats.external_cameras import read_colmap, read_external_cameras

CAMERA = Intrinsics(640, 480, 700.0, 702.0, 318.2, 243.9, [-0.1, 0.02, 0.001, -0.002, 0.0])
POSES = {
    f"IMG_{i}.JPG": Pose(
        Rotation.from_euler("xyz", [10 * i, 20, -5 * i], degrees=True).as_matrix(), np.array([0.1 * i, -0.2, 2.0])
    )
    for i in range(3)
}


def write_colmap(folder, intrinsics, poses):
    import pycolmap

    K = intrinsics
    model = pycolmap.Reconstruction()
    params = [K.fx, K.fy, K.cx + 0.5, K.cy + 0.5, *K.dist[:4]]
    model.add_camera_with_trivial_rig(
        pycolmap.Camera(model="OPENCV", width=K.width, height=K.height, params=params, camera_id=1)
    )
    for image_id, (name, pose) in enumerate(sorted(poses.items()), start=1):
        image = pycolmap.Image(name=f"photos/{name}", camera_id=1, image_id=image_id)
        model.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(pose.R), pose.t))
    folder.mkdir(parents=True)
    model.write_text(folder)
    return folder


def write_metashape(path, intrinsics, poses, chunk_scale=2.0, chunk_rotation=None, chunk_translation=(1.0, 2.0, 3.0)):
    """poses are world-to-camera in the *world*; the file holds them in chunk coordinates."""
    K = intrinsics
    chunk_rotation = np.eye(3) if chunk_rotation is None else chunk_rotation
    chunk = np.eye(4)
    chunk[:3, :3], chunk[:3, 3] = chunk_scale * chunk_rotation, chunk_translation
    cameras = []
    for index, (name, pose) in enumerate(sorted(poses.items())):
        camera_to_world = np.eye(4)
        camera_to_world[:3, :3], camera_to_world[:3, 3] = pose.R.T, pose.center
        camera_to_chunk = np.linalg.inv(chunk) @ camera_to_world
        values = " ".join(f"{v:.17g}" for v in camera_to_chunk.ravel())
        label = name.rsplit(".", 1)[0]
        cameras.append(f'<camera id="{index}" sensor_id="0" label="{label}"><transform>{values}</transform></camera>')
    k1, k2, p1, p2, k3 = K.dist
    path.write_text(
        f"""<?xml version="1.0" encoding="UTF-8"?>
<document version="1.5.0"><chunk label="Chunk 1" enabled="true">
<sensors next_id="1"><sensor id="0" label="phone" type="frame">
<resolution width="{K.width}" height="{K.height}"/>
<calibration type="frame" class="adjusted"><resolution width="{K.width}" height="{K.height}"/>
<f>{K.fy!r}</f><cx>{K.cx + 0.5 - K.width / 2!r}</cx><cy>{K.cy + 0.5 - K.height / 2!r}</cy><b1>{K.fx - K.fy!r}</b1>
<k1>{k1!r}</k1><k2>{k2!r}</k2><k3>{k3!r}</k3><p1>{p2!r}</p1><p2>{p1!r}</p2></calibration>
</sensor></sensors>
<cameras next_id="3" next_group_id="0">{"".join(cameras)}</cameras>
<transform><rotation>{" ".join(f"{v:.17g}" for v in chunk_rotation.ravel())}</rotation>
<translation>{" ".join(f"{v:.17g}" for v in chunk_translation)}</translation><scale>{chunk_scale!r}</scale></transform>
</chunk></document>"""
    )
    return path


def assert_same(read, intrinsics, poses):
    assert set(read.poses) == set(poses)
    for name, pose in poses.items():
        np.testing.assert_allclose(read.poses[name].R, pose.R, atol=1e-9)
        np.testing.assert_allclose(read.poses[name].t, pose.t, atol=1e-9)
        got = read.intrinsics[name]
        np.testing.assert_allclose(
            [got.width, got.height, got.fx, got.fy, got.cx, got.cy, *got.dist],
            [
                intrinsics.width,
                intrinsics.height,
                intrinsics.fx,
                intrinsics.fy,
                intrinsics.cx,
                intrinsics.cy,
                *intrinsics.dist,
            ],
            atol=1e-9,
        )


def test_a_colmap_model_reads_into_opencv_conventions(tmp_path):
    folder = write_colmap(tmp_path / "sparse", CAMERA, POSES)
    assert_same(read_colmap(folder, sorted(POSES)), CAMERA, POSES)
    # the path of one of its files works too, and photos it lacks are simply absent
    read = read_external_cameras(folder / "images.txt", [*sorted(POSES), "other.jpg"])
    assert read.tool == "COLMAP" and "other.jpg" not in read.poses


def test_a_metashape_export_reads_into_opencv_conventions(tmp_path):
    rotation = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    path = write_metashape(tmp_path / "cameras.xml", CAMERA, POSES, chunk_rotation=rotation)
    read = read_external_cameras(path, sorted(POSES))
    assert read.tool == "Metashape"
    assert_same(read, CAMERA, POSES)


def test_files_naming_other_photos_or_no_model_are_refused(tmp_path):
    folder = write_colmap(tmp_path / "sparse", CAMERA, POSES)
    with pytest.raises(PipelineError, match=r"names none of the photos in images/ \(it has e.g. photos/IMG_0.JPG"):
        read_colmap(folder, ["view_000.jpg"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(PipelineError, match="is not a COLMAP sparse model"):
        read_colmap(tmp_path / "empty", ["view_000.jpg"])
    (tmp_path / "bad.xml").write_text("<document><chunk>")
    with pytest.raises(PipelineError, match="is not valid XML"):
        read_external_cameras(tmp_path / "bad.xml", ["view_000.jpg"])
