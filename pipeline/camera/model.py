"""Camera models and the conventions that tie OpenCV, COLMAP and Mitsuba together.

Poses follow COLMAP: ``R, t`` map world to camera (``x_cam = R x_world + t``),
camera axes x right, y down, z forward; ``qvec`` is COLMAP's (w, x, y, z).
Intrinsics follow OpenCV: pixel (0, 0) is the *centre* of the top-left pixel and
distortion is ``(k1, k2, p1, p2, k3)``. Mitsuba's camera looks down +z with +x to
the left and +y up, and its pixel (0, 0) is the top-left *corner*; the helpers
below convert.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

# Mitsuba camera axes expressed in COLMAP camera axes (x left = -x right, y up = -y down).
_MITSUBA_FROM_COLMAP = np.diag([-1.0, -1.0, 1.0])


@dataclass
class Intrinsics:
    """A pinhole camera with OpenCV radial-tangential distortion."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: list[float] = field(default_factory=lambda: [0.0] * 5)
    """(k1, k2, p1, p2, k3)"""

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def to_json(self) -> dict:
        return asdict(self)

    def without_distortion(self) -> "Intrinsics":
        """The same pinhole, distortion left out."""
        return Intrinsics(self.width, self.height, float(self.fx), float(self.fy), float(self.cx), float(self.cy))

    @classmethod
    def from_json(cls, data: dict) -> "Intrinsics":
        return cls(**{k: data[k] for k in ("width", "height", "fx", "fy", "cx", "cy", "dist")})


@dataclass
class Pose:
    """World-to-camera rigid transform, COLMAP convention."""

    R: np.ndarray
    t: np.ndarray

    @property
    def center(self) -> np.ndarray:
        return -self.R.T @ self.t

    @property
    def qvec(self) -> np.ndarray:
        x, y, z, w = Rotation.from_matrix(self.R).as_quat()
        return np.array([w, x, y, z])

    @classmethod
    def look_at(cls, center, target, up=(0.0, 0.0, 1.0), roll_deg: float = 0.0) -> "Pose":
        center, target, up = (np.asarray(v, dtype=float) for v in (center, target, up))
        forward = target - center
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, up)
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        R = np.stack([right, down, forward])
        R = Rotation.from_euler("z", roll_deg, degrees=True).as_matrix() @ R
        return cls(R, -R @ center)

    def mitsuba_to_world(self) -> np.ndarray:
        """4x4 ``to_world`` matrix for a Mitsuba sensor at this pose."""
        M = np.eye(4)
        M[:3, :3] = self.R.T @ _MITSUBA_FROM_COLMAP
        M[:3, 3] = self.center
        return M

    def to_json(self) -> dict:
        return {
            "R": self.R.tolist(),
            "t": self.t.tolist(),
            "qvec": self.qvec.tolist(),
            "center": self.center.tolist(),
        }

    @classmethod
    def from_json(cls, data: dict) -> "Pose":
        return cls(np.asarray(data["R"], dtype=float), np.asarray(data["t"], dtype=float))


@dataclass(frozen=True)
class Similarity:
    """x_truth = scale * R @ x_estimate + t."""

    scale: float
    R: np.ndarray
    t: np.ndarray

    @classmethod
    def identity(cls) -> "Similarity":
        return cls(1.0, np.eye(3), np.zeros(3))

    def points(self, x: np.ndarray) -> np.ndarray:
        return self.scale * x @ self.R.T + self.t

    def pose(self, pose: Pose) -> Pose:
        """The same camera in the new frame (rotation and centre; scale moves the centre)."""
        R = pose.R @ self.R.T
        return Pose(R, -R @ self.points(pose.center[None])[0])

    def then(self, other: "Similarity") -> "Similarity":
        """``other`` applied after this one."""
        return Similarity(other.scale * self.scale, other.R @ self.R, other.points(self.t[None])[0])

    def matrix(self) -> np.ndarray:
        M = np.eye(4)
        M[:3, :3] = self.scale * self.R
        M[:3, 3] = self.t
        return M

    def to_json(self) -> dict:
        return {"scale": float(self.scale), "R": self.R.tolist(), "t": self.t.tolist()}

    @classmethod
    def from_json(cls, data: dict) -> "Similarity":
        return cls(float(data["scale"]), np.asarray(data["R"], float), np.asarray(data["t"], float))


def project(points: np.ndarray, intrinsics: Intrinsics, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (N, 2) and depths (N,) of world points in an undistorted
    pinhole view; points at or behind the camera get finite pixels (check the depth)."""
    cam = points @ pose.R.T + pose.t
    z = cam[:, 2]
    safe = np.where(z > 1e-9, z, 1e-9)
    return np.stack(
        [intrinsics.fx * cam[:, 0] / safe + intrinsics.cx, intrinsics.fy * cam[:, 1] / safe + intrinsics.cy], axis=-1
    ), z


def ground_hits(intrinsics: Intrinsics, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel's ray (pixel centres, distortion ignored) meets the plane z = 0:
    the points (h, w, 3) and the distance along the ray (h, w), not positive where the
    ray does not reach the plane."""
    columns, rows = np.meshgrid(np.arange(intrinsics.width), np.arange(intrinsics.height))
    camera_rays = [(columns - intrinsics.cx) / intrinsics.fx, (rows - intrinsics.cy) / intrinsics.fy]
    rays = np.stack([*camera_rays, np.ones(columns.shape)], -1) @ pose.R
    with np.errstate(divide="ignore", invalid="ignore"):
        distance = -pose.center[2] / rays[..., 2]
    return pose.center + distance[..., None] * rays, distance


COVERAGE_LIMIT_PX = 1e7
"""How far outside the image mesh_coverage keeps a triangle's corner."""


def mesh_coverage(
    vertices: np.ndarray, faces: np.ndarray, intrinsics: Intrinsics, pose: Pose, factor: int = 4
) -> np.ndarray:
    """Fraction of each pixel a mesh covers in the (distorted) view, rasterised at
    ``factor`` times the resolution: a mask from known geometry and cameras."""
    projected, _ = cv2.projectPoints(
        vertices, cv2.Rodrigues(pose.R)[0], pose.t, intrinsics.K, np.array(intrinsics.dist)
    )
    # pixel centres at integers: the fine grid's sample for coarse x is (x + 0.5) * factor - 0.5
    fine = (projected[:, 0] + 0.5) * factor - 0.5
    canvas = np.zeros((intrinsics.height * factor, intrinsics.width * factor), np.float32)
    triangles = fine[faces]
    # Non-finite corners have no place in the image; far ones are brought in to where
    # 16 * x still fits an int32 (OpenCV's fixed point), which moves no visible edge.
    triangles = np.clip(triangles[np.isfinite(triangles).all(axis=(1, 2))], -COVERAGE_LIMIT_PX, COVERAGE_LIMIT_PX)
    # one call per triangle: fillPoly would treat overlapping triangles as one even-odd shape
    for triangle in np.round(triangles * 16).astype(np.int32):
        cv2.fillConvexPoly(canvas, triangle, 1.0, shift=4)
    return cv2.resize(canvas, (intrinsics.width, intrinsics.height), interpolation=cv2.INTER_AREA)


def pinhole_render_size(intrinsics: Intrinsics, margin: int = 4) -> tuple[int, int]:
    """Size of a centred pinhole image (focal fx) that covers the distorted frame."""
    w, h = intrinsics.width, intrinsics.height
    border = np.array(
        [[x, y] for x in np.linspace(0, w - 1, 33) for y in (0, h - 1)]
        + [[x, y] for y in np.linspace(0, h - 1, 33) for x in (0, w - 1)],
        dtype=np.float64,
    )
    ideal = cv2.undistortPoints(border[:, None], intrinsics.K, np.asarray(intrinsics.dist))[:, 0]
    half = np.abs(ideal).max(axis=0) * intrinsics.fx + margin
    return int(2 * np.ceil(half[0])), int(2 * np.ceil(half[1]))


def distortion_maps(intrinsics: Intrinsics, render_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap maps that turn a centred pinhole render into the distorted photo.

    For every photo pixel, undistort its coordinates to the ideal image plane and
    look it up in the render (whose focal length is ``fx`` and whose optical axis
    passes through its centre), the way a real lens bends rays.
    """
    if not np.isclose(intrinsics.fx, intrinsics.fy):
        raise ValueError("the synthetic camera has square pixels (fx == fy)")
    u, v = np.meshgrid(np.arange(intrinsics.width), np.arange(intrinsics.height))
    pixels = np.stack([u.ravel(), v.ravel()], axis=-1).astype(np.float64)[:, None]
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
    ideal = cv2.undistortPoints(pixels, intrinsics.K, np.asarray(intrinsics.dist), criteria=criteria)[:, 0]
    render_w, render_h = render_size
    # Render pixel index j has its centre at continuous coordinate j + 0.5.
    map_x = ideal[:, 0] * intrinsics.fx + render_w / 2 - 0.5
    map_y = ideal[:, 1] * intrinsics.fy + render_h / 2 - 0.5
    shape = (intrinsics.height, intrinsics.width)
    return map_x.reshape(shape).astype(np.float32), map_y.reshape(shape).astype(np.float32)


def similarity_umeyama(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Scale s, rotation R, translation t minimising |s R source + t - target|^2."""
    mu_s, mu_t = source.mean(0), target.mean(0)
    xs, xt = source - mu_s, target - mu_t
    U, D, Vt = np.linalg.svd(xt.T @ xs / len(source))
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    scale = np.trace(np.diag(D) @ S) / xs.var(0).sum()
    return scale, R, mu_t - scale * R @ mu_s


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix, in degrees."""
    # Rotation.magnitude stays accurate for tiny angles, unlike arccos of the trace.
    return float(np.degrees(Rotation.from_matrix(R).magnitude()))


def ideal_pinhole(intrinsics: Intrinsics, alpha: float, max_size: int) -> Intrinsics:
    """The distortion-free camera with square pixels that photos of ``intrinsics`` are
    undistorted to.

    ``alpha`` is OpenCV's free scaling (0: only valid pixels, 1: every source pixel
    kept); ``max_size`` (0 for none) caps the longer side, scaling the focal length
    and principal point with the pixels.
    """
    size = (intrinsics.width, intrinsics.height)
    if any(intrinsics.dist):
        K, _ = cv2.getOptimalNewCameraMatrix(intrinsics.K, np.asarray(intrinsics.dist), size, alpha, size)
    else:
        K = intrinsics.K
    # Square pixels: renderers (Mitsuba's perspective sensor) have no pixel aspect,
    # and a calibrated fx / fy differs from 1 by noise (0.5 % at 384 px).
    focal = float(np.sqrt(K[0, 0] * K[1, 1]))
    pinhole = Intrinsics(size[0], size[1], focal, focal, K[0, 2], K[1, 2])
    return scaled(pinhole, max_size / max(size)) if 0 < max_size < max(size) else pinhole


def scaled(intrinsics: Intrinsics, factor: float, exact: bool = False) -> Intrinsics:
    """The same camera for images resized by ``factor`` (pixel centres stay pixel centres):
    to the rounded size (``cv2.resize`` with a size), or with ``exact`` by the factor
    itself on both axes (``cv2.resize`` with fx = fy = factor; square pixels stay square)."""
    width, height = round(intrinsics.width * factor), round(intrinsics.height * factor)
    sx, sy = (factor, factor) if exact else (width / intrinsics.width, height / intrinsics.height)
    return Intrinsics(
        width,
        height,
        intrinsics.fx * sx,
        intrinsics.fy * sy,
        (intrinsics.cx + 0.5) * sx - 0.5,
        (intrinsics.cy + 0.5) * sy - 0.5,
        list(intrinsics.dist),
    )


def resize_exact(image: np.ndarray, factor: float) -> np.ndarray:
    """``image`` area-averaged by exactly ``factor`` on both axes: the pixels of
    ``scaled(intrinsics, factor, exact=True)``."""
    return image if factor == 1.0 else cv2.resize(image, None, fx=factor, fy=factor, interpolation=cv2.INTER_AREA)


def undistort(image: np.ndarray, source: Intrinsics, target: Intrinsics) -> np.ndarray:
    """Resample a photo taken with ``source`` as the pinhole camera ``target`` sees it.

    Undistortion runs at the source resolution (target's focal scaled up); a smaller
    target is then reached by area averaging, which does not alias as remap would.
    Masks go through as float and are thresholded afterwards.
    """
    factor = target.width / source.width
    full = scaled(target, 1 / factor) if factor < 1 else target
    if any(source.dist) or not np.allclose(source.K, full.K):
        map_x, map_y = cv2.initUndistortRectifyMap(
            source.K, np.asarray(source.dist), None, full.K, (full.width, full.height), cv2.CV_32FC1
        )
        image = cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    if factor < 1:
        image = cv2.resize(image, (target.width, target.height), interpolation=cv2.INTER_AREA)
    return image
