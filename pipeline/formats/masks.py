"""masks.json (stage masks): ``{"source", "images": {photo name: {"mask": PNG
relative to the file's folder, "source", "coverage", "touches_border"}}}``; a mask
is an 8-bit PNG the size of the undistorted photo, white where the specimen is."""

from __future__ import annotations

import json
from pathlib import Path


def write_masks(path: Path, source: str, report: dict[str, dict]) -> Path:
    path.write_text(json.dumps({"source": source, "images": report}, indent=1))
    return path


def read_masks(masks_json: Path) -> dict[str, Path]:
    """Photo name -> its mask PNG."""
    images = json.loads(masks_json.read_text())["images"]
    return {name: masks_json.parent / entry["mask"] for name, entry in images.items()}
