"""`pipeline fit` against the original tool's loop on a suite of kits drawn from seeds.

    .venv/bin/python -m bench.fit_speed [--kits 20] [--materials principled volumetric]
                                        [--configs defaults ...] [--budget 300] [--repeat 1]
                                        [--first-seed 0] [--write]

The kits, their targets and the original tool's loop: bench/fit_kits.py. Runs:

- ``original``: the original tool's loop (bench/fit_kits.py: ``original_loop``); it
  stops at the target or after ``--budget`` seconds.
- `pipeline fit` (pipeline.fit.scene_fit.fit_scene) with named settings
  (``CONFIGS``; ``defaults`` are the command's), the parameters named by property
  as a user names them; it runs to its own stopping rule and its log says when it
  met the targets; its result is the state it ends in. A run's seconds are those to
  its end (what a user waits for `pipeline fit`).

Each run is repeated ``--repeat`` times and the last is reported (later runs find
Dr.Jit's kernels compiled). A run's outcome is stored in its kit's folder under
``--work``; a later call with the same folder reuses it when the code the run executes
(``FIT_CODE`` for `pipeline fit`, bench/fit_kits.py's ``ORIGINAL_CODE`` for the
original loop) is as committed then (no uncommitted change there), on the same
machine and variant, with the same budget and repeats: a suite too long for one
sitting is run in parts (``--kits``, ``--first-seed``, ``--materials``), over
sessions that change other parts of the pipeline, and written whole by a last call
over every kit.

The table has one row per kit and run; the summary per material and configuration:
the share of kits whose result meets every target, the median ratio of the original
loop's time to target to the configuration's (a kit the original never reached
counts at its budget: a lower bound) and the median seconds to the end. The
machine's variant is Mitsuba's automatic choice (cuda_ad_rgb where a GPU works).
``--write`` puts the table into docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import code_version, machine, write_section
from bench.fit_kits import (
    ORIGINAL_CODE,
    Clock,
    Kit,
    Outcome,
    draw_kit,
    errors,
    kit_xml,
    original_loop,
    references,
    store_outcome,
    stored_outcome,
    within,
)
from pipeline.cli.fit import FitOptions
from pipeline.fit import engine
from pipeline.fit.scene_fit import FilmSizes
from pipeline.render import mitsuba_variant

DEFAULT_SIZES = FilmSizes(
    FitOptions.__dataclass_fields__["max_size"].default, FitOptions.__dataclass_fields__["coarse_to_fine"].default
)

FIT_CODE = (
    "pipeline/__init__.py",
    "pipeline/camera",
    "pipeline/core",
    "pipeline/fit",
    "pipeline/formats",
    "pipeline/imaging",
    "pipeline/render",
    "pipeline/cli/fit.py",
    "pipeline/cli/options.py",
    "pipeline/cli/registry.py",
    "bench/common.py",
    "bench/fit_kits.py",
    "bench/fit_speed.py",
)
"""What a kit's runs execute (the packages `pipeline fit` imports, and this bench):
a stored outcome is reused while these are unchanged."""

CONFIGS = {
    "defaults": (engine.FitSettings(), DEFAULT_SIZES),
    "without the medium's defaults": (engine.FitSettings(image_memory=0, step_halvings=0), DEFAULT_SIZES),
    "not whitened": (engine.FitSettings(whiten=False), DEFAULT_SIZES),
    "halved steps": (engine.FitSettings(image_memory=0, step_halvings=2), DEFAULT_SIZES),
    "16 spp, 4 for the gradient": (
        engine.FitSettings(spp=16, spp_grad=4, image_memory=0, step_halvings=0),
        DEFAULT_SIZES,
    ),
    "image memory 10": (engine.FitSettings(image_memory=10, step_halvings=0), DEFAULT_SIZES),
    "image memory 10, halved steps": (engine.FitSettings(image_memory=10, step_halvings=2), DEFAULT_SIZES),
    "defaults, not frozen": (engine.FitSettings(freeze=False), DEFAULT_SIZES),
    "defaults at full size": (engine.FitSettings(), FilmSizes(0)),
    "max_size only": (engine.FitSettings(), FilmSizes(DEFAULT_SIZES.max_size, coarse_to_fine=False)),
}
"""`pipeline fit`'s settings to compare with the original loop: the loop's settings and
the films' sizes. ``defaults`` are those `pipeline fit` runs with when given no option
(with a medium, the image memory and halved steps: pipeline.fit.settings.FitSettings);
``without the medium's defaults`` is ``--image-memory 0 --step-halvings 0``;
``max_size only`` is ``--no-coarse-to-fine``; ``halved steps`` is ``--step-halvings 2
--image-memory 0``; ``16 spp, 4 for the gradient`` is ``--spp 16 --spp-grad 4`` without
the memory or halvings; ``image memory 10`` is ``--image-memory 10 --step-halvings 0``;
``image memory 10, halved steps`` is ``--image-memory 10 --step-halvings 2`` (a medium's
defaults, on any scene)."""


def pipeline_fit(kit: Kit, folder: Path, settings: engine.FitSettings, sizes: FilmSizes, clock: Clock) -> dict:
    """`pipeline fit` (pipeline.fit.scene_fit.fit_scene, what the command calls) on the
    kit's file, the parameters named by property as a user names them; it runs to its own
    stopping rule. Its log's parameters after each step are checked against the targets;
    the time before the loop (loading the scene and the references) counts. Returns its
    params.json (the values it ends with, and why it stopped)."""
    from pipeline.fit.scene_fit import SceneFit, fit_scene, property_name

    out = folder / "fit_out"
    loop_started = []
    fit = engine.fit

    def timed_fit(*args, **kwargs):
        loop_started.append(time.perf_counter())
        return fit(*args, **kwargs)

    engine.fit = timed_fit
    started = time.perf_counter()
    try:
        request = SceneFit(
            kit_xml(kit, kit.start(), folder),
            folder / "references",
            tuple(kit.truth),
            settings,
            out_dir=out,
            sizes=sizes,
        )
        params = fit_scene(request)
    finally:
        engine.fit = fit
    log = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    for entry in log:
        values = {property_name(key): v if len(v) > 1 else v[0] for key, v in entry["params"].items()}
        clock.record(loop_started[0] - started + entry["seconds"], values)
    result = json.loads(params.read_text())
    return {
        "values": {property_name(key): v if len(v) > 1 else v[0] for key, v in result["params"].items()},
        "stopped": result.get("stopped", "-"),
        "seconds": time.perf_counter() - started,
    }


def run(kit: Kit, folder: Path, name: str, budget: float, repeat: int, conditions: dict, mi, dr) -> Outcome:
    """The run ``name`` on the kit in ``folder``, or its outcome stored there by an earlier
    run under the same ``conditions`` (per kind of run, "original" or "pipeline fit":
    the same committed code, machine and variant) and with the same budget and repeats."""
    kind = "original" if name == "original" else "pipeline fit"
    key = conditions[kind] | {"budget": budget if name == "original" else None, "repeat": repeat}
    if not key["code"].endswith("+changes") and (outcome := stored_outcome(folder, name, key)) is not None:
        return outcome
    for _ in range(repeat):
        clock = Clock(kit, budget)
        if name == "original":
            original_loop(kit, folder, clock, mi, dr)
            stopped = "target" if clock.reached else "budget"
            outcome = Outcome(clock.reached, clock.steps, clock.last, stopped, clock.elapsed())
        else:
            result = pipeline_fit(kit, folder, *CONFIGS[name], clock)
            outcome = Outcome(clock.reached, clock.steps, result["values"], result["stopped"], result["seconds"])
    store_outcome(folder, name, key, outcome)
    return outcome


def summary_lines(outcomes: dict[tuple[str, str], list[tuple[Kit, Outcome, Outcome]]], budget: float) -> list[str]:
    """Per material and configuration: the share of kits whose result meets every
    target, the median time-to-target ratio against the original loop, and the median
    time the run took to its end."""
    lines = [
        "| material | run | kits | result within every target | reached the targets at some step "
        "| median ratio to the original | median seconds to the end |"
    ]
    lines.append("|---|---|---|---|---|---|---|")
    for (material, name), rows in outcomes.items():
        final_ok = sum(within(kit, result.final) for kit, result, _ in rows)
        reached = sum(result.reached is not None for _, result, _ in rows)
        ratios = [
            (original.reached or budget) / result.reached for _, result, original in rows if result.reached is not None
        ]
        median = f"{np.median(ratios):.1f}x" if ratios else "-"
        lines.append(
            f"| {material} | {name} | {len(rows)} | {final_ok} ({100 * final_ok / len(rows):.0f} %) | "
            f"{reached} | {median} | {np.median([result.seconds for _, result, _ in rows]):.0f} |"
        )
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kits", type=int, default=20, help="kits per material (seeds first-seed ...)")
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--materials", nargs="*", default=["principled", "volumetric"])
    parser.add_argument("--configs", nargs="*", default=["defaults"])
    parser.add_argument("--budget", type=float, default=300.0, help="seconds the original loop may run per kit")
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--work", type=Path, help="keep each kit's scene and references here (default: a new folder)")
    parser.add_argument("--write", action="store_true", help="rewrite docs/benchmarks.md's section")
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="fit_speed_"))
    variant = mitsuba_variant.activate()
    import drjit as dr
    import mitsuba as mi

    version = code_version(*FIT_CODE, label="fitting code")
    original_version = code_version(*ORIGINAL_CODE, label="original loop's code")
    conditions = {
        kind: {"code": v.partition(", ")[2], "machine": machine(), "variant": variant}
        for kind, v in (("pipeline fit", version), ("original", original_version))
    }
    print(f"variant {variant}, {version}, {original_version.partition(', ')[2]}")
    lines = [
        "| kit | material | scene | run | time to target | steps | stopped | seconds | errors of the result | ratio |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    print("\n".join(lines))
    outcomes: dict[tuple[str, str], list[tuple[Kit, Outcome, Outcome]]] = {}
    for material in args.materials:
        for seed in range(args.first_seed, args.first_seed + args.kits):
            kit = draw_kit(seed, material)
            folder = work / f"{material}-{seed}"
            folder.mkdir(parents=True, exist_ok=True)
            references(kit, folder, mi)
            original = run(kit, folder, "original", args.budget, args.repeat, conditions, mi, dr)
            for name in ["original", *args.configs]:
                outcome = (
                    original
                    if name == "original"
                    else run(kit, folder, name, args.budget, args.repeat, conditions, mi, dr)
                )
                if name != "original":
                    outcomes.setdefault((material, name), []).append((kit, outcome, original))
                reached = f"{outcome.reached:.1f} s" if outcome.reached is not None else "never"
                ratio = "-"
                if name != "original" and outcome.reached is not None:
                    ratio = f"{(original.reached or args.budget) / outcome.reached:.1f}x"
                    ratio = ratio if original.reached is not None else f">{ratio}"
                shown = ", ".join(f"{n} {e:.3f}" for n, e in errors(kit, outcome.final).items())
                lines.append(
                    f"| {seed} | {material} | {kit.describe()} | {name} | {reached} | {outcome.steps} | "
                    f"{outcome.stopped} | {outcome.seconds:.0f} | {shown} | {ratio} |"
                )
                print(lines[-1], flush=True)
    summary = summary_lines(outcomes, args.budget)
    print("\n".join(summary))
    if args.write:
        options = " ".join(o for o in sys.argv[1:] if o != "--write").replace(str(args.work), "DIR")
        intro = [
            "## Fitting speed",
            "",
            f"{machine()} Mitsuba variant {variant}; code: {version}. Command:",
            f"`.venv/bin/python -m bench.fit_speed {options}",
            "--write`. The kits and the targets: bench/fit_kits.py's docstring; the runs: bench/fit_speed.py's.",
            "A result within every target is what the fit returns; a ratio is the original loop's time to",
            "target over the run's (>: the original never got there within the budget).",
            "",
            *summary,
            "",
        ]
        write_section("fit-speed", intro + lines)


if __name__ == "__main__":
    main()
