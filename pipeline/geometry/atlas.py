"""Where a mesh's UV atlas lies on its surface, and which surface points a camera sees.

Used by ``pipeline score`` (the truth baked into a fitted atlas; the surface the
photos see), by the uv stage (texels two charts share) and by the synthetic
studio (the specimen as a Mitsuba mesh). Texels
follow Mitsuba's bitmap lookup: texel (row, col) has its centre at
uv = ((col + 0.5) / width, (row + 0.5) / height), row 0 at v = 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy import ndimage


@dataclass(frozen=True)
class Texels:
    """The texels of an atlas whose centre lies inside a chart, on the surface."""

    shape: tuple[int, int]
    """(height, width) of the atlas."""
    index: np.ndarray
    """(n,) flat indices (row * width + col) into the atlas."""
    points: np.ndarray
    """(n, 3) the texel centres on the surface."""

    def fill_between_charts(self, values: np.ndarray) -> np.ndarray:
        """An (h, w, channels) atlas holding ``values`` (n, channels) at the chart texels
        and, between charts, the nearest chart texel's value (so that bilinear reads at
        a chart's edge see no gap)."""
        height, width = self.shape
        atlas = np.zeros((height * width, values.shape[1]), dtype=values.dtype)
        atlas[self.index] = values
        outside = np.ones(height * width, dtype=bool)
        outside[self.index] = False
        _, (rows, cols) = ndimage.distance_transform_edt(outside.reshape(height, width), return_indices=True)
        return atlas.reshape(height, width, -1)[rows, cols]


FACE_TEXELS_CHUNK = 1 << 20
"""Candidate texels (bounding-box texels of the faces) tested at once: about 100 MB of
arrays, whatever the atlas's size."""


def _face_texels(textured: trimesh.Trimesh, shape: tuple[int, int]):
    """Chunks, in face order, of (face per texel, flat indices of the texels of an atlas of
    ``shape`` whose centre lies in that face's UV triangle, edges included, and the
    centres' barycentric weights (n, 3)); within a face, texels in row-major order."""
    height, width = shape
    corners = textured.visual.uv[textured.faces] * (width, height) - 0.5  # texel-centre coordinates
    lo = np.maximum(np.ceil(corners.min(axis=1)).astype(int), 0)
    hi = np.minimum(np.floor(corners.max(axis=1)).astype(int), (width - 1, height - 1))
    edges = np.stack([corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]], axis=-1)  # columns
    determinant = edges[:, 0, 0] * edges[:, 1, 1] - edges[:, 0, 1] * edges[:, 1, 0]
    faces = np.flatnonzero((hi >= lo).all(axis=1) & (np.abs(determinant) >= 1e-12))
    columns = hi[faces, 0] - lo[faces, 0] + 1
    counts = columns * (hi[faces, 1] - lo[faces, 1] + 1)
    # The inverse of each kept face's edge matrix, for the weights of every texel it covers.
    kept_edges = edges[faces]
    inverse = np.stack([kept_edges[:, 1, 1], -kept_edges[:, 0, 1], -kept_edges[:, 1, 0], kept_edges[:, 0, 0]], axis=-1)
    inverse = (inverse / determinant[faces, None]).reshape(-1, 2, 2)
    ends = np.cumsum(counts)
    first = 0
    while first < len(faces):
        last = max(first + 1, int(np.searchsorted(ends, (ends[first - 1] if first else 0) + FACE_TEXELS_CHUNK)))
        chunk_counts = counts[first:last]
        kept = np.repeat(np.arange(first, last), chunk_counts)  # per candidate texel: its face among the kept
        face = faces[kept]
        local = np.arange(chunk_counts.sum()) - np.repeat(np.cumsum(chunk_counts) - chunk_counts, chunk_counts)
        cols, rows = lo[face, 0] + local % columns[kept], lo[face, 1] + local // columns[kept]
        offset = np.c_[cols, rows] - corners[face, 0]
        weights = np.einsum("nij,nj->ni", inverse[kept], offset)
        weights = np.c_[1 - weights.sum(axis=1), weights]
        inside = (weights >= -1e-9).all(axis=1)
        yield face[inside], rows[inside] * width + cols[inside], weights[inside]
        first = last


def chart_texels(textured: trimesh.Trimesh, shape: tuple[int, int]) -> Texels:
    """Rasterise ``textured``'s UV triangles at the texel centres of an atlas of ``shape``."""
    index, points = [], []
    for face, texels, weights in _face_texels(textured, shape):
        index.append(texels)
        points.append(np.einsum("ni,nij->nj", weights, textured.vertices[textured.faces[face]]))
    # A texel centre on an edge shared by two faces is rasterised twice: keep the
    # later face's.
    if not index:
        return Texels(shape, np.zeros(0, dtype=int), np.zeros((0, 3)))
    index, last = np.unique(np.concatenate(index)[::-1], return_index=True)
    return Texels(shape, index, np.concatenate(points)[::-1][last])


def overlapping_texels(textured: trimesh.Trimesh, shape: tuple[int, int]) -> int:
    """How many texel centres of an atlas of ``shape`` lie strictly inside two or more
    UV triangles of ``textured``: surface points that would share one texel. A valid
    atlas has none."""
    covered = np.zeros(shape[0] * shape[1], dtype=int)
    for _, texels, weights in _face_texels(textured, shape):
        covered += np.bincount(texels[(weights > 1e-6).all(axis=1)], minlength=len(covered))
    return int(np.count_nonzero(covered > 1))


def mitsuba_mesh(mesh: trimesh.Trimesh, name: str, props=None):
    """``mesh`` as a Mitsuba mesh (positions and faces only), with plugin ``props``
    (BSDF, medium, emitter) bound at construction; needs Mitsuba's variant set."""
    import mitsuba as mi

    shape = mi.Mesh(
        name,
        len(mesh.vertices),
        len(mesh.faces),
        props if props is not None else mi.Properties(),
        has_vertex_normals=False,
    )
    params = mi.traverse(shape)
    params["vertex_positions"] = mi.Float(mesh.vertices.astype(np.float32).ravel())
    params["faces"] = mi.UInt32(mesh.faces.astype(np.uint32).ravel())
    params.update()
    return shape


def occluder(mesh: trimesh.Trimesh):
    """A Mitsuba scene of ``mesh`` alone, to test visibility against."""
    import mitsuba as mi

    return mi.load_dict({"type": "scene", "occluder": mitsuba_mesh(mesh, "occluder")})


def unoccluded(scene, points: np.ndarray, normals: np.ndarray, center: np.ndarray, offset: float) -> np.ndarray:
    """Whether each of ``points`` (on the surface of ``scene``'s mesh, facing ``normals``)
    faces ``center`` and nothing in ``scene`` lies between them. The ray leaves the
    surface by ``offset`` and stops as far short of the camera."""
    import mitsuba as mi

    to_camera = center - points
    distance = np.linalg.norm(to_camera, axis=1)
    to_camera = to_camera / distance[:, None]
    origins = np.asarray(points + offset * to_camera, dtype=np.float32)
    directions = np.asarray(to_camera, dtype=np.float32)
    # Ray3f(ray, maxt): the three-argument constructor reads its third as a time.
    rays = mi.Ray3f(
        mi.Ray3f(mi.Point3f(*map(mi.Float, origins.T)), mi.Vector3f(*map(mi.Float, directions.T))),
        mi.Float(np.asarray(distance - 2 * offset, dtype=np.float32)),
    )
    hidden = np.array(scene.ray_test(rays), dtype=bool)
    return ((to_camera * normals).sum(axis=1) > 0) & ~hidden
