"""Where a volumetric fit that missed its targets stopped, in its loss landscape.

    .venv/bin/python -m bench.studies.volumetric_landscape --work DIR --kits 7 [--run defaults]
        [--studies trajectory line gradient compass model trust common forward] [--spp 32] [--seeds 16]
        [--samples 60] [--radius 1] [--rounds 3] [--confirm 0] [--jacobian-spp 8]

For each volumetric kit whose stored run (bench/fit_speed.py's ``--work`` folder and
configuration, ``--run``) ended outside a target, the loss the fits minimise is estimated
by the dual estimator (bench/studies/kit_identifiability.py's ``losses``: two renders
per view at ``--spp``, the same seeds at every point) and printed relative to the
truth's. Distances are in targets (bench/fit_kits.py), in bench/studies/gradient_noise.py's
coordinates (alpha, eta, albedo r g b, log sigma_t). Studies:

- trajectory: every tenth step of the run's log (fit_out/log.jsonl) scored: whether the
  lowest-scoring state the fit passed through lies within target (what keeping the best
  state by the training views' score would return);
- line: the loss on the straight line from the result to the truth, eleven points;
- gradient: the fit's gradient (4 spp, gradient_noise.py's) averaged over ``--seeds``
  seeds at the current point: its largest z-score, the cosine of its descent direction
  (target units) with the way to the truth, and a step along it of the length among
  0.25-8 targets that lowers the loss most (none if none does); ``--rounds`` times;
- compass: one coordinate at a time moved by 2 targets either way, kept where the loss
  falls; the move halved when no coordinate's does, down to a quarter target;
- model: a quadratic fitted to the loss at ``--samples`` points drawn uniformly within
  ``--radius`` targets of the current point (inside bench/fit_kits.py's BOUNDS); its
  minimum within 1.5 radii is the next point; ``--rounds`` times;
- trust: a trust region on models of the loss, each loss from its own seeds (so that
  the quadratic's regression averages their noise away): each round draws ``--samples``
  points within ``--radius`` targets of the current point (the radius per coordinate),
  fits a quadratic to every point drawn so far within twice the radius, floors its
  Hessian's eigenvalues (a noisy model's saddle sends every step to a corner), and
  moves to its minimum within the radius where the fitted quadratic predicts a fall
  beyond twice its own standard error (the regression's residuals give the noise);
  with ``--confirm K``, only where K losses at the step's end average below K at its
  start (all of them join the model); else the point stays, the radius shrinks by a
  third (down to half a target) and the next round's samples join the model;
  ``--rounds`` times;
- common: whether renders with the same seeds share their noise when one coordinate
  moves (what finite differences and models of the loss lean on): at the truth, for
  moves of 0.5, 2 and 8 targets either way, the mean squared difference of the two
  renders with the same seeds and the expected one (the dual estimator over two other
  seed pairs), both relative to two independent renders' at one point;
- forward: Gauss-Newton rounds from the result with per-pixel Jacobians in forward
  mode (the scene's ``volpath`` with evaluated loops: the fits' ``prbvolpath`` has no
  forward mode), one pass per coordinate and view at ``--jacobian-spp``; the
  Gauss-Newton matrix by the dual estimator (two Jacobians from independent seeds, so
  their noise does not add to its diagonal), its eigenvalues floored at a thousandth of
  the largest, the residual at ``--spp``; each step capped at ``--radius`` targets and
  taken whatever the loss says; ``--rounds`` times.

Limitations: whole films at the kit's size (the fits' coarse levels and windows are not
modelled); the loss at one point has a seed noise of about one to two percent at 32 spp,
partly common to nearby points. The forward-mode Jacobians differentiate ``volpath``'s
own sampling (a free flight's distance moves with sigma_t), not ``prbvolpath``'s
detached sampling.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

from bench.fit_kits import BOUNDS, INTEGRATORS, draw_kit, errors, kit_xml, stored_outcome, target, within
from bench.studies.gradient_noise import COORDINATES, KEYS, UNITS, gradients, set_coordinates
from bench.studies.kit_identifiability import losses
from pipeline.render import mitsuba_variant

STUDIES = ("trajectory", "line", "gradient", "compass", "model", "trust", "common", "forward")
LOG_NAMES = {key: name for name, key in KEYS.items()}
"""The fit log's parameter keys, by property name."""
COORDINATE_PROPERTIES = ("alpha", "eta", "albedo", "albedo", "albedo", "sigma_t")
"""The property each coordinate moves."""
LOWER = np.array([BOUNDS["alpha"][0], BOUNDS["eta"][0], *[BOUNDS["albedo"][0]] * 3, np.log(BOUNDS["sigma_t"][0])])
UPPER = np.array([BOUNDS["alpha"][1], BOUNDS["eta"][1], *[BOUNDS["albedo"][1]] * 3, np.log(BOUNDS["sigma_t"][1])])


def coordinates(values: dict) -> np.ndarray:
    return np.array([values["alpha"], values["eta"], *values["albedo"], np.log(values["sigma_t"])], float)


def values_of(x: np.ndarray) -> dict:
    return {
        "alpha": float(x[0]),
        "eta": float(x[1]),
        "albedo": [float(v) for v in x[2:5]],
        "sigma_t": float(np.exp(x[5])),
    }


class Landscape:
    """One kit's loss (relative to the truth's) and distance from the truth in targets."""

    def __init__(self, kit, folder: Path, spp: int, mi):
        self.kit, self.folder, self.spp, self.mi = kit, folder, spp, mi
        self.truth = coordinates(kit.truth)
        self.truth_loss = float(losses(kit, kit.truth, folder, spp, mi).sum())

    def loss(self, x: np.ndarray) -> float:
        return float(losses(self.kit, values_of(x), self.folder, self.spp, self.mi).sum()) / self.truth_loss

    def worst(self, x: np.ndarray) -> float:
        """The largest error, in targets."""
        return max(error / target(name) for name, error in errors(self.kit, values_of(x)).items())

    def describe(self, x: np.ndarray, loss: float | None = None) -> str:
        """``x``'s loss (``loss`` when already known) and largest error."""
        return f"loss {self.loss(x) if loss is None else loss:.3f}, worst {self.worst(x):.2f} targets"


class Renders:
    """The kit's scene with its material set by coordinates, rendered view by view into one
    flat array (every view's pixels, then the next's)."""

    def __init__(self, land: Landscape, integrator: str):
        mi = land.mi
        with tempfile.TemporaryDirectory() as scratch:
            self.scene = mi.load_file(str(kit_xml(land.kit, land.kit.truth, Path(scratch))))
        self.integrator = mi.load_dict({"type": integrator, "max_depth": INTEGRATORS["volumetric"][2]})
        self.params, self.land = mi.traverse(self.scene), land
        self.references = [
            mi.TensorXf(mi.Bitmap(str(land.folder / "references" / f"view_{view}.exr")))
            for view in range(land.kit.views)
        ]
        self.reference = np.concatenate([np.array(reference).ravel() for reference in self.references])

    def __call__(self, x: np.ndarray, seed: int, spp: int) -> np.ndarray:
        set_coordinates(self.params, np.clip(x, LOWER, UPPER))
        self.params.update()
        return np.concatenate(
            [
                np.array(
                    self.land.mi.render(
                        self.scene, self.params, sensor=view, integrator=self.integrator, spp=spp, seed=seed + 17 * view
                    )
                ).ravel()
                for view in range(self.land.kit.views)
            ]
        )

    def jacobian(self, x: np.ndarray, seed: int, spp: int, dr) -> np.ndarray:
        """(pixels, 6): each coordinate's derivative of the image, per target, in forward mode."""
        mi, columns = self.land.mi, []
        for coordinate, unit in enumerate(UNITS):
            name = COORDINATE_PROPERTIES[coordinate]
            key = KEYS[name]
            set_coordinates(self.params, np.clip(x, LOWER, UPPER))
            dr.enable_grad(self.params[key])
            self.params.update()
            if name == "albedo":
                dr.set_grad(self.params[key], mi.Color3f(*map(float, np.eye(3)[coordinate - 2])))
            else:  # log sigma_t's tangent moves sigma_t by sigma_t
                dr.set_grad(self.params[key], float(np.exp(x[5])) if name == "sigma_t" else 1.0)
            derivatives = []
            for view in range(self.land.kit.views):
                image = mi.render(
                    self.scene, self.params, sensor=view, integrator=self.integrator, spp=spp, seed=seed + 31 * view
                )
                dr.forward_to(image)
                derivatives.append(np.array(dr.grad(image)).ravel())
            dr.disable_grad(self.params[key])
            columns.append(np.concatenate(derivatives) * unit)
        return np.stack(columns, axis=1)


def trajectory(land: Landscape, log: list[dict]) -> list[str]:
    states = [
        (entry["iteration"], coordinates({LOG_NAMES[k]: v if len(v) > 1 else v[0] for k, v in entry["params"].items()}))
        for entry in log
        if entry["iteration"] % 10 == 0 and "params" in entry
    ]
    scored = [(step, land.loss(state), land.worst(state)) for step, state in states]
    step, loss, worst = min(scored, key=lambda row: row[1])
    within_share = np.mean([row[2] <= 1 for row in scored])
    correlation = np.corrcoef([row[1] for row in scored], [row[2] for row in scored])[0, 1]
    return [
        f"  trajectory: {len(scored)} states; the lowest loss at step {step}: {loss:.3f}, worst {worst:.2f} targets; "
        f"{within_share:.0%} of the states within every target; loss against worst error: r = {correlation:.2f}"
    ]


def line(land: Landscape, x: np.ndarray) -> list[str]:
    points = [(t, land.loss((1 - t) * x + t * land.truth)) for t in np.linspace(0, 1, 11)]
    return ["  line to the truth: " + ", ".join(f"{t:.1f}: {loss:.3f}" for t, loss in points)]


def gradient(land: Landscape, x: np.ndarray, seeds: int, rounds: int, mi, dr) -> list[str]:
    render = Renders(land, INTEGRATORS["volumetric"][1])
    lines, current = [], land.loss(x)
    for number in range(rounds):
        rows = gradients(render.scene, render.integrator, render.references, x, seeds, mi, dr)
        mean, error = rows.mean(axis=0), rows.std(axis=0, ddof=1) / np.sqrt(seeds)
        direction = -mean * UNITS**2
        direction /= np.linalg.norm(direction / UNITS)
        way = (land.truth - x) / UNITS
        cosine = float(direction / UNITS @ way / np.linalg.norm(way))
        trials = [
            (length, land.loss(np.clip(x + length * direction, LOWER, UPPER))) for length in (0.25, 0.5, 1, 2, 4, 8)
        ]
        length, loss = min(trials, key=lambda row: row[1])
        if loss < current:
            x, current = np.clip(x + length * direction, LOWER, UPPER), loss
        lines.append(
            f"  gradient round {number + 1}: largest |z| {np.max(np.abs(mean / error)):.1f}, cosine with the way to "
            f"the truth {cosine:+.2f}, step {length if loss <= current else 0} targets: {land.describe(x, current)}"
        )
    return lines


def compass(land: Landscape, x: np.ndarray) -> list[str]:
    lines, current, move, evaluations = [], land.loss(x), 2.0, 0
    while move >= 0.25:
        improved = False
        for coordinate in range(6):
            for sign in (1, -1):
                trial = x.copy()
                trial[coordinate] += sign * move * UNITS[coordinate]
                loss, evaluations = land.loss(np.clip(trial, LOWER, UPPER)), evaluations + 1
                if loss < current:
                    x, current, improved = np.clip(trial, LOWER, UPPER), loss, True
                    break
        lines.append(f"  compass, moves of {move} targets: {land.describe(x, current)} after {evaluations} losses")
        move = move if improved else move / 2
    return lines


def _quadratic_features(z: np.ndarray) -> np.ndarray:
    z = np.atleast_2d(z)
    pairs = [z[:, i] * z[:, j] for i in range(z.shape[1]) for j in range(i, z.shape[1])]
    return np.column_stack([np.ones(len(z)), z, *pairs])


def model(land: Landscape, x: np.ndarray, samples: int, radius: float, rounds: int) -> list[str]:
    rng, lines = np.random.default_rng(0), []
    for number in range(rounds):
        points = np.clip(x + rng.uniform(-radius, radius, (samples, 6)) * UNITS, LOWER, UPPER)
        offsets = (points - x) / UNITS
        values = np.array([land.loss(p) for p in points])
        coefficients = np.linalg.lstsq(_quadratic_features(offsets), values, rcond=None)[0]
        bounds = [
            (max(-1.5 * radius, lo), min(1.5 * radius, hi)) for lo, hi in zip((LOWER - x) / UNITS, (UPPER - x) / UNITS)
        ]
        found = min(
            (
                minimize(lambda z: float((_quadratic_features(z) @ coefficients)[0]), start, bounds=bounds)
                for start in (np.zeros(6), offsets[np.argmin(values)])
            ),
            key=lambda result: result.fun,
        )
        x = x + found.x * UNITS
        lines.append(
            f"  model round {number + 1}: lowest sampled loss {values.min():.3f}, the quadratic's minimum "
            f"{found.fun:.3f} at {np.round(found.x, 1).tolist()} targets: {land.describe(x)}"
        )
    return lines


def _convex_minimum(coefficients: np.ndarray, bounds: list[tuple[float, float]]) -> np.ndarray:
    """The minimum within ``bounds`` of the quadratic (``_quadratic_features``' order)
    with its Hessian's eigenvalues floored at a thousandth of the largest: a noisy
    model's saddle would otherwise send every step to a corner."""
    size = len(bounds)
    gradient, hessian, index = coefficients[1 : size + 1], np.zeros((size, size)), size + 1
    for i in range(size):
        for j in range(i, size):
            hessian[i, j] = hessian[j, i] = coefficients[index] * (2 if i == j else 1)
            index += 1
    values, vectors = np.linalg.eigh(hessian)
    hessian = vectors @ np.diag(np.maximum(values, 1e-3 * max(values.max(), 1e-12))) @ vectors.T
    return minimize(
        lambda z: (gradient @ z + z @ hessian @ z / 2, gradient + hessian @ z), np.zeros(size), jac=True, bounds=bounds
    ).x


def trust(
    land: Landscape, x: np.ndarray, spp: int, samples: int, radius: float, rounds: int, confirm: int
) -> list[str]:
    render, rng = Renders(land, INTEGRATORS["volumetric"][0]), np.random.default_rng(0)
    seeds = iter(range(100_000, 10**9, 2))
    scale = land.truth_loss / land.kit.views  # the per-view mean of the truth's loss

    def loss(point: np.ndarray) -> float:
        seed = next(seeds)
        first, second = (render(point, s, spp) - render.reference for s in (seed, seed + 1))
        return float(np.mean(first * second)) / scale

    drawn, values, lines = np.empty((0, 6)), np.empty(0), []
    for number in range(rounds):
        started = time.perf_counter()
        points = np.clip(x + rng.uniform(-radius, radius, (samples, 6)) * UNITS, LOWER, UPPER)
        drawn, values = np.vstack([drawn, points]), np.append(values, [loss(p) for p in points])
        offsets = (drawn - x) / UNITS
        near = np.max(np.abs(offsets), axis=1) <= 2 * radius
        features = _quadratic_features(offsets[near])
        coefficients, *_ = np.linalg.lstsq(features, values[near], rcond=None)
        residual = values[near] - features @ coefficients
        noise = float(np.sqrt(residual @ residual / max(near.sum() - features.shape[1], 1)))
        covariance = noise**2 * np.linalg.pinv(features.T @ features)
        found = _convex_minimum(
            coefficients,
            [(max(-radius, lo), min(radius, hi)) for lo, hi in zip((LOWER - x) / UNITS, (UPPER - x) / UNITS)],
        )
        difference = (_quadratic_features(np.zeros(6)) - _quadratic_features(found))[0]
        fall, error = float(difference @ coefficients), float(np.sqrt(difference @ covariance @ difference))
        moved, confirmation = fall > 2 * error, ""
        if moved and confirm:
            candidate = x + found * UNITS
            here, there = (
                np.array([loss(x) for _ in range(confirm)]),
                np.array([loss(candidate) for _ in range(confirm)]),
            )
            drawn, values = (
                np.vstack([drawn, [x] * confirm, [candidate] * confirm]),
                np.concatenate([values, here, there]),
            )
            moved = there.mean() < here.mean()
            spread = np.sqrt((here.var(ddof=1) + there.var(ddof=1)) / confirm)
            confirmation = f", confirmed {'yes' if moved else 'no'} ({here.mean() - there.mean():+.3f} +- {spread:.3f})"
        if moved:
            x = x + found * UNITS
        else:
            radius = max(radius * 2 / 3, 0.5)
        lines.append(
            f"  trust round {number + 1}: {int(near.sum())} losses in the model, noise {noise:.3f}; predicted fall "
            f"{fall:.3f} +- {error:.3f}{confirmation}: {'moved' if moved else 'stayed'}, radius now {radius:.2f}: "
            f"worst {land.worst(x):.2f} targets ({time.perf_counter() - started:.0f} s)"
        )
    return lines


def common(land: Landscape, spp: int) -> list[str]:
    render, x = Renders(land, INTEGRATORS["volumetric"][1]), land.truth
    independent = float(np.mean((render(x, 1, spp) - render(x, 2, spp)) ** 2))
    lines = []
    for move in (0.5, 2.0, 8.0):
        cells = []
        for coordinate, name in enumerate(COORDINATES):
            shift = np.eye(6)[coordinate] * move * UNITS[coordinate]
            same = np.mean((render(x + shift, 1, spp) - render(x - shift, 1, spp)) ** 2)
            expected = np.mean(
                (render(x + shift, 3, spp) - render(x - shift, 3, spp))
                * (render(x + shift, 4, spp) - render(x - shift, 4, spp))
            )
            cells.append(f"{name} {same / independent:.3f} ({expected / independent:.3f})")
        lines.append(
            f"  common, moves of {move} targets either way, the same seeds' squared difference (the expected "
            f"one) over independent seeds': " + ", ".join(cells)
        )
    return lines


def forward(land: Landscape, x: np.ndarray, spp: int, jacobian_spp: int, radius: float, rounds: int, dr) -> list[str]:
    derivative, render = Renders(land, INTEGRATORS["volumetric"][0]), Renders(land, INTEGRATORS["volumetric"][1])
    lines = []
    for number in range(rounds):
        with dr.scoped_set_flag(dr.JitFlag.SymbolicLoops, False):  # volpath's loops differentiate when evaluated
            first, second = (derivative.jacobian(x, seed + 100 * number, jacobian_spp, dr) for seed in (1000, 5000))
        residual = render(x, 9000 + 100 * number, spp) - render.reference
        matrix = (first.T @ second + second.T @ first) / 2
        noise_share = np.diag(first.T @ first + second.T @ second) / 2 / np.diag(matrix)
        values, vectors = np.linalg.eigh(matrix)
        floored = vectors @ np.diag(np.maximum(values, 1e-3 * values.max())) @ vectors.T
        step = -np.linalg.solve(floored, (first + second).T @ residual / 2)
        length = float(np.linalg.norm(step))
        x = np.clip(x + step * min(1.0, radius / length) * UNITS, LOWER, UPPER)
        lines.append(
            f"  forward round {number + 1}: the matrix's eigenvalues over its largest "
            f"{np.round(values / values.max(), 3).tolist()}, each diagonal with the Jacobians' own noise over "
            f"without {np.round(noise_share, 1).tolist()}; Gauss-Newton step {length:.1f} targets: {land.describe(x)}"
        )
    return lines


def _run_log(folder: Path, result: np.ndarray) -> list[dict] | None:
    """The folder's fit log (fit_out/, the last run bench/fit_speed.py made there) when
    that run ended at ``result``; else None."""
    written = json.loads((folder / "fit_out" / "params.json").read_text())["params"]
    values = {LOG_NAMES[key]: value if len(value) > 1 else value[0] for key, value in written.items()}
    if not np.allclose(coordinates(values), result):
        return None
    return [json.loads(line) for line in (folder / "fit_out" / "log.jsonl").read_text().splitlines()]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, required=True, help="bench/fit_speed.py's --work folder")
    parser.add_argument("--kits", required=True, help="volumetric kit seeds, comma-separated")
    parser.add_argument("--run", default="defaults", help="bench/fit_speed.py's configuration")
    parser.add_argument("--studies", nargs="*", default=list(STUDIES), choices=STUDIES)
    parser.add_argument("--spp", type=int, default=32, help="samples per pixel of each loss render")
    parser.add_argument("--seeds", type=int, default=16, help="gradients averaged (gradient)")
    parser.add_argument("--samples", type=int, default=60, help="losses per quadratic (model), per round (trust)")
    parser.add_argument(
        "--radius",
        type=float,
        default=1.0,
        help="targets about the point (model; trust's first); a step's cap (forward)",
    )
    parser.add_argument("--rounds", type=int, default=3, help="steps (gradient, model, trust, forward)")
    parser.add_argument(
        "--confirm", type=int, default=0, help="losses at each end of a step the model found (trust); 0: none"
    )
    parser.add_argument("--jacobian-spp", type=int, default=8, help="samples per pixel of a Jacobian (forward)")
    args = parser.parse_args()
    mitsuba_variant.activate()
    import drjit as dr
    import mitsuba as mi

    for seed in (int(s) for s in args.kits.split(",")):
        kit, folder = draw_kit(seed, "volumetric"), args.work / f"volumetric-{seed}"
        outcome = stored_outcome(folder, args.run)
        if outcome is None or within(kit, outcome.final):
            print(f"kit {seed}: no stored {args.run} run outside its targets")
            continue
        started = time.perf_counter()
        land = Landscape(kit, folder, args.spp, mi)
        x = coordinates(outcome.final)
        print(f"kit {seed}: {kit.describe()}; the result: {land.describe(x)}", flush=True)
        log = _run_log(folder, x)
        studies = {
            "trajectory": lambda: trajectory(land, log) if log else ["  trajectory: fit_out/ holds another run's log"],
            "line": lambda: line(land, x),
            "gradient": lambda: gradient(land, x, args.seeds, args.rounds, mi, dr),
            "compass": lambda: compass(land, x),
            "model": lambda: model(land, x, args.samples, args.radius, args.rounds),
            "trust": lambda: trust(land, x, args.spp, args.samples, args.radius, args.rounds, args.confirm),
            "common": lambda: common(land, args.spp),
            "forward": lambda: forward(land, x, args.spp, args.jacobian_spp, args.radius, args.rounds, dr),
        }
        for name in args.studies:
            print("\n".join(studies[name]()), flush=True)
        print(f"  ({time.perf_counter() - started:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
