import numpy as np

from pipeline.geometry.turntable import Turntable
from tests.support.turntable_views import CAMERA, pose_at


def test_the_model_reproduces_a_turning_table_seen_by_a_still_camera():
    """The circle in the frame of the photo at angle 0 (how the circular-motion solver
    states it): every pose of the table turned about world z is the model's at its angle,
    and angle_of inverts it."""
    axis = CAMERA.R @ np.array([0.0, 0.0, 1.0])
    point = CAMERA.R @ np.array([0.0, 0.0, CAMERA.center[2]]) + CAMERA.t  # the axis at the camera's height
    model = Turntable(axis, point, np.eye(3), np.zeros(3), {})
    for angle in np.radians([0.0, 17.0, 95.0, 181.0, 300.0]):
        truth = pose_at(angle)
        # The same camera in the photo-0 frame: world points x map to CAMERA's frame.
        expected_R = truth.R @ CAMERA.R.T
        expected_t = truth.t - expected_R @ CAMERA.t
        pose = model.pose(angle)
        np.testing.assert_allclose(pose.R, expected_R, atol=1e-12)
        np.testing.assert_allclose(pose.t, expected_t, atol=1e-12)
        assert abs(np.angle(np.exp(1j * (model.angle_of(pose) - angle)))) < 1e-9
        rotation, offset = model.residuals_at(pose, angle)
        assert rotation < 1e-6 and offset < 1e-9
    assert abs(model.radius - np.hypot(*CAMERA.center[:2])) < 1e-12
