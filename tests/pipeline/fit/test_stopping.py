"""The trend test that stops a noisy fit: it must not fire while a value still drifts
under noise larger than its drift per step, and must fire once everything only jitters."""

import numpy as np

from pipeline.fit.stopping import still, trend_z


def _ar1(rng, n: int, rho: float, scale: float) -> np.ndarray:
    """Noise whose neighbouring steps are alike, as Adam's momentum makes them."""
    noise = np.zeros(n)
    for i in range(1, n):
        noise[i] = rho * noise[i - 1] + scale * rng.normal()
    return noise


def _log(values: np.ndarray, losses: np.ndarray) -> list[dict]:
    return [{"relative_loss": float(loss), "params": {"roughness": [float(v)]}} for v, loss in zip(values, losses)]


def test_a_trend_stands_out_and_noise_does_not():
    rng = np.random.default_rng(0)
    steps = np.arange(40)
    assert trend_z(0.01 * steps + rng.normal(0, 0.02, 40)) > 4
    assert trend_z(np.full(40, 0.35)) == 0.0  # clamped at a bound
    assert trend_z(0.5 - 0.01 * steps) == np.inf  # a noiseless line
    # Correlated noise without drift: the widened standard error keeps false trends rare
    # (plain least squares would call most of these series trending).
    false_trends = [trend_z(_ar1(rng, 60, 0.9, 0.01)) > 2 for _ in range(300)]
    assert np.mean(false_trends) < 0.25


def test_a_value_drifting_under_a_flat_loss_keeps_the_fit_going():
    """The trap of a loss-based rule: the loss is flat within its noise while a
    parameter still walks towards the truth (roughness 0.5 -> 0.35 over 200 steps)."""
    rng = np.random.default_rng(1)
    n = 120
    drifting = 0.35 + 0.15 * np.exp(-np.arange(n) / 200) + _ar1(rng, n, 0.8, 0.002)
    log = _log(drifting, 1.0 + rng.normal(0, 0.05, n))
    # checked after every step, as the loop does, with the default window
    assert all(still(log[:steps], 40, 2.0) is None for steps in range(1, n + 1))


def test_a_fit_that_only_jitters_stops_and_says_why():
    rng = np.random.default_rng(2)
    n = 60
    converged = 0.35 + _ar1(rng, n, 0.8, 0.002)
    log = _log(converged, 1.0 + rng.normal(0, 0.05, n))
    reasons = [still(log[:steps], 20, 2.0) for steps in range(1, n + 1)]
    first = next(steps for steps, reason in enumerate(reasons, 1) if reason is not None)
    assert 20 <= first <= 40, first
    assert "nothing moved beyond its noise over the last 20 steps" in reasons[first - 1]
    assert all(reason is None for reason in reasons[:19])  # too few steps to judge
    assert still(log, 20, 0.0) is None  # switched off


def test_the_loop_does_not_stop_while_the_held_out_error_still_falls():
    """A still trajectory stops the loop only once the held-out error has stopped
    falling: while its latest render is the best so far, the fit goes on."""
    from pipeline.fit.loop import BestState, _stop_reason
    from pipeline.fit.settings import LoopSettings

    rng = np.random.default_rng(0)
    log = [{"relative_loss": 1.0 + 0.01 * rng.standard_normal(), "params": {"x": [0.5]}} for _ in range(60)]
    for iteration in (20, 40, 60):
        log[iteration - 1]["validation_error"] = 1.0 / iteration
        log[iteration - 1]["iteration"] = iteration
    settings = LoopSettings(still_threshold=2.0, window=40)
    assert _stop_reason(settings, log, log[-1], BestState({}, 60, 1 / 60)) is None
    assert "nothing moved" in _stop_reason(settings, log, log[-1], BestState({}, 40, 1 / 40))
