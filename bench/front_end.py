"""Benchmark of the capture front end (issue 4): calibration, undistortion, masks, check.

Runs the real stages on copies of the bundled samples (and on ../shared/captures/
porous-cube when present) and rewrites the "Capture front end" section of
docs/benchmarks.md. Usage: ``.venv/bin/python -m bench.front_end`` (after bin/bootstrap).
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import ROOT, run_stages, write_section
from pipeline.camera.board import BoardDetector, homography_residual_px, straightness_px
from pipeline.camera.model import Intrinsics, undistort
from pipeline.capture.check import check_capture
from pipeline.core.config import load_config
from pipeline.core.sections import BoardSection, schema
from pipeline.formats.cameras import read_cameras
from pipeline.imaging.photo_io import gray_uint8, read_photo
from pipeline.synthetic.score import score_masks
from stages import STAGES

POROUS_CUBE = ROOT.parent / "shared" / "captures" / "porous-cube"


def calibration_rows(capture: Path, outputs: dict) -> list[str]:
    group = json.loads(outputs["calibrate"]["calibration"].read_text())["groups"][0]
    truth, _ = read_cameras(capture / "ground_truth" / "cameras.json")
    source = Intrinsics.from_json(group["intrinsics"])
    camera = json.loads(outputs["undistort"]["pinhole"].read_text())["cameras"][0]
    target = Intrinsics.from_json(camera["intrinsics"])
    detector, board = BoardDetector(BoardSection(), 12), BoardSection()
    raw, lines, planes = [], [], []
    for shot in sorted((capture / "calibration").glob("*.jpg")):
        linear = read_photo(shot).pixels
        before, after = (
            detector.detect(gray_uint8(linear)),
            detector.detect(gray_uint8(undistort(linear, source, target))),
        )
        if before is not None and after is not None:
            raw.append(homography_residual_px(before))
            lines.append(straightness_px(after, board))
            planes.append(homography_residual_px(after))
    return [
        f"| {capture.name}: focal length | {source.fx:.2f} px vs true {truth.fx:.2f} px "
        f"({100 * abs(source.fx / truth.fx - 1):.2f} %), ± {group['focal_std_px']:.2f} px (1 sigma) |",
        f"| {capture.name}: principal point error | {np.hypot(source.cx - truth.cx, source.cy - truth.cy):.2f} px |",
        f"| {capture.name}: RMS reprojection error | {group['rms_px']:.3f} px over {group['shots_used']} shots "
        f"({len(group['dropped'])} dropped) |",
        f"| {capture.name}: board corners off their row/column line, undistorted | max {max(lines):.3f} px "
        f"over {len(lines)} shots |",
        f"| {capture.name}: board corners off the best homography: raw / undistorted | max {max(raw):.3f} px / "
        f"{max(planes):.3f} px |",
    ]


def main() -> None:
    rows, timing_rows = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for sample in ("bird", "bird_volumetric"):
            capture = Path(shutil.copytree(ROOT / "sample_captures" / sample, Path(tmp) / sample))
            outputs, seconds = run_stages(capture, "masks")
            rows += calibration_rows(capture, outputs)
            scores = list(
                score_masks(
                    capture / "ground_truth", outputs["undistort"]["pinhole"], outputs["masks"]["masks_json"]
                ).values()
            )
            rows.append(
                f"| {sample}: mask IoU (neutral_backdrop), {len(scores)} photos | mean {np.mean(scores):.3f}, "
                f"min {min(scores):.3f} |"
            )
            photos = len(scores)
            timing_rows.append(
                f"| {sample} ({photos} photos) | "
                + " | ".join(f"{seconds[s]:.1f} s" for s in ("calibrate", "undistort", "masks"))
                + " |"
            )
        if POROUS_CUBE.is_dir():
            capture = Path(tmp) / "porous-cube"
            capture.mkdir()
            (capture / "images").symlink_to(POROUS_CUBE / "images")
            started = time.time()
            problems = check_capture(capture, load_config(schema(STAGES), capture))
            elapsed = time.time() - started
            strays = [p.file for p in problems if p.check == "strays"]
            rows.append(
                f"| porous-cube: `pipeline check` | {len(problems)} problems in {elapsed:.0f} s; strays: "
                f"{', '.join(strays) or 'none'} |"
            )
    section = write_section(
        "front-end",
        [
            "## Capture front end (issue 4)",
            "",
            "Stages calibrate, undistort and masks on the standard preset, scored against the",
            "ground truth. Reproduce: `.venv/bin/python -m bench.front_end` (rewrites this section).",
            "",
            "| measurement | result |",
            "|---|---|",
            *rows,
            "",
            "| capture | calibrate | undistort | masks |",
            "|---|---|---|---|",
            *timing_rows,
        ],
    )
    print(section)


if __name__ == "__main__":
    main()
