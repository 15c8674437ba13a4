"""Benchmark of the material model chosen by evidence (issue 27, point 3): with the
model left open (``capture.material = auto``), does fit_material pick principled for
the bird, volumetric for bird_volumetric, and opaque for an opaque specimen?

Captures: copies of sample_captures/bird (principled) and bird_volumetric
(volumetric), and ``pipeline synth --material glossy_paint`` (an opaque painted bird,
30 views at 560x420, seed 3). Each runs to fit_material on the standard preset with
``capture.material = auto``. Reported per capture: the true model, every candidate's
held-out error and seconds, the model chosen and why, the path-depth check, the
chosen model's parameter errors and fit_material's wall time.

Usage: ``.venv/bin/python -m bench.model_choice [--captures bird,bird_volumetric,glossy_paint]
[--workdir DIR] [--margin FRACTION]`` (after bin/bootstrap); about 40 minutes on 2 cores. A ``--workdir``
keeps the captures and their stage caches.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from bench.common import run_stages, write_section
from bench.fitting import _copy_sample, _error_cells
from pipeline.synthetic.options import SynthOptions
from pipeline.synthetic.score import score_heldout, score_material
from pipeline.synthetic.synth import synthesize
from stages.fit_material import Config as FitMaterialConfig

SYNTHESIZED = {"glossy_paint": SynthOptions(material="glossy_paint", seed=3)}
"""Captures rendered here rather than copied from sample_captures/."""


def _capture(name: str, work: Path) -> Path:
    if name not in SYNTHESIZED:
        return _copy_sample(name, work)
    capture = work / name
    if not (capture / "capture.toml").is_file():
        synthesize(capture, SYNTHESIZED[name])
    return capture


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--captures", default="bird,bird_volumetric,glossy_paint")
    parser.add_argument("--workdir", type=Path, help="keep captures and caches here")
    parser.add_argument(
        "--margin", type=float, default=FitMaterialConfig().model_margin, help="fit_material.model_margin"
    )
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        work = args.workdir or Path(folder)
        work.mkdir(parents=True, exist_ok=True)
        for name in args.captures.split(","):
            capture = _capture(name, work)
            truth = json.loads((capture / "ground_truth" / "material.json").read_text())
            outputs, seconds = run_stages(
                capture, "fit_material", "capture.material=auto", f"fit_material.model_margin={args.margin}"
            )
            params = json.loads(outputs["fit_material"]["params"].read_text())
            choice = params["model_choice"]
            candidates = ", ".join(
                f"{c['model']} {c['validation_mse']:.4g} ({c['seconds']:.0f} s)" for c in choice["candidates"]
            )
            errors = _error_cells(score_material(params, truth)) if params["model"] == truth["model"] else {}
            error_text = ", ".join(f"{k} {text}" for k, (_, text) in errors.items()) or "-"
            verdict = "yes" if params["model"] == truth["model"] else "**no**"
            psnr = score_heldout(outputs["fit_material"]["heldout"])["psnr_db_mean"]
            rows.append(
                f"| {name} | {truth['model']} | {candidates} | {params['model']} ({verdict}) | {choice['why']} | "
                f"{choice['depth']['why']} | {error_text} | {psnr:.1f} dB | {seconds['fit_material']:.0f} s |"
            )
    print(
        write_section(
            "model-choice",
            [
                "### The material model chosen by evidence (issue 27, point 3)",
                "",
                "fit_material on the standard preset with `capture.material = auto`: principled (with the",
                "light) first, then opaque from it, volumetric only when principled beat opaque by more",
                f"than `fit_material.model_margin` ({args.margin:.0%}); the simplest within the margin of the best",
                "held-out MSE kept; then the held-out photos rendered at twice the path depth.",
                f"Reproduce: `.venv/bin/python -m bench.model_choice --captures {args.captures} --margin {args.margin}`.",
                "",
                "| capture | true model | candidates: held-out MSE (time) | chosen (right?) | why | depth |"
                " errors | held-out PSNR | fit_material |",
                "|---|---|---|---|---|---|---|---|---|",
                *rows,
            ],
        )
    )


if __name__ == "__main__":
    main()
