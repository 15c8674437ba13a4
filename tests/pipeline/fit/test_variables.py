import numpy as np

from pipeline.fit.variables import GradientWhitening, MaterialVariables
from pipeline.render.parameters import FitParameter

TRUTH = np.array([0.6, 0.4])
ROTATION = np.array([[1.0, -1.0], [1.0, 1.0]]) / np.sqrt(2.0)
CURVATURE = ROTATION @ np.diag([100.0, 1.0]) @ ROTATION.T
"""Two values that trade off along the diagonal: steep across it, flat along it."""


def test_whitened_gradients_have_unit_spread_in_every_direction():
    rng = np.random.default_rng(0)
    whitening = GradientWhitening()
    noise = np.linalg.cholesky(CURVATURE)
    whitened = np.array([whitening.whiten(noise @ rng.normal(size=2)) for _ in range(4000)])
    # The moment of the later gradients, whitened by a moment that has settled.
    np.testing.assert_allclose(whitened[2000:].T @ whitened[2000:] / 2000, np.eye(2), atol=0.15)


def _fit_valley(mi, whiten: bool, steps: int, seed: int = 1) -> np.ndarray:
    """Adam on a quadratic valley whose gradient noise is its curvature's (a Monte Carlo
    gradient's near the optimum), from a start along the valley."""
    import drjit as dr

    parameters = [FitParameter(name, f"{name}.value", 0.0, 1.0, learning_rate=0.01) for name in ("a", "b")]
    variables = MaterialVariables(parameters, {0: {"a.value": mi.Float(0.1), "b.value": mi.Float(0.9)}}, [], 1, whiten)
    variables.register(1.0)
    rng, noise = np.random.default_rng(seed), np.linalg.cholesky(CURVATURE)
    for _ in range(steps):
        values = np.array([variables.optimizer[p.name][0] for p in parameters])
        gradient = CURVATURE @ (values - TRUTH) + noise @ rng.normal(size=2)
        for parameter, g in zip(parameters, gradient):
            dr.set_grad(variables.optimizer[parameter.name], mi.Float(float(g)))
        variables.whiten_gradients()
        variables.optimizer.step()
        variables.clamp()
    return np.array([variables.snapshot()[p.name][0] for p in parameters])


def test_whitened_steps_follow_a_diagonal_valley_that_plain_steps_crawl_along(mi):
    """300 steps of 0.01 could cross the valley's 0.5 many times over."""
    plain, whitened = (np.abs(_fit_valley(mi, whiten, 300) - TRUTH).max() for whiten in (False, True))
    assert whitened < 0.15 and plain > 0.25, (whitened, plain)


def test_a_single_value_steps_as_plain_adam_does(mi):
    """Whitening one channel is a scale, which Adam's normalisation removes."""
    import drjit as dr

    values = []
    for whiten in (False, True):
        parameter = FitParameter("a", "a.value", 0.0, 1.0, learning_rate=0.01)
        variables = MaterialVariables([parameter], {0: {"a.value": mi.Float(0.1)}}, [], 1, whiten)
        variables.register(1.0)
        for g in np.random.default_rng(2).normal(size=20):
            dr.set_grad(variables.optimizer["a"], mi.Float(float(g)))
            variables.whiten_gradients()
            variables.optimizer.step()
        values.append(variables.snapshot()["a"])
    np.testing.assert_allclose(*values, rtol=1e-6)


def test_the_whitening_resumes_from_its_checkpointed_moment(mi):
    def variables():
        parameters = [FitParameter(name, f"{name}.value", 0.0, 1.0) for name in ("a", "b")]
        made = MaterialVariables(parameters, {0: {"a.value": mi.Float(0.5), "b.value": mi.Float(0.5)}}, [], 1, True)
        made.register(1.0)
        return made

    rng = np.random.default_rng(3)
    stepped = variables()
    for _ in range(5):
        stepped.whitening.whiten(rng.normal(size=2))
    resumed = variables()
    assert variables().optimiser_arrays() == {}  # nothing to save before a step
    resumed.restore_optimiser_arrays(stepped.optimiser_arrays())
    gradient = rng.normal(size=2)
    np.testing.assert_array_equal(resumed.whitening.whiten(gradient), stepped.whitening.whiten(gradient))
