"""CAPTURE/output/report.html: one self-contained page of a capture's results, to
look at rather than read. Every image is embedded (PNG data URIs), so the file
opens offline, mailed or copied alone.

=======================  ==================================================================
section                  from
=======================  ==================================================================
summary                  the total time, the preset and settings, the library versions,
                         and links to the final files beside the page (output/)
3D view                  export's glb in a three.js viewer (pipeline.viewer), with the
                         texture map of the last fit stage that kept one
score                    score.json's figures, when a synthetic capture was scored
stages                   each stage's state for the current settings (cached, ran, to run,
                         disabled), seconds, cache key and key figures (its metrics)
cameras and mesh         sfm's cameras.json and the last mesh (fit_geometry's, else uv's),
                         drawn from above and from the side
held-out photos          per fit stage, per photo it held out: the photo, the render and
                         their difference (the PNGs of heldout/; a scale gives the
                         difference's values), PSNR over the mask; a click enlarges
trajectories             per fit stage, log.jsonl: training loss, held-out error and every
                         parameter (a texture's or map's channel means) against the step
parameters               the last fit stage's values, fit_material's bounds and units
choices                  the material model; the light (each candidate's held-out error and
                         seconds, and why the winner won); the texture kept or not and why;
                         fit_geometry's rounds
warnings                 the WARNING lines of each stage's log
=======================  ==================================================================

The page is built from what the cache holds for the current settings
(``pipeline report`` rewrites it; ``pipeline run`` writes it at the end). Stage
outputs are found by the names the stages declare (``sfm.cameras``,
``fit_material.params``, ...); a stage that has not run leaves its sections out.
"""

from __future__ import annotations

import base64
import html
import io
import json
import time
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from pipeline.core.cache import LOG_FILE
from pipeline.core.errors import DiskFull
from pipeline.core.fsutil import atomic_write_text, disk_full_error
from pipeline.core.runner import PlannedStage
from pipeline.formats.cameras import read_views
from pipeline.formats.scene_folder import heldout_names
from pipeline.imaging.photo_io import srgb_encode
from pipeline.synthetic.score import score_heldout, summary_rows
from pipeline.viewer import viewer_fragment

REPORT_HTML = "report.html"
FINAL_FILES = ("scene.xml", "params.json", "specimen.glb", "heldout", "README.txt")
"""The files at the top of output/ the summary links to."""
FIT_STAGES = (("fit_material", "fitted_dir"), ("fit_texture", "textured_dir"), ("fit_geometry", "geometry_dir"))
STYLE = """
body { font-family: sans-serif; margin: 2em; max-width: 1200px; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; }
td, th { border: 1px solid #ccc; padding: 3px 8px; text-align: left; vertical-align: top; font-size: 0.9em; }
th { background: #f0f0f0; }
figure { display: inline-block; margin: 0 0.5em 0.5em 0; }
figure img { max-width: 260px; image-rendering: pixelated; border: 1px solid #ccc; }
figure.plot img { max-width: 100%; image-rendering: auto; }
figcaption { font-size: 0.8em; color: #555; }
figure img.enlarged { max-width: 95vw; width: 95vw; cursor: zoom-out; }
figure img { cursor: zoom-in; }
.note { font-size: 0.8em; color: #555; margin: 0; }
.viewer { border: 1px solid #ccc; margin-bottom: 0.5em; }
.warning { color: #a40; font-family: monospace; font-size: 0.85em; }
"""
# After load, the page records how many of its images decoded: a headless browser
# reads it back from the DOM (tests/pipeline/test_report.py).
CHECK_IMAGES = """
window.addEventListener('load', function () {
  var images = Array.from(document.images);
  var loaded = images.filter(function (i) { return i.complete && i.naturalWidth > 0; });
  document.body.setAttribute('data-images', images.length);
  document.body.setAttribute('data-images-loaded', loaded.length);
});
"""


# A thumbnail clicked grows to the window's width; clicked again, back.
ENLARGE = """
document.addEventListener('click', function (event) {
  if (event.target.tagName === 'IMG' && event.target.closest('figure')) {
    event.target.classList.toggle('enlarged');
  }
});
"""


@dataclass(frozen=True)
class StageRecord:
    """One stage as the report shows it."""

    name: str
    state: str
    """cached, ran, to run or disabled (for the current settings)."""
    seconds: float | None
    key: str
    metrics: dict[str, Any] = field(default_factory=dict)
    outputs: dict[str, Path] = field(default_factory=dict)
    """The stage's outputs by declared name; empty when it has no result for these settings."""
    warnings: tuple[str, ...] = ()


def records(plan: list[PlannedStage], ran: set[str] = frozenset()) -> list[StageRecord]:
    """The report's view of a plan over every stage: those in ``ran`` ran just now;
    a stage with a cached result shows it, warnings from its log included."""
    result = []
    for item in plan:
        state = {"cached": "cached", "run": "to run", "disabled": "disabled"}[item.action]
        entry = item.entry
        if item.stage.name in ran:
            state = "ran"
        if entry is None:
            result.append(StageRecord(item.stage.name, state, None, item.key))
            continue
        log = entry.path / LOG_FILE
        lines = log.read_text(errors="replace").splitlines() if log.is_file() else []
        warnings = tuple(line.split(" WARNING ", 1)[1] for line in lines if " WARNING " in line)
        result.append(
            StageRecord(
                item.stage.name,
                state,
                entry.status["seconds"],
                item.key,
                entry.status.get("metrics", {}),
                entry.outputs,
                warnings,
            )
        )
    return result


def write(capture_dir: Path, stages: list[StageRecord], settings: RunSettings | None = None) -> Path:
    """Write CAPTURE/output/report.html from ``stages``; returns its path."""
    by_name = {s.name: s for s in stages}
    parts = [
        f"<h1>{_text(capture_dir.name)}</h1>",
        f"<p>{_text(str(capture_dir.resolve()))}; written {time.strftime('%Y-%m-%d %H:%M')}</p>",
        _summary_section(capture_dir, stages, settings),
        _view_section(by_name),
        _score_section(capture_dir),
        _stages_section(stages),
        _cameras_section(by_name),
        _choices_section(by_name),
        _parameters_section(by_name),
        _heldout_section(by_name),
        _trajectories_section(by_name),
        _warnings_section(stages),
    ]
    page = (
        "<!DOCTYPE html>\n<html><head><meta charset='utf-8'>"
        f"<title>{_text(capture_dir.name)}: pipeline report</title><style>{STYLE}</style>"
        f"<script>{CHECK_IMAGES}{ENLARGE}</script></head><body>\n"
        + "\n".join(p for p in parts if p)
        + "\n</body></html>\n"
    )
    path = capture_dir / "output" / REPORT_HTML
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        atomic_write_text(path, page)
    except OSError as error:
        if disk_full_error(error):
            raise DiskFull(path.parent, f"writing {path.name}", "the previous report was kept") from error
        raise
    return path


@dataclass(frozen=True)
class RunSettings:
    """What the run was asked for, as the report's summary shows it."""

    preset: str
    overrides: tuple[str, ...]
    """The ``-s`` settings, as given."""
    sources: tuple[str, ...]
    """The config files read, in order."""


LIBRARIES = ("specimen-pipeline", "mitsuba", "drjit", "pycolmap", "numpy", "opencv-contrib-python-headless", "trimesh")


def _versions() -> list[list[str]]:
    rows = []
    for name in LIBRARIES:
        try:
            rows.append([name, metadata.version(name)])
        except metadata.PackageNotFoundError:
            rows.append([name, "not installed"])
    return rows


def _summary_section(capture_dir: Path, stages: list[StageRecord], settings: RunSettings | None) -> str:
    total = sum(s.seconds or 0.0 for s in stages)
    parts = [f"<h2>Summary</h2><p>Total stage time {total:.1f} s (each stage's own run, cached ones included)."]
    if settings is not None:
        overrides = ", ".join(settings.overrides) or "none"
        parts.append(f" Preset {_text(settings.preset)}; settings given: {_text(overrides)}; config files: ")
        parts.append(_text(", ".join(settings.sources) or "none") + ".")
    parts.append("</p>")
    output = capture_dir / "output"
    finals = [name for name in FINAL_FILES if (output / name).exists()]
    if finals:
        links = ", ".join(f"<a href='{_text(name)}'>{_text(name)}</a>" for name in finals)
        parts.append(f"<p>Final files (beside this page; README.txt says what each is): {links}.</p>")
    parts.append(_table(["library", "version"], _versions()))
    return "".join(parts)


def _view_section(by_name: dict[str, StageRecord]) -> str:
    export = by_name.get("export")
    if export is None or "glb" not in export.outputs:
        return ""
    parts = ["<h2>3D view</h2><p>export's specimen.glb: drag to turn, scroll to zoom.</p>"]
    parts.append(viewer_fragment(export.outputs["glb"].read_bytes(), element_id="specimen-view"))
    for stage, folder_output in reversed(FIT_STAGES):
        record = by_name.get(stage)
        texture = None if record is None or folder_output not in record.outputs else record.outputs[folder_output]
        if texture is not None and (texture / "base_color.png").is_file():
            parts.append(_image((texture / "base_color.png").read_bytes(), f"{stage}: base colour texture (UV atlas)"))
            break
    return "".join(parts)


def _score_section(capture_dir: Path) -> str:
    path = capture_dir / "output" / "score.json"
    if not path.is_file():
        return ""
    rows = [list(row) for row in summary_rows(json.loads(path.read_text()))]
    return "<h2>Score against the ground truth</h2>" + _table(["part", "metric", "value"], rows)


def _difference_scale() -> str:
    """A bar from black to white labelled with the linear difference each shade shows:
    the PNGs hold 4 |render - photo|, sRGB-encoded."""
    ramp = np.tile(np.linspace(0.0, 1.0, 256), (12, 1))
    bar = io.BytesIO()
    Image.fromarray(np.round(ramp * 255).astype(np.uint8)).save(bar, format="PNG")
    labels = "".join(
        f"<span style='position:absolute;left:{encoded * 256:.0f}px'>{value:g}</span>"
        for value in (0.0, 0.005, 0.02, 0.08, 0.25)
        for encoded in [float(srgb_encode(np.array(4 * value)))]
    )
    source = "data:image/png;base64," + base64.b64encode(bar.getvalue()).decode("ascii")
    return (
        "<div class='scale'><img src='" + source + "' alt='difference scale' width='256' height='12'>"
        f"<div style='position:relative;height:1.2em;font-size:0.75em'>{labels}</div>"
        "<p class='note'>difference: |render - photo| in linear radiance</p></div>"
    )


def _text(value: Any) -> str:
    return html.escape(str(value))


def _number(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, list) and all(isinstance(v, (int, float)) for v in value):
        return "[" + ", ".join(_number(float(v)) for v in value) + "]"
    return str(value)


def _table(header: list[str], rows: list[list[Any]]) -> str:
    head = "".join(f"<th>{_text(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{_text(_number(c))}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _image(data: bytes, caption: str, plot: bool = False) -> str:
    """An embedded PNG: a photo-sized thumbnail, or (``plot``) a figure at full width."""
    source = "data:image/png;base64," + base64.b64encode(data).decode("ascii")
    kind = " class='plot'" if plot else ""
    return (
        f"<figure{kind}><img src='{source}' alt='{_text(caption)}'><figcaption>{_text(caption)}</figcaption></figure>"
    )


def _figure_png(figure) -> bytes:
    import matplotlib.pyplot as plt

    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=80, bbox_inches="tight")
    plt.close(figure)
    return buffer.getvalue()


def _json(record: StageRecord | None, output: str) -> dict | None:
    if record is None or output not in record.outputs:
        return None
    return json.loads(record.outputs[output].read_text())


def _stages_section(stages: list[StageRecord]) -> str:
    rows = []
    for stage in stages:
        figures = ", ".join(f"{k} {_number(v)}" for k, v in stage.metrics.items() if not isinstance(v, (dict, list)))
        seconds = "-" if stage.seconds is None else f"{stage.seconds:.1f}"
        rows.append([stage.name, stage.state, seconds, stage.key[:10], figures])
    return "<h2>Stages</h2>" + _table(["stage", "state", "seconds", "key", "key figures"], rows)


def _cameras_section(by_name: dict[str, StageRecord]) -> str:
    sfm = by_name.get("sfm")
    if sfm is None or "cameras" not in sfm.outputs:
        return ""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import trimesh

    poses = [pose for _, pose in read_views(sfm.outputs["cameras"]).values()]
    centres = np.array([p.center for p in poses])
    axes_z = np.array([p.R[2] for p in poses])
    mesh_stage, mesh_path = _last_mesh(by_name)
    mesh = trimesh.load(mesh_path, force="mesh", process=False) if mesh_path is not None else None
    figure, views = plt.subplots(1, 2, figsize=(10, 5))
    for view, (a, b, label) in zip(views, ((0, 1, "from above (x, y)"), (0, 2, "from the side (x, z)"))):
        if mesh is not None:
            view.triplot(mesh.vertices[:, a], mesh.vertices[:, b], mesh.faces, lw=0.2, color="0.6")
        length = 0.1 * float(np.ptp(centres, axis=0).max() or 1.0)
        view.quiver(centres[:, a], centres[:, b], axes_z[:, a], axes_z[:, b], color="tab:blue", angles="xy",
                    scale_units="xy", scale=1 / length, width=0.004)  # fmt: skip
        view.scatter(centres[:, a], centres[:, b], s=8, color="tab:blue")
        view.set_aspect("equal")
        view.set_title(label)
    caption = f"{len(poses)} cameras (blue: centre and viewing direction)" + (
        f" over {mesh_stage}'s mesh" if mesh_path else ""
    )
    return "<h2>Cameras and mesh</h2>" + _image(_figure_png(figure), caption, plot=True)


def _last_mesh(by_name: dict[str, StageRecord]) -> tuple[str, Path | None]:
    """(stage, mesh file) of the latest mesh: fit_geometry's, else uv's, cleanup's or mesh's."""
    geometry = by_name.get("fit_geometry")
    if geometry is not None and "geometry_dir" in geometry.outputs:
        return "fit_geometry", geometry.outputs["geometry_dir"] / "mesh.ply"
    for stage in ("uv", "cleanup", "mesh"):
        if (record := by_name.get(stage)) is not None and "mesh" in record.outputs:
            return stage, record.outputs["mesh"]
    return "", None


def _candidates_table(what: str, candidates: list[dict]) -> str:
    """pipeline.fit.candidates' summaries as a table."""
    rows = [[c["model"], c["validation_mse"], c["start_validation_mse"], c["seconds"]] for c in candidates]
    return _table([what, "held-out MSE", "at the start", "seconds"], rows)


def _choices_section(by_name: dict[str, StageRecord]) -> str:
    material = _json(by_name.get("fit_material"), "params")
    if material is None:
        return ""
    parts = [f"<h2>Choices</h2><p>Material model: {_text(material['model'])}.</p>"]
    choice = material.get("model_choice", {})
    if len(choice.get("candidates", [])) > 1:
        parts.append(f"<p>{_text(choice['why'])}.</p>")
        parts.append(_candidates_table("material model", choice["candidates"]))
    if choice.get("depth"):
        parts.append(f"<p>Path depth: {_text(choice['depth']['why'])}.</p>")
    light = material.get("light")
    if light:
        parts.append(f"<p>Light: {_text(light['chosen']['model'])} ({_text(light['why'])}).</p>")
        parts.append(_candidates_table("light model", light["candidates"]))
    texture = _json(by_name.get("fit_texture"), "params")
    if texture is not None:
        kept = "kept" if texture.get("kept") else "not kept"
        parts.append(f"<p>Texture ({_text(texture['parameter'])}): {kept}: {_text(texture.get('reason', ''))}.</p>")
    geometry = _json(by_name.get("fit_geometry"), "params")
    if geometry is not None and geometry.get("rounds"):
        rows = [
            [index + 1, kind, passed["validation_start"], passed["validation"]]
            for index, done in enumerate(geometry["rounds"])
            for kind, passed in done.items()
        ]
        parts.append(_table(["round", "pass", "held-out error before", "after"], rows))
    return "".join(parts)


def _parameters_section(by_name: dict[str, StageRecord]) -> str:
    material = _json(by_name.get("fit_material"), "params")
    if material is None:
        return ""
    last, stage = material, "fit_material"
    for name, _ in FIT_STAGES[1:]:
        if (params := _json(by_name.get(name), "params")) is not None and "params" in params:
            last, stage = params, name
    units = material.get("units", {})
    rows = [
        [name, value, material["bounds"].get(name, "-"), units.get(name, "")] for name, value in last["params"].items()
    ]
    return f"<h2>Parameters ({_text(stage)})</h2>" + _table(["parameter", "value", "bounds", "units"], rows)


def _heldout_section(by_name: dict[str, StageRecord]) -> str:
    parts = []
    for stage, _ in FIT_STAGES:
        record = by_name.get(stage)
        if record is None or "heldout" not in record.outputs or not record.outputs["heldout"].is_dir():
            continue
        folder = record.outputs["heldout"]
        scores = score_heldout(folder)
        if not scores["views"]:
            continue
        if not parts:
            parts.append(_difference_scale())
        parts.append(f"<h3>{_text(stage)}: mean PSNR {scores['psnr_db_mean']:.1f} dB</h3>")
        for name in heldout_names(folder):
            figures = [
                _image((folder / f"{name}.{kind}.png").read_bytes(), f"{name}: {kind}")
                for kind in ("reference", "render", "difference")
                if (folder / f"{name}.{kind}.png").is_file()
            ]
            parts.append(f"<div>{''.join(figures)}<p>{_text(name)}: {scores['per_view'][name]:.1f} dB</p></div>")
    return "<h2>Held-out photos</h2>" + "".join(parts) if parts else ""


def _trajectories_section(by_name: dict[str, StageRecord]) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    parts = []
    for stage, folder_output in FIT_STAGES:
        record = by_name.get(stage)
        if record is None or folder_output not in record.outputs:
            continue
        log_path = record.outputs[folder_output] / "log.jsonl"
        if not log_path.is_file():
            continue
        log = [json.loads(line) for line in log_path.read_text().splitlines() if line.strip()]
        if not log:
            continue
        steps = np.arange(1, len(log) + 1)
        names = sorted({n for entry in log for n in entry.get("params", {})})
        figure, axes = plt.subplots(1, 1 + len(names), figsize=(3.2 * (1 + len(names)), 2.8), squeeze=False)
        axes = axes[0]
        axes[0].semilogy(steps, [e.get("loss", np.nan) for e in log], lw=0.8, label="training loss")
        validated = [(i + 1, e["validation_error"]) for i, e in enumerate(log) if e.get("validation_error") is not None]
        if validated:
            axes[0].semilogy(*zip(*validated), "o-", ms=3, label="held-out error")
        axes[0].set_xlabel("step")
        axes[0].legend(fontsize=7)
        for axis, name in zip(axes[1:], names):
            values = [e.get("params", {}).get(name) for e in log]
            axis.plot(steps, _padded(values), lw=0.8)
            axis.set_title(name, fontsize=8)
            axis.set_xlabel("step")
        parts.append(_image(_figure_png(figure), f"{stage}: loss, held-out error and parameters per step", plot=True))
    return "<h2>Trajectories</h2>" + "".join(parts) if parts else ""


def _padded(values: list) -> list[list[float]]:
    """Per-step values as rows of equal length (a parameter missing at a step: NaN)."""
    width = max(len(v) for v in values if v is not None)
    return [[np.nan] * width if v is None else list(v) for v in values]


def _warnings_section(stages: list[StageRecord]) -> str:
    lines = [f"<p class='warning'>{_text(s.name)}: {_text(w)}</p>" for s in stages for w in s.warnings]
    return "<h2>Warnings</h2>" + ("".join(lines) if lines else "<p>none</p>")
