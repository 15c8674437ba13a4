"""How close to the truth a volumetric fit-speed kit's references let any fit end.

    .venv/bin/python -m bench.studies.kit_bounds --kits 0,1,2,5,6,7,13,15,16 [--spp 256] [--seed 5000]

bench/fit_speed.py's references are renders of the truth at REFERENCE_SPP, so they
carry Monte Carlo noise, and the values that fit them best (what every fit of them
minimises: the squared error of the expected image, pipeline.fit.loop) lie off the
truth by a draw of that noise. Linearised at the truth, the best fit's error is
J^+ e (J: the expected image's Jacobian by the fitted coordinates, e: the references'
noise), whose covariance is the least-squares sandwich

    C = A^-1 B A^-1,  A = sum over pixels of J_p J_p^T,  B = sum of s_p^2 J_p J_p^T,

with s_p^2 the variance of a reference pixel. Per kit and coordinate (alpha, eta, the
three albedo channels, log sigma_t) this prints C's standard deviation in units of the
coordinate's target (bench/fit_kits.py: sigma_t's is relative), and the probability
that the best fit ends within every target, drawn from N(0, C). Summed over kits, that
probability is how many kits a fit without any error of its own would end within every
target: the ceiling of issue 52's success rate on these kits.

Every render is the scene's own integrator's (the references'), at ``--spp``. J_p by
central differences (STEPS), both ends with one seed so that most of their noise is
common (prbvolpath does not differentiate forward in Mitsuba 3.9); twice, with two
seeds, and A and B take the symmetrised products of the two estimates, so that their
own noise does not add. s_p^2 as half the squared difference of two more renders,
scaled to REFERENCE_SPP. Another ``--seed`` draws every render anew: how far the
figures move with it is their own uncertainty.

Limitations: volumetric kits only; linear about the truth (a valley that bends within
a target is not seen), with the differences' own bias (second order in the steps);
the fits' coarse levels and step noise are not modelled, only where their objective's
minimum lies.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from bench.fit_kits import REFERENCE_SPP, draw_kit, kit_xml
from bench.studies.gradient_noise import COORDINATES, UNITS, set_coordinates
from pipeline.core import progress
from pipeline.render import mitsuba_variant

STEPS = np.array([0.1, 0.1, 0.05, 0.05, 0.05, 0.2])
"""Half the central differences' spans (alpha, eta, albedo r g b, log sigma_t): two
renders with one seed part ways where a path refracts, so alpha's and eta's
differences over bench/studies/gradient_noise.py's 0.02 are mostly noise (the
covariance estimated from them came out indefinite)."""
DRAWS = 200_000
"""Draws from N(0, C) for the probability of ending within every target."""


def jacobian(scene, view: int, x: np.ndarray, spp: int, seed: int, mi) -> np.ndarray:
    """(6, pixels * 3): the view's image derivative by each coordinate at ``x``, by
    central differences of renders with one seed."""
    params = mi.traverse(scene)
    rows = []
    for column, step in enumerate(STEPS):
        ends = []
        for sign in (1, -1):
            moved = x.copy()
            moved[column] += sign * step
            set_coordinates(params, moved)
            params.update()
            ends.append(np.array(mi.render(scene, sensor=view, spp=spp, seed=seed)).ravel())
        rows.append((ends[0] - ends[1]) / (2 * step))
    set_coordinates(params, x)
    params.update()
    return np.array(rows)


def reference_variance(scene, view: int, spp: int, seed: int, mi) -> np.ndarray:
    """(pixels * 3,): each reference pixel's variance at REFERENCE_SPP, from two renders
    at ``spp`` of the scene's own integrator (the references')."""
    first, second = (np.array(mi.render(scene, sensor=view, spp=spp, seed=seed + k)).ravel() for k in (0, 1))
    return np.square(first - second) / 2 * spp / REFERENCE_SPP


def covariance(kit, spp: int, first_seed: int, mi) -> np.ndarray:
    """C of the module docstring, in the coordinates."""
    with tempfile.TemporaryDirectory() as scratch:
        scene = mi.load_file(str(kit_xml(kit, kit.truth, Path(scratch))))
    truth = kit.truth
    x = np.array([truth["alpha"], truth["eta"], *truth["albedo"], np.log(truth["sigma_t"])])
    n = len(COORDINATES)
    A, B = np.zeros((n, n)), np.zeros((n, n))
    for view in progress.track(range(kit.views), f"kit {kit.seed}: views"):
        seed = first_seed + 10 * view
        first = jacobian(scene, view, x, spp, seed, mi)
        second = jacobian(scene, view, x, spp, seed + 1, mi)
        variance = reference_variance(scene, view, spp, seed + 2, mi)
        products = first @ second.T
        A += (products + products.T) / 2
        weighted = (first * variance) @ second.T
        B += (weighted + weighted.T) / 2
    A_inverse = np.linalg.inv(A)
    return A_inverse @ B @ A_inverse


def within_probability(C: np.ndarray, rng: np.random.Generator) -> float:
    """The share of draws from N(0, C) within every target (albedo's channels each
    within its target, sigma_t's relative error exp(d) - 1 within its own)."""
    draws = rng.multivariate_normal(np.zeros(len(C)), C, size=DRAWS, method="eigh")
    errors = np.abs(draws)
    errors[:, -1] = np.abs(np.expm1(draws[:, -1]))
    return float(np.mean(np.all(errors <= UNITS, axis=1)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kits", default="0,1,2,5,6,7,13,15,16", help="volumetric kit seeds, comma-separated")
    parser.add_argument("--spp", type=int, default=256, help="samples per pixel of each render")
    parser.add_argument("--seed", type=int, default=5000, help="first render seed (the references used 100 on)")
    args = parser.parse_args()
    mitsuba_variant.activate()
    import mitsuba as mi

    rng = np.random.default_rng(0)
    header = " ".join(f"{name:>11s}" for name in COORDINATES)
    print(f"standard deviation of the best fit, in targets:\n kit {header}  P(within every target)")
    total, estimated = 0.0, 0
    for seed in (int(s) for s in args.kits.split(",")):
        kit = draw_kit(seed, "volumetric")
        C = covariance(kit, args.spp, args.seed, mi)
        eigenvalues = np.linalg.eigvalsh(C)
        if eigenvalues.min() <= 0:
            print(f"{seed:4d} covariance not positive definite (eigenvalues {eigenvalues}): more --spp", flush=True)
            continue
        probability = within_probability(C, rng)
        total, estimated = total + probability, estimated + 1
        spread = " ".join(f"{s:11.2f}" for s in np.sqrt(np.diag(C)) / UNITS)
        print(f"{seed:4d} {spread}  {probability:.2f}   ({kit.describe()})", flush=True)
    print(
        f"of {estimated} kits estimated, expected within every target for a fit without error of its own: {total:.1f}"
    )


if __name__ == "__main__":
    main()
