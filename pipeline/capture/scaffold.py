"""``pipeline new``: a capture folder ready for a photo session.

Writes the folders the stages read, a capture.toml in which every setting is
written out with its documentation (the capture's own sections active, the
stages' sections commented out so the preset decides), and a README with the
checklist for the session.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from pipeline.core import progress
from pipeline.core.config import load_config, toml_section
from pipeline.core.errors import ConfigError
from pipeline.core.fsutil import atomic_write_text
from pipeline.core.sections import SHARED_SECTIONS, CaptureSection, schema
from pipeline.core.stage import Stage
from pipeline.imaging.photo_io import list_photos

FOLDERS = {
    "images": "the specimen photos (JPEG, PNG, TIFF or EXR), any names, sorted order = turntable order",
    "calibration": "10-20 photos of the printed board, same camera and zoom as images/",
    "background": "optional: plates of the empty set from the same camera position(s)",
    "masks": "optional: your own masks, one PNG per photo named like it (white = specimen)",
}

CHECKLIST = """\
# {name}

{description}

Folders: {folders}

## Before the session
- [ ] Print the board: `pipeline board --out board {path}` (prints at 100 %, no fit to page);
      measure a square and put the measured size into `[board]` of capture.toml.
- [ ] Set the camera to manual: fixed exposure, ISO, white balance and focus distance;
      no zoom changes (each zoom setting needs its own calibration). Shoot RAW+JPEG or
      16-bit TIFF if you can: linear data fits materials better.
- [ ] Light: diffuse and constant for the whole session (softboxes, no mixed daylight).
      Write the rig into `[light]` of capture.toml: positions and sizes in metres.
- [ ] Background: a neutral (grey, white or black) non-reflective set, and the specimen
      standing on the printed board. On a turntable or ring any plain set the specimen
      does not share a colour with does (masks.segmenter "auto" learns the set's colours
      from the photos' borders); handheld on a coloured set: `masks.segmenter = "centre_prior"`.

## Calibration shots (calibration/)
- [ ] 10-20 photos of the flat board alone, filling half the frame or more, from varied
      angles (up to 45 degrees) and positions, the board reaching the frame's corners in some.
- [ ] Sharp: no motion blur, the whole board in focus.
- [ ] Colour (optional): one shot of a ColorChecker 24 (Classic, 24 patches) where the
      specimen stands, under the session's lights and camera settings, filling a third of
      the frame or more: every photo is then colour-corrected to the chart's references.

## Specimen photos (images/)
- [ ] 30-80 photos on two or three rings around the specimen (low, middle, high), plus a
      few from above; 60-80 % overlap between neighbours (about every 10-15 degrees).
- [ ] The whole specimen in every frame, with some margin; the board visible in most.
- [ ] Turntable (`capture.rig = "turntable"`): camera and lights fixed, only the table
      turns; name the photos in turning order; 40-80 photos per turn (5-9 degree steps)
      so that neighbours share features; a patterned mat or the board on the table.
      A timed table that turns by equal steps: `sfm.turntable_steps = "even"`.
- [ ] Ring (`capture.rig = "ring"`): the camera carried round the still specimen on one
      circle (a gantry or arm), at one height and distance.
- [ ] Translucent specimens: include back-lit and side-lit views if the rig allows.

## Background plate (background/, optional)
- [ ] With camera and lights untouched, remove the specimen and shoot the empty set once
      per camera position (one plate per photo, named like it) or once for a fixed camera.

## After the session
- [ ] `pipeline check {path}`: blur, exposure, duplicates, strays, board, masks.
- [ ] `pipeline run {path} --preset draft` for a quick end-to-end look, then the default.
"""


def _capture_toml(description: str, rig: str, stages: tuple[Stage, ...]) -> str:
    lines = [
        "# The capture's settings. The sections above the line describe this capture;",
        "# fill them in. The stage sections below are commented out: the preset",
        "# (configs/*.toml, chosen with --preset) decides them unless you uncomment a",
        "# setting here to change it for this capture only. `pipeline config CAPTURE`",
        "# shows the value every setting ends up with.",
        "",
    ]
    sections = {"capture": CaptureSection(description=description, rig=rig)}
    for name, cls in SHARED_SECTIONS.items():
        if name != "mitsuba":
            lines += toml_section(name, sections.get(name, cls())) + [""]
    lines += ["# " + "-" * 70, ""]
    for name, cls in schema(stages).items():
        if name not in sections and (name == "mitsuba" or name not in SHARED_SECTIONS):
            lines += toml_section(name, cls(), commented=True) + [""]
    return "\n".join(lines)


def create_capture(path: Path, description: str, rig: str, stages: tuple[Stage, ...]) -> Path:
    if path.exists() and not path.is_dir():
        raise ConfigError(f"{path} is a file: name a new folder for the capture")
    if path.exists() and any(path.iterdir()):
        raise ConfigError(f"{path} already exists and is not empty: choose a new folder for the capture")
    for folder in FOLDERS:
        (path / folder).mkdir(parents=True, exist_ok=True)
    atomic_write_text(path / "capture.toml", _capture_toml(description, rig, stages))
    folders = "; ".join(f"`{folder}/`: {what}" for folder, what in FOLDERS.items())
    atomic_write_text(
        path / "README.md",
        CHECKLIST.format(name=path.name, description=description or "(no description)", folders=folders, path=path),
    )
    load_config(schema(stages), path)  # the template must load as it is
    return path


def take_photos(folder: Path, images: Path) -> int:
    """The photos directly in ``folder`` into ``images``: hard links (no space taken, the
    originals untouched) where both lie on one file system, else copies. Their count."""
    photos = list_photos(folder)
    for photo in progress.track(photos, "taking the photos"):
        try:
            os.link(photo, images / photo.name)
        except OSError:
            shutil.copy2(photo, images / photo.name)
    return len(photos)
