"""Known intrinsics from a file (``calibrate.known_intrinsics``): a lab calibration or
an earlier one, for photos that carry no board shots of their own.

==================  ==============================================================
format              what is read
==================  ==============================================================
``.json``           the pipeline's own ``intrinsics.json`` (calibrate's export):
                    ``width``, ``height``, ``fx``, ``fy``, ``cx``, ``cy`` and
                    optionally ``dist`` ([k1, k2, p1, p2, k3])
``.yml``, ``.yaml``, OpenCV's FileStorage as its calibration sample writes it:
``.xml``            ``camera_matrix`` (3x3), ``distortion_coefficients`` (up to
                    k1, k2, p1, p2, k3), ``image_width``, ``image_height``
==================  ==============================================================

Both use OpenCV's conventions: the first pixel's centre at (0, 0), as
pipeline.camera.model. A calibration at another resolution of the same aspect is
scaled to the photos (:func:`fitted_to`). Limitations: OpenCV's rational and
thin-prism terms (coefficients past the fifth) and fisheye models are refused.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np

from pipeline.camera.model import Intrinsics, scaled
from pipeline.core.errors import PipelineError

OPENCV_SUFFIXES = (".yml", ".yaml", ".xml")


def _from_json(path: Path, setting: str) -> Intrinsics:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise PipelineError(f"{setting}: cannot read {path} as JSON ({error})") from error
    missing = [k for k in ("width", "height", "fx", "fy", "cx", "cy") if not isinstance(data, dict) or k not in data]
    if missing:
        raise PipelineError(
            f"{setting}: {path} lacks {', '.join(missing)}: give width, height, fx, fy, cx, cy (pixels) "
            "and optionally dist [k1, k2, p1, p2, k3], as calibrate's intrinsics.json has them"
        )
    try:
        K = np.array([[data["fx"], 0, data["cx"]], [0, data["fy"], data["cy"]], [0, 0, 1]], dtype=float)
        dist = [float(d) for d in data.get("dist") or []]
    except (TypeError, ValueError) as error:
        raise PipelineError(f"{setting}: {path} holds a value that is not a number ({error})") from error
    return _checked(path, setting, data["width"], data["height"], K, dist)


def _from_opencv(path: Path, setting: str) -> Intrinsics:
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not storage.isOpened():
        raise PipelineError(f"{setting}: cannot read {path} as an OpenCV YAML or XML file")
    try:
        K = storage.getNode("camera_matrix").mat()
        dist = storage.getNode("distortion_coefficients").mat()
        width, height = storage.getNode("image_width").real(), storage.getNode("image_height").real()
    finally:
        storage.release()
    if K is None or K.shape != (3, 3) or not width or not height:
        raise PipelineError(
            f"{setting}: {path} lacks camera_matrix (3x3), image_width or image_height: "
            "give the file OpenCV's calibration sample writes"
        )
    return _checked(path, setting, width, height, K, [] if dist is None else dist.ravel().tolist())


def _checked(path: Path, setting: str, width, height, K: np.ndarray, dist: list) -> Intrinsics:
    values = [width, height, K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist]
    if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
        raise PipelineError(f"{setting}: {path} holds a value that is not a finite number")
    if len(dist) > 5 and any(dist[5:]):
        raise PipelineError(
            f"{setting}: {path} has {len(dist)} distortion coefficients: only k1, k2, p1, p2, k3 are "
            "supported (recalibrate without OpenCV's rational or thin-prism model)"
        )
    if width != int(width) or height != int(height) or width <= 0 or height <= 0 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise PipelineError(f"{setting}: {path} needs a positive whole image size and positive focal lengths")
    if K[0, 1] != 0:
        raise PipelineError(f"{setting}: {path} has skew {K[0, 1]}: cameras with skew are not supported")
    dist5 = [float(d) for d in dist[:5]] + [0.0] * (5 - min(len(dist), 5))
    return Intrinsics(int(width), int(height), float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), dist5)


def read_known_intrinsics(path: Path, setting: str) -> Intrinsics:
    """The intrinsics in ``path`` (formats above); ``setting`` names the config key in errors."""
    if not path.is_file():
        raise PipelineError(
            f"{setting}: {path} is not a file: give the path of the calibration, relative to the capture"
        )
    if path.suffix.lower() == ".json":
        return _from_json(path, setting)
    if path.suffix.lower() in OPENCV_SUFFIXES:
        return _from_opencv(path, setting)
    raise PipelineError(
        f"{setting}: {path} is neither .json nor an OpenCV file ({', '.join(OPENCV_SUFFIXES)}): "
        "convert it to one of them"
    )


def fitted_to(intrinsics: Intrinsics, size: tuple[int, int], source: Path, setting: str) -> Intrinsics:
    """``intrinsics`` for photos of ``size`` (width, height): as given, or scaled from a
    calibration at another resolution of the same aspect; anything else is refused."""
    if (intrinsics.width, intrinsics.height) == tuple(size):
        return intrinsics
    # The same frame at another resolution: the height scaled by the widths' ratio
    # rounds to the photos' height.
    resized = scaled(intrinsics, size[0] / intrinsics.width)
    if (resized.width, resized.height) != tuple(size):
        raise PipelineError(
            f"{setting}: {source} is for {intrinsics.width}x{intrinsics.height} images, but the photos are "
            f"{size[0]}x{size[1]}, which is not the same frame scaled: give the calibration of the camera and "
            "resolution the photos were taken with (photos turned upright count as another frame)"
        )
    return resized
