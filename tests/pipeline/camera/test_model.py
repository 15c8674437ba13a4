import cv2
import numpy as np
import pytest

from pipeline.camera.model import Intrinsics, Pose, distortion_maps, pinhole_render_size, similarity_umeyama

INTRINSICS = Intrinsics(160, 120, 150.0, 150.0, 82.3, 57.1, [-0.09, 0.035, 0.0008, -0.0005, 0.0])


def test_look_at_puts_target_on_the_optical_axis_with_z_up_pointing_up_in_the_image():
    pose = Pose.look_at([0.3, -0.2, 0.25], [0.0, 0.0, 0.05])
    target_cam = pose.R @ np.array([0.0, 0.0, 0.05]) + pose.t
    assert np.allclose(target_cam[:2], 0, atol=1e-12) and target_cam[2] > 0
    above_cam = pose.R @ np.array([0.0, 0.0, 0.10]) + pose.t
    assert above_cam[1] / above_cam[2] < target_cam[1] / target_cam[2]  # higher = smaller image y
    assert np.allclose(pose.R @ pose.R.T, np.eye(3)) and np.isclose(np.linalg.det(pose.R), 1)


def test_distortion_maps_send_each_photo_pixel_to_its_ideal_ray():
    render_size = pinhole_render_size(INTRINSICS)
    map_x, map_y = distortion_maps(INTRINSICS, render_size)
    rng = np.random.default_rng(0)
    points = np.c_[rng.uniform(-0.4, 0.4, (50, 2)), np.ones(50)]
    distorted, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), INTRINSICS.K, np.array(INTRINSICS.dist))
    u, v = distorted[:, 0].T
    inside = (u > 1) & (u < INTRINSICS.width - 2) & (v > 1) & (v < INTRINSICS.height - 2)
    assert inside.sum() > 20
    for (x, y, _), pu, pv in zip(points[inside], u[inside], v[inside]):
        # bilinear read of the maps at the (sub-pixel) distorted position
        mx = cv2.getRectSubPix(map_x, (1, 1), (float(pu), float(pv)))[0, 0]
        my = cv2.getRectSubPix(map_y, (1, 1), (float(pu), float(pv)))[0, 0]
        assert mx == pytest.approx(x * INTRINSICS.fx + render_size[0] / 2 - 0.5, abs=0.02)
        assert my == pytest.approx(y * INTRINSICS.fy + render_size[1] / 2 - 0.5, abs=0.02)


def test_pinhole_render_covers_the_whole_distorted_frame():
    width, height = pinhole_render_size(INTRINSICS)
    map_x, map_y = distortion_maps(INTRINSICS, (width, height))
    assert map_x.min() >= 0 and map_x.max() <= width - 1
    assert map_y.min() >= 0 and map_y.max() <= height - 1


def test_umeyama_recovers_a_similarity():
    rng = np.random.default_rng(1)
    source = rng.normal(size=(20, 3))
    R = cv2.Rodrigues(np.array([0.3, -1.2, 0.5]))[0]
    target = 2.5 * source @ R.T + np.array([1.0, -2.0, 0.5])
    scale, R_est, t = similarity_umeyama(source, target)
    assert scale == pytest.approx(2.5) and np.allclose(R_est, R) and np.allclose(t, [1.0, -2.0, 0.5])


@pytest.mark.slow
def test_mitsuba_sensor_at_a_pose_sees_what_opencv_projects():
    from pipeline.render import mitsuba_variant

    mitsuba_variant.activate()
    import mitsuba as mi

    pose = Pose.look_at([0.3, 0.1, 0.2], [0.0, 0.0, 0.0])
    width, height, f = 200, 150, 180.0
    point = np.array([0.05, 0.03, 0.02])
    scene = mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "path", "max_depth": 1},
            "camera": {
                "type": "perspective",
                "fov": float(np.degrees(2 * np.arctan(width / 2 / f))),
                "fov_axis": "x",
                "to_world": mi.ScalarTransform4f(pose.mitsuba_to_world().tolist()),
                "film": {"type": "hdrfilm", "width": width, "height": height},
                "sampler": {"type": "independent", "sample_count": 16},
            },
            "dot": {
                "type": "sphere",
                "center": point.tolist(),
                "radius": 0.004,
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}},
            },
        }
    )
    image = np.asarray(mi.render(scene))[..., 0]
    ys, xs = np.nonzero(image > 0.5)
    K = Intrinsics(width, height, f, f, width / 2 - 0.5, height / 2 - 0.5).K
    projected, _ = cv2.projectPoints(point[None], cv2.Rodrigues(pose.R)[0], pose.t, K, None)
    assert xs.mean() == pytest.approx(projected[0, 0, 0], abs=0.3)
    assert ys.mean() == pytest.approx(projected[0, 0, 1], abs=0.3)
