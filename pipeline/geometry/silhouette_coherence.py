"""Silhouette coherence of a circular motion: the epipolar tangency errors of pairs of
the photos' outlines (``pipeline.geometry.silhouette_tangency`` explains the geometry),
vectorised over the pairs, as residuals of the circular-motion bundle adjustment.

Why: features on a plain or glossy specimen standing on a plain table are shading and
highlights, which stay with the light instead of turning with the specimen. They fit a
circular motion as tightly as true features do and pull its axis, focal length and
angles off by degrees, with uncertainties that say tenths. The outlines turn with the
specimen. Weighted by their own measured noise against the features' (``prior``), they
decide what such features leave loose and leave alone what true features pin down
(Hernandez, Schmitt and Cipolla, "Silhouette coherence for camera calibration under
circular motion", 2007, fit the whole motion to silhouettes alone).

Residuals are signed, in pixels, one per outer tangent, four per pair: positive where
the tangent carried over from the other photo misses this outline, negative where it
cuts it. Under circular motion a pair's relative pose depends on its turn alone:
R = Rot(axis, b - a), t = p - R p.

Limitations: outlines are convex hulls, so concavities say nothing; a pair whose epipole
lies inside either outline (photos from nearly the same or the opposite side) gives
zeros; a mask that takes in a shadow or part of the table moves the tangents it
touches, which the robust loss bounds but does not remove.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PARTNERS = 8
"""Partners per photo, spread over the turns that constrain a pair; more cost time and
add little (neighbouring partners' tangents carry nearly the same information)."""
MIN_TURN_DEG, MAX_TURN_DEG = 15.0, 165.0
"""Turns between partners: nearer 0 or 180 degrees the epipole falls inside the outline."""
LOSS_SCALE = 3.0
"""Cauchy loss scale of the tangency residuals, in their standard deviations."""


@dataclass(frozen=True)
class Outlines:
    """Convex outlines of some photos, padded to one length: (n, V, 2) pixels, each
    outline's last vertex repeated (a repeated vertex changes no tangent)."""

    pixels: np.ndarray
    views: np.ndarray
    """(n,) the photo (solver index) of each outline."""

    @classmethod
    def of(cls, hulls: dict[int, np.ndarray]) -> "Outlines":
        longest = max(len(h) for h in hulls.values())
        padded = np.stack([np.concatenate([h, np.repeat(h[-1:], longest - len(h), axis=0)]) for h in hulls.values()])
        return cls(padded.astype(float), np.array(list(hulls), int))


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


def _rotations(axis: np.ndarray, turns: np.ndarray) -> np.ndarray:
    """(P, 3, 3) rotations about ``axis`` by ``turns`` (Rodrigues)."""
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    c, s = np.cos(turns)[:, None, None], np.sin(turns)[:, None, None]
    return np.eye(3) + s * k + (1 - c) * (k @ k)


def _skew(t: np.ndarray) -> np.ndarray:
    zero = np.zeros(len(t))
    return np.stack(
        [
            np.stack([zero, -t[:, 2], t[:, 1]], 1),
            np.stack([t[:, 2], zero, -t[:, 0]], 1),
            np.stack([-t[:, 1], t[:, 0], zero], 1),
        ],
        1,
    )


def _dehomogenise(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(P, 2) image points of (P, 3) camera-frame points, and whether each lies in front."""
    front = points[:, 2] > 1e-9
    return points[:, :2] / np.where(front, points[:, 2], 1.0)[:, None], front


def _outside(hulls: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(P,) whether each point lies outside its convex outline (P, V, 2), either orientation."""
    edges = np.roll(hulls, -1, axis=1) - hulls
    to_point = points[:, None, :] - hulls
    cross = edges[..., 0] * to_point[..., 1] - edges[..., 1] * to_point[..., 0]
    return ~(np.all(cross >= 0, axis=1) | np.all(cross <= 0, axis=1))


def _tangent_points(hulls: np.ndarray, epipoles: np.ndarray) -> np.ndarray:
    """(P, 2, 2) the outline vertices on the two outer tangents from each epipole."""
    offsets = hulls - epipoles[:, None, :]
    towards = hulls.mean(axis=1) - epipoles
    cross = towards[:, None, 0] * offsets[..., 1] - towards[:, None, 1] * offsets[..., 0]
    angles = np.arctan2(cross, np.einsum("pvi,pi->pv", offsets, towards))
    rows = np.arange(len(hulls))
    return np.stack([hulls[rows, np.argmin(angles, axis=1)], hulls[rows, np.argmax(angles, axis=1)]], axis=1)


def _signed_tangency(lines: np.ndarray, hulls: np.ndarray) -> np.ndarray:
    """(P, 2) signed distance of each of two lines (P, 2, 3), normalised, from touching
    the outline (P, V, 2): positive when it misses, negative when it cuts through."""
    signed = np.einsum("pli,pvi->plv", lines[..., :2], hulls) + lines[..., 2:3]
    low, high = signed.min(axis=2), signed.max(axis=2)
    return np.where(low > 0, low, np.where(high < 0, -high, -np.minimum(high, -low)))


def tangency_residuals(
    axis: np.ndarray, point: np.ndarray, turns: np.ndarray, normalised: np.ndarray, pairs: np.ndarray, focal: float
) -> np.ndarray:
    """(P, 4) signed tangency errors in pixels of ``pairs`` (indices into ``normalised``,
    the outlines in normalised camera coordinates) turned by ``turns`` (P,: the second
    photo's angle less the first's, radians) about the circular motion's ``axis`` through
    ``point`` (camera frame); 0 where a pair gives no constraint."""
    a, b = pairs[:, 0], pairs[:, 1]
    R = _rotations(axis, turns)
    t = point - R @ point
    E = _skew(t) @ R
    # The epipoles: camera b's centre seen from a, and a's seen from b.
    epipole_a, front_a = _dehomogenise(-np.einsum("pji,pj->pi", R, t))
    epipole_b, front_b = _dehomogenise(t)
    hull_a, hull_b = normalised[a], normalised[b]
    valid = front_a & front_b & _outside(hull_a, epipole_a) & _outside(hull_b, epipole_b)
    tangents_a, tangents_b = _tangent_points(hull_a, epipole_a), _tangent_points(hull_b, epipole_b)
    ones = np.ones((len(pairs), 2, 1))
    lines_in_b = np.einsum("pij,pkj->pki", E, np.concatenate([tangents_a, ones], axis=2))
    lines_in_a = np.einsum("pji,pkj->pki", E, np.concatenate([tangents_b, ones], axis=2))
    residuals = np.zeros((len(pairs), 4))
    for columns, lines, hulls in ((slice(0, 2), lines_in_b, hull_b), (slice(2, 4), lines_in_a, hull_a)):
        norm = np.hypot(lines[..., 0], lines[..., 1])
        usable = valid[:, None] & (norm > 1e-12)
        lines = lines / np.where(usable, norm, 1.0)[..., None]
        residuals[:, columns] = np.where(usable, _signed_tangency(lines, hulls) * focal, 0.0)
    return residuals


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
