"""calibration.json (stage calibrate): one group per camera setting, each with its
intrinsics (pipeline.camera.model.Intrinsics as JSON) and the photos taken with it."""

from __future__ import annotations

import json
from pathlib import Path


def read_camera_groups(calibration_json: Path) -> list[dict]:
    """The camera settings, each ``{"camera", "intrinsics", "images", ...}``."""
    return json.loads(calibration_json.read_text())["groups"]
