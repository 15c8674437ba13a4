"""Whether a fit that stops short of a kit's targets could have told from its gradients.

    .venv/bin/python -m bench.studies.stop_gradients --material volumetric --kits 0,1 [--work DIR]

Runs `pipeline fit`'s defaults on kits of bench/fit_kits.py (bench/fit_speed.py's
``pipeline_fit``, in a folder of its own under ``--work``) and records, at every step,
each fitted value's latent (log space where the parameter has one) and its gradient
as the loss gave it, before the whitening. Printed per kit and per level of the
coarse-to-fine fit, over the level's last half of steps (what its running average
weighs), coordinate by coordinate in units of the kit's targets (bench/fit_kits.py):

- how far the steps' mean lies from the truth;
- the steps' mean gradient in standard errors of that mean (its steps' spread over
  the square root of their count): within about 2 the gradients do not say which way
  the truth lies, however far off the values are.

With ``--regress``, also per level: the zero of the gradients regressed on the values
over the level's last half (a linear model, its Hessian symmetrised and floored to
positive definite), in targets off the truth, and its spread over 200 bootstrap
resamples of the steps: whether the fit's own gradients locate the answer where their
mean does not.

Limitations: the standard error takes the steps' gradients as independent (their
seeds are); a coordinate's gradient mixes the pull of every other coordinate's offset.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from bench.fit_kits import Clock, target
from bench.fit_speed import CONFIGS, pipeline_fit
from bench.studies.kit_folders import kits_with_references
from pipeline.fit import engine, variables
from pipeline.fit.scene_fit import property_name
from pipeline.render import mitsuba_variant


def recorded_fit(kit, folder: Path, dr) -> list[dict]:
    """`pipeline fit`'s defaults on ``kit`` in ``folder``; per step, each parameter's
    latent and gradient (flattened), and which level's loop took it."""
    steps: list[dict] = []
    whiten, fit = variables.MaterialVariables.whiten_gradients, engine.fit
    levels = [-1]

    def counted(*args, **kwargs):
        levels[0] += 1  # scene_fit runs one engine.fit per level
        return fit(*args, **kwargs)

    def recording(self) -> None:
        level = levels[0]
        for parameter in self.parameters:
            latent = self.optimizer[parameter.name]
            steps.append(
                {
                    "level": level,
                    "name": parameter.name,
                    "log": parameter.log,
                    "latent": np.ravel(np.array(latent, np.float64)),
                    "gradient": np.ravel(np.array(dr.grad(latent), np.float64)),
                }
            )
        whiten(self)

    variables.MaterialVariables.whiten_gradients, engine.fit = recording, counted
    try:
        pipeline_fit(kit, folder, *CONFIGS["defaults"], Clock(kit, 0.0))
    finally:
        variables.MaterialVariables.whiten_gradients, engine.fit = whiten, fit
    return steps


def level_lines(kit, steps: list[dict]) -> list[str]:
    """Per level, per coordinate: the last half's mean off the truth and its mean
    gradient in standard errors."""
    lines = []
    for level in sorted({s["level"] for s in steps}):
        latents, gradients, labels, offsets = _level_arrays(kit, steps, level)
        off = offsets(latents.mean(axis=0))
        error = gradients.std(axis=0, ddof=1) / np.sqrt(len(latents))
        z = gradients.mean(axis=0) / np.where(error > 0, error, np.inf)
        parts = [f"{n} {o:+.1f} targets off, gradient {g:+.1f} se" for n, o, g in zip(labels, off, z)]
        lines.append(f"  level {level + 1}, last {len(latents)} steps: " + "; ".join(parts))
    return lines


def _level_arrays(kit, steps: list[dict], level: int):
    """The level's last half: latents and gradients (steps x coordinates), the
    coordinates' labels, and a function from latents to offsets off the truth in targets."""
    names = list(dict.fromkeys(s["name"] for s in steps if s["level"] == level))
    per_name = {n: [s for s in steps if s["level"] == level and s["name"] == n] for n in names}
    count = min(len(rows) for rows in per_name.values())
    start = count // 2
    latents = np.hstack([np.array([r["latent"] for r in per_name[n][start:count]]) for n in names])
    gradients = np.hstack([np.array([r["gradient"] for r in per_name[n][start:count]]) for n in names])
    layout, labels = [], []
    for name in names:
        prop, first = property_name(name), per_name[name][0]
        truth = np.ravel(kit.truth[prop]).astype(np.float64)
        layout.append((len(first["latent"]), first["log"], truth, target(prop) * (truth if prop == "sigma_t" else 1.0)))
        labels += [prop] if len(truth) == 1 else [f"{prop}[{channel}]" for channel in range(len(truth))]

    def offsets(point: np.ndarray) -> np.ndarray:
        parts, index = [], 0
        for width, log, truth, scale in layout:
            value = point[index : index + width]
            parts.append(((np.exp(value) if log else value) - truth) / scale)
            index += width
        return np.concatenate(parts)

    return latents, gradients, labels, offsets


def regressed_zero(latents: np.ndarray, gradients: np.ndarray) -> np.ndarray:
    """Where the linear model of the gradients in the values is zero: the mean point
    moved by the regressed Hessian's inverse (eigenvalues floored at a thousandth of the
    largest) times the mean gradient."""
    centred = latents - latents.mean(axis=0)
    design = np.c_[centred, np.ones(len(latents))]
    coefficients = np.linalg.lstsq(design, gradients, rcond=None)[0]
    hessian = 0.5 * (coefficients[:-1].T + coefficients[:-1])
    eigenvalues, vectors = np.linalg.eigh(hessian)
    floored = np.maximum(eigenvalues, 1e-3 * max(eigenvalues.max(), 1e-30))
    return latents.mean(axis=0) - vectors @ ((vectors.T @ coefficients[-1]) / floored)


def regression_lines(kit, steps: list[dict]) -> list[str]:
    """Per level: the regressed zero off the truth and its bootstrap spread, in targets."""
    lines, rng = [], np.random.default_rng(0)
    for level in sorted({s["level"] for s in steps}):
        latents, gradients, labels, offsets = _level_arrays(kit, steps, level)
        zero = offsets(regressed_zero(latents, gradients))
        resampled = []
        for _ in range(200):
            pick = rng.integers(0, len(latents), len(latents))
            resampled.append(offsets(regressed_zero(latents[pick], gradients[pick])))
        spread = np.std(resampled, axis=0)
        lines.append(
            f"  level {level + 1}, last {len(latents)} steps, regressed zero: "
            + ", ".join(f"{n} {z:+.1f} (bootstrap sd {d:.1f})" for n, z, d in zip(labels, zero, spread))
            + ", in targets"
        )
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--material", choices=("principled", "volumetric"), default="volumetric")
    parser.add_argument("--kits", default="0,1", help="kit seeds, comma-separated")
    parser.add_argument("--work", type=Path, default=None, help="kit folders (references kept); default: temporary")
    parser.add_argument("--regress", action="store_true", help="also the zero of the gradients regressed on the values")
    args = parser.parse_args()
    mitsuba_variant.activate()
    import drjit as dr
    import mitsuba as mi

    for kit, folder in kits_with_references(args.material, args.kits, args.work, mi):
        steps = recorded_fit(kit, folder, dr)
        lines = [f"{args.material} kit {kit.seed}: {kit.describe()}", *level_lines(kit, steps)]
        if args.regress:
            lines += regression_lines(kit, steps)
        print("\n".join(lines), flush=True)


if __name__ == "__main__":
    main()
