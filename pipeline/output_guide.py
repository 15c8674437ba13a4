"""CAPTURE/output/README.txt: what each published file is, written with report.html.

The guide is built from output/manifest.json, so it lists exactly what this run
published: the final results at the top of output/ (each with the stage it came
from), each stage's folder under output/stages/, and the files written beside them.
A file the table below does not know is listed with its stage alone.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

from pipeline.core.errors import DiskFull
from pipeline.core.fsutil import atomic_write_text, disk_full_error
from pipeline.core.publish import MANIFEST, OUTPUT, STAGES, current_manifest

README_TXT = "README.txt"

KNOWN = {
    "scene.xml": "the final scene: `mitsuba scene.xml` renders the first photo's view",
    "view-*.xml": "the same scene from each photo's camera",
    "specimen.xml": "the specimen's shape and material, included by the scenes",
    "params.json": "the fitted values, start values, bounds, stopping reason, seconds",
    "heldout": "held-out photos: NAME.reference, .render, .difference (PNG; EXR linear)",
    "mesh.ply": "the specimen's mesh (metres, z up, UVs, vertex normals)",
    "base_color.png": "the fitted base-colour texture, sRGB",
    "base_color.exr": "the fitted base-colour texture, linear",
    "environment.exr": "the fitted environment light, linear",
    "board.png": "the calibration board's texture, as the scene shows it",
    "scene.json": "the scene's cameras, light and units, for the fit stages",
    "preview.png": "the first view as the scene stage rendered it, before any fit",
    "loss.png": "the fit's loss and held-out error against the step",
    "log.jsonl": "the fit, one JSON line per step",
    "specimen.glb": "the specimen as glTF 2.0 (y up) for Blender and three.js",
}
BESIDE = {
    "report.html": "the run's report (opens offline)",
    "score.json": "the outputs against the ground truth (`pipeline score`)",
    MANIFEST: "each published file's size, SHA-256, stage and cache key",
}


def _what(name: str) -> str:
    if name.startswith("view-") and name.endswith(".xml"):
        return KNOWN["view-*.xml"]
    return KNOWN.get(name, "")


def text(capture_dir: Path) -> str:
    """The guide to the capture's published output/, from its manifest."""
    manifest = current_manifest(capture_dir) or {}
    top: dict[str, str] = {}
    stages: dict[str, list[str]] = defaultdict(list)
    for path, record in sorted(manifest.items()):
        if path.startswith(STAGES + "/"):
            stages[path.split("/")[1]].append(path.split("/", 2)[2])
        else:
            top[path] = record["stage"]
    lines = [f"Results of the pipeline for {capture_dir.resolve().name}.", ""]
    if top:
        lines += ["The final results, and the stage each is from:", ""]
        views = sorted(name for name in top if _what(name) == KNOWN["view-*.xml"])
        for name, stage in top.items():
            if name in views[1:]:
                continue
            shown = f"view-*.xml ({len(views)})" if name in views else name + ("/" if name == "heldout" else "")
            lines.append(f"  {shown:18s} {stage:13s} {_what(name)}")
        lines.append("")
    if stages:
        lines += [f"{STAGES}/STAGE/: each stage's own results, kept for inspection and `pipeline score`:", ""]
        for stage, files in stages.items():
            lines.append(f"  {STAGES}/{stage + '/':24s} {', '.join(files[:4])}{', ...' if len(files) > 4 else ''}")
        lines.append("")
    # The report and the manifest are always written with the guide; score.json by `pipeline score`.
    beside = [name for name in BESIDE if name != "score.json" or (capture_dir / OUTPUT / name).is_file()]
    lines += ["Beside them:", ""] + [f"  {name:32s} {BESIDE[name]}" for name in beside]
    lines += ["", "Files the pipeline did not write are kept; an edited result is restored and your copy kept"]
    lines += ["beside it as NAME.edited.EXT."]
    return "\n".join(lines) + "\n"


def write(capture_dir: Path) -> Path:
    """Write CAPTURE/output/README.txt; returns its path."""
    path = capture_dir / OUTPUT / README_TXT
    try:
        atomic_write_text(path, text(capture_dir))
    except OSError as error:
        if disk_full_error(error):
            raise DiskFull(path.parent, f"writing {path.name}", "the previous guide and report were kept") from error
        raise
    return path
