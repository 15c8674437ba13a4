"""Inputs that could make a stage wait for ever, each run by the real CLI in its own
process under a watchdog: a FIFO wherever a file is read, and a mesh whose vertices
are not numbers. Each must end at once with its message and exit code."""

import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from tests.support.toy_stages import REPOSITORY

pytestmark = pytest.mark.slow
WATCHDOG_S = 120
CLI = "import sys; from pipeline.cli import main; sys.exit(main(sys.argv[1:]))"


def _fifo(path):
    if path.exists():
        path.unlink()
    path.parent.mkdir(parents=True, exist_ok=True)
    os.mkfifo(path)


def _non_finite_mesh(capture):
    import trimesh

    mesh = trimesh.load(capture / "ground_truth" / "mesh.ply", process=False)
    vertices = np.array(mesh.vertices)
    vertices[::5] = np.nan
    trimesh.Trimesh(vertices, mesh.faces, process=False).export(capture / "bad.ply")


MESH = ["--until", "mesh", "-s", "cameras.source='external'", "-s", "mesh.source='bad.ply'"]
CASES = [
    # (id, stage that reads it, spoil(capture), argv after CAPTURE, exit code, message); every
    # file a setting names (cameras.source, mesh.source) goes through the environment map's check.
    (
        "photo",
        "undistort",
        lambda c: _fifo(c / "images" / "v.jpg"),
        ["--until", "undistort"],
        0,
        "v.jpg is not a photo",
    ),
    (
        "mask",
        "masks",
        lambda c: _fifo(c / "masks" / "view_000.png"),
        ["--until", "masks"],
        0,
        "view_000.png is not a mask",
    ),
    (
        "board-shot",
        "calibrate",
        lambda c: _fifo(c / "calibration" / "s.jpg"),
        ["--until", "calibrate"],
        0,
        "s.jpg is not a photo",
    ),
    ("capture-toml", "planning", lambda c: _fifo(c / "capture.toml"), [], 2, "capture.toml is a FIFO"),
    ("envmap", "scene", lambda c: _fifo(c / "room.exr"), ["-s", "light.environment_map='room.exr'"], 2, "is a FIFO"),
    ("non-finite-mesh", "mesh", _non_finite_mesh, MESH, 1, "vertices are NaN or infinite"),
]


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_a_hostile_input_ends_at_once_with_its_message(tiny_capture, tmp_path, case):
    from tests.support.byo_capture import byo_capture

    name, stage, spoil, argv, code, message = case
    capture = byo_capture(tiny_capture, tmp_path / "capture")
    shutil.rmtree(capture / "output", ignore_errors=True)
    spoil(capture)
    try:
        done = subprocess.run(
            [sys.executable, "-c", CLI, "run", str(capture), *argv],
            capture_output=True,
            text=True,
            cwd=REPOSITORY,
            timeout=WATCHDOG_S,
        )
    except subprocess.TimeoutExpired:
        pytest.fail(f"{stage} waited over {WATCHDOG_S} s on a hostile {name}")
    assert done.returncode == code, done.stderr[-2000:]
    assert message in done.stderr and "Traceback" not in done.stderr
