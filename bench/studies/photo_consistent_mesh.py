"""The mesh stage's mesh moved to where the photos agree: does finer geometry from the
photos lift a real capture's held-out PSNR? (issue 26, point 4)

For a capture whose stages up to the mesh are cached, each round:

1. every photo's depth is searched by plane sweep (pipeline.geometry.stereo) within
   ``--span`` (relative) of the mesh's own depth at each pixel, against its nearest
   viewpoints, and kept where its NCC score passes 0.8 and a neighbour's depth map agrees;
2. each vertex seen by a photo (the surface its pixel sees, within 0.2 % of depth)
   takes that photo's depth as a move along its normal (the move along the ray,
   projected on the normal), averaged over the photos with weights cos(angle between
   the normal and the direction to the camera);
3. the moves are spread and smoothed over the mesh (ten Jacobi steps of a weighted
   uniform Laplacian: vertices without a depth take their neighbours') and applied.

The moved mesh is written as a PLY; run the capture with it as a given mesh
(``-s mesh.source=FILE``: it goes through cleanup, uv, scene and the fits like the
stage's own) and score fit_texture's heldout/ against the run without it.

Usage: ``.venv/bin/python -m bench.studies.photo_consistent_mesh CAPTURE OUT.ply [-s KEY=VALUE ...]
[--rounds 2] [--span 0.01]``, then
``.venv/bin/pipeline run CAPTURE -s mesh.source=OUT.ply [-s ...] --until fit_texture``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import scipy.sparse as sparse
import trimesh

from bench.studies.ceiling import cached_outputs
from pipeline.camera.model import project, scaled
from pipeline.core import progress
from pipeline.formats.cameras import read_views
from pipeline.formats.masks import read_masks
from pipeline.formats.pinhole import read_photos
from pipeline.geometry import stereo

MIN_SCORE = 0.8
"""NCC a depth must reach to move the mesh (the mesh stage carves from 0.5)."""
VISIBLE = 0.002
"""Relative depth within which a vertex is the surface its pixel sees."""


def stereo_views(mesh: trimesh.Trimesh, outputs: dict, span: float) -> tuple[list, list]:
    """Per photo a StereoView searching ``span`` either side of the mesh's depth, and that depth."""
    masks = read_masks(outputs["masks"]["masks_json"])
    photos = read_photos(outputs["undistort"]["pinhole"])
    views, depths = [], []
    for name, (intrinsics, pose) in sorted(read_views(outputs["sfm"]["cameras"]).items()):
        grey = cv2.imread(str(photos[name]["srgb"]), cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255
        mask = cv2.imread(str(masks[name]), cv2.IMREAD_GRAYSCALE) > 127
        full = scaled(intrinsics, 1.0, exact=True)
        near, _ = stereo.hull_depths(mesh, full, pose)
        seen = np.isfinite(near)
        low = np.where(seen, near * (1 - span), np.inf).astype(np.float32)
        high = np.where(seen, near * (1 + span), 0.0).astype(np.float32)
        views.append(stereo.StereoView(full, pose, grey, mask, low, high))
        depths.append(near)
    return views, depths


def normal_moves(mesh: trimesh.Trimesh, views: list, surface_depths: list, kept: list) -> tuple[np.ndarray, np.ndarray]:
    """Per vertex the cos-weighted mean move along its normal that the kept depths ask
    for, and the sum of the weights (0: no photo saw it with a depth)."""
    normals = mesh.vertex_normals
    moves, weights = np.zeros(len(mesh.vertices)), np.zeros(len(mesh.vertices))
    for view, surface, depth_map in zip(views, surface_depths, kept):
        pixels, z = project(mesh.vertices, view.intrinsics, view.pose)
        u, v = np.round(pixels[:, 0]).astype(int), np.round(pixels[:, 1]).astype(int)
        height, width = depth_map.shape
        inside = (u >= 0) & (u < width) & (v >= 0) & (v < height) & (z > 0)
        found, front = np.zeros(len(z)), np.full(len(z), np.inf)
        found[inside], front[inside] = depth_map[v[inside], u[inside]], surface[v[inside], u[inside]]
        on = inside & (found > 0) & (z <= front * (1 + VISIBLE))
        camera = mesh.vertices[on] @ view.pose.R.T + view.pose.t
        move = (camera * (found[on] / z[on])[:, None] - camera) @ view.pose.R  # back to the world's axes
        to_camera = view.pose.center - mesh.vertices[on]
        cos = np.clip(np.einsum("ij,ij->i", to_camera / np.linalg.norm(to_camera, axis=1)[:, None], normals[on]), 0, 1)
        moves[on] += cos * np.einsum("ij,ij->i", move, normals[on])
        weights[on] += cos
    return np.divide(moves, weights, out=np.zeros_like(moves), where=weights > 0.5), weights


def smoothed(mesh: trimesh.Trimesh, moves: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """``moves`` spread to vertices without one and smoothed (module docstring, step 3)."""
    edges = mesh.edges_unique
    count = len(mesh.vertices)
    adjacency = sparse.coo_matrix(
        (np.ones(2 * len(edges)), (np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]])),
        shape=(count, count),
    ).tocsr()
    degree = np.maximum(np.asarray(adjacency.sum(axis=1)).ravel(), 1)
    trust = np.minimum(weights, 2.0) / 2.0
    for _ in range(10):
        moves = trust * moves + (1 - trust) * (adjacency @ moves) / degree
        moves = 0.5 * moves + 0.5 * (adjacency @ moves) / degree
    return moves


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("capture", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("-s", "--set", dest="overrides", action="append", default=[])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--span", type=float, default=0.01, help="depth searched either side of the mesh, relative")
    args = parser.parse_args()
    outputs = cached_outputs(args.capture, "mesh", args.overrides)
    mesh = trimesh.load(outputs["mesh"]["mesh"], force="mesh", process=False)
    for round_ in progress.track(range(args.rounds), "rounds"):
        views, surface_depths = stereo_views(mesh, outputs, args.span)
        neighbours = stereo.neighbours([v.pose for v in views], 4, 3.0, 45.0)
        depths, scores = [], []
        for view, others in progress.track(zip(views, neighbours), "stereo", total=len(views)):
            depth, score = stereo.plane_sweep(view, [views[j] for j in others], 48, 7, 2, stereo.MIN_TEXTURE)
            depths.append(depth)
            scores.append(score)
        typical = float(np.median([np.median(d[np.isfinite(d)]) for d in surface_depths]))
        kept = stereo.consistent_depths(views, depths, scores, neighbours, MIN_SCORE, 0.2 * args.span * typical, 1)
        moves, weights = normal_moves(mesh, views, surface_depths, kept)
        moves = smoothed(mesh, moves, weights)
        print(
            f"round {round_ + 1}: {100 * np.mean(weights > 0.5):.0f} % of the vertices seen with a depth; "
            f"move median {np.median(np.abs(moves)):.3g}, 90th percentile {np.percentile(np.abs(moves), 90):.3g} "
            f"(the mesh's diagonal {np.linalg.norm(mesh.extents):.4g})"
        )
        mesh = trimesh.Trimesh(mesh.vertices + moves[:, None] * mesh.vertex_normals, mesh.faces, process=False)
    mesh.export(args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
