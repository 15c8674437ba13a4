"""Benchmark of the geometry stages (issue 5): sfm, mesh, cleanup, uv.

Runs the real stages on a copy of sample_captures/bird, on a synthetic turntable
capture rendered here (a plain bird, uneven steps), and on ../shared/captures/
porous-cube when present; measures the mesh resolution's trade of time against
accuracy; rewrites the "Geometry" section of docs/benchmarks.md.
Usage: ``.venv/bin/python -m bench.geometry`` (after bin/bootstrap; about 15 minutes
on 2 cores with the porous cube, 3 without).
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import trimesh

from bench.common import ROOT, run_stages, write_section
from pipeline.formats.cameras import read_cameras, read_views
from pipeline.synthetic.score import score_cameras, score_mesh
from pipeline.synthetic.synth import SynthOptions, synthesize

POROUS_CUBE = ROOT.parent / "shared" / "captures" / "porous-cube"
GEOMETRY_STAGES = ("sfm", "mesh", "cleanup", "uv")
TURNTABLE = SynthOptions(
    views=24, rings=(25.0,), width=384, height=288, spp=16, rig="turntable", turn_jitter=0.4, texture="plain", seed=0
)


def pose_errors(capture: Path, cameras_json: Path) -> dict:
    _, truth = read_cameras(capture / "ground_truth" / "cameras.json")
    metrics, _ = score_cameras({n: pose for n, (_, pose) in read_views(cameras_json).items()}, truth)
    return metrics


def shape(mesh_ply: Path) -> dict:
    """Closedness and how box-like a mesh is (volume over its oriented box's: 1 for a
    box, 0.52 for a sphere)."""
    mesh = trimesh.load(mesh_ply, force="mesh")
    mesh.merge_vertices(merge_tex=True, merge_norm=True)
    box = mesh.bounding_box_oriented
    extents = np.sort(box.primitive.extents)
    return {
        "watertight": mesh.is_watertight,
        "genus": round(1 - mesh.euler_number / 2) if mesh.is_watertight else None,
        "faces": len(mesh.faces),
        "box_fill": mesh.volume / box.volume,
        "aspect": extents / extents[-1],
    }


REFINEMENT_HEAD = [
    "The hull's refinement on the bird (`mesh.refine`; the standard is poisson; stereo is",
    'what the real captures run with, docs/benchmarks.md "Real light"):',
    "",
    "| mesh.refine | mesh stage time | Chamfer distance | shading normals (mean error) |",
    "|---|---|---|---|",
]


def bird_rows(tmp: Path) -> tuple[list[str], list[str], list[str], list[str]]:
    capture = Path(
        shutil.copytree(
            ROOT / "sample_captures" / "bird", tmp / "bird", ignore=shutil.ignore_patterns(".pipeline", "output")
        )
    )
    outputs, seconds = run_stages(capture, "uv")
    cameras = pose_errors(capture, outputs["sfm"]["cameras"])
    sfm = json.loads(outputs["sfm"]["report"].read_text())
    truth = trimesh.load(capture / "ground_truth" / "mesh.ply", force="mesh")
    chamfer = {
        s: score_mesh(trimesh.load(outputs[s]["mesh"], force="mesh"), truth)["chamfer_pct_of_diagonal"]
        for s in ("mesh", "cleanup", "uv")
    }
    rows = [
        f"| bird: photos registered | {cameras['registered']} of {cameras['images']} |",
        f"| bird: rotation error (aligned) | median {cameras['rotation_error_deg_median']:.2f} deg, "
        f"max {cameras['rotation_error_deg_max']:.2f} deg |",
        f"| bird: SfM reprojection error, track length | {sfm['mean_reprojection_error_px']:.2f} px, "
        f"{sfm['mean_track_length']:.2f} |",
        f"| bird: world frame | {sfm['frame']['source']} in {sfm['frame']['photos']} photos "
        f"(centres agree to {sfm['frame']['centre_residual_mm_median']:.1f} mm) |",
        *[f"| bird: Chamfer distance, {s} stage | {chamfer[s]:.2f} % of the diagonal |" for s in chamfer],
        f"| bird: uv mesh | {_shape_text(shape(outputs['uv']['mesh']))} |",
    ]
    timing = [
        f"| bird ({cameras['images']} photos, 560x420) | "
        + " | ".join(f"{seconds[s]:.1f} s" for s in GEOMETRY_STAGES)
        + " |"
    ]
    trade = []
    for resolution in (64, 96, 128, 192, 256):
        outputs, seconds = run_stages(capture, "mesh", f"mesh.resolution={resolution}")
        mesh = trimesh.load(outputs["mesh"]["mesh"], force="mesh")
        trade.append(
            f"| {resolution} | {seconds['mesh']:.1f} s | {score_mesh(mesh, truth)['chamfer_pct_of_diagonal']:.2f} % |"
        )
    tolerance = []
    for views in (0, 1, 2):
        outputs, _ = run_stages(capture, "mesh", f"mesh.carve_tolerance={views}")
        mesh = trimesh.load(outputs["mesh"]["mesh"], force="mesh")
        tolerance.append(
            f"| {views} | {score_mesh(mesh, truth)['chamfer_pct_of_diagonal']:.2f} % | "
            f"{mesh.volume / truth.volume:.3f} |"
        )
    refinement = []
    for refine in ("none", "poisson", "stereo"):
        outputs, seconds = run_stages(capture, "mesh", f"mesh.refine={refine}")
        scores = score_mesh(trimesh.load(outputs["mesh"]["mesh"], force="mesh"), truth)
        refinement.append(
            f"| {refine} | {seconds['mesh']:.1f} s | {scores['chamfer_pct_of_diagonal']:.2f} % | "
            f"{scores['shading_normal_error_deg']:.1f} deg |"
        )
    return rows, timing, trade, tolerance + ["", *REFINEMENT_HEAD, *refinement]


def _shape_text(s: dict) -> str:
    genus = f", genus {s['genus']}" if s["genus"] is not None else ""
    return (
        f"{s['faces']} faces, {'watertight' if s['watertight'] else 'NOT watertight'}{genus}, "
        f"volume / oriented box {s['box_fill']:.2f}, box sides {' : '.join(f'{e:.2f}' for e in s['aspect'])}"
    )


def turntable_rows(tmp: Path) -> tuple[list[str], list[str]]:
    capture = synthesize(tmp / "turntable", TURNTABLE)
    outputs, seconds = run_stages(capture, "sfm")
    cameras = pose_errors(capture, outputs["sfm"]["cameras"])
    report = json.loads(outputs["sfm"]["report"].read_text())
    sources = ", ".join(f"{source} {len(names)}" for source, names in report["circular"]["pose_source"].items())
    rows = [
        f"| turntable: photos posed | {len(read_views(outputs['sfm']['cameras']))} of {cameras['images']} "
        f"(poses from: {sources}) |",
        f"| turntable: rotation error (aligned) | median {cameras['rotation_error_deg_median']:.2f} deg, "
        f"max {cameras['rotation_error_deg_max']:.2f} deg |",
    ]
    timing = [
        f"| synthetic turntable ({TURNTABLE.views} photos, {TURNTABLE.width}x{TURNTABLE.height}) | "
        f"{seconds['sfm']:.1f} s | - | - | - |"
    ]
    return rows, timing


def porous_rows(tmp: Path) -> tuple[list[str], list[str]]:
    capture = tmp / "porous-cube"
    capture.mkdir()
    (capture / "images").symlink_to(POROUS_CUBE / "images")
    (capture / "capture.toml").write_text(
        '[capture]\nrig = "handheld"\n\n[board]\nkind = "none"\n\n[masks]\nsegmenter = "centre_prior"\n'
    )
    outputs, seconds = run_stages(capture, "uv")
    report = json.loads(outputs["sfm"]["report"].read_text())
    rows = [
        f"| porous-cube: photos registered | {report['registered']} of {report['photos']} "
        f"(left out: {', '.join(report['unregistered']) or 'none'}) |",
        f"| porous-cube: SfM reprojection error, track length | {report['mean_reprojection_error_px']:.2f} px, "
        f"{report['mean_track_length']:.2f} |",
        f"| porous-cube: world frame | {report['frame']['source']} ({report['frame']['units']}) |",
        f"| porous-cube: cleaned mesh | {_shape_text(shape(outputs['cleanup']['mesh']))} |",
    ]
    timing = [
        f"| porous-cube ({report['photos']} photos, 1024x1024) | "
        + " | ".join(f"{seconds[s]:.1f} s" for s in GEOMETRY_STAGES)
        + " |"
    ]
    return rows, timing


def main() -> None:
    with tempfile.TemporaryDirectory() as folder:
        tmp = Path(folder)
        rows, timing, trade, tolerance = bird_rows(tmp)
        turntable, turntable_timing = turntable_rows(tmp)
        rows += turntable
        timing += turntable_timing
        if POROUS_CUBE.is_dir():
            porous, porous_timing = porous_rows(tmp)
            rows += porous
            timing += porous_timing
    section = write_section(
        "geometry",
        [
            "## Geometry (issue 5)",
            "",
            "Stages sfm, mesh, cleanup and uv on the standard preset. Errors are against the",
            "ground truth after a similarity alignment (the bird's frame is also metric without it).",
            "The turntable capture: `pipeline synth --rig turntable --turn-jitter 0.4 --texture plain",
            "--views 24 --width 384 --height 288 --spp 16 --rings 25`. Reproduce:",
            "`.venv/bin/python -m bench.geometry` (rewrites this section).",
            "",
            "| measurement | result |",
            "|---|---|",
            *rows,
            "",
            "Stage times (wall clock, 2 cores; the turntable row is sfm only):",
            "",
            "| capture | sfm | mesh | cleanup | uv |",
            "|---|---|---|---|---|",
            *timing,
            "",
            "Speed against accuracy: the mesh stage's voxel resolution on the bird (Chamfer of",
            "the mesh stage's output; the presets use 96 / 128 / 192):",
            "",
            "| mesh.resolution | mesh stage time | Chamfer distance |",
            "|---|---|---|",
            *trade,
            "",
            "The carve tolerance (views allowed to disagree before a voxel is carved) on the bird:",
            "each view more keeps what that many views alone would carve (the standard is 0).",
            "",
            "| mesh.carve_tolerance | Chamfer distance | volume / true volume |",
            "|---|---|---|",
            *tolerance,
        ],
    )
    print(section)


if __name__ == "__main__":
    main()
