"""A scene folder (stage scene, copied and refined by the fit stages): a
self-contained Mitsuba 3 scene that renders as it is, and the fit results kept
beside it.

==================  =============================================================
file                content
==================  =============================================================
scene.xml           every registered photo's sensor, the light, the integrator
view-NAME.xml       one photo's sensor with its own light (a turntable's light
                    rides with the camera)
specimen.xml        mesh, material (and board, ground): included by the above
mesh.ply            the specimen's mesh with UVs
scene.json          the description: model, integrator, light frame, near clip,
                    parameters (Mitsuba key, value, bounds, units), view files
params.json         (fit stages) the fitted values with bounds and units
log.jsonl           (fit stages) one JSON object per iteration
loss.png            (fit stages) loss and held-out error against iteration
heldout/            (fit stages) per held-out photo NAME.render.exr,
                    NAME.reference.exr and NAME.mask.png (the pixels scored), and
                    NAME.reference.png, NAME.render.png, NAME.difference.png to look at
environment.exr     (estimated light) the fitted lat-long environment map
==================  =============================================================
"""

from __future__ import annotations

import shutil
import xml.etree.ElementTree as ET
from pathlib import Path

from pipeline.core import jsonio

SCENE_XML = "scene.xml"
SPECIMEN_XML = "specimen.xml"
MESH_PLY = "mesh.ply"
DESCRIPTION_JSON = "scene.json"
PARAMS_JSON = "params.json"
LOG_JSONL = "log.jsonl"
LOSS_PNG = "loss.png"
HELDOUT = "heldout"
FIT_RESULTS = (HELDOUT, LOG_JSONL, LOSS_PNG, PARAMS_JSON)
"""What a fit stage adds to a scene folder; a copy without them is a plain scene."""


def copy_scene(source: Path, target: Path) -> Path:
    """``source``'s scene into the new folder ``target``, without fit results."""
    shutil.copytree(source, target, ignore=shutil.ignore_patterns(*FIT_RESULTS))
    return target


def write_log(path: Path, entries: list[dict]) -> Path:
    with path.open("w") as handle:
        for entry in entries:
            handle.write(jsonio.dumps(entry) + "\n")
    return path


def heldout_files(folder: Path, name: str) -> tuple[Path, Path, Path]:
    """(render, reference, mask) of one held-out photo in a heldout/ folder."""
    return (folder / f"{name}.render.exr", folder / f"{name}.reference.exr", folder / f"{name}.mask.png")


def heldout_names(folder: Path) -> list[str]:
    """The photos a heldout/ folder holds, sorted."""
    return sorted(p.name.removesuffix(".render.exr") for p in folder.glob("*.render.exr"))


def texture_png(scene_dir: Path, parameter: str) -> Path | None:
    """The PNG beside the bitmap that the folder's specimen.xml loads for ``parameter``, if any."""
    for element in ET.parse(scene_dir / SPECIMEN_XML).getroot().iter("texture"):
        if element.get("name") == parameter and element.get("type") == "bitmap":
            filename = next(e.get("value") for e in element.iter("string") if e.get("name") == "filename")
            return (scene_dir / filename).with_suffix(".png")
    return None
