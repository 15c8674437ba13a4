"""Whether a volumetric fit-speed kit's gradient at the truth is biased or only noisy.

    .venv/bin/python -m bench.studies.gradient_noise --kits 7,6,16,13 [--seeds 16] [--work DIR]

For each kit of bench/fit_kits.py (volumetric material), at its true values and against
its references: the L2 loss's gradient as the fits take it (the differentiable
integrator at 4 spp), over ``--seeds`` render seeds, in the fit's coordinates (alpha,
eta, the three albedo channels, log sigma_t); and the Jacobian of the mean gradient,
by finite differences with the same seeds (so that most of the noise is common to
both ends). Printed per coordinate, in units of its target (bench/fit_kits.py):

- the mean gradient's z-score (its mean over its standard error): a bias shows as a
  z well beyond 2;
- where the mean gradient is zero, -J^-1 G, off the truth: where a fit that averaged
  that many steps' gradients would settle;
- a rough scale of that point's seed noise, |J^-1| applied to the gradients'
  standard errors (not a full covariance).

Limitations: one Jacobian per kit, with fixed steps; the fits' windows, masks and
loss weights are not modelled (whole films, plain L2).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from bench.fit_kits import INTEGRATORS, SIGMA_T_TARGET, TARGETS, draw_kit, kit_xml, references
from pipeline.render import mitsuba_variant

KEYS = {
    "alpha": "shape_bsdf.alpha.value",
    "eta": "shape_bsdf.eta",
    "albedo": "shape_medium.albedo.value.value",
    "sigma_t": "shape_medium.sigma_t.value.value",
}
COORDINATES = ("alpha", "eta", "albedo_r", "albedo_g", "albedo_b", "log_sigma_t")
STEPS = np.array([0.02, 0.02, 0.02, 0.02, 0.02, 0.05])
"""Finite-difference steps of the coordinates."""
UNITS = np.array([TARGETS["alpha"], TARGETS["eta"], *[TARGETS["albedo"]] * 3, SIGMA_T_TARGET])
TRAINING_SPP = 4


def set_coordinates(params, x: np.ndarray) -> None:
    """The kit's material at ``x`` (alpha, eta, albedo r g b, log sigma_t) in ``params``
    (mi.traverse of its scene; ``params.update()`` is the caller's)."""
    values = {"alpha": [x[0]], "eta": [x[1]], "albedo": x[2:5], "sigma_t": [np.exp(x[5])]}
    for name, value in values.items():
        params[KEYS[name]] = type(params[KEYS[name]])(*map(float, value))


def gradients(scene, integrator, references_, x: np.ndarray, seeds: int, mi, dr) -> np.ndarray:
    """(seeds, 6): the loss's gradient in the coordinates at ``x``, one row per seed."""
    params = mi.traverse(scene)
    rows = []
    for seed in range(seeds):
        set_coordinates(params, x)
        for key in KEYS.values():
            dr.enable_grad(params[key])
        params.update()
        for view, reference in enumerate(references_):
            image = mi.render(
                scene, params, sensor=view, integrator=integrator, spp=TRAINING_SPP, seed=1000 * seed + view
            )
            dr.backward(dr.mean(dr.square(image - reference), axis=None) / len(references_))
        grad = {name: np.array(dr.grad(params[key])).ravel() for name, key in KEYS.items()}
        rows.append(np.concatenate([grad["alpha"], grad["eta"], grad["albedo"], grad["sigma_t"] * np.exp(x[5])]))
    return np.array(rows)


def study(seed: int, seeds: int, work: Path, mi, dr) -> list[str]:
    """The printed lines of one kit."""
    kit = draw_kit(seed, "volumetric")
    folder = work / f"volumetric-{seed}"
    folder.mkdir(parents=True, exist_ok=True)
    reference_dir = references(kit, folder, mi)
    scene = mi.load_file(str(kit_xml(kit, kit.truth, folder)))
    integrator = mi.load_dict({"type": INTEGRATORS["volumetric"][1], "max_depth": INTEGRATORS["volumetric"][2]})
    references_ = [mi.TensorXf(mi.Bitmap(str(reference_dir / f"view_{i}.exr"))) for i in range(kit.views)]
    truth = kit.truth
    x0 = np.array([truth["alpha"], truth["eta"], *truth["albedo"], np.log(truth["sigma_t"])])
    at_truth = gradients(scene, integrator, references_, x0, seeds, mi, dr)
    jacobian = np.zeros((6, 6))
    for column in range(6):
        shifted = x0.copy()
        shifted[column] += STEPS[column]
        difference = gradients(scene, integrator, references_, shifted, seeds, mi, dr) - at_truth
        jacobian[:, column] = difference.mean(axis=0) / STEPS[column]
    symmetric = (jacobian + jacobian.T) / 2
    mean, error = at_truth.mean(axis=0), at_truth.std(axis=0, ddof=1) / np.sqrt(seeds)
    zero = -np.linalg.solve(symmetric, mean)
    noise = np.abs(np.linalg.solve(symmetric, np.diag(error))).max(axis=1)
    lines = [f"kit {seed}: {kit.describe()}"]
    for name, z, offset, spread, unit in zip(COORDINATES, mean / error, zero, noise, UNITS):
        lines.append(
            f"  {name:12s} gradient z {z:+5.1f}; zero of the mean gradient {offset / unit:+.2f} targets "
            f"off the truth (seed noise {spread / unit:.2f})"
        )
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kits", default="7,6,16,13", help="volumetric kit seeds, comma-separated")
    parser.add_argument("--seeds", type=int, default=16, help="render seeds per gradient")
    parser.add_argument("--work", type=Path, default=None, help="kit folders (references kept); default: temporary")
    args = parser.parse_args()
    mitsuba_variant.activate()
    import drjit as dr
    import mitsuba as mi

    work = args.work or Path(tempfile.mkdtemp(prefix="gradient-noise-"))
    for seed in (int(s) for s in args.kits.split(",")):
        print("\n".join(study(seed, args.seeds, work, mi, dr)), flush=True)


if __name__ == "__main__":
    main()
