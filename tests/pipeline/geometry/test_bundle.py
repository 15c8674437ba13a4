import numpy as np

from pipeline.geometry.bundle import Observations, Prior, Problem, adjust


def _project(g: np.ndarray, views: np.ndarray, points: np.ndarray, obs: Observations) -> np.ndarray:
    """Cameras looking down +z from (x, y, z) per view; one focal length and principal point."""
    camera = points[obs.point] - views[obs.view]
    return g[0] * camera[:, :2] / camera[:, 2:3] + g[1:3]


def _problem(rng, noise_px: float, outliers: int = 0):
    """Six cameras at different depths seeing 80 points. The gauge: the first two cameras
    (lateral and depth scales each trade off with the focal length otherwise)."""
    views = rng.uniform([-0.3, -0.3, -0.6], [0.3, 0.3, 0.6], (6, 3))
    points = rng.uniform([-0.5, -0.5, 2.0], [0.5, 0.5, 3.0], (80, 3))
    view, point = np.meshgrid(np.arange(6), np.arange(80), indexing="ij")
    obs = Observations(view.ravel(), point.ravel(), np.zeros((480, 2)))
    truth = np.array([300.0, 64.0, 48.0])
    obs.pixels = _project(truth, views, points, obs) + rng.normal(0, noise_px, (480, 2))
    obs.pixels[:outliers] += 40.0
    free_views = np.ones((6, 3), bool)
    free_views[:2] = False
    problem = Problem(
        _project,
        obs,
        np.array([True, False, False]),
        free_views,
        np.array([1e-4, 1e-4, 1e-4]),
        np.array([1e-7] * 3),
        1e-7,
    )
    return problem, truth, views, points


def test_adjust_recovers_cameras_and_points_from_a_perturbed_start():
    rng = np.random.default_rng(0)
    problem, truth, views, points = _problem(rng, noise_px=0.2)
    start_views = views + rng.normal(0, 0.02, views.shape)
    start_views[:2] = views[:2]
    result = adjust(problem, truth * [1.05, 1, 1], start_views, points + rng.normal(0, 0.02, points.shape))
    assert abs(result.global_params[0] - truth[0]) < 2.0
    np.testing.assert_allclose(result.view_params, views, atol=3e-3)
    assert np.median(result.errors_px) < 0.35
    assert abs(result.sigma_px - 0.2) < 0.05
    # The covariance covers the free parameters and predicts the focal length's spread.
    assert result.covariance.shape == (1 + 12, 1 + 12)
    assert 0 < np.sqrt(result.covariance[0, 0]) < 2.0


def test_outliers_do_not_pull_the_solution():
    rng = np.random.default_rng(1)
    problem, truth, views, points = _problem(rng, noise_px=0.2, outliers=20)
    result = adjust(problem, truth, views, points)
    assert abs(result.global_params[0] - truth[0]) < 2.0
    assert np.sum(result.errors_px > 10) == 20  # the outliers stay outliers


def test_a_prior_holds_parameters_the_observations_do_not():
    rng = np.random.default_rng(2)
    problem, truth, views, points = _problem(rng, noise_px=0.2)
    problem.free_global = np.array([True, True, False])  # cx: free, confounded with the views' x
    problem.priors = [Prior(lambda g, v: np.array([(g[1] - 64.0) * 100.0]))]
    result = adjust(problem, truth, views, points)
    assert abs(result.global_params[1] - 64.0) < 0.05


def test_a_prior_s_own_view_jacobian_gives_what_forward_differences_give():
    """A prior on differences of the views' parameters, once differentiated by the bundle
    adjuster view by view and once by its own Jacobian: the same solution and covariance."""
    rng = np.random.default_rng(4)
    problem, truth, views, points = _problem(rng, noise_px=0.2)

    def residuals(g, v):
        return (np.diff(v[:, 0]) - 0.5) * 30.0

    def view_jacobian(g, v):
        J = np.zeros((len(v) - 1, len(v), v.shape[1]))
        rows = np.arange(len(v) - 1)
        J[rows, rows, 0], J[rows, rows + 1, 0] = -30.0, 30.0
        return J

    without = adjust(problem, truth, views, points)
    problem.priors = [Prior(residuals)]
    by_differences = adjust(problem, truth, views, points)
    problem.priors = [Prior(residuals, view_jacobian)]
    by_own = adjust(problem, truth, views, points)
    assert np.allclose(by_own.view_params, by_differences.view_params, atol=1e-6)
    assert np.allclose(by_own.covariance, by_differences.covariance, rtol=1e-4, atol=1e-12)
    assert np.sum(residuals(truth, by_own.view_params) ** 2) < np.sum(residuals(truth, without.view_params) ** 2)


def test_views_tied_to_nothing_get_an_infinite_variance():
    """Two groups of cameras seeing disjoint points: the second group can slide as a
    whole, so its positions are unknown, however well its own points fix it inside."""
    rng = np.random.default_rng(3)
    problem, truth, views, points = _problem(rng, noise_px=0.2)
    second = problem.observations.view >= 3
    keep = (second & (problem.observations.point >= 40)) | (~second & (problem.observations.point < 40))
    problem.observations = problem.observations.subset(keep)
    result = adjust(problem, truth, views, points)
    std = np.sqrt(np.diag(result.covariance))
    # Free parameters: the focal length, then views 2..5 (x, y, z each).
    assert np.all(np.isfinite(std[:4])) and np.all(np.isinf(std[4:]))
