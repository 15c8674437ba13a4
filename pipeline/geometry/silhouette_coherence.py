"""Silhouette coherence of a circular motion: the epipolar tangency errors of pairs of
the photos' outlines (``pipeline.geometry.silhouette_tangency``) under the motion, as
residuals of the circular-motion bundle adjustment.

Why: features on a plain or glossy specimen standing on a plain table are shading and
highlights, which stay with the light instead of turning with the specimen. They fit a
circular motion as tightly as true features do and pull its axis, focal length and
angles off by degrees, with uncertainties that say tenths. The outlines turn with the
specimen. Weighted by their own measured noise against the features' (``prior``), they
decide what such features leave loose and leave alone what true features pin down
(Hernandez, Schmitt and Cipolla, "Silhouette coherence for camera calibration under
circular motion", 2007, fit the whole motion to silhouettes alone).

Residuals are signed, in pixels, one per outer tangent, four per pair. Under circular
motion a pair's relative pose depends on its turn alone: R = Rot(axis, b - a), t = p - R p.

Limitations: outlines are convex hulls, so concavities say nothing; a pair whose epipole
lies inside either outline (photos from nearly the same or the opposite side) gives
zeros; a mask that takes in a shadow or part of the table moves the tangents it
touches, which the robust loss bounds but does not remove.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.geometry import silhouette_tangency

PARTNERS = 8
"""Partners per photo, spread over the turns that constrain a pair; more cost time and
add little (neighbouring partners' tangents carry nearly the same information)."""
MIN_TURN_DEG, MAX_TURN_DEG = 15.0, 165.0
"""Turns between partners: nearer 0 or 180 degrees the epipole falls inside the outline."""
LOSS_SCALE = 3.0
"""Cauchy loss scale of the tangency residuals, in their standard deviations."""


@dataclass(frozen=True)
class Outlines:
    """Convex outlines of some photos, padded to one length (``silhouette_tangency.padded``)."""

    pixels: np.ndarray
    """(n, V, 2) pixels."""
    views: np.ndarray
    """(n,) the photo (solver index) of each outline."""

    @classmethod
    def of(cls, hulls: dict[int, np.ndarray]) -> "Outlines":
        return cls(silhouette_tangency.padded(list(hulls.values())), np.array(list(hulls), int))


def choose_pairs(angles: np.ndarray) -> np.ndarray:
    """(P, 2) indices into ``angles`` of the pairs compared: for each photo up to
    ``PARTNERS`` others whose turn from it lies between MIN_TURN_DEG and MAX_TURN_DEG,
    spread over that range; each pair once."""
    turns = np.degrees(np.abs(np.angle(np.exp(1j * (angles[None, :] - angles[:, None])))))
    chosen = set()
    for i in range(len(angles)):
        candidates = np.flatnonzero((turns[i] > MIN_TURN_DEG) & (turns[i] < MAX_TURN_DEG))
        candidates = candidates[np.argsort(turns[i, candidates])]
        picked = candidates[np.linspace(0, len(candidates) - 1, min(PARTNERS, len(candidates))).astype(int)]
        chosen |= {(min(i, j), max(i, j)) for j in picked}
    return np.array(sorted(chosen), int).reshape(-1, 2)


def tangency_residuals(
    axis: np.ndarray, point: np.ndarray, turns: np.ndarray, normalised: np.ndarray, pairs: np.ndarray, focal: float
) -> np.ndarray:
    """(P, 4) signed tangency errors in pixels of ``pairs`` (indices into ``normalised``,
    the outlines in normalised camera coordinates) turned by ``turns`` (P,: the second
    photo's angle less the first's, radians) about the circular motion's ``axis`` through
    ``point`` (camera frame); 0 where a pair gives no constraint."""
    R = Rotation.from_rotvec(np.outer(turns, axis)).as_matrix()
    errors, _ = silhouette_tangency.tangency_errors(
        R, point - R @ point, normalised[pairs[:, 0]], normalised[pairs[:, 1]]
    )
    return errors * focal


def robust_sigma(residuals: np.ndarray) -> float:
    """The residuals' standard deviation from their median absolute value (zeros, the
    pairs without a constraint, left out)."""
    used = np.abs(residuals[residuals != 0])
    return float(1.4826 * np.median(used)) if len(used) else np.inf


def weighted(residuals: np.ndarray, sigma: float, feature_sigma: float) -> np.ndarray:
    """Residuals for a least-squares sum beside feature reprojection errors of standard
    deviation ``feature_sigma``: each tangency error in its own standard deviations
    (``sigma``) under a Cauchy loss, in the features' pixels."""
    n = residuals / sigma
    return feature_sigma * np.sign(n) * LOSS_SCALE * np.sqrt(np.log1p((n / LOSS_SCALE) ** 2))
