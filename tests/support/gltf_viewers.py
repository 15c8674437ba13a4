"""The glb as viewers see it: the Khronos glTF validator (npm ``gltf-validator``, which
bin/test installs under .cache/npm) and three.js in headless Chromium (Debian's
chromium, which bin/test installs) through pipeline.viewer."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from pipeline.camera.model import Intrinsics, Pose
from pipeline.imaging.photo_io import read_photo
from pipeline.viewer import viewer_fragment

REPOSITORY = Path(__file__).resolve().parents[2]
NPM_PREFIX = REPOSITORY / ".cache" / "npm"
VALIDATE = """
const fs = require('fs');
require('gltf-validator').validateBytes(new Uint8Array(fs.readFileSync(process.argv[1])))
  .then(report => console.log(JSON.stringify(report.issues)))
  .catch(error => { console.error(String(error)); process.exit(1); });
"""
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--enable-unsafe-swiftshader",  # WebGL in software
    "--use-angle=swiftshader",
    "--disable-background-networking",
    "--disable-component-update",
    "--no-first-run",
    "--hide-scrollbars",
)


def validator_issues(glb: Path) -> dict:
    """The Khronos validator's issues (numErrors, numWarnings, messages...); skips the
    test where node or the validator is not installed (bin/test installs both)."""
    node = shutil.which("node")
    if node is None or not (NPM_PREFIX / "node_modules" / "gltf-validator").is_dir():
        pytest.skip("node or gltf-validator is not installed (bin/test installs them)")
    environment = {**os.environ, "NODE_PATH": str(NPM_PREFIX / "node_modules")}
    result = subprocess.run(
        [node, "-e", VALIDATE, str(glb)], capture_output=True, text=True, timeout=120, env=environment, check=True
    )
    return json.loads(result.stdout)


def three_js_renders(glb: bytes, view: tuple[Intrinsics, Pose], backgrounds: tuple[str, ...], folder: Path):
    """Linear RGB renders of the glb from ``view``, one per background colour, by
    three.js in headless Chromium (one browser run: the viewers side by side)."""
    chromium = shutil.which("chromium")
    if chromium is None:
        pytest.skip("chromium is not installed (bin/test installs Debian's package)")
    width, height = view[0].width, view[0].height
    fragments = "".join(
        viewer_fragment(glb, element_id=f"view{i}", view=view, background=colour)
        for i, colour in enumerate(backgrounds)
    )
    page = folder / "viewers.html"
    page.write_text(
        '<!DOCTYPE html><html><head><meta charset="utf-8"><style>body{margin:0;display:flex}</style></head>'
        f"<body>{fragments}</body></html>"
    )
    shot = folder / "viewers.png"
    # Headless Chromium takes the shot when its virtual time runs out; on a busy machine a
    # viewer has now and then not drawn the glb by then (seen once: still its bare
    # background). Such a shot is taken again.
    for _ in range(3):
        subprocess.run(
            [chromium, *CHROMIUM_FLAGS, f"--window-size={width * len(backgrounds)},{height}"]
            + ["--virtual-time-budget=5000", f"--screenshot={shot}", page.as_uri()],
            capture_output=True,
            timeout=180,
            check=True,
        )
        pixels = read_photo(shot, "srgb").pixels
        views = [np.ascontiguousarray(pixels[:, i * width : (i + 1) * width]) for i in range(len(backgrounds))]
        if not any(np.ptp(view.reshape(-1, view.shape[-1]), axis=0).max() < 1e-3 for view in views):
            return views
    pytest.fail(f"three.js drew nothing in a viewer in three tries ({page})")
