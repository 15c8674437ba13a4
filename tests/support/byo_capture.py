"""A synthetic capture whose cameras and mesh come "from another tool": its ground
truth written as a COLMAP text model (external/) next to the true mesh."""

from __future__ import annotations

import shutil
from pathlib import Path

from pipeline.formats.cameras import read_cameras


def byo_capture(source: Path, folder: Path) -> Path:
    import pycolmap

    capture = shutil.copytree(source, folder, ignore=shutil.ignore_patterns(".pipeline", "output"))
    K, poses = read_cameras(capture / "ground_truth" / "cameras.json")
    model = pycolmap.Reconstruction()
    params = [K.fx, K.fy, K.cx + 0.5, K.cy + 0.5, *K.dist[:4]]
    camera = pycolmap.Camera(model="OPENCV", width=K.width, height=K.height, params=params, camera_id=1)
    model.add_camera_with_trivial_rig(camera)
    for image_id, (name, pose) in enumerate(sorted(poses.items()), start=1):
        image = pycolmap.Image(name=name, camera_id=1, image_id=image_id)
        model.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(pose.R), pose.t))
    (capture / "external").mkdir()
    model.write_text(capture / "external")
    return capture
