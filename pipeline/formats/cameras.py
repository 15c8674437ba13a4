"""cameras.json (stage sfm; ``ground_truth/`` of a synthetic capture): pinhole
intrinsics and a world-to-camera pose per photo, and the world frame.

``{"convention", "intrinsics": the most common camera, "images": {name: {pose,
optional "intrinsics" of its own}}, "frame": {"source", "metric", "units", "up",
"ground_plane": [a, b, c, d] or null, ...}}``. Poses follow COLMAP: x_cam = R
x_world + t, camera x right, y down, z forward.
"""

from __future__ import annotations

import json
from pathlib import Path

from pipeline.camera.model import Intrinsics, Pose


def write_cameras(
    path: Path,
    intrinsics: Intrinsics | dict[str, Intrinsics],
    poses: dict[str, Pose],
    frame: dict | None = None,
) -> None:
    """The plain JSON camera file shared by ground truth and the sfm stage.

    ``intrinsics`` is one camera for all images, or one per image name (several
    camera settings); then each image entry carries its own and the top-level
    ``intrinsics`` is the most common one. ``frame`` describes the world frame.
    """
    if isinstance(intrinsics, Intrinsics):
        common, own = intrinsics, {}
    else:
        settings = [json.dumps(i.to_json(), sort_keys=True) for i in intrinsics.values()]
        common = Intrinsics.from_json(json.loads(max(set(settings), key=settings.count)))
        own = {name: i for name, i in intrinsics.items() if i != common}
    data = {
        "convention": "COLMAP: x_cam = R x_world + t; camera x right, y down, z forward",
        "intrinsics": common.to_json(),
        "images": {
            name: {**pose.to_json(), **({"intrinsics": own[name].to_json()} if name in own else {})}
            for name, pose in sorted(poses.items())
        },
    }
    if frame is not None:
        data["frame"] = frame
    path.write_text(json.dumps(data, indent=1))


def read_cameras(path: Path) -> tuple[Intrinsics, dict[str, Pose]]:
    """The most common intrinsics and every image's pose."""
    data = json.loads(path.read_text())
    poses = {name: Pose.from_json(p) for name, p in data["images"].items()}
    return Intrinsics.from_json(data["intrinsics"]), poses


def read_views(path: Path) -> dict[str, tuple[Intrinsics, Pose]]:
    """Every image's own intrinsics and pose."""
    data = json.loads(path.read_text())
    common = Intrinsics.from_json(data["intrinsics"])
    return {
        name: (Intrinsics.from_json(entry["intrinsics"]) if "intrinsics" in entry else common, Pose.from_json(entry))
        for name, entry in data["images"].items()
    }


def read_frame(path: Path) -> dict:
    """The world frame's description (empty when the file has none)."""
    return json.loads(path.read_text()).get("frame", {})
