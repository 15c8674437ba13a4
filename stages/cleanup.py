"""Stage cleanup: a manifold, watertight mesh of a chosen size, through pymeshlab.

In order: duplicate and unreferenced vertices are removed, non-manifold edges
repaired, components smaller than ``min_component_fraction`` of the largest's
diagonal dropped, holes up to ``max_hole_edges`` edges closed; isotropic
remeshing makes triangles even (fitting and UV unwrapping both suffer from
slivers), quadric edge collapse decimates to ``target_faces``, and a few Taubin
steps smooth without shrinking. Watertightness, genus and face count are
measured at the end (pymeshlab's topological measures).

==================  =============================================================
output              content
==================  =============================================================
mesh.ply            the cleaned mesh
cleanup.json        faces and vertices before and after, watertight, genus,
                    boundary edges, components
==================  =============================================================

Limitations: hole closing fills holes up to ``max_hole_edges`` edges; larger
ones (a specimen cut off by the frame) stay open and are reported. Decimation
keeps shape, not texture seams (there are none yet: uv runs after).
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

from pipeline import logger
from pipeline.core.config import Range
from pipeline.core.stage import Stage, StageInputs, StageResult
from pipeline.geometry import meshlab


@dataclass(frozen=True)
class Config:
    """Mesh repair, remeshing, decimation and smoothing."""

    min_component_fraction: Annotated[float, Range(0.0, 1.0)] = 0.1
    """Components whose bounding-box diagonal is below this fraction of the whole mesh's
    are removed (floating blobs from a bad mask); the largest is always kept."""
    max_hole_edges: Annotated[int, Range(3, None)] = 100
    """Largest hole closed, in boundary edges."""
    remesh_edge_fraction: Annotated[float, Range(0.0, 0.2)] = 0.01
    """Target edge length of isotropic remeshing, as a fraction of the bounding-box
    diagonal; 0 skips remeshing."""
    remesh_iterations: Annotated[int, Range(1, 50)] = 5
    """Iterations of isotropic remeshing."""
    target_faces: Annotated[int, Range(100, None)] = 20000
    """Faces after decimation (meshes with fewer are left as they are)."""
    smoothing_steps: Annotated[int, Range(0, 100)] = 3
    """Taubin smoothing steps (lambda 0.5, mu -0.53: no shrinking)."""


def main(conf: Config, inputs: StageInputs, out_dir: Path) -> StageResult:
    # 1. Repair, remesh, decimate and smooth, in pymeshlab's own process.
    mesh_ply = out_dir / "mesh.ply"
    measures = meshlab.run("clean", inputs.upstream["mesh"]["mesh"], mesh_ply, dataclasses.asdict(conf))
    after = measures["after"]

    # 2. Say what the settings could not reach.
    if after["faces"] > conf.target_faces:
        # Seen on a sphere whose hole was closed before remeshing: the collapse makes no step.
        logger.warning(
            "decimation stopped at %d faces, above cleanup.target_faces = %d", after["faces"], conf.target_faces
        )
    if not after["watertight"]:
        logger.warning(
            "the cleaned mesh has %d boundary edges: holes larger than cleanup.max_hole_edges = %d",
            after["boundary_edges"],
            conf.max_hole_edges,
        )
    report = out_dir / "cleanup.json"
    report.write_text(json.dumps(measures, indent=1))
    return StageResult({"mesh": mesh_ply, "report": report}, after)


STAGE = Stage(
    name="cleanup",
    version=1,
    config=Config,
    main=main,
    needs=("mesh.mesh",),
    outputs=("mesh", "report"),
    exports=("mesh",),
)
