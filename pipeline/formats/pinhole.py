"""pinhole.json (stage undistort): the undistorted photos and their cameras.

``cameras`` lists one entry per camera setting, ``{"camera", "calibrated_by",
"source", "intrinsics"}`` (what calibrated it: board, known, exif, prior or external; the
calibrated camera and the ideal pinhole the photos were remapped to); ``images``
and ``background`` map each photo or plate name to
``{"camera": index, "srgb": PNG, "linear": EXR, "encoding", "bits"}``, the paths
relative to the file's folder.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

Folder = Literal["images", "background"]


def write_pinhole(path: Path, cameras: list[dict], listing: dict[str, dict[str, dict]]) -> Path:
    path.write_text(json.dumps({"cameras": cameras, **listing}, indent=1))
    return path


def read_camera_settings(pinhole_json: Path) -> list[dict]:
    """Per camera setting: ``calibrated_by``, ``source`` and ``intrinsics`` (pinhole) as JSON."""
    return json.loads(pinhole_json.read_text())["cameras"]


def read_photos(pinhole_json: Path, folder: Folder = "images") -> dict[str, dict]:
    """Photo name -> its entry, with ``srgb`` and ``linear`` as absolute paths."""
    listing = json.loads(pinhole_json.read_text())
    base = pinhole_json.parent
    return {
        name: entry | {"srgb": base / entry["srgb"], "linear": base / entry["linear"]}
        for name, entry in listing[folder].items()
    }


def linear_photos(pinhole_json: Path) -> dict[str, Path]:
    """Photo name -> its linear-radiance EXR."""
    return {name: entry["linear"] for name, entry in read_photos(pinhole_json).items()}
