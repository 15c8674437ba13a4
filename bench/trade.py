"""Benchmark of the speed/accuracy trade (issue 27, point 1): the knobs that cost time,
swept one at a time around the standard preset, with the presets placed on the front.

Every point is a real ``pipeline run`` (a process of its own, so its peak memory is its
own) on a copy of the capture; stage caches are shared between points, and a point's
time is the sum of the wall times of every stage it depends on (a cached stage counts
with the time of the run that computed it), so it is what a fresh run of that
configuration costs. Per point: that time, the peak resident memory of the run that
computed it, held-out PSNR over the specimen's eroded mask after its last fit stage,
and on synthetic captures each material parameter's error and the worst error over its
target (issue 6's targets).

Groups (``--groups``):

material   fit_material alone: max_size (working resolution), spp, batch (views per
           step), iterations, the early stop (still_threshold), and recording
           each view's step with dr.freeze or tracing it every time
mesh       mesh.resolution, through fit_material
texture    fit_texture's finest resolution and number of levels
geometry   fit_geometry's rounds, through fit_geometry
presets    draft, standard and final end to end (``--presets``)
candidates the standard preset end to end with one of fit_material's cheaper settings
           that matched it in the material group, to see whether the whole
           pipeline's result keeps up before the preset moves
scaling    fit_material for 30 iterations at several max_size, spp and batch values:
           the median time of one iteration, and the slope of its logarithm against
           that of pixels per view, samples per pixel and views per step

Memory over iterations is read from the material group's iterations points (peak
memory at 50, 150 and 300 iterations) and from the resident memory sampled every
half second during the 300-iteration run.

Outputs: docs/trade.png (held-out PSNR and the worst parameter error against time,
log time axis, the Pareto front drawn, presets marked) and the ``trade`` section of
docs/benchmarks.md.

Usage: ``.venv/bin/python -m bench.trade [--samples bird,bird_volumetric,temple-ring]
[--groups material,mesh,texture,geometry,presets,scaling] [--presets draft,standard,final]
[--only fit_material.spp=4,...] [--workdir DIR] [--captures ../shared/captures]`` (after
bin/bootstrap). temple-ring runs with the template light (``light.model = given``), as
estimating it costs 12 minutes a point here. ``--only`` keeps, of the swept points, those
whose every change is listed (each group's unchanged point and the presets always run):
a volumetric fit costs five times a principled one here, so a capture can be swept on the
knobs another capture showed to matter. With a ``--workdir`` finished points are kept
(their memory figures in points/), so an interrupted run resumes; each capture's points
are added to ``trade-CAPTURE.json`` there, each with the commit that measured it, and the
section and plot show every point kept in the folder.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import psutil

from bench.common import ROOT, run_stages, write_section
from bench.fitting import TARGETS, _copy_sample, _error_cells
from bench.light import _prepare_real
from pipeline.synthetic.score import score_heldout, score_material

PLOT = ROOT / "docs" / "trade.png"
FIT_STAGES = ("fit_material", "fit_texture", "fit_geometry")
REAL = {"temple-ring": ("board.kind=none", "light.model=given")}
"""Settings per real capture: no board; the template light (see the module docstring)."""
RSS_INTERVAL_S = 0.5
SCALING_ITERATIONS = 30
SCALING = {
    "fit_material.max_size": (64, 256),
    "fit_material.spp": (4, 64),
    "fit_material.batch": (1, 4),
}
"""Knob -> values for the cost slopes, besides the standard preset's (SCALING_STANDARD),
which the others hold."""
SCALING_STANDARD = {"fit_material.max_size": 128, "fit_material.spp": 16, "fit_material.batch": 2}


@dataclass(frozen=True)
class Point:
    """One configuration: a preset, the settings changed from it, and the last stage run."""

    group: str
    until: str
    preset: str = "standard"
    overrides: tuple[str, ...] = ()

    @property
    def label(self) -> str:
        changed = ", ".join(o.split(".", 1)[1] for o in self.overrides) or "as is"
        return f"{self.preset} to {self.until}: {changed}"

    @property
    def slug(self) -> str:
        return re.sub(r"[^a-z0-9]+", "-", f"{self.preset}-{self.until}-{'-'.join(self.overrides)}".lower()).strip("-")


@dataclass
class Measured:
    """What one point cost and gave."""

    point: Point
    seconds: float
    stage_seconds: dict[str, float]
    peak_rss_mb: float
    rss_mb: list[tuple[float, float]] = field(default_factory=list)
    psnr_db: float | None = None
    errors: dict[str, str] = field(default_factory=dict)
    worst_over_target: float | None = None
    iteration_seconds: float | None = None
    commit: str = ""
    """The commit that measured it ("+": with uncommitted changes to code or presets)."""
    computed: bool = True
    """Whether the point's own run computed its last stage (else that stage came from the
    cache of another point, and the peak memory is not its)."""


def points_for(groups: list[str], presets: list[str], only: set[str] | None = None) -> list[Point]:
    grid = {
        "material": [
            Point("material", "fit_material"),
            *(
                Point("material", "fit_material", overrides=(f"fit_material.{knob}={value}",))
                for knob, values in (
                    ("max_size", (64, 192)),
                    ("spp", (4, 32)),
                    ("batch", (1, 4)),
                    ("iterations", (50, 300)),
                    ("freeze", ("false",)),
                )
                for value in values
            ),
            Point(
                "material", "fit_material", overrides=("fit_material.iterations=300", "fit_material.still_threshold=2")
            ),
        ],
        "mesh": [Point("mesh", "fit_material", overrides=(f"mesh.resolution={r}",)) for r in (96, 192)],
        "texture": [
            Point("texture", "fit_texture"),
            *(Point("texture", "fit_texture", overrides=(f"fit_texture.max_resolution={r}",)) for r in (64, 256)),
            Point("texture", "fit_texture", overrides=("fit_texture.levels=2",)),
        ],
        "geometry": [Point("geometry", "fit_geometry", overrides=("fit_geometry.rounds=1",))],
        "presets": [Point("presets", "export", preset=p) for p in presets],
        "candidates": [
            Point("candidates", "export", overrides=(change,))
            for change in ("fit_material.max_size=64", "fit_material.spp=4")
        ],
        "scaling": [
            Point("scaling", "fit_material", overrides=(f"fit_material.iterations={SCALING_ITERATIONS}",)),
            *(
                Point(
                    "scaling",
                    "fit_material",
                    overrides=(f"{knob}={v}", f"fit_material.iterations={SCALING_ITERATIONS}"),
                )
                for knob, values in SCALING.items()
                for v in values
            ),
        ],
    }
    chosen = [p for g in groups for p in grid[g]]
    return [p for p in chosen if only is None or p.group == "presets" or set(p.overrides) <= only]


class MemorySampler(threading.Thread):
    """Resident memory of a process and its children, every RSS_INTERVAL_S."""

    def __init__(self, pid: int):
        super().__init__(daemon=True)
        self.process, self.samples, self.started = psutil.Process(pid), [], time.perf_counter()

    def run(self) -> None:
        while True:
            try:
                family = [self.process, *self.process.children(recursive=True)]
                rss = sum(p.memory_info().rss for p in family)
            except psutil.NoSuchProcess:
                return
            self.samples.append((time.perf_counter() - self.started, rss / 2**20))
            time.sleep(RSS_INTERVAL_S)


def _run_point(capture: Path, point: Point, extra: tuple[str, ...], log: Path) -> tuple[float, list]:
    """Run the point in a process of its own: (peak RSS in MiB, sampled RSS)."""
    command = [str(Path(sys.executable).parent / "pipeline"), "run", str(capture), "--until", point.until]
    command += ["--preset", point.preset, *(a for o in (*extra, *point.overrides) for a in ("-s", o))]
    with log.open("w") as out:
        process = subprocess.Popen(command, stdout=out, stderr=subprocess.STDOUT)
        sampler = MemorySampler(process.pid)
        sampler.start()
        _, status, usage = os.wait4(process.pid, 0)
    sampler.join()
    if status != 0:
        raise RuntimeError(f"{' '.join(command)} failed; see {log}")
    return usage.ru_maxrss / 1024, sampler.samples


def _iteration_seconds(fitted_dir: Path) -> float:
    """The median wall time of one fit_material iteration (validation steps excluded by the median)."""
    rows = [json.loads(line) for line in (fitted_dir / "log.jsonl").read_text().splitlines()]
    return float(np.median(np.diff([r["seconds"] for r in rows])[5:]))


def measure(
    capture: Path, point: Point, extra: tuple[str, ...], work: Path, truth: dict | None, commit: str
) -> Measured:
    record = work / "points" / capture.name / f"{point.slug}.json"
    if record.is_file():
        kept = json.loads(record.read_text())
        peak, samples, commit = kept["peak_rss_mb"], kept["rss_mb"], kept["commit"]
    else:
        record.parent.mkdir(parents=True, exist_ok=True)
        print(f"[trade] {capture.name}: {point.label}", flush=True)
        peak, samples = _run_point(capture, point, extra, record.with_suffix(".log"))
        record.write_text(json.dumps({"peak_rss_mb": peak, "rss_mb": samples, "commit": commit}))
    outputs, seconds = run_stages(capture, point.until, *extra, *point.overrides, preset=point.preset)
    last = [s for s in FIT_STAGES if s in outputs][-1]
    computed = f"stage {point.until} done in" in record.with_suffix(".log").read_text()
    measured = Measured(point, sum(seconds.values()), seconds, peak, samples, commit=commit, computed=computed)
    measured.psnr_db = score_heldout(outputs[last]["heldout"])["psnr_db_mean"]
    if point.group == "scaling":
        measured.iteration_seconds = _iteration_seconds(outputs["fit_material"]["fitted_dir"])
    if truth is not None:
        params = json.loads(outputs[last]["params"].read_text())
        cells = _error_cells(score_material({"model": params.get("model", truth["model"])} | params, truth))
        measured.errors = {name: text for name, (_, text) in cells.items()}
        ratios = [error / TARGETS[name][1] for name, (error, _) in cells.items() if TARGETS[name][1]]
        measured.worst_over_target = max(ratios) if ratios else None
    return measured


def kept(path: Path) -> list[Measured]:
    """The points of one ``trade-CAPTURE.json`` (none when it is absent)."""
    if not path.is_file():
        return []
    return [
        Measured(**(m | {"point": Point(**(m["point"] | {"overrides": tuple(m["point"]["overrides"])}))}))
        for m in json.loads(path.read_text())
    ]


def pareto(points: list[Measured], value) -> set[int]:
    """Indices of the points no other point beats in both time and ``value`` (lower is better)."""
    front, best = set(), math.inf
    for index in sorted(range(len(points)), key=lambda i: (points[i].seconds, value(points[i]))):
        if value(points[index]) < best:
            front.add(index)
            best = value(points[index])
    return front


def plot(results: dict[str, list[Measured]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [
        ("held-out PSNR (dB)", lambda m: m.psnr_db, lambda m: -m.psnr_db),
        ("worst parameter error / target", lambda m: m.worst_over_target, lambda m: m.worst_over_target),
    ]
    figure, axes = plt.subplots(len(results), 2, figsize=(12, 4.2 * len(results)), squeeze=False)
    for row, (sample, measured) in enumerate(results.items()):
        swept = [m for m in measured if m.point.group != "scaling"]
        for column, (name, shown, lower_is_better) in enumerate(panels):
            axis = axes[row][column]
            usable = [m for m in swept if shown(m) is not None]
            if not usable:
                axis.set_axis_off()
                continue
            front = pareto(usable, lower_is_better)
            for index, m in enumerate(usable):
                preset = m.point.group == "presets"
                axis.scatter(
                    m.seconds,
                    shown(m),
                    s=90 if preset else 28,
                    marker="*" if preset else "o",
                    color="tab:red" if preset else ("tab:blue" if index in front else "tab:gray"),
                    zorder=3,
                )
                if preset:
                    axis.annotate(m.point.preset, (m.seconds, shown(m)), textcoords="offset points", xytext=(6, 4))
            line = sorted((usable[i].seconds, shown(usable[i])) for i in front)
            axis.step(*zip(*line), where="post", color="tab:blue", lw=1, label="Pareto front")
            axis.set_xscale("log")
            if column == 1:
                axis.set_yscale("log")
                axis.axhline(1.0, color="k", lw=0.6, ls=":")
            axis.set(xlabel="pipeline wall time to this result (s, 2 cores)", ylabel=name, title=sample)
            axis.legend(loc="best", fontsize=8)
    figure.tight_layout()
    figure.savefig(PLOT, dpi=110)
    plt.close(figure)


def slopes(sample: str, measured: list[Measured]) -> list[str]:
    """log-log slope of one iteration's time against each scaling knob's cost measure."""
    lines = []
    scaling = [m for m in measured if m.point.group == "scaling"]
    for knob, standard in SCALING_STANDARD.items():
        by_value = {
            float(m.point.overrides[0].split("=")[1]) if len(m.point.overrides) == 2 else float(standard): m
            for m in scaling
            if len(m.point.overrides) == 1 or m.point.overrides[0].startswith(knob + "=")
        }
        if len(by_value) < 2:
            continue
        values = sorted(by_value)
        rows = [by_value[v] for v in values]
        x = np.array(values)
        x = x**2 if knob.endswith("max_size") else x  # pixels per view grow as the side squared
        y = np.array([m.iteration_seconds for m in rows])
        slope = np.polyfit(np.log(x), np.log(y), 1)[0]
        times = ", ".join(f"{v:g} -> {1000 * t:.0f} ms" for v, t in zip(values, y, strict=True))
        measure_name = {"fit_material.max_size": "pixels per view", "fit_material.spp": "spp"}.get(
            knob, "views per step"
        )
        commits = ", ".join(sorted({m.commit for m in rows}))
        lines.append(f"| {sample} ({commits}) | {knob} | {times} | {measure_name} | {slope:.2f} |")
    return lines


def memory_lines(sample: str, measured: list[Measured]) -> list[str]:
    rows = [
        m
        for m in measured
        if m.point.group == "material"
        and m.computed
        and (m.point.overrides or ("",))[0].startswith("fit_material.iterations")
        and len(m.point.overrides) == 1
    ]
    standard = next((m for m in measured if m.point.group == "material" and not m.point.overrides and m.computed), None)
    lines = []
    for m in sorted([*rows, *([standard] if standard else [])], key=lambda m: m.stage_seconds["fit_material"]):
        its = m.point.overrides[0].split("=")[1] if m.point.overrides else "150"
        lines.append(f"- {sample} ({m.commit}), {its} iterations: peak {m.peak_rss_mb:.0f} MiB")
    longest = max(rows, key=lambda m: m.stage_seconds["fit_material"], default=None)
    # A minute at least: over a shorter run the slope says nothing of growth.
    if longest and len(longest.rss_mb) > 10 and longest.rss_mb[-1][0] >= 60:
        t, rss = np.array(longest.rss_mb).T
        half = t >= t[-1] / 2
        slope = np.polyfit(t[half] / 60, rss[half], 1)[0]
        quartiles = ", ".join(f"{rss[int(q * (len(rss) - 1))]:.0f}" for q in (0.25, 0.5, 0.75, 1.0))
        lines.append(
            f"- {sample}, during the {longest.point.overrides[0].split('=')[1]}-iteration run: resident memory at a quarter, "
            f"half, three quarters and the end of its {t[-1]:.0f} s: {quartiles} MiB; over its second half "
            f"{slope:+.1f} MiB a minute"
        )
    return lines


def table(sample: str, measured: list[Measured]) -> list[str]:
    lines = []
    swept = [m for m in measured if m.point.group != "scaling"]
    fronts = pareto(swept, lambda m: -m.psnr_db)
    for index, m in enumerate(swept):
        stages = ", ".join(f"{s} {m.stage_seconds[s]:.0f}" for s in FIT_STAGES if s in m.stage_seconds)
        errors = ", ".join(f"{k} {v}" for k, v in m.errors.items()) or "-"
        worst = f"{m.worst_over_target:.2f}" if m.worst_over_target is not None else "-"
        memory = f"{m.peak_rss_mb:.0f} MiB" if m.computed else "cached"
        lines.append(
            f"| {sample} ({m.commit}) | {m.point.label} | {m.seconds:.0f} s ({stages}) | {memory} | "
            f"{m.psnr_db:.1f} dB{' (front)' if index in fronts else ''} | {errors} | {worst} |"
        )
    return lines


def _commit() -> str:
    """HEAD's short hash, with "+" when code or presets differ from it (docs may: the bench writes them)."""

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()

    return git("rev-parse", "--short", "HEAD") + (
        "+" if git("status", "--porcelain", "pipeline", "stages", "configs", "bench") else ""
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", default="bird,bird_volumetric,temple-ring")
    parser.add_argument("--groups", default="material,mesh,texture,geometry,presets,scaling")
    parser.add_argument("--presets", default="draft,standard,final")
    parser.add_argument("--only", help="comma-separated changes: sweep only points made of these")
    parser.add_argument("--workdir", type=Path, help="keep captures, caches and points here")
    parser.add_argument("--captures", type=Path, default=ROOT.parent / "shared" / "captures")
    args = parser.parse_args()
    only = set(args.only.split(",")) if args.only else None
    commit = _commit()
    with tempfile.TemporaryDirectory() as folder:
        work = args.workdir or Path(folder)
        work.mkdir(parents=True, exist_ok=True)
        for sample in args.samples.split(","):
            if sample in REAL:
                if not (args.captures / sample).is_dir():
                    print(f"[trade] {sample}: not found in {args.captures}, skipped")
                    continue
                capture, extra, truth = _prepare_real(sample, args.captures, work), REAL[sample], None
            else:
                capture, extra = _copy_sample(sample, work), ()
                truth = json.loads((capture / "ground_truth" / "material.json").read_text())
            points = points_for(args.groups.split(","), args.presets.split(","), only)
            record = work / f"trade-{sample}.json"
            measured = {m.point: m for m in kept(record)}
            for point in points:
                measured[point] = measure(capture, point, extra, work, truth, commit)
                record.write_text(json.dumps([asdict(m) for m in measured.values()], indent=1))
        results = {path.stem.removeprefix("trade-"): kept(path) for path in sorted(work.glob("trade-*.json"))}
    plot(results)
    lines = [line for sample, measured in results.items() for line in table(sample, measured)]
    scaling = [line for sample, measured in results.items() for line in slopes(sample, measured)]
    memory = [line for sample, measured in results.items() for line in memory_lines(sample, measured)]
    print(
        write_section(
            "trade",
            [
                "### The speed/accuracy trade (issue 27, point 1)",
                "",
                "Reproduce: `.venv/bin/python -m bench.trade --workdir DIR --samples CAPTURE --groups ... "
                "[--only ...]` (the groups and samples: bench/trade.py's docstring); the section shows every point",
                "kept in DIR, each with the commit that measured it.",
                "Machine: the 2-core, 24 GiB VM, no GPU (llvm_ad_rgb). Time: the sum of the wall times of",
                "every stage the result depends on. Memory: the peak resident memory of the run that",
                "computed the point. Errors after the last fit stage run (worst: the largest error over its",
                "target; below 1 meets every target). ![trade](trade.png)",
                "",
                "| capture | point | time (fit stages, s) | peak memory | held-out PSNR | errors | worst |",
                "|---|---|---|---|---|---|---|",
                *lines,
                "",
                "Cost of one fit_material iteration (median; batch 2, spp 16, 128 px unless varied):",
                "",
                "| capture | knob | values -> time per iteration | grows with | log-log slope |",
                "|---|---|---|---|---|",
                *scaling,
                "",
                "Memory over iterations (fit_material, standard otherwise):",
                "",
                *memory,
            ],
        )
    )


if __name__ == "__main__":
    main()
