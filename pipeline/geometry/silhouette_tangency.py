"""A photo's angle on a circular motion from its silhouette: epipolar tangency.

Two views of one object share the plane through both camera centres that grazes
the object: in each view it is an epipolar line tangent to the silhouette (its
outer tangents from the epipole), and the two tangents correspond (Wong and
Cipolla, "Structure and motion from silhouettes", 2001). With the circular motion
known from the photos that features placed, a photo's angle is the one at which
its outline's tangents and those of placed photos agree; a group of photos whose
angles are known relative to each other (features tie them together but not to
the placed photos) is placed as one, all its outlines at once. Unlike matching a
silhouette against a visual hull, it needs no hull, and unlike features it works
on a plain, glossy or translucent specimen.

The error of a pair is in pixels: each outer tangent of one outline, carried to
the other view as an epipolar line, is moved that far from touching the other
outline (``tangency_errors``, signed: positive where it misses, negative where it
cuts through; vectorised over pairs). Outlines are convex hulls of the masks
(tangents from a point outside a shape touch its convex hull), in normalised camera
coordinates.

Limitations: partners seen nearly from the same or the opposite side give no
constraint (the epipole then lies far out or inside the outline) and are skipped;
a symmetric outline can leave two angles equally good, which ``place`` reports
as ambiguous rather than choose.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

CAP_PX = 10.0
"""Tangency errors are capped here: one bad mask must not outweigh the rest."""


def outline(mask: np.ndarray) -> np.ndarray | None:
    """The convex hull of a mask's foreground as (k, 2) pixel coordinates, or None when empty."""
    points = cv2.findNonZero(mask.astype(np.uint8))
    if points is None or len(points) < 3:
        return None
    return cv2.convexHull(points.reshape(-1, 1, 2)).reshape(-1, 2).astype(float)


def padded(hulls: list[np.ndarray]) -> np.ndarray:
    """(n, V, 2) outlines padded to one length, each one's last vertex repeated (a
    repeated vertex changes no tangent)."""
    longest = max(len(h) for h in hulls)
    return np.stack([np.concatenate([h, np.repeat(h[-1:], longest - len(h), axis=0)]) for h in hulls]).astype(float)


def cross_matrices(t: np.ndarray) -> np.ndarray:
    """(P, 3, 3) cross-product matrices of ``t`` (P, 3): ``cross_matrices(t)[k] @ w = t[k] x w``."""
    zero = np.zeros(len(t))
    rows = [[zero, -t[:, 2], t[:, 1]], [t[:, 2], zero, -t[:, 0]], [-t[:, 1], t[:, 0], zero]]
    return np.stack([np.stack(row, 1) for row in rows], 1)


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


def tangency_errors(
    R: np.ndarray, t: np.ndarray, hulls_a: np.ndarray, hulls_b: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Signed tangency errors (normalised units) of pairs of outlines (P, V, 2, normalised
    camera coordinates) whose second camera is ``R`` (P, 3, 3), ``t`` (P, 3) from the
    first (X_b = R X_a + t): (P, 4), the two tangents of a carried to b, then those of b
    carried to a; positive where a carried tangent misses the outline, negative where it
    cuts it. And (P,) whether the pair constrains anything: both epipoles in front of
    their camera and outside their outline."""
    E = cross_matrices(t) @ R
    # The epipoles: camera b's centre seen from a, and a's seen from b.
    epipole_a, front_a = _dehomogenise(-np.einsum("pji,pj->pi", R, t))
    epipole_b, front_b = _dehomogenise(t)
    valid = front_a & front_b & _outside(hulls_a, epipole_a) & _outside(hulls_b, epipole_b)
    ones = np.ones((len(t), 2, 1))
    tangents_a = np.concatenate([_tangent_points(hulls_a, epipole_a), ones], axis=2)
    tangents_b = np.concatenate([_tangent_points(hulls_b, epipole_b), ones], axis=2)
    errors = np.zeros((len(t), 4))
    for columns, lines, hulls in (
        (slice(0, 2), np.einsum("pij,pkj->pki", E, tangents_a), hulls_b),
        (slice(2, 4), np.einsum("pji,pkj->pki", E, tangents_b), hulls_a),
    ):
        norm = np.hypot(lines[..., 0], lines[..., 1])
        valid &= np.all(norm > 1e-12, axis=1)
        errors[:, columns] = _signed_tangency(lines / np.maximum(norm, 1e-300)[..., None], hulls)
    return np.where(valid[:, None], errors, 0.0), valid


@dataclass(frozen=True)
class Placement:
    """The angle a silhouette placed a photo at, and how sure that is."""

    angle: float
    error_px: float
    """RMS tangency error at the angle over the tangents kept (see ``place``)."""
    runner_up_px: float
    """The best error at an angle more than ``separation_deg`` away (inf when none)."""
    partners: int
    rivals: tuple[tuple[float, float], ...] = ()
    """(angle, error) of the other local minima more than ``separation_deg`` away, best first."""


def _errors_px(members, angle: float, pose_at, partners, focal_px: float) -> np.ndarray:
    """(members x partners, 4) tangency errors in pixels of the ``members`` (hull,
    relative angle) at ``angle``, capped; nan where a partner gives no constraint."""
    Rs, ts, hulls_a, hulls_b = [], [], [], []
    for hull, relative in members:
        R_a, t_a = pose_at(angle + relative)
        for partner_hull, (R_b, t_b) in partners:
            R = R_b @ R_a.T
            Rs.append(R)
            ts.append(t_b - R @ t_a)
            hulls_a.append(hull)
            hulls_b.append(partner_hull)
    if not Rs:
        return np.zeros((0, 4))
    both = padded(hulls_a + hulls_b)
    errors, valid = tangency_errors(np.array(Rs), np.array(ts), both[: len(Rs)], both[len(Rs) :])
    return np.where(valid[:, None], np.minimum(np.abs(errors) * focal_px, CAP_PX), np.nan)


def place(
    members: list[tuple[np.ndarray, float]],
    pose_at: "callable",
    partners: list[tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]],
    candidates: np.ndarray,
    focal_px: float,
    separation_deg: float = 5.0,
) -> Placement | None:
    """The candidate angle whose pose (``pose_at(angle)`` -> (R, t)) makes the tangents
    of the ``members`` (outline, angle relative to the one placed: one photo's is 0)
    agree best with those of the ``partners`` (outline, pose), refined to 1/32 degree;
    None when no partner constrains any candidate.

    Two passes, for masks that are wrong along part of the outline (where the specimen
    meets the table, cut off or fattened by shadow: on a synthetic turntable 4-10 px
    off where the rest agreed to 0.2-1.3 px): the median error over all tangents finds
    the angle roughly; the tangents within 3 times the median there (at least 2 px)
    are kept, and their RMS error places the photo and judges the placement."""
    errors = np.array([_errors_px(members, a, pose_at, partners, focal_px) for a in candidates])
    with np.errstate(all="ignore"):
        rough = np.nanmedian(errors.reshape(len(candidates), -1), axis=1)
    if not np.isfinite(rough).any():
        return None
    at_rough = errors[int(np.nanargmin(rough))]
    kept = at_rough <= max(2.0, 3 * float(np.nanmedian(at_rough)))

    def cost(values: np.ndarray) -> float:
        chosen = values[kept]
        chosen = chosen[np.isfinite(chosen)]
        return float(np.sqrt(np.mean(chosen**2))) if len(chosen) else np.inf

    costs = np.array([cost(e) for e in errors])
    best = int(np.argmin(costs))
    step = float(np.median(np.diff(candidates))) if len(candidates) > 1 else np.radians(0.25)
    fine = np.arange(candidates[best] - step, candidates[best] + step, np.radians(1 / 32))
    fine_costs = [cost(_errors_px(members, a, pose_at, partners, focal_px)) for a in fine]
    angle = float(fine[int(np.argmin(fine_costs))])
    far = np.abs(np.angle(np.exp(1j * (candidates - angle)))) > np.radians(separation_deg)
    runner_up = float(costs[far].min()) if far.any() else np.inf
    lower = costs <= np.roll(costs, 1)
    upper = costs <= np.roll(costs, -1)
    minima = np.flatnonzero(lower & upper & far & np.isfinite(costs))
    rivals = tuple((float(candidates[i]), float(costs[i])) for i in minima[np.argsort(costs[minima])])
    return Placement(angle, float(min(fine_costs)), runner_up, int(kept.any(axis=1).sum()), rivals)
