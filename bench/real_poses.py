"""Poses on real captures: registered photos, pose sources, errors against a reference, time.

    .venv/bin/python bench/real_poses.py [--captures ../shared/captures] [--work /tmp/real-poses]
                                         [--preset standard] [--only temple-ring porous-cube]

Each capture in ``--captures`` (read its README) becomes a pipeline capture in
``--work`` (`pipeline new`, the photos copied, the rig the README names, run
with `-s board.kind=none`: no board was photographed) and runs `pipeline run --until sfm` (cached between runs of this bench).
Printed per capture: photos, registered, where the poses came from (sfm.json),
the time of the sfm stage, and for temple-ring the pose errors against its
calibrated reference cameras after a similarity alignment of the centres
(pipeline.synthetic.score.score_cameras): rotation and viewing-direction error,
median and max.

temple-ring's reference (reference/templeR_par.txt, Middlebury's K [R t]) fits
the photos as published only when turned by 90 degrees: with K, R, t as given,
a quarter of the reference bounding box projects outside the 480x640 photos and
the masks carve no visual hull; turned (u' = v, v' = 639 - u, the camera's axes
turned about its optical axis to match), the box projects inside every photo and
the hull builds. The principal point is then (246.9, 336.7) in the photos,
7 and 17 px from the centre. ``--reference-as-given`` scores against the par file
as it is (viewing directions do not depend on the turn; rotations do).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from pipeline.camera.model import Pose
from pipeline.formats.cameras import read_cameras
from pipeline.synthetic.score import score_cameras

RIGS = {"temple-ring": "handheld", "porous-cube": "handheld"}
"""temple-ring: a gantry moved the camera around a still object (a ring of viewpoints,
not a turntable in the pipeline's sense: a still camera and room, the specimen turning)."""
TURN = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
"""The reference camera's axes turned about its optical axis: x' = y, y' = -x."""


def middlebury_poses(par: Path, turned: bool) -> dict[str, Pose]:
    poses = {}
    for line in par.read_text().splitlines()[1:]:
        if not line.strip():
            continue
        name, *values = line.split()
        numbers = np.array(values, float)
        R, t = numbers[9:18].reshape(3, 3), numbers[18:21]
        poses[name] = Pose(TURN @ R, TURN @ t) if turned else Pose(R, t)
    return poses


def direction_errors(estimate: dict[str, Pose], truth: dict[str, Pose], rotation: np.ndarray) -> np.ndarray:
    """Angles between aligned and true viewing directions (R^T [0, 0, 1]), degrees."""
    angles = []
    for name in sorted(set(estimate) & set(truth)):
        seen = rotation @ estimate[name].R.T @ np.array([0.0, 0.0, 1.0])
        true = truth[name].R.T @ np.array([0.0, 0.0, 1.0])
        angles.append(np.degrees(np.arccos(np.clip(seen @ true, -1.0, 1.0))))
    return np.array(angles)


def prepare(source: Path, work: Path, rig: str) -> Path:
    capture = work / source.name
    if (capture / "capture.toml").is_file():
        return capture
    pipeline = [str(Path(sys.executable).parent / "pipeline")]
    subprocess.run([*pipeline, "--quiet", "new", str(capture), "--rig", rig], check=True)
    for photo in sorted((source / "images").iterdir()):
        shutil.copy2(photo, capture / "images" / photo.name)
    return capture


def run_sfm(capture: Path, preset: str) -> float:
    started = time.perf_counter()
    pipeline = [str(Path(sys.executable).parent / "pipeline"), "--quiet"]
    command = [*pipeline, "run", str(capture), "--until", "sfm", "--preset", preset, "-s", "board.kind=none"]
    subprocess.run(command, check=True)
    return time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--captures", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "captures")
    parser.add_argument("--work", type=Path, default=Path("/tmp/real-poses"))
    parser.add_argument("--preset", default="standard")
    parser.add_argument("--only", nargs="*", default=sorted(RIGS))
    parser.add_argument("--reference-as-given", action="store_true")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    print(
        "| capture | photos | registered / kept | poses from | run --until sfm | rotation error median / max | "
        "direction error median / max |"
    )
    print("|---|---|---|---|---|---|---|")
    for name in args.only:
        capture = prepare(args.captures / name, args.work, RIGS[name])
        seconds = run_sfm(capture, args.preset)
        output = capture / "output"
        _, poses = read_cameras(output / "cameras.json")
        key = json.loads((output / "manifest.json").read_text())["cameras.json"]["key"]
        report = json.loads((capture / ".pipeline" / "cache" / "sfm" / key / "sfm.json").read_text())
        sources = report.get("turntable", {}).get("pose_source") or {report.get("poses_from", "SfM"): list(poses)}
        from_text = ", ".join(f"{source} {len(names)}" for source, names in sources.items())
        errors = "-", "-"
        reference = args.captures / name / "reference" / "templeR_par.txt"
        if reference.is_file():
            truth = middlebury_poses(reference, turned=not args.reference_as_given)
            metrics, similarity = score_cameras(poses, truth)
            directions = direction_errors(poses, truth, similarity.R)
            errors = (
                f"{metrics['rotation_error_deg_median']:.2f} / {metrics['rotation_error_deg_max']:.2f} deg",
                f"{np.median(directions):.2f} / {directions.max():.2f} deg",
            )
        print(
            f"| {name} | {report['photos']} | {report['registered']} / {len(poses)} | {from_text} | {seconds:.0f} s "
            f"| {errors[0]} | {errors[1]} |"
        )


if __name__ == "__main__":
    main()
