"""Whether a fit's gradient should take its samples in the primal render or in the
gradient's: Mitsuba renders an l2 loss's gradient in two passes, the image at ``spp``
and the derivative's paths at ``spp_grad`` (mi.render), with independent seeds.

    .venv/bin/python -m bench.studies.gradient_samples --material volumetric --kit 7 \
        [--pairs 4:4,8:4,16:4,8:2,16:2,4:1] [--seeds 12] [--work DIR]

For one kit of bench/fit_kits.py at its true values (the end of a fit, where noise
decides where it settles): the loss's gradient over every view, as the fits take it
(plain l2, the kit's differentiable integrator), over ``--seeds`` render seeds per pair
of sample counts. Printed per pair: the seconds per gradient, each fitted channel's
variance over the first pair's, and the efficiency (variance times seconds, the first
pair's over this pair's; above 1 a fit averaging for a given time ends closer).

Near the optimum the image's noise times the derivative is most of the gradient's
noise for a value the image is smooth in (a colour), and the derivative's own noise
for one it is not (an index of refraction bends the paths): how the two split decides
which pass should take the samples.

Limitations: one point (the truth), whole films, no masks; a variance from a dozen
seeds is known to about 40 %, so a ratio of about 1 says nothing.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from bench.fit_kits import INTEGRATORS, kit_xml
from bench.studies.kit_folders import kits_with_references
from pipeline.render import mitsuba_variant


def fitted_keys(params, kit, dr) -> list[str]:
    """The scene parameters a fit of ``kit`` steps (its material's, named in its truth)."""
    return [
        key
        for key in params.keys()
        if key.startswith(("shape_bsdf.", "shape_medium."))
        and any(f".{name}" in key for name in kit.truth)
        and dr.is_diff_v(params[key])
    ]


def gradient_rows(scene, integrator, references_, keys, pair, seeds, mi, dr) -> tuple[np.ndarray, float]:
    """(seeds, channels) gradients of the l2 loss over every view at ``pair`` (spp,
    spp_grad), and the seconds per gradient (after one untimed gradient)."""
    params = mi.traverse(scene)
    spp, spp_grad = pair

    def gradient(seed: int) -> np.ndarray:
        for key in keys:
            dr.enable_grad(params[key])
        params.update()
        for view, reference in enumerate(references_):
            image = mi.render(
                scene, params, sensor=view, integrator=integrator, spp=spp, spp_grad=spp_grad, seed=1000 * seed + view
            )
            dr.backward(dr.mean(dr.square(image - reference), axis=None) / len(references_))
        row = np.concatenate([np.array(dr.grad(params[key])).ravel() for key in keys])
        for key in keys:
            dr.disable_grad(params[key])
        return row

    gradient(seeds + 1)
    started = time.perf_counter()
    rows = np.array([gradient(seed) for seed in range(1, seeds + 1)])
    return rows, (time.perf_counter() - started) / seeds


def study(material: str, seed: int, pairs: list[tuple[int, int]], seeds: int, work: Path | None, mi, dr) -> list[str]:
    """The printed lines of one kit."""
    kit, folder = next(kits_with_references(material, str(seed), work, mi))
    reference_dir = folder / "references"
    scene = mi.load_file(str(kit_xml(kit, kit.truth, folder)))
    integrator = mi.load_dict({"type": INTEGRATORS[material][1], "max_depth": INTEGRATORS[material][2]})
    references_ = [mi.TensorXf(mi.Bitmap(str(reference_dir / f"view_{i}.exr"))) for i in range(kit.views)]
    params = mi.traverse(scene)
    keys = fitted_keys(params, kit, dr)
    channels = [f"{key.split('.')[1]}[{c}]" for key in keys for c in range(np.size(np.array(params[key])))]
    measured = {pair: gradient_rows(scene, integrator, references_, keys, pair, seeds, mi, dr) for pair in pairs}
    first_rows, first_seconds = measured[pairs[0]]
    first_variance = first_rows.var(axis=0, ddof=1)
    lines = [f"{material} kit {seed}: {kit.describe()}", f"  channels: {', '.join(channels)}"]
    for pair, (rows, seconds) in measured.items():
        ratio = rows.var(axis=0, ddof=1) / first_variance
        efficiency = first_seconds / (ratio * seconds)
        standardised = (rows - rows.mean(axis=0)) / rows.std(axis=0)
        kurtosis = (standardised**4).mean(axis=0) - 3
        lines.append(
            f"  spp {pair[0]:2d}, spp_grad {pair[1]:2d}: {seconds:.3f} s per gradient; variance / first pair's "
            f"{' '.join(f'{r:.2f}' for r in ratio)}; efficiency geometric mean "
            f"{np.exp(np.log(efficiency).mean()):.2f} (range {efficiency.min():.2f}-{efficiency.max():.2f}); "
            f"excess kurtosis at most {kurtosis.max():.1f}"
        )
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--material", choices=sorted(INTEGRATORS), default="volumetric")
    parser.add_argument("--kit", type=int, default=7, help="the kit's seed")
    parser.add_argument(
        "--pairs", default="4:4,8:4,16:4,8:2,16:2,4:1", help="spp:spp_grad pairs, the first the baseline"
    )
    parser.add_argument("--seeds", type=int, default=12, help="render seeds per pair")
    parser.add_argument("--work", type=Path, default=None, help="kit folders (references kept); default: temporary")
    args = parser.parse_args()
    mitsuba_variant.activate()
    import drjit as dr
    import mitsuba as mi

    pairs = [(int(a), int(b)) for a, b in (pair.split(":") for pair in args.pairs.split(","))]
    print("\n".join(study(args.material, args.kit, pairs, args.seeds, args.work, mi, dr)), flush=True)


if __name__ == "__main__":
    main()
