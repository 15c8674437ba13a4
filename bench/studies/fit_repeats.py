"""How often `pipeline fit` ends within every target on a kit, over the fit's seeds.

    .venv/bin/python -m bench.studies.fit_repeats --material volumetric --kits 0,6,7 \
        [--runs 6] [--configs defaults ...] [--work DIR]

bench/fit_speed.py runs each kit once per configuration; where a fit's end is a draw
(its values wander about the answer by about a target), one run says little about a
configuration, and the same kit lands on either side of a target from run to run.
This runs each configuration of bench/fit_speed.py (``CONFIGS``) ``--runs`` times per
kit, the fit's seed (batch order and render seeds) set to the run's index, and prints
one line per run (within every target or not, the time to target, the seconds to the
end, the largest error in units of its target) and per kit and configuration the count
within every target.

Limitations: runs are not stored (each call fits anew); a kit's references are kept
in ``--work``.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from bench.fit_kits import Clock, errors, target, within
from bench.fit_speed import CONFIGS, pipeline_fit
from bench.studies.kit_folders import kits_with_references
from pipeline.render import mitsuba_variant


def runs_of(kit, folder: Path, config: str, runs: int) -> list[str]:
    """One line per run of ``config`` on ``kit``, then the count within every target."""
    settings, sizes = CONFIGS[config]
    lines, within_count = [], 0
    for run in range(runs):
        clock = Clock(kit, 0.0)
        result = pipeline_fit(kit, folder, replace(settings, seed=run), sizes, clock)
        ok = within(kit, result["values"])
        within_count += ok
        name, worst = max(((n, e / target(n)) for n, e in errors(kit, result["values"]).items()), key=lambda x: x[1])
        reached = "never" if clock.reached is None else f"{clock.reached:.1f} s"
        lines.append(
            f"  {config}, seed {run}: {'within every target' if ok else 'outside'}; to target {reached}; "
            f"{result['seconds']:.0f} s to the end; largest error {name} {worst:.2f} targets"
        )
    lines.append(f"  {config}: {within_count} of {runs} runs within every target")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--material", choices=("principled", "volumetric"), default="volumetric")
    parser.add_argument("--kits", default="0,6,7", help="kit seeds, comma-separated")
    parser.add_argument("--runs", type=int, default=6, help="fit seeds per kit and configuration")
    parser.add_argument("--configs", nargs="+", default=["defaults"], choices=sorted(CONFIGS))
    parser.add_argument("--work", type=Path, default=None, help="kit folders (references kept); default: temporary")
    args = parser.parse_args()
    mitsuba_variant.activate()
    import mitsuba as mi

    for kit, folder in kits_with_references(args.material, args.kits, args.work, mi):
        print(f"{args.material} kit {kit.seed}: {kit.describe()}", flush=True)
        for config in args.configs:
            print("\n".join(runs_of(kit, folder, config, args.runs)), flush=True)


if __name__ == "__main__":
    main()
