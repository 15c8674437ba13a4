"""Inputs that could make a stage wait for ever, each run by the real CLI under a
watchdog (an alarm that ends the test instead of the suite hanging): a FIFO wherever a
file is read, and a mesh whose vertices are not numbers. Each must end at once with its
message and exit code."""

import os
import shutil
import signal

import numpy as np
import pytest

from pipeline.cli import main as cli_main

pytestmark = pytest.mark.slow
WATCHDOG_S = 120


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
    # a kernel file that blocks when read (/proc/kmsg) or never ends: refused by its file system
    (
        "kernel-file",
        "planning",
        lambda c: None,
        ["--dry-run", "-s", "light.environment_map='/proc/kmsg'"],
        2,
        "a file the kernel makes up (proc)",
    ),
]


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_a_hostile_input_ends_at_once_with_its_message(tiny_capture, tmp_path, capsys, caplog, case):
    from tests.support.byo_capture import byo_capture

    name, stage, spoil, argv, code, message = case
    capture = byo_capture(tiny_capture, tmp_path / "capture")
    shutil.rmtree(capture / "output", ignore_errors=True)
    spoil(capture)

    def expire(signum, frame):
        raise TimeoutError(f"{stage} waited over {WATCHDOG_S} s on a hostile {name}")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.alarm(WATCHDOG_S)
    try:
        assert cli_main(["run", str(capture), *argv]) == code
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    err = capsys.readouterr().err + caplog.text
    assert message in err and "Traceback" not in err
