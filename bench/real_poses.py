"""Poses on real captures and on synthetic captures made to fail like real ones:
photos posed, by what, errors against a reference, self-calibration, time.

    .venv/bin/python bench/real_poses.py [--captures ../shared/captures] [--work /tmp/real-poses]
                                         [--preset standard] [--only NAME ...]

Cases (``--only`` picks some by name):

- ``temple-ring`` (rig handheld) and ``temple-ring-ring`` (rig ring): Middlebury's
  templeRing from ``--captures``, scored against its calibrated reference cameras.
- ``porous-cube``: 76 handheld phone photos, one of them a stray room shot (no reference).
- ``hard-turntable`` and ``hard-turntable-room``: the synthetic twin of the real turntable
  capture issue 24 describes (`pipeline synth --rig turntable`, 60 views at 256x256, a glossy
  plain specimen, a dark plate with sparse dots, a still textured room, no board, no EXIF
  focal length, uneven steps); features from what moves (the room masked out, the default)
  and from everywhere (``sfm.feature_mask = everywhere``).
- ``hard-turntable-white``: the same photos cut out on white.
- ``bird``: the bundled sample (handheld rings, the board), the targets of the earlier issues.

Each capture becomes a pipeline capture in ``--work`` (`pipeline new` with the rig and the
photos for the real ones; `pipeline synth` for the synthetic ones, rendered once) and runs
`pipeline run --until sfm` (real captures with `-s board.kind=none`: no board was photographed).
Errors are after a similarity alignment of the camera centres (Umeyama): rotation, and
viewing direction (R^T [0 0 1]), median and max.

temple-ring's reference (reference/templeR_par.txt, Middlebury's K [R t]) fits the photos as
published only when turned by 90 degrees: with K, R, t as given, a quarter of the reference
bounding box projects outside the 480x640 photos and the masks carve no visual hull; turned
(u' = v, v' = 639 - u, the camera's axes turned about its optical axis to match), the box
projects inside every photo and the hull builds. Its principal point is then (246.9, 336.7),
7 and 17 px from the centre. The reference cameras of the 16 photos from the opposite gantry
latitude lack the 180-degree turn those photos were published with, so their rotation errors
read 180 degrees while their viewing directions are right: the rotation column counts the
turn out (``--reference-as-given`` scores against the par file as it is).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.camera.model import Pose
from pipeline.formats.cameras import read_cameras
from pipeline.synthetic.score import score_cameras

TURN = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
"""The reference camera's axes turned about its optical axis: x' = y, y' = -x."""
HALF_TURN = np.diag([-1.0, -1.0, 1.0])
HARD_TURNTABLE = [
    "--rig", "turntable", "--views", "60", "--width", "256", "--height", "256", "--rings", "25",
    "--material", "glossy_paint", "--texture", "plain", "--table", "dots", "--calibration-shots", "0",
    "--no-exif-focal", "--turn-jitter", "0.3", "--spp", "32", "--seed", "7",
]  # fmt: skip


@dataclass(frozen=True)
class Case:
    name: str
    source: str
    """'shared:NAME' (a folder of ../shared/captures), 'synth:BACKDROP' (the hard turntable
    with that backdrop, rendered once into the work folder) or 'sample:NAME'."""
    rig: str = "handheld"
    overrides: tuple[str, ...] = field(default_factory=tuple)


CASES = [
    Case("temple-ring", "shared:temple-ring", "handheld", overrides=("board.kind=none",)),
    Case("temple-ring-ring", "shared:temple-ring", "ring", overrides=("board.kind=none",)),
    Case("porous-cube", "shared:porous-cube", "handheld", overrides=("board.kind=none",)),
    Case("hard-turntable", "synth:room"),
    Case("hard-turntable-room", "synth:room", overrides=("sfm.feature_mask=everywhere",)),
    Case("hard-turntable-white", "synth:white"),
    Case("bird", "sample:bird"),
]


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


def rotation_errors(estimate: dict[str, Pose], truth: dict[str, Pose], rotation: np.ndarray) -> np.ndarray:
    """Rotation errors (degrees) after the alignment, a half turn about the optical axis
    counted out (temple-ring's reference lacks it for half its photos)."""
    errors = []
    for name in sorted(set(estimate) & set(truth)):
        relative = estimate[name].R @ rotation.T @ truth[name].R.T
        angles = [
            np.degrees(np.arccos(np.clip((np.trace(M) - 1) / 2, -1, 1))) for M in (relative, HALF_TURN @ relative)
        ]
        errors.append(min(angles))
    return np.array(errors)


def _pipeline(*arguments: str) -> list[str]:
    return [str(Path(sys.executable).parent / "pipeline"), "--quiet", *arguments]


def prepare(case: Case, captures: Path, work: Path) -> Path:
    capture = work / case.name
    if (capture / "capture.toml").is_file():
        return capture
    kind, _, name = case.source.partition(":")
    if kind == "shared":
        subprocess.run(_pipeline("new", str(capture), "--rig", case.rig), check=True)
        for photo in sorted((captures / name / "images").iterdir()):
            shutil.copy2(photo, capture / "images" / photo.name)
    elif kind == "sample":
        shutil.copytree(
            Path(__file__).resolve().parents[1] / "sample_captures" / name,
            capture,
            ignore=shutil.ignore_patterns(".pipeline", "output"),
        )
    else:
        twin = work / f"synth-{name}"
        if not (twin / "capture.toml").is_file():
            subprocess.run(_pipeline("synth", str(twin), *HARD_TURNTABLE, "--backdrop", name), check=True)
        shutil.copytree(twin, capture, ignore=shutil.ignore_patterns(".pipeline", "output"))
    return capture


def reference(case: Case, captures: Path, capture: Path, as_given: bool) -> dict[str, Pose] | None:
    if case.source.startswith("shared:"):
        par = captures / case.source.split(":")[1] / "reference" / "templeR_par.txt"
        return middlebury_poses(par, turned=not as_given) if par.is_file() else None
    _, truth = read_cameras(capture / "ground_truth" / "cameras.json")
    return truth


def calibration_summary(report: dict) -> str:
    """f, principal point and k1 as sfm.json reports them: adjusted or held."""
    found = report.get("circular", {}).get("self_calibration") or next(
        iter(report.get("self_calibration", {}).values()), None
    )
    if not found or "values" not in found:
        return found.get("skipped", "-") if found else "board or not tried"
    values = found["values"]
    parts = []
    for name in ("f", "cx", "cy", "k1"):
        entry = values[name]
        parts.append(f"{name} {entry['value']:.4g}{'' if entry['adjusted'] else ' (held)'}")
    return ", ".join(parts)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--captures", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "captures")
    parser.add_argument("--work", type=Path, default=Path("/tmp/real-poses"))
    parser.add_argument("--preset", default="standard")
    parser.add_argument("--only", nargs="*", default=[case.name for case in CASES])
    parser.add_argument("--reference-as-given", action="store_true")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    print(
        "| capture | rig | photos | posed | posed by | rotation error median / max | "
        "direction error median / max | intrinsics (self-calibration) | sfm stage |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for case in CASES:
        if case.name not in args.only:
            continue
        if case.source.startswith("shared:") and not (args.captures / case.source.split(":")[1]).is_dir():
            print(f"| {case.name} | {case.rig} | (not in {args.captures}) |||||||")
            continue
        capture = prepare(case, args.captures, args.work)
        overrides = (
            [f"capture.rig={case.rig}", *case.overrides] if case.source.startswith("shared:") else list(case.overrides)
        )
        command = _pipeline("run", str(capture), "--until", "sfm", "--preset", args.preset)
        for override in overrides:
            command += ["-s", override]
        rig = tomllib.loads((capture / "capture.toml").read_text())["capture"]["rig"]
        rig = next((o.split("=")[1] for o in overrides if o.startswith("capture.rig=")), rig)
        started = time.perf_counter()
        finished = subprocess.run(command).returncode == 0
        seconds = time.perf_counter() - started
        if not finished:
            print(f"| {case.name} | {rig} | - | failed (see its log) | - | - | - | - | {seconds:.0f} s |")
            continue
        output = capture / "output"
        _, poses = read_cameras(output / "cameras.json")
        key = json.loads((output / "manifest.json").read_text())["cameras.json"]["key"]
        entry = capture / ".pipeline" / "cache" / "sfm" / key
        report = json.loads((entry / "sfm.json").read_text())
        stage_seconds = json.loads((entry / "status.json").read_text()).get("seconds", seconds)
        sources = report.get("circular", {}).get("pose_source") or {report.get("poses_from", "SfM"): list(poses)}
        by = ", ".join(f"{source} {len(names)}" for source, names in sources.items() if names)
        errors = "-", "-"
        truth = reference(case, args.captures, capture, args.reference_as_given)
        if truth is not None:
            _, similarity = score_cameras(poses, truth)
            rotations = rotation_errors(poses, truth, similarity.R)
            directions = direction_errors(poses, truth, similarity.R)
            errors = (
                f"{np.median(rotations):.2f} / {rotations.max():.2f} deg",
                f"{np.median(directions):.2f} / {directions.max():.2f} deg",
            )
        print(
            f"| {case.name} | {rig} | {report['photos']} | {len(poses)} | {by} | {errors[0]} | {errors[1]} "
            f"| {calibration_summary(report)} | {stage_seconds:.0f} s |",
            flush=True,
        )


if __name__ == "__main__":
    main()
