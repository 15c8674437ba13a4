"""The printed calibration board: its image, its detection, its 3D corner positions.

One definition serves ``pipeline board`` (printing), the calibrate stage and
``pipeline check`` (detection), the masks stage (whether the photos show the board),
the sfm stage (metric scale) and ``pipeline synth`` (rendering), so that what is
printed is what is detected.

Board coordinates follow OpenCV: origin at the top-left corner of the printed
pattern, x to the right, y down the page, z into the board, in metres. Corner
``k`` of a ChArUco board and inner corner ``k`` of a checkerboard (row-major,
``squares_x - 1`` per row) are the same point.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pipeline.camera.model import Intrinsics, Pose
from pipeline.core.sections import BoardSection


@dataclass
class BoardDetection:
    """Corners of the board found in one image."""

    ids: np.ndarray
    """Corner ids, shape (N,)."""
    image_points: np.ndarray
    """Pixel positions (OpenCV convention: (0, 0) is the centre of the top-left pixel), (N, 2)."""
    object_points: np.ndarray
    """Positions on the board in metres, (N, 3)."""


def make_charuco_board(board: BoardSection) -> "cv2.aruco.CharucoBoard":
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary))
    return cv2.aruco.CharucoBoard(
        (board.squares_x, board.squares_y), board.square_mm / 1000, board.marker_mm / 1000, dictionary
    )


def board_image(board: BoardSection, pixels_per_square: int = 120) -> np.ndarray:
    """The printed pattern as a grayscale uint8 image, without margin."""
    if board.kind == "charuco":
        size = (board.squares_x * pixels_per_square, board.squares_y * pixels_per_square)
        return make_charuco_board(board).generateImage(size, marginSize=0, borderBits=1)
    if board.kind == "checkerboard":
        # Same parity as OpenCV's ChArUco boards: the top-left square is black.
        squares = (np.indices((board.squares_y, board.squares_x)).sum(axis=0) % 2).astype(np.uint8) * 255
        return np.kron(squares, np.ones((pixels_per_square, pixels_per_square), np.uint8))
    raise ValueError("board.kind = 'none' has no image")


def corner_positions(board: BoardSection) -> np.ndarray:
    """Board coordinates (metres) of every inner corner, indexed by corner id."""
    i, j = np.meshgrid(np.arange(1, board.squares_x), np.arange(1, board.squares_y))
    grid = np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], axis=-1)
    return grid * board.square_mm / 1000


class BoardDetector:
    """Finds the configured board in grayscale uint8 images."""

    def __init__(self, board: BoardSection, min_corners: int = 6):
        if board.kind == "none":
            raise ValueError("board.kind = 'none': there is no board to detect")
        self.board = board
        self.min_corners = min_corners
        self.corners = corner_positions(board)
        if board.kind == "charuco":
            # Markers a few pixels across, foreshortened on a table, are often rejected
            # at first; refining against the board layout recovers them (on a
            # 384 px turntable capture: 3 of 24 views found the board without it, 24 with).
            charuco = cv2.aruco.CharucoParameters()
            charuco.tryRefineMarkers = True
            # Marker bits are sampled at 8 px per cell instead of 4: a marker 10 px
            # wide decodes more often (7 of 12 photos of a 256 px capture instead of 4).
            markers = cv2.aruco.DetectorParameters()
            markers.perspectiveRemovePixelPerCell = 8
            self.charuco = cv2.aruco.CharucoDetector(make_charuco_board(board), charuco, markers)

    def detect(self, gray: np.ndarray) -> BoardDetection | None:
        """The corners found, or None when fewer than ``min_corners`` were."""
        if self.board.kind == "charuco":
            corners, ids, _, _ = self.charuco.detectBoard(gray)
            if ids is None:
                return None
            ids, points = ids.ravel(), corners.reshape(-1, 2)
        else:
            pattern = (self.board.squares_x - 1, self.board.squares_y - 1)
            found, points = cv2.findChessboardCornersSB(gray, pattern, flags=cv2.CALIB_CB_EXHAUSTIVE)
            if not found:
                return None
            ids, points = np.arange(len(points)), points.reshape(-1, 2)
        if len(ids) < self.min_corners:
            return None
        return BoardDetection(ids, points.astype(np.float64), self.corners[ids])


def found_in_any(board: BoardSection, images: Iterable[np.ndarray]) -> bool:
    """Whether the board is detected in any of ``images`` (grayscale uint8), looking no
    further than the first that shows it; False for ``board.kind = 'none'``."""
    if board.kind == "none":
        return False
    detector = BoardDetector(board)
    return any(detector.detect(image) is not None for image in images)


def board_to_world(board: BoardSection) -> np.ndarray:
    """4x4 transform from OpenCV board coordinates to the world frame.

    OpenCV's board frame has its origin at the top-left corner of the printed
    image, x to the right, y down the image and z into the board. The world frame
    (of synthetic captures and of the sfm stage when the board is seen) has z up
    and the board centred on the origin, so the board's z points down.
    """
    width, height = board.squares_x * board.square_mm / 1000, board.squares_y * board.square_mm / 1000
    M = np.diag([1.0, -1.0, -1.0, 1.0])
    M[:3, 3] = [-width / 2, height / 2, 0.0]
    return M


def homography_residual_px(detection: BoardDetection) -> float:
    """Largest distance of a corner from the best projective map of the flat board.

    A pinhole camera sees a plane through a homography, which keeps every line
    straight; lens distortion shows as residuals that grow towards the frame's edge.
    """
    H, _ = cv2.findHomography(detection.object_points[:, :2], detection.image_points, 0)
    mapped = cv2.perspectiveTransform(detection.object_points[None, :, :2], H)[0]
    return float(np.linalg.norm(mapped - detection.image_points, axis=1).max())


def straightness_px(detection: BoardDetection, board: BoardSection) -> float:
    """Largest distance of a corner from the line fitted through its board row or column."""
    columns = board.squares_x - 1
    worst = 0.0
    for labels in (detection.ids // columns, detection.ids % columns):
        for label in np.unique(labels):
            points = detection.image_points[labels == label]
            if len(points) < 3:
                continue
            centred = points - points.mean(axis=0)
            normal = np.linalg.svd(centred)[2][1]
            worst = max(worst, float(np.abs(centred @ normal).max()))
    return worst


PAPER_MM = {"A4": (210.0, 297.0), "A3": (297.0, 420.0), "letter": (215.9, 279.4)}
PAGE_MARGIN_MM = 12.0


MAX_PRINT_PIXELS = 100e6
"""Largest printable pattern written: an A3 page at 600 dpi is about 70 megapixels."""


def board_size_mm(board: BoardSection) -> tuple[float, float]:
    return board.squares_x * board.square_mm, board.squares_y * board.square_mm


def page_layout(board: BoardSection, paper: str) -> tuple[tuple[float, float], tuple[float, float]]:
    """(page size, board's bottom-left corner on the page), in mm; the board is centred
    on the page, turned to landscape when that is how it fits."""
    width, height = board_size_mm(board)
    short, long = PAPER_MM[paper]
    for page in ((short, long), (long, short)):
        if width + 2 * PAGE_MARGIN_MM <= page[0] and height + 2 * PAGE_MARGIN_MM + 15 <= page[1]:
            return page, ((page[0] - width) / 2, (page[1] - height) / 2 + 5)
    raise ValueError(
        f"a board of {board.squares_x} x {board.squares_y} squares of {board.square_mm} mm "
        f"({width:.0f} x {height:.0f} mm) does not fit on {paper} paper with {PAGE_MARGIN_MM:.0f} mm margins: "
        "choose a larger --paper or a smaller board.square_mm"
    )


def write_printable(board: BoardSection, stem: Path, paper: str = "A4", dpi: int = 300) -> tuple[Path, Path]:
    """``stem``.png (the pattern alone, its DPI in the metadata) and ``stem``.pdf (the
    pattern at its physical size on a page, with a caption and a 50 mm scale bar)."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    from pipeline.imaging.photo_io import write_image

    (page_w, page_h), (left, bottom) = page_layout(board, paper)
    pixels_per_square = round(board.square_mm / 25.4 * dpi)
    pixels = board.squares_x * board.squares_y * pixels_per_square**2
    if pixels > MAX_PRINT_PIXELS:
        most = int(dpi * (MAX_PRINT_PIXELS / pixels) ** 0.5)
        raise ValueError(
            f"the board would be {pixels / 1e6:.0f} megapixels at {dpi} dpi, more than any printer resolves: "
            f"choose --dpi {most} or less"
        )
    pattern = board_image(board, pixels_per_square)
    png = write_image(
        stem.with_suffix(".png"),
        pattern,
        {"XResolution": float(dpi), "YResolution": float(dpi), "ResolutionUnit": "in"},
    )
    width, height = board_size_mm(board)
    figure = plt.figure(figsize=(page_w / 25.4, page_h / 25.4))
    axes = figure.add_axes((left / page_w, bottom / page_h, width / page_w, height / page_h))
    axes.imshow(pattern, cmap="gray", vmin=0, vmax=255, interpolation="nearest", aspect="auto")
    axes.set_axis_off()
    details = f"{board.kind} {board.squares_x} x {board.squares_y}, square {board.square_mm:g} mm" + (
        f", marker {board.marker_mm:g} mm, {board.dictionary}" if board.kind == "charuco" else ""
    )
    figure.text(left / page_w, (bottom - 6) / page_h, details, fontsize=8, va="top")
    figure.text(
        left / page_w,
        (bottom - 10) / page_h,
        "Print at 100 % (no 'fit to page'). Measure a square and the bar, and set "
        "board.square_mm (and marker_mm) to what you measure.",
        fontsize=7,
        va="top",
    )
    bar_y = (bottom - 15) / page_h
    figure.add_artist(plt.Line2D([left / page_w, (left + 50) / page_w], [bar_y, bar_y], color="black", linewidth=1.5))
    figure.text((left + 52) / page_w, bar_y, "50 mm", fontsize=7, va="center")
    pdf = stem.with_suffix(".pdf")
    figure.savefig(pdf, dpi=dpi)
    plt.close(figure)
    return png, pdf


def board_poses(
    board: BoardSection,
    photos: dict[str, dict],
    intrinsics: dict[str, Intrinsics],
    min_corners: int,
    max_error_px: float,
) -> tuple[dict[str, Pose], dict[str, float]]:
    """World pose (board_to_world's frame) and RMS reprojection error of every photo
    (``{"srgb": 8-bit file}``) whose board shows ``min_corners`` corners and whose
    board pose reprojects within ``max_error_px``."""
    if board.kind == "none":
        return {}, {}
    detector = BoardDetector(board, min_corners)
    B = board_to_world(board)
    poses, errors = {}, {}
    for name, photo in photos.items():
        gray = cv2.imread(str(photo["srgb"]), cv2.IMREAD_GRAYSCALE)
        detection = detector.detect(gray)
        if detection is None:
            continue
        K = intrinsics[name].K
        found, rvec, tvec = cv2.solvePnP(
            detection.object_points, detection.image_points, K, None, flags=cv2.SOLVEPNP_IPPE
        )
        if not found:
            continue
        rvec, tvec = cv2.solvePnPRefineLM(detection.object_points, detection.image_points, K, None, rvec, tvec)
        projected = cv2.projectPoints(detection.object_points, rvec, tvec, K, None)[0].reshape(-1, 2)
        rms = float(np.sqrt(np.mean(np.sum((projected - detection.image_points) ** 2, axis=1))))
        if rms > max_error_px:
            continue
        R_board = cv2.Rodrigues(rvec)[0]
        R = R_board @ B[:3, :3].T
        poses[name] = Pose(R, tvec.ravel() - R @ B[:3, 3])
        errors[name] = rms
    return poses, errors
