"""How close a visual hull's shading normals come to the true surface's.

bench/fitting.py's oracle part shows that on bird_volumetric the fitted alpha (the
rough dielectric's roughness) is as far off as the mesh's shading normals are: it
meets its target only with normals a few degrees from the truth. This benchmark
measures what silhouettes give, each hull built by the mesh stage and cleaned by the
cleanup stage on the standard preset, and scored by ``pipeline score``'s
shading-normal error:

1. the pipeline's own run: its masks, its poses;
2. the same poses with the true masks (the synthetic renderer's, undistorted like
   the photos): what better segmentation would give;
3. exact silhouettes (the true mesh rasterised) from the true cameras, for the
   sample's capture design and denser ones: what more photos would give.

Rewrites the "hull-normals" section of docs/benchmarks.md. Usage:
``.venv/bin/python -m bench.studies.hull_normals [--workdir DIR]`` (after bin/bootstrap; about
5 minutes on 2 cores alone, 10 when it shared them with two other runs).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np
import trimesh

from bench.common import ROOT, run_stages, truth_in_reconstruction, write_section
from pipeline.camera.model import Intrinsics, Pose, mesh_coverage, undistort
from pipeline.core.config import load_config
from pipeline.core.sections import schema
from pipeline.core.stage import StageInputs
from pipeline.formats.cameras import write_cameras
from pipeline.synthetic.options import SynthOptions
from pipeline.synthetic.score import score_mesh
from pipeline.synthetic.synth import lens_intrinsics, specimen_poses
from stages import STAGES, cleanup, mesh

# (views, rings in degrees) of the exact-silhouette rows; the first is bird_volumetric's
DESIGNS = (
    (20, (18.0, 42.0)),
    (30, (18.0, 42.0)),
    (60, (10.0, 25.0, 40.0, 55.0, 75.0)),
    (120, (10.0, 25.0, 40.0, 55.0, 75.0)),
)


def _cleaned_hull(
    capture: Path, config: dict, folder: Path, cameras_json: Path, masks: dict[str, np.ndarray], sparse: Path | None
) -> trimesh.Trimesh:
    """The mesh and cleanup stages, configured by ``config`` (``capture``'s), on these
    cameras and masks (no sparse points when ``sparse`` is None)."""
    (folder / "masks").mkdir(parents=True)
    for name, mask in masks.items():
        cv2.imwrite(str(folder / "masks" / f"{Path(name).stem}.png"), mask.astype(np.uint8) * 255)
    masks_json = folder / "masks.json"
    masks_json.write_text(
        json.dumps({"source": "bench", "images": {name: {"mask": f"masks/{Path(name).stem}.png"} for name in masks}})
    )
    mesh_conf = config["mesh"] if sparse else dataclasses.replace(config["mesh"], refine="none")
    upstream = {"sfm": {"cameras": cameras_json, "sparse": sparse}, "masks": {"masks_json": masks_json}}
    (folder / "mesh").mkdir()
    upstream["mesh"] = mesh.main(mesh_conf, StageInputs(capture, (), upstream, {}), folder / "mesh").outputs
    (folder / "cleanup").mkdir()
    cleaned = cleanup.main(config["cleanup"], StageInputs(capture, (), upstream, {}), folder / "cleanup").outputs
    return trimesh.load(cleaned["mesh"], force="mesh")


def _true_masks(capture: Path, pinhole_json: Path) -> dict[str, np.ndarray]:
    """The synthetic renderer's masks, brought into the undistorted frame like the photos."""
    pinhole = json.loads(pinhole_json.read_text())
    masks = {}
    for name, photo in pinhole["images"].items():
        camera = pinhole["cameras"][photo["camera"]]
        source, target = Intrinsics.from_json(camera["source"]), Intrinsics.from_json(camera["intrinsics"])
        truth = cv2.imread(str(capture / "ground_truth" / "masks" / f"{Path(name).stem}.png"), cv2.IMREAD_GRAYSCALE)
        masks[name] = undistort((truth > 127).astype(np.float32), source, target) >= 0.5
    return masks


def _row(label: str, hull: trimesh.Trimesh, truth: trimesh.Trimesh) -> str:
    score = score_mesh(hull, truth)
    return (
        f"| {label} | {score['shading_normal_error_deg']:.1f} deg | {score['shading_normal_error_deg_median']:.1f} deg "
        f"| {score['chamfer_pct_of_diagonal']:.2f} % |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--workdir", type=Path, help="keep the capture and its caches here (default: a temporary folder)"
    )
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as temporary:
        work = args.workdir or Path(temporary)
        capture = work / "bird_volumetric"
        if not capture.is_dir():
            shutil.copytree(
                ROOT / "sample_captures" / "bird_volumetric",
                capture,
                ignore=shutil.ignore_patterns(".pipeline", "output"),
            )
        outputs, _ = run_stages(capture, "cleanup")
        config = load_config(schema(STAGES), capture, "standard", [])
        _, truth_here = truth_in_reconstruction(capture, outputs)
        rows = [
            _row(
                "the pipeline: its masks and poses (mesh, cleanup)",
                trimesh.load(outputs["cleanup"]["mesh"], force="mesh"),
                truth_here,
            )
        ]
        hulls = work / "hull-normals"
        shutil.rmtree(hulls, ignore_errors=True)
        true_masks = _true_masks(capture, outputs["undistort"]["pinhole"])
        registered = set(json.loads(outputs["sfm"]["cameras"].read_text())["images"])
        rows.append(
            _row(
                "the pipeline's poses, the true masks",
                _cleaned_hull(
                    capture,
                    config,
                    hulls / "true-masks",
                    outputs["sfm"]["cameras"],
                    {n: m for n, m in true_masks.items() if n in registered},
                    outputs["sfm"]["sparse"],
                ),
                truth_here,
            )
        )
        truth = trimesh.load(capture / "ground_truth" / "mesh.ply", force="mesh")
        synth = json.loads((capture / "ground_truth" / "synth.json").read_text())["options"]
        for views, rings in DESIGNS:
            options = SynthOptions(
                views=views,
                rings=rings,
                width=synth["width"],
                height=synth["height"],
                hfov=synth["hfov"],
                distance=synth["distance"],
                seed=synth["seed"],
            )
            pinhole = dataclasses.replace(lens_intrinsics(options), dist=[0.0] * 5)
            # drawn as `pipeline synth` draws them: the first design gives the sample's own cameras
            poses: dict[str, Pose] = {
                f"view_{i:03d}.jpg": pose
                for i, pose in enumerate(specimen_poses(options, np.random.default_rng(options.seed)))
            }
            folder = hulls / f"{views}-views-{len(rings)}-rings"
            folder.mkdir(parents=True)
            # The board lies in z = 0 of the true frame: the ground plane the mesh stage clips at.
            write_cameras(folder / "cameras.json", pinhole, poses, frame={"ground_plane": [0.0, 0.0, 1.0, 0.0]})
            masks = {n: mesh_coverage(truth.vertices, truth.faces, pinhole, p) > 0.5 for n, p in poses.items()}
            rings_text = ", ".join(f"{r:.0f}" for r in rings)
            rows.append(
                _row(
                    f"exact silhouettes, true cameras: {views} views on rings at {rings_text} deg",
                    _cleaned_hull(capture, config, folder, folder / "cameras.json", masks, None),
                    truth,
                )
            )
    print(
        write_section(
            "hull-normals",
            [
                "### What silhouettes give: the visual hull's shading normals",
                "",
                "The cleaned visual hull of bird_volumetric (mesh and cleanup stages, standard",
                "preset) against the true surface, in the reconstruction's frame for the first two",
                "rows and in the true frame for the rest: `pipeline score`'s shading-normal error",
                "(mean and median angle between the normal Mitsuba shades with and the true",
                "surface's) and Chamfer distance. Rows 3 on: the true mesh rasterised from the true",
                "cameras (undistorted, the sample's size and lens), for the sample's 20 views and",
                "denser captures. Reproduce: `.venv/bin/python -m bench.studies.hull_normals`.",
                "",
                "| hull from | shading-normal error, mean | median | Chamfer distance |",
                "|---|---|---|---|",
                *rows,
            ],
        )
    )


if __name__ == "__main__":
    main()
