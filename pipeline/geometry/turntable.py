"""The turntable model: a fixed camera and an object turning about one axis (or,
equally, a camera carried round a still object on one circle).

In the object's frame the camera moves on a circle: photo i, taken after the table
turned by ``angle[i]``, has the pose

    R_i = R_fixed @ Rot(axis, angle_i),     c_i = Rot(axis, angle_i)^T (c_fixed - o) + o

with ``o`` a point on the axis. The model has 6 + 2 + 2 degrees of freedom plus
one angle per photo, against 6 per photo for free poses. The circular-motion
solver (pipeline.geometry.circular_motion) finds it from feature matches.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.camera.model import Pose, rotation_angle_deg


def _turn(axis: np.ndarray, angle: float) -> np.ndarray:
    return Rotation.from_rotvec(axis * angle).as_matrix()


@dataclass
class Turntable:
    axis: np.ndarray
    """Unit vector; the table turns by +angle about it from one photo to the next."""
    point: np.ndarray
    """A point on the axis."""
    R_fixed: np.ndarray
    c_fixed: np.ndarray
    angles: dict[str, float]
    """Angle of each placed photo, radians."""

    def pose(self, angle: float) -> Pose:
        turn = _turn(self.axis, angle)
        R = self.R_fixed @ turn
        centre = turn.T @ (self.c_fixed - self.point) + self.point
        return Pose(R, -R @ centre)

    @property
    def radius(self) -> float:
        offset = self.c_fixed - self.point
        return float(np.linalg.norm(offset - self.axis * (offset @ self.axis)))

    def angle_of(self, pose: Pose) -> float:
        """The angle whose model rotation is nearest to ``pose``'s."""
        rotvec = Rotation.from_matrix(self.R_fixed.T @ pose.R).as_rotvec()
        return float(rotvec @ self.axis)

    def residuals_at(self, pose: Pose, angle: float) -> tuple[float, float]:
        """Rotation difference (degrees) and centre distance (fraction of the radius)
        between ``pose`` and the model's pose at ``angle``."""
        model = self.pose(angle)
        return rotation_angle_deg(model.R @ pose.R.T), float(np.linalg.norm(model.center - pose.center) / self.radius)
