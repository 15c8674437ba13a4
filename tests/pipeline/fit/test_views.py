"""pipeline.fit.views: every view's window one size, cut from its photo and rendered
by a camera whose whole film is the window."""

from dataclasses import replace

import cv2
import numpy as np
import pytest
import trimesh

from pipeline.camera.model import Pose, resize_exact, scaled
from pipeline.fit.views import (
    BOARD_MARGIN,
    PHOTO_BLUR_PX,
    BoardPixels,
    board_weight,
    mask_windows,
    pixel_filter,
    specimen_masks,
)
from pipeline.render import scene_xml
from tests.support.sphere_views import RADIUS, K, sphere_mask, sphere_views


def _box_mask(shape, x0, y0, x1, y1):
    mask = np.zeros(shape, bool)
    mask[y0:y1, x0:x1] = True
    return mask


def test_every_window_has_one_size_and_holds_its_mask():
    shape = (300, 400)
    masks = {
        "wide": _box_mask(shape, 50, 100, 350, 160),
        "tall": _box_mask(shape, 180, 20, 220, 280),
        "small": _box_mask(shape, 10, 10, 30, 40),
        "empty": np.zeros(shape, bool),
    }
    windows = mask_windows(masks, max_size=64)
    assert set(windows) == {"wide", "tall", "small"}
    assert len({(w.width, w.height) for w in windows.values()}) == 1
    assert max(windows["wide"].width, windows["wide"].height) <= 64
    for name, window in windows.items():
        covered = window.cut(masks[name].astype(np.float32)).sum() / window.scale**2
        assert covered == pytest.approx(masks[name].sum(), rel=0.02), name


def test_a_window_is_at_most_max_size_whatever_the_boxs_size():
    """Scaling a box to max_size lands a rounding error above it for some sizes (187 px at
    48, for one): the window must not grow a pixel past max_size for it."""
    windows = [
        mask_windows({"v": _box_mask((300, 2100), 20, 100, 20 + span, 140)}, max_size=48)["v"]
        for span in range(60, 2000)
    ]
    assert {max(window.width, window.height) for window in windows} == {48}


def test_a_window_past_the_photos_edge_is_zero_there_and_scores_nothing_there():
    shape = (120, 160)
    corner = _box_mask(shape, 0, 0, 20, 20)
    windows = mask_windows({"corner": corner, "middle": _box_mask(shape, 40, 30, 120, 90)}, max_size=200)
    window = windows["corner"]
    assert window.x < 0 and window.y < 0
    inside = window.inside()
    assert inside[0, 0] == 0 and inside[-1, -1] == 1
    assert window.cut(np.ones(shape, np.float32))[0, 0] == 0


@pytest.mark.slow
def test_the_windows_camera_renders_the_window_of_the_whole_photo(mi):
    """The principal point moved instead of a film crop: the same pixels as cutting the
    window out of a render of the whole (scaled) photo."""
    pose = Pose.look_at([0.25, 0.1, 0.12], [0.0, 0.0, 0.0], up=[0.0, 0.0, 1.0])
    scene = mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "path", "max_depth": 3},
            "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 0.5}},
            "ball": {"type": "sphere", "radius": 0.05, "bsdf": {"type": "diffuse"}},
        }
    )
    window = mask_windows({"view": sphere_mask(pose)}, max_size=48)["view"]
    assert window.scale < 1

    def render(intrinsics):
        sensor = scene_xml.load_sensor(scene_xml.sensor_properties(intrinsics, pose, 64, 0.01))
        return np.asarray(mi.render(scene, sensor=sensor, spp=64, seed=1))

    whole = render(scaled(K, window.scale, exact=True))
    expected = replace(window, scale=1.0, photo_shape=whole.shape[:2]).cut(whole)  # only the cut
    rendered = render(window.intrinsics(K))
    inside = window.inside() > 0
    # Right: 0.016 (noise); the principal point 0.3 px off: 0.052, 1 px off: 0.148.
    assert np.percentile(np.abs(rendered - expected)[inside], 99) < 0.03


def test_a_mask_that_took_in_backdrop_is_cut_to_the_meshs_outline_with_a_warning(tmp_path, caplog):
    trimesh.creation.icosphere(subdivisions=4, radius=RADIUS).export(tmp_path / "mesh.ply")
    views = sphere_views(2)
    masks = {}
    for i, view in enumerate(views):
        mask = view.mask.copy()
        if i == 1:
            mask[:, :30] = True  # a strip of coloured wall, taken for specimen
        masks[f"v{i}.jpg"] = tmp_path / f"v{i}.png"
        cv2.imwrite(str(masks[f"v{i}.jpg"]), mask.astype(np.uint8) * 255)
    cameras = {f"v{i}.jpg": (view.intrinsics, view.pose) for i, view in enumerate(views)}
    cut = specimen_masks(tmp_path / "mesh.ply", cameras, masks)
    for i, view in enumerate(views):
        kept = cut[f"v{i}.jpg"]
        assert (kept & view.mask).sum() / (kept | view.mask).sum() > 0.95
    assert "v1.jpg" in caplog.text and "v0.jpg" not in caplog.text
    caplog.clear()
    specimen_masks(tmp_path / "mesh.ply", cameras, masks)  # a stage loads its views again
    assert "v1.jpg" not in caplog.text


def test_the_boards_print_counts_outside_the_specimen_and_widens_the_window():
    views = sphere_views(2)
    board = BoardPixels((0.12, 0.09), count=True)
    for view in views:
        masks = {"v": view.mask}
        narrow = mask_windows(masks, max_size=400)["v"]
        window = mask_windows(masks, max_size=400, board_margin=BOARD_MARGIN)["v"]
        assert window.width > narrow.width and window.height > narrow.height
        weight = board_weight(window, view.intrinsics, view.pose, board, view.mask)
        # every weighted pixel's ray meets the print, none is the specimen or next to it
        camera = window.intrinsics(view.intrinsics)
        rows, columns = np.nonzero(weight)
        rays = np.stack([(columns - camera.cx) / camera.fx, (rows - camera.cy) / camera.fy, np.ones(len(rows))], 1)
        rays = rays @ view.pose.R
        hits = view.pose.center + (-view.pose.center[2] / rays[:, 2])[:, None] * rays
        assert np.all(np.abs(hits[:, :2]) < [0.12, 0.09])
        assert not (weight & (window.cut(view.mask.astype(np.float32)) > 0)).any()
        assert weight.sum() > 0.1 * weight.size  # the cameras look down on the print round the sphere


@pytest.mark.slow
def test_a_window_averaged_down_from_its_photo_renders_as_sharp_as_the_photo(mi):
    """A photo of a fine checker (Mitsuba's default filter at full resolution), averaged
    down four times: the window's filter (pixel_filter) re-renders it closer than
    Mitsuba's default, which blurs past the averaged photo, and a photo shown at its own
    resolution keeps about the default (0.5 px)."""
    pose = Pose.look_at([0.25, 0.1, 0.12], [0.0, 0.0, 0.0], up=[0.0, 0.0, 1.0])
    checker = {"type": "checkerboard", "to_uv": mi.ScalarTransform4f().scale([24, 24, 1])}
    scene = mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "path", "max_depth": 2},
            "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
            "ball": {"type": "sphere", "radius": 0.05, "bsdf": {"type": "diffuse", "reflectance": checker}},
        }
    )
    big = scaled(K, 4.0, exact=True)

    def render(intrinsics, rfilter):
        properties = scene_xml.sensor_properties(intrinsics, pose, 128, 0.01, rfilter=rfilter)
        return np.asarray(mi.render(scene, sensor=scene_xml.load_sensor(properties), spp=128, seed=3))

    photo = resize_exact(render(big, None), 0.25)
    errors = {
        label: float(np.mean((render(K, rfilter) - photo) ** 2))
        for label, rfilter in (("window", pixel_filter(0.25)), ("default", None))
    }
    # measured: window 0.000026, default 0.000175 (seven times the error)
    assert errors["window"] < 0.5 * errors["default"], errors
    assert pixel_filter(1.0)["stddev"] == pytest.approx(np.sqrt(1 / 12 + PHOTO_BLUR_PX**2))
    assert 0.45 < pixel_filter(0.5)["stddev"] < 0.5  # the sample bird's windows: about the default


def test_held_out_photos_beyond_what_a_capture_has_are_fewer_with_a_warning(caplog):
    from pipeline.fit.views import held_out_names

    names = [f"view_{i:03d}" for i in range(6)]
    assert held_out_names(names, 2) == ["view_002", "view_003"] and "held_out" not in caplog.text
    held = held_out_names(names, 1000)
    assert len(held) == 5 and "held_out = 1000, but with 6 photos at most 5 are held out" in caplog.text
    assert held_out_names(names[:2], 1) == [] and "too few to hold any out" in caplog.text
