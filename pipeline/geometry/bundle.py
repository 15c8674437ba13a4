"""Bundle adjustment for camera models with few parameters: Levenberg-Marquardt on
reprojection errors, the 3D points eliminated by the Schur complement.

The camera side is a handful of *global* parameters (intrinsics, a rig's geometry)
plus a few parameters *per view* (a turntable's angle); every observation depends
on the global parameters, its own view's and its own point's. The camera model is
any ``project(global, views, points, observations) -> pixels``; its Jacobian is the
model's own where it gives one (``Problem.jacobians``), else taken by forward
differences, one evaluation per global parameter, per view parameter (all views at
once) and per point coordinate (all points at once), so a model can be a plain
vectorised function.

The reduced camera system is dense (global + views x per-view parameters, tens to
a few hundred), the points' 3x3 blocks are inverted in closed form: memory and time
grow linearly with the observations. Outliers are down-weighted with Cauchy's loss
(iteratively reweighted). ``Result.covariance`` is the camera parameters' covariance
(the inverse of the reduced system at the solution, scaled by the residuals'
variance): the basis of the uncertainties the sfm stage reports.

Priors (``Problem.priors``) add residuals on the camera parameters alone, in pixel
units (a turntable's even steps, its outlines' coherence); one whose residuals depend
on the views through few differences gives its own view Jacobian rather than one
evaluation per view.

Limitations: forward differences limit the attainable precision to about 1e-7 of
a parameter's scale, far below what pixels constrain, and cost one projection per
parameter; the dense reduced system
suits problems with up to a few hundred camera parameters, not a city.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

Projection = Callable[[np.ndarray, np.ndarray, np.ndarray, "Observations"], np.ndarray]


@dataclass(frozen=True)
class Prior:
    """Residuals on the camera parameters alone, in pixel units."""

    residuals: Callable[[np.ndarray, np.ndarray], np.ndarray]
    """(global (G,), views (n, k)) -> (r,) residuals."""
    view_jacobian: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None
    """(global, views) -> (r, n, k) derivatives by the view parameters, or None for
    forward differences, one evaluation per free view parameter."""


@dataclass
class Observations:
    """Where points were seen: observation k is point ``point[k]`` in view ``view[k]`` at ``pixels[k]``."""

    view: np.ndarray
    point: np.ndarray
    pixels: np.ndarray
    keypoint: np.ndarray | None = None
    """Optional: the index of each observation's keypoint in its view, carried along."""

    def subset(self, keep: np.ndarray) -> "Observations":
        keypoint = None if self.keypoint is None else self.keypoint[keep]
        return Observations(self.view[keep], self.point[keep], self.pixels[keep], keypoint)


def keep_inliers(
    observations: Observations,
    points: np.ndarray,
    inliers: np.ndarray,
) -> tuple[Observations, np.ndarray]:
    """The ``inliers`` of ``observations`` and the points they still see twice, renumbered."""
    observations = observations.subset(inliers)
    seen = np.bincount(observations.point, minlength=len(points)) >= 2
    renumber = np.cumsum(seen) - 1
    observations = observations.subset(seen[observations.point])
    observations.point = renumber[observations.point]
    return observations, points[seen]


def noise_px(project: Projection, g: np.ndarray, views: np.ndarray, points: np.ndarray, obs: Observations) -> float:
    """The reprojection noise at a state, as ``adjust`` measures it (``Result.sigma_px``);
    1 px without observations, at least 1e-3 px (a weight divides by it)."""
    if not len(obs.view):
        return 1.0
    errors = np.linalg.norm(project(g, views, points, obs) - obs.pixels, axis=1)
    return max(float(np.median(errors)) / 1.1774, 1e-3)


@dataclass
class Problem:
    """A bundle adjustment problem: a camera model, its free parameters and the observations."""

    project: Projection
    """(global (G,), views (n, k), points (M, 3), observations) -> (m, 2) predicted pixels."""
    observations: Observations
    free_global: np.ndarray
    """(G,) bool: which global parameters are adjusted."""
    free_views: np.ndarray
    """(n, k) bool: which per-view parameters are adjusted."""
    global_steps: np.ndarray
    """(G,) finite-difference steps, about 1e-6 of each parameter's natural scale."""
    view_steps: np.ndarray
    """(k,) finite-difference steps of the per-view parameters."""
    point_step: float
    """Finite-difference step of the point coordinates."""
    loss_scale_px: float = 2.0
    """Cauchy loss scale: residuals of this many pixels get half weight."""
    priors: list[Prior] = field(default_factory=list)
    jacobians: Callable[[np.ndarray, np.ndarray, np.ndarray, "Observations"], tuple] | None = None
    """Optional: ``project``'s pixels with their derivatives by every global parameter
    (m, 2, G), every view parameter (m, 2, k) and the point (m, 2, 3), from the same
    arguments; None for forward differences."""


@dataclass
class Result:
    global_params: np.ndarray
    view_params: np.ndarray
    points: np.ndarray
    errors_px: np.ndarray
    """(m,) reprojection error of each observation at the solution."""
    covariance: np.ndarray
    """Covariance of the free camera parameters: the free global ones, then the free
    view entries in row-major order (``Problem.free_views``)."""
    sigma_px: float
    """Robust estimate of the reprojection noise (1.4826 x median error / 1.18)."""
    iterations: int
    cost: float
    history: list[float] = field(default_factory=list)


def _cauchy_weights(errors: np.ndarray, scale: float) -> np.ndarray:
    return 1.0 / (1.0 + (errors / scale) ** 2)


def _robust_cost(errors: np.ndarray, scale: float) -> float:
    return float(np.sum(scale**2 * np.log1p((errors / scale) ** 2)))


class _Linearisation:
    """Jacobians of the residuals at one parameter state, in the block layout the
    Schur complement needs."""

    def __init__(self, problem: Problem, g: np.ndarray, V: np.ndarray, X: np.ndarray):
        obs = problem.observations
        free_g = np.flatnonzero(problem.free_global)
        if problem.jacobians is not None:
            predicted, J_global, self.J_view, self.J_point = problem.jacobians(g, V, X, obs)
            self.J_global = J_global[:, :, free_g]
        else:
            predicted, self.J_global, self.J_view, self.J_point = _forward_differences(problem, g, V, X, free_g)
        self.residuals = predicted - obs.pixels  # (m, 2)
        self.J_view = self.J_view * problem.free_views[obs.view][:, None, :]
        blocks = [_prior_jacobian(problem, prior, g, V) for prior in problem.priors]
        self.prior_residuals = np.concatenate([residuals for residuals, _ in blocks]) if blocks else np.zeros(0)
        n_cam = len(free_g) + int(np.count_nonzero(problem.free_views))
        self.J_prior = np.vstack([J for _, J in blocks]) if blocks else np.zeros((0, n_cam))


def _forward_differences(problem: Problem, g: np.ndarray, V: np.ndarray, X: np.ndarray, free_g: np.ndarray):
    """``project``'s pixels and their Jacobians by the free global parameters, the view
    parameters and the point, by forward differences."""
    obs = problem.observations
    predicted = problem.project(g, V, X, obs)
    J_global = np.empty((len(obs.view), 2, len(free_g)))
    for column, index in enumerate(free_g):
        moved = g.copy()
        moved[index] += problem.global_steps[index]
        J_global[:, :, column] = (problem.project(moved, V, X, obs) - predicted) / problem.global_steps[index]
    J_view = np.empty((len(obs.view), 2, V.shape[1]))
    for j in range(V.shape[1]):
        moved = V.copy()
        moved[:, j] += problem.view_steps[j]
        J_view[:, :, j] = (problem.project(g, moved, X, obs) - predicted) / problem.view_steps[j]
    J_point = np.empty((len(obs.view), 2, 3))
    for j in range(3):
        moved = X.copy()
        moved[:, j] += problem.point_step
        J_point[:, :, j] = (problem.project(g, V, moved, obs) - predicted) / problem.point_step
    return predicted, J_global, J_view, J_point


def _prior_jacobian(problem: Problem, prior: Prior, g: np.ndarray, V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A prior's residuals and their Jacobian by the free camera parameters (the free
    global ones, then the free view entries in row-major order)."""
    residuals = prior.residuals(g, V)
    columns = []
    for index in np.flatnonzero(problem.free_global):
        moved = g.copy()
        moved[index] += problem.global_steps[index]
        columns.append((prior.residuals(moved, V) - residuals) / problem.global_steps[index])
    if prior.view_jacobian is not None:
        by_view = prior.view_jacobian(g, V)
        columns += [by_view[:, view, j] for view, j in zip(*np.nonzero(problem.free_views))]
    else:
        for view, j in zip(*np.nonzero(problem.free_views)):
            moved = V.copy()
            moved[view, j] += problem.view_steps[j]
            columns.append((prior.residuals(g, moved) - residuals) / problem.view_steps[j])
    return residuals, np.column_stack(columns) if columns else np.zeros((len(residuals), 0))


def _camera_index(problem: Problem) -> tuple[int, np.ndarray]:
    """Number of free camera parameters and, per (view, entry), its column or -1."""
    n_global = int(np.count_nonzero(problem.free_global))
    columns = -np.ones(problem.free_views.shape, int)
    columns[problem.free_views] = n_global + np.arange(np.count_nonzero(problem.free_views))
    return n_global + int(np.count_nonzero(problem.free_views)), columns


def _normal_equations(problem: Problem, lin: _Linearisation, weights: np.ndarray, n_points: int):
    """Blocks of J^T W J and J^T W r: U (cameras), V (points, 3x3 each), W (cameras x
    points, as (cameras, points, 3)), and the two gradients. An observation's camera
    Jacobian has the global columns and its own view's: the view blocks are summed per
    column rather than formed densely (observations x cameras would not fit in memory
    for a hundred photos)."""
    obs = problem.observations
    n_cam, view_columns = _camera_index(problem)
    n_global = lin.J_global.shape[2]
    weighted_global = lin.J_global * weights[:, None, None]
    U = np.zeros((n_cam, n_cam))
    U[:n_global, :n_global] = np.einsum("mic,mid->cd", weighted_global, lin.J_global)
    g_cam = np.zeros(n_cam)
    g_cam[:n_global] = np.einsum("mic,mi->c", weighted_global, lin.residuals)
    W = np.zeros((n_cam, n_points, 3))
    np.add.at(W[:n_global].transpose(1, 0, 2), obs.point, np.einsum("mic,mia->mca", weighted_global, lin.J_point))
    columns = view_columns[obs.view]  # (m, k): each observation's view columns, -1 where held
    for j in range(problem.free_views.shape[1]):
        has = columns[:, j] >= 0
        column = columns[has, j]
        weighted = lin.J_view[has, :, j] * weights[has, None]
        cross = np.zeros((n_cam, n_global))
        np.add.at(cross, column, np.einsum("mic,mi->mc", lin.J_global[has], weighted))
        U[:, :n_global] += cross
        U[:n_global, :] += cross.T
        for other in range(problem.free_views.shape[1]):
            both = has & (columns[:, other] >= 0)
            values = np.einsum("mi,mi->m", lin.J_view[both, :, j] * weights[both, None], lin.J_view[both, :, other])
            np.add.at(U, (columns[both, j], columns[both, other]), values)
        np.add.at(g_cam, column, np.einsum("mi,mi->m", weighted, lin.residuals[has]))
        np.add.at(W, (column, obs.point[has]), np.einsum("mi,mia->ma", weighted, lin.J_point[has]))
    V = np.zeros((n_points, 3, 3))
    np.add.at(V, obs.point, np.einsum("mia,mib->mab", lin.J_point * weights[:, None, None], lin.J_point))
    g_point = np.zeros((n_points, 3))
    np.add.at(g_point, obs.point, np.einsum("mia,mi->ma", lin.J_point * weights[:, None, None], lin.residuals))
    if len(lin.prior_residuals):
        U += lin.J_prior.T @ lin.J_prior
        g_cam += lin.J_prior.T @ lin.prior_residuals
    return U, V, W, g_cam, g_point


def _solve_step(U, V, W, g_cam, g_point, damping: float):
    """The damped Gauss-Newton step (cameras, points) by the Schur complement."""
    n_cam = U.shape[0]
    U_damped = U + damping * np.diag(np.maximum(np.diag(U), 1e-12))
    V_damped = V + damping * np.maximum(np.diagonal(V, axis1=1, axis2=2), 1e-12)[:, :, None] * np.eye(3)
    V_inv = np.linalg.inv(V_damped)
    Y = np.einsum("cpa,pab->cpb", W, V_inv)
    S = U_damped - Y.reshape(n_cam, -1) @ W.reshape(n_cam, -1).T
    rhs = -g_cam + np.einsum("cpa,pa->c", Y, g_point)
    delta_cam = np.linalg.solve(S, rhs) if n_cam else np.zeros(0)
    delta_points = -np.einsum("pab,pb->pa", V_inv, g_point + np.einsum("cpa,c->pa", W, delta_cam))
    return delta_cam, delta_points


def _apply(problem: Problem, g, V, X, delta_cam, delta_points):
    n_global = int(np.count_nonzero(problem.free_global))
    g, V = g.copy(), V.copy()
    g[problem.free_global] += delta_cam[:n_global]
    V[problem.free_views] += delta_cam[n_global:]
    return g, V, X + delta_points


def _errors(problem: Problem, g, V, X) -> np.ndarray:
    obs = problem.observations
    return np.linalg.norm(problem.project(g, V, X, obs) - obs.pixels, axis=1)


def _total_cost(problem: Problem, g, V, X) -> float:
    cost = _robust_cost(_errors(problem, g, V, X), problem.loss_scale_px)
    return cost + sum(float(np.sum(prior.residuals(g, V) ** 2)) for prior in problem.priors)


def adjust(
    problem: Problem,
    global_params: np.ndarray,
    view_params: np.ndarray,
    points: np.ndarray,
    max_iterations: int = 50,
    tolerance: float = 1e-7,
) -> Result:
    """Levenberg-Marquardt from the given parameters; stops when an accepted step lowers
    the robust cost by less than ``tolerance`` of it, or after ``max_iterations``."""
    g, V, X = global_params.astype(float).copy(), view_params.astype(float).copy(), points.astype(float).copy()
    cost = _total_cost(problem, g, V, X)
    damping, history, iterations = 1e-3, [cost], 0
    for iterations in range(1, max_iterations + 1):
        lin = _Linearisation(problem, g, V, X)
        weights = _cauchy_weights(np.linalg.norm(lin.residuals, axis=1), problem.loss_scale_px)
        U, Vb, W, g_cam, g_point = _normal_equations(problem, lin, weights, len(X))
        improved = False
        for _ in range(10):
            step = _solve_step(U, Vb, W, g_cam, g_point, damping)
            g_new, V_new, X_new = _apply(problem, g, V, X, *step)
            new_cost = _total_cost(problem, g_new, V_new, X_new)
            if np.isfinite(new_cost) and new_cost < cost:
                improved = True
                break
            damping *= 10
        if not improved:
            break
        decrease = (cost - new_cost) / max(cost, 1e-300)
        g, V, X, cost = g_new, V_new, X_new, new_cost
        history.append(cost)
        damping = max(damping / 10, 1e-9)
        if decrease < tolerance:
            break
    return _result(problem, g, V, X, iterations, cost, history)


def _result(problem: Problem, g, V, X, iterations: int, cost: float, history: list[float]) -> Result:
    lin = _Linearisation(problem, g, V, X)
    errors = np.linalg.norm(lin.residuals, axis=1)
    weights = _cauchy_weights(errors, problem.loss_scale_px)
    U, Vb, W, _, _ = _normal_equations(problem, lin, weights, len(X))
    n_cam = U.shape[0]
    V_inv = np.linalg.pinv(Vb)
    S = U - np.einsum("cpa,pab->cpb", W, V_inv).reshape(n_cam, -1) @ W.reshape(n_cam, -1).T
    # The median error of 2D Gaussian noise is 1.18 sigma.
    sigma = float(np.median(errors) / 1.1774) if len(errors) else 0.0
    return Result(g, V, X, errors, _covariance(S) * sigma**2, sigma, iterations, cost, history)


def _covariance(S: np.ndarray) -> np.ndarray:
    """The inverse of the reduced system; a parameter the observations leave free (a
    group of views tied to the rest by nothing: its common angle) gets an infinite
    variance, where a pseudo-inverse would report none. Decided on the system scaled
    to a unit diagonal: parameters in pixels and in radians differ by ten orders of
    magnitude in their curvature without being any less determined."""
    if not len(S):
        return np.zeros((0, 0))
    diagonal = np.diag(S).copy()
    unconstrained = diagonal <= 0
    scale = 1 / np.sqrt(np.where(unconstrained, 1.0, diagonal))
    scaled = (S * scale[:, None] * scale[None, :] + (S * scale[:, None] * scale[None, :]).T) / 2
    values, vectors = np.linalg.eigh(scaled)
    null = values <= 1e-10 * max(values.max(), 1e-300)
    covariance = (vectors[:, ~null] / values[~null]) @ vectors[:, ~null].T * scale[:, None] * scale[None, :]
    unconstrained |= np.any(np.abs(vectors[:, null]) > 1e-3, axis=1)
    covariance[unconstrained, :] = np.inf
    covariance[:, unconstrained] = np.inf
    return covariance
