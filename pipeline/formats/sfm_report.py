"""sfm.json: how the sfm stage posed the photos (for people, the report and benchmarks;
the poses themselves are in cameras.json).

The fields every run writes are typed; ``details`` holds what one way of posing adds:
``circular`` (the rig's solution: each photo's angle and its uncertainty),
``self_calibration``, ``residual_distortion``, ``silhouette_iou``, ``below_ground``,
``posed_by_board``, ``replaced_by_board``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from pipeline.formats.records import JsonRecord


@dataclass(kw_only=True)
class SfmReport(JsonRecord):
    """sfm.json (see the module docstring)."""

    photos: int
    """Photos given."""
    poses_from: str
    """What posed them: SfM, circular motion (turntable or ring), or [cameras] source."""
    registered: int
    """Photos with a pose before the consistency checks."""
    unregistered: dict[str, str]
    """Each photo without a pose, and the likely cause."""
    frame: dict
    """The world frame's description (cameras.json's frame)."""
    points: int | None = None
    """Sparse points of the model (None: poses from another tool)."""
    mean_reprojection_error_px: float | None = None
    mean_track_length: float | None = None
    board_reprojection_px: dict[str, float] = field(default_factory=dict)
    """Each photo's board pose's RMS reprojection error, where the board was found."""


__all__ = ["SfmReport"]
