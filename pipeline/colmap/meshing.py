"""Screened Poisson surface reconstruction of oriented points (one thread: deterministic)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import trimesh


def screened_poisson(
    points: np.ndarray, normals: np.ndarray, depth: int, point_weight: float, work_dir: Path
) -> trimesh.Trimesh:
    """COLMAP's screened Poisson reconstruction, untrimmed (so closed) and on one
    thread. Unlike pymeshlab's, it returns the same mesh, vertex for vertex, on
    every run: cleanup's decimation and the UV charts depend on that order."""
    cloud_ply, mesh_ply = work_dir / "poisson_input.ply", work_dir / "poisson_output.ply"
    oriented = np.hstack([points, normals]).astype("<f4")
    header = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {len(oriented)}\n"
        + "".join(f"property float {name}\n" for name in ("x", "y", "z", "nx", "ny", "nz"))
        + "end_header\n"
    )
    cloud_ply.write_bytes(header.encode() + oriented.tobytes())
    options = pycolmap.PoissonMeshingOptions()
    options.depth, options.point_weight, options.trim, options.num_threads = depth, point_weight, 0.0, 1
    pycolmap.poisson_meshing(cloud_ply, mesh_ply, options)
    mesh = trimesh.load(mesh_ply, force="mesh", process=True)
    cloud_ply.unlink()
    mesh_ply.unlink()
    return mesh
