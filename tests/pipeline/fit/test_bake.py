"""pipeline.fit.bake on a tiny scene: a glossy principled square whose base colour is an
8x8 bitmap of known texels, under a sky and a softbox, photographed from four sides."""

import numpy as np
import pytest

from pipeline.camera.model import Intrinsics, Pose
from pipeline.fit.bake import bake_bitmap, texels_hit
from pipeline.fit.loop import FitView
from pipeline.render import light, scene_xml

pytestmark = pytest.mark.slow
K = Intrinsics(96, 96, 120.0, 120.0, 47.5, 47.5)
KEY = "specimen.bsdf.base_color.data"
SIZE = (8, 8)


def _truth() -> np.ndarray:
    rng = np.random.default_rng(3)
    return rng.uniform(0.1, 0.9, (*SIZE, 3)).astype(np.float32)


def _views(mi, texture: np.ndarray, references: list[np.ndarray] | None = None) -> list[FitView]:
    softbox = mi.ScalarTransform4f().look_at(origin=[0.5, 0.3, 1.2], target=[0, 0, 0], up=[0, 0, 1]).scale(0.3)
    bitmap = {"type": "bitmap", "id": "specimen_base_color", "data": mi.TensorXf(texture), "raw": True}
    scene = mi.load_dict(
        {
            "type": "scene",
            "environment": {
                "type": "constant",
                "id": "environment",
                "radiance": {"type": "rgb", "value": [0.4, 0.4, 0.4]},
            },
            "softbox": {
                "type": "rectangle",
                "id": "softbox",
                "to_world": softbox,
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [4.0, 4.0, 4.0]}},
            },
            "specimen": {
                "type": "rectangle",
                "id": "specimen",
                "to_world": mi.ScalarTransform4f().scale(0.2),
                "bsdf": {
                    "type": "principled",
                    "id": "specimen_bsdf",
                    # nearest: each texel's colour alone on its square (the bake's own assumption)
                    "base_color": {**bitmap, "filter_type": "nearest"},
                    "roughness": 0.3,
                    "specular": 0.5,
                },
            },
        }
    )
    eyes = ([0.3, 0.0, 0.6], [0.0, 0.3, 0.6], [-0.3, 0.0, 0.6], [0.0, -0.3, 0.6])
    return _seen_from(mi, scene, 3, eyes, ([0.0, 0.0, 0.0], [0.0, 0.0, 1.0]), references)


def _seen_from(mi, scene, depth: int, eyes, target_up, references: list[np.ndarray] | None) -> list[FitView]:
    """``scene`` as a view from each eye towards ``target_up``'s target, ``references``
    its photos (black when None)."""
    integrator = mi.load_dict({"type": "prb", "max_depth": depth})
    views = []
    for index, eye in enumerate(eyes):
        pose = Pose.look_at(eye, target_up[0], up=target_up[1])
        sensor = scene_xml.load_sensor(scene_xml.sensor_properties(K, pose, 16, 0.01))
        reference = references[index] if references else np.zeros((K.height, K.width, 3), np.float32)
        views.append(FitView(f"view{index}", scene, sensor, reference, None, integrator))
    return views


@pytest.fixture(scope="module")
def photos(mi) -> list[np.ndarray]:
    """Each view rendered with the true bitmap (many samples: the photos)."""
    return [
        np.array(mi.render(v.scene, sensor=v.sensor, integrator=v.integrator, spp=256, seed=7))
        for v in _views(mi, _truth())
    ]


def test_every_pixel_centre_on_the_square_finds_its_texel(mi):
    """The texel a pixel's ray meets is the one whose colour the pixel shows (rows follow
    v, columns u); rays past the square find none."""
    texture = np.zeros((*SIZE, 3), np.float32)
    texture[..., 0] = np.arange(64).reshape(SIZE) / 64.0  # each texel's index in red, no light needed
    views = _views(mi, texture)
    emitting = mi.load_dict({"type": "aov", "aovs": "uv:uv"})
    view = views[0]
    uv = np.array(mi.render(view.scene, sensor=view.sensor, integrator=emitting, spp=1, seed=0))
    index = texels_hit(view, "specimen", SIZE)
    hit = index >= 0
    assert 0.2 < hit.mean() < 0.95
    inside = hit & (np.abs(uv[..., 0] * 8 - np.round(uv[..., 0] * 8)) > 0.2)
    inside &= np.abs(uv[..., 1] * 8 - np.round(uv[..., 1] * 8)) > 0.2
    expected = np.floor(uv[..., 1] * 8) * 8 + np.floor(uv[..., 0] * 8)
    assert np.mean(index[inside] == expected[inside]) > 0.95


def test_the_bake_recovers_the_true_texels_from_the_photos(mi, photos):
    """Under the true light and constants the least-squares texels match the truth,
    though the square is glossy (the specular part is not the colour's); the scene's
    bitmap is put back."""
    start = np.full((2, 2, 3), 0.5, np.float32)
    views = _views(mi, start, photos)
    texture, seen, scale = bake_bitmap(views, KEY, "specimen", SIZE, 64, (0.001, 1.0), [v.scene for v in views])
    assert seen == 1.0 and scale == 1.0  # the light is bright enough: it stays
    assert np.abs(texture - _truth()).mean() < 0.025
    assert np.abs(texture - _truth()).max() < 0.1
    assert np.array(mi.traverse(views[0].scene)[KEY]).shape == (2, 2, 3)


def test_texels_no_photo_sees_take_the_nearest_seen_value(mi, photos):
    """A bitmap four times finer than any view resolves leaves texels unseen: they take
    their nearest seen neighbour's value, never 0 or the bounds; values stay in bounds."""
    views = _views(mi, np.full((2, 2, 3), 0.5, np.float32), photos)
    texture, seen, _ = bake_bitmap(views[:1], KEY, "specimen", (128, 128), 16, (0.2, 0.8))
    assert 0.05 < seen < 0.9
    assert texture.min() >= 0.2 and texture.max() <= 0.8
    coarse = texture.reshape(8, 16, 8, 16, 3).mean(axis=(1, 3))
    assert np.abs(coarse - np.clip(_truth(), 0.2, 0.8)).mean() < 0.04


def test_a_light_too_dim_for_the_brightest_texels_is_raised_until_they_fit(mi, photos):
    """The photos' light halved (a level guessed too low): the true texels would need
    colours up to 1.8. Without ``relit`` they are cut to 1 and the scene is left alone;
    with it the light rises by the smallest factor that fits 99 % of the texels under
    1, the texels come out as the truth over that factor (relative to the true light),
    and every emitter of the scene is multiplied by it."""
    views = _views(mi, np.full((2, 2, 3), 0.5, np.float32), photos)
    scene = views[0].scene
    light.rescale_scenes([scene], 0.5)
    cut, _, kept = bake_bitmap(views, KEY, "specimen", SIZE, 64, (0.001, 1.0))
    assert kept == 1.0 and (cut.max(axis=-1) >= 1.0).mean() > 0.3
    texture, _, scale = bake_bitmap(views, KEY, "specimen", SIZE, 64, (0.001, 1.0), [scene])
    needed = 2 * _truth().max(axis=-1).ravel()
    assert scale == pytest.approx(np.quantile(needed, 0.99), rel=0.05)
    assert np.abs(texture * scale / 2 - _truth()).mean() < 0.03
    params = mi.traverse(scene)
    assert np.allclose(params["softbox.emitter.radiance.value"], 4.0 * 0.5 * scale, rtol=1e-5)
    assert np.allclose(params["environment.radiance.value"], 0.4 * 0.5 * scale, rtol=1e-5)


def _groove_views(mi, folder, texture: np.ndarray, references: list[np.ndarray] | None = None) -> list[FitView]:
    """A pale diffuse V-groove (two 0.4 m walls meeting at a right angle, one bitmap
    across both: u 0-0.5 on the left wall, 0.5-1 on the right) under a sky, seen from
    three places above it: each wall sees the other over a quarter of its sky."""
    obj = folder / "groove.obj"
    obj.write_text(
        "v -0.2 -0.2 0.2\nv 0 -0.2 0\nv 0 0.2 0\nv -0.2 0.2 0.2\nv 0.2 -0.2 0.2\nv 0.2 0.2 0.2\n"
        "vt 0 0\nvt 0.5 0\nvt 0.5 1\nvt 0 1\nvt 1 0\nvt 1 1\n"
        "f 1/1 2/2 3/3\nf 1/1 3/3 4/4\nf 2/2 5/5 6/6\nf 2/2 6/6 3/3\n"
    )
    bitmap = {"type": "bitmap", "id": "specimen_base_color", "data": mi.TensorXf(texture), "raw": True}
    scene = mi.load_dict(
        {
            "type": "scene",
            "environment": {"type": "constant", "id": "environment", "radiance": {"type": "rgb", "value": [1.0] * 3}},
            "specimen": {
                "type": "obj",
                "id": "specimen",
                "filename": str(obj),
                "face_normals": True,
                "bsdf": {
                    "type": "principled",
                    "id": "specimen_bsdf",
                    "base_color": {**bitmap, "filter_type": "nearest"},
                    "roughness": 1.0,
                    "specular": 0.0,
                },
            },
        }
    )
    eyes = ([0.15, 0.0, 0.8], [-0.15, 0.05, 0.8], [0.0, -0.1, 0.8])
    return _seen_from(mi, scene, 6, eyes, ([0.0, 0.0, 0.1], [0.0, 1.0, 0.0]), references)


def test_rounds_remove_the_darkening_of_light_the_specimen_reflects_onto_itself(mi, tmp_path):
    """In a pale groove each wall is lit by the other too: the first solution, whose D
    holds those bounces at colour 1, comes out darker than the truth; two more rounds
    bring the texels to it and the renders to the photos."""
    truth = np.random.default_rng(5).uniform(0.6, 0.95, (*SIZE, 3)).astype(np.float32)
    photos = [
        np.array(mi.render(v.scene, sensor=v.sensor, integrator=v.integrator, spp=256, seed=11))
        for v in _groove_views(mi, tmp_path, truth)
    ]
    views = _groove_views(mi, tmp_path, np.full((2, 2, 3), 0.5, np.float32), photos)
    once, seen, _ = bake_bitmap(views, KEY, "specimen", SIZE, 64, (0.001, 1.0))
    thrice, _, _ = bake_bitmap(views, KEY, "specimen", SIZE, 64, (0.001, 1.0), rounds=3)
    assert seen == 1.0
    assert np.mean(once - truth) < -0.04  # the one-round bake is biased dark
    assert abs(np.mean(thrice - truth)) < 0.01
    assert np.abs(thrice - truth).mean() < 0.4 * np.abs(once - truth).mean()


def test_rounds_raise_a_guessed_light_again_when_they_brighten_texels_past_the_bound(mi, tmp_path):
    """The groove's photos under half their light (a level guessed too low): the first
    round raises the light until its texels fit under 1, the rounds brighten them past
    it, and the light rises again, so that no more than HEADROOM of the texels end on
    the bound and the renders match the photos (the first round alone renders dark)."""
    truth = np.random.default_rng(5).uniform(0.6, 0.95, (*SIZE, 3)).astype(np.float32)
    photos = [
        np.array(mi.render(v.scene, sensor=v.sensor, integrator=v.integrator, spp=256, seed=11))
        for v in _groove_views(mi, tmp_path, truth)
    ]

    def bias(rounds: int) -> tuple[float, float, float]:
        views = _groove_views(mi, tmp_path, np.full((2, 2, 3), 0.5, np.float32), photos)
        scene = views[0].scene
        light.rescale_scenes([scene], 0.5)
        texture, _, scale = bake_bitmap(views, KEY, "specimen", SIZE, 64, (0.001, 1.0), [scene], rounds)
        params = mi.traverse(scene)
        params[KEY] = mi.TensorXf(texture)
        params.update()
        rendered, seen = [], []
        for view, photo in zip(views, photos):
            image = np.array(mi.render(scene, sensor=view.sensor, integrator=view.integrator, spp=256, seed=3))
            on = texels_hit(view, "specimen", SIZE) >= 0
            rendered.append(image[on].sum())
            seen.append(photo[on].sum())
        at_bound = float((texture.max(axis=-1) >= 1.0).mean())
        return sum(rendered) / sum(seen) - 1.0, at_bound, scale

    once, once_at_bound, once_scale = bias(1)
    thrice, thrice_at_bound, thrice_scale = bias(3)
    assert once < -0.03 and once_at_bound <= 1 / 64
    assert abs(thrice) < 0.01 and thrice_at_bound <= 1 / 64
    assert thrice_scale > once_scale > 1.0


def test_a_bake_that_sees_no_texel_leaves_the_light_and_returns_the_lower_bound(mi, photos):
    """No pixel meets the shape (another shape's id): nothing is seen, the light is not
    raised in any round, and every texel is the lower bound."""
    views = _views(mi, np.full((2, 2, 3), 0.5, np.float32), photos)
    texture, seen, scale = bake_bitmap(views, KEY, "no-such-shape", SIZE, 4, (0.2, 1.0), [views[0].scene], 2)
    assert seen == 0.0 and scale == 1.0
    assert np.all(texture == np.float32(0.2))
    assert np.allclose(mi.traverse(views[0].scene)["environment.radiance.value"], 0.4)
