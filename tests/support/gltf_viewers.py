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


def headless_chromium(arguments: list[str], drawn) -> str:
    """Headless Chromium with ``arguments`` (the test skips where it is not installed:
    bin/test installs Debian's package), run again, up to three times in all, until
    ``drawn(stdout)`` holds; the last run's stdout. Chromium takes its shot or dumps its
    page when its virtual time runs out, and on a busy machine a WebGL view has now and
    then not drawn the glb by then (seen: a bare background, an undrawn report)."""
    chromium = shutil.which("chromium")
    if chromium is None:
        pytest.skip("chromium is not installed (bin/test installs Debian's package)")
    for _ in range(3):
        command = [chromium, *CHROMIUM_FLAGS, *arguments]
        stdout = subprocess.run(command, capture_output=True, text=True, timeout=180, check=True).stdout
        if drawn(stdout):
            break
    return stdout


def three_js_renders(glb: bytes, view: tuple[Intrinsics, Pose], backgrounds: tuple[str, ...], folder: Path):
    """Linear RGB renders of the glb from ``view``, one per background colour, by
    three.js in headless Chromium (one browser run: the viewers side by side)."""
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

    def views() -> list[np.ndarray]:
        pixels = read_photo(shot, "srgb").pixels
        return [np.ascontiguousarray(pixels[:, i * width : (i + 1) * width]) for i in range(len(backgrounds))]

    def every_viewer_drew(_: str) -> bool:
        return not any(np.ptp(v.reshape(-1, v.shape[-1]), axis=0).max() < 1e-3 for v in views())

    size = f"--window-size={width * len(backgrounds)},{height}"
    headless_chromium([size, "--virtual-time-budget=5000", f"--screenshot={shot}", page.as_uri()], every_viewer_drew)
    if not every_viewer_drew(""):
        pytest.fail(f"three.js drew nothing in a viewer in three tries ({page})")
    return views()
