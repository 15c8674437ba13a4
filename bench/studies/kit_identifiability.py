"""Whether a fit-speed kit's references determine its true values.

    .venv/bin/python -m bench.studies.kit_identifiability --work DIR [--runs defaults]
                                                         [--materials ...] [--spp 128] [--write]

bench/fit_speed.py counts a kit as missed when a run ends outside a parameter's target.
A miss is the fit's fault only when the references tell the truth from where the fit
ended. For each kit folder that bench left in ``DIR`` whose stored run (``--runs``)
ended outside a target, this renders the kit's views at the truth and at the run's
result, both with the same seeds (the two renders share their sampler's numbers until
the parameters send their paths apart, so most of their noise is common), and scores
each against the references by the squared error of the expected image (what the
fits minimise), estimated from two renders (Deng et al.'s dual estimator).

A result whose loss is no higher than the truth's fits the references as well as the
truth does: those photos do not tell the two apart, and no fit of them can be expected
to end at the truth. The ratio's spread over the views says how sure that is. Rewrites
docs/benchmarks.md's "kit-identifiability" section with ``--write``.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from bench.common import machine, write_section
from bench.fit_kits import draw_kit, errors, kit_xml, stored_outcome, target, within
from pipeline.core import progress
from pipeline.render import mitsuba_variant

SEED = 1000
"""First render seed (a view's two are SEED plus twice its index, and one more); the
references used 100 on."""


def losses(kit, values: dict, folder: Path, spp: int, mi) -> np.ndarray:
    """Per view: the dual estimator (two renders) of the squared error of the kit's
    expected image at ``values`` against its references.
    One render's plain squared error would add the render's own variance, which the
    parameters change (a thinner medium scatters less and renders less noisy)."""
    with tempfile.TemporaryDirectory() as scratch:
        scene = mi.load_file(str(kit_xml(kit, values, Path(scratch))))
    result = []
    for view in range(kit.views):
        reference = np.array(mi.Bitmap(str(folder / "references" / f"view_{view}.exr")))
        first, second = (
            np.array(mi.render(scene, sensor=view, spp=spp, seed=SEED + 2 * view + k)) - reference for k in (0, 1)
        )
        result.append(float(np.mean(first * second)))
    return np.array(result)


def outside_targets(kit, values: dict) -> str:
    return ", ".join(f"{name} {error:.3f}" for name, error in errors(kit, values).items() if error > target(name))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, required=True, help="bench/fit_speed.py's --work folder")
    parser.add_argument("--runs", nargs="*", default=["defaults"], help="bench/fit_speed.py's configurations")
    parser.add_argument("--materials", nargs="*", default=["principled", "volumetric"])
    parser.add_argument("--spp", type=int, default=128, help="samples per pixel of each render")
    parser.add_argument("--write", action="store_true", help="rewrite docs/benchmarks.md's section")
    args = parser.parse_args()
    variant = mitsuba_variant.activate()
    import mitsuba as mi

    lines = [
        "| kit | material | run | outside its target | loss at the truth | loss at the result | "
        "result / truth (views' range) |",
        "|---|---|---|---|---|---|---|",
    ]
    print("\n".join(lines))
    candidates = [
        (material, seed, run)
        for material in args.materials
        for seed in sorted(int(p.name.rpartition("-")[2]) for p in args.work.glob(f"{material}-*"))
        for run in args.runs
    ]
    determined = undetermined = 0
    examined = []
    for material, seed, run in progress.track(candidates, "kits"):
        kit, folder = draw_kit(seed, material), args.work / f"{material}-{seed}"
        outcome = stored_outcome(folder, run)
        if outcome is None:
            continue
        examined.append(f"{material} {seed}")
        if within(kit, outcome.final):
            continue
        truth = losses(kit, kit.truth, folder, args.spp, mi)
        result = losses(kit, outcome.final, folder, args.spp, mi)
        ratios = result / truth
        tells_apart = bool(ratios.min() > 1.0)  # every view scores the result worse
        determined += tells_apart
        undetermined += not tells_apart
        lines.append(
            f"| {seed} | {material} | {run} | {outside_targets(kit, outcome.final)} | {np.mean(truth):.4g} | "
            f"{np.mean(result):.4g} | {np.mean(result) / np.mean(truth):.3f} "
            f"({ratios.min():.3f}-{ratios.max():.3f}) |"
        )
        print(lines[-1], flush=True)
    verdict = (
        f"Kits with a stored run: {', '.join(examined)}. "
        f"Of {determined + undetermined} missed runs, {determined} ended where every view's loss is above the "
        f"truth's (the references tell the result from the truth) and {undetermined} where they do not."
    )
    print(verdict)
    if args.write:
        runs = " ".join(repr(r) if " " in r else r for r in args.runs)
        options = f"--work DIR --materials {' '.join(args.materials)} --runs {runs} --spp {args.spp}"
        intro = [
            "### Whether the missed kits' references determine their values",
            "",
            f"{machine()} Mitsuba variant {variant}. Command (DIR: bench/fit_speed.py's --work folder):",
            f"`.venv/bin/python -m bench.studies.kit_identifiability {options} --write`.",
            "A loss is the squared error of the expected image against the references (what the fits",
            f"minimise), estimated from two renders at {args.spp} spp, the truth's and the result's with",
            "the same seeds (bench/studies/kit_identifiability.py's docstring).",
            "",
            verdict,
            "",
        ]
        write_section("kit-identifiability", intro + lines)


if __name__ == "__main__":
    main()
