import numpy as np
import trimesh

from pipeline.geometry.atlas import chart_texels, overlapping_texels


def _square(uv_scale: float = 1.0) -> trimesh.Trimesh:
    """The unit square in the z = 0 plane as two triangles, its UVs equal to x, y
    (times ``uv_scale``)."""
    vertices = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
    mesh = trimesh.Trimesh(vertices, [[0, 1, 2], [0, 2, 3]], process=False)
    mesh.visual = trimesh.visual.TextureVisuals(uv=vertices[:, :2] * uv_scale)
    return mesh


def test_texel_centres_land_where_their_uv_is_on_the_surface():
    texels = chart_texels(_square(), (4, 8))
    assert len(texels.index) == 32  # every centre once, also those on the shared diagonal
    rows, cols = np.divmod(texels.index, 8)
    np.testing.assert_allclose(texels.points[:, 0], (cols + 0.5) / 8)
    np.testing.assert_allclose(texels.points[:, 1], (rows + 0.5) / 4)  # row 0 at v = 0
    np.testing.assert_allclose(texels.points[:, 2], 0.0)


def test_texels_between_charts_copy_the_nearest_chart_texel():
    texels = chart_texels(_square(uv_scale=0.5), (4, 4))  # the chart covers the lower-left quarter
    assert sorted(texels.index.tolist()) == [0, 1, 4, 5]
    atlas = texels.fill_between_charts(np.arange(4, dtype=float)[:, None] + 1)[..., 0]
    assert set(np.unique(atlas)) == {1.0, 2.0, 3.0, 4.0}
    assert atlas[3, 3] == atlas[1, 1] and atlas[0, 3] == atlas[0, 1]


def test_a_mesh_without_charts_has_no_texels():
    texels = chart_texels(_square(uv_scale=0.01), (4, 4))  # too small to hold a texel centre
    assert texels.index.size == 0 and texels.points.shape == (0, 3)


def test_uv_triangles_that_share_texels_are_counted():
    square = _square(uv_scale=0.5)
    assert overlapping_texels(square, (8, 8)) == 0  # two triangles meet on an edge only
    doubled = trimesh.util.concatenate([square, square])
    doubled.visual = trimesh.visual.TextureVisuals(uv=np.vstack([square.visual.uv] * 2))
    assert overlapping_texels(doubled, (8, 8)) > 0


def test_rasterising_in_chunks_gives_the_texels_of_one_pass(monkeypatch):
    from pipeline.geometry import atlas

    sphere = trimesh.creation.icosphere(subdivisions=2)
    angles = np.arctan2(sphere.vertices[:, 1], sphere.vertices[:, 0])
    sphere.visual = trimesh.visual.TextureVisuals(
        uv=np.c_[(angles + np.pi) / (2 * np.pi), sphere.vertices[:, 2] / 2 + 0.5]
    )
    whole = chart_texels(sphere, (64, 64))
    monkeypatch.setattr(atlas, "FACE_TEXELS_CHUNK", 50)  # a few faces per chunk, some alone
    chunked = chart_texels(sphere, (64, 64))
    np.testing.assert_array_equal(chunked.index, whole.index)
    np.testing.assert_allclose(chunked.points, whole.points)
    assert overlapping_texels(sphere, (64, 64)) > 0  # the seam's faces wrap across the atlas
