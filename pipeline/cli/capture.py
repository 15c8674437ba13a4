"""Commands on a capture folder before the pipeline runs: ``new``, ``board``, ``check``."""

from __future__ import annotations

import json
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

from pipeline.cli import registry
from pipeline.cli.options import Arg
from pipeline.cli.registry import ConfigLayers, capture_dir, command
from pipeline.core.config import Range, load_config
from pipeline.core.errors import ConfigError
from pipeline.core.sections import schema


@dataclass(frozen=True)
class NewOptions:
    """Create a capture folder with a documented capture.toml and a session checklist."""

    capture: Annotated[str, Arg(positional=True)]
    """New folder, e.g. captures/bird."""
    description: str = ""
    """What the specimen is."""
    rig: Literal["handheld", "turntable", "ring"] = "handheld"
    """Capture rig (capture.rig in capture.toml)."""
    photos: Annotated[str | None, Arg(metavar="FOLDER")] = None
    """A folder of photos (as COLMAP or Meshroom take them) to put into the new capture's
    images/: hard links where the file system allows, else copies; the folder is left as
    it is."""


@dataclass(frozen=True)
class BoardOptions:
    """Write a printable calibration board (PNG and PDF)."""

    out: str
    """File name without extension; writes OUT.png and OUT.pdf."""
    capture: Annotated[str | None, Arg(positional=True)] = None
    """Use this capture's [board] section."""
    paper: Literal["A4", "A3", "letter"] = "A4"
    """Page size of the PDF."""
    dpi: Annotated[int, Range(72, 2400)] = 300
    """Resolution of the PNG and of the PDF's image."""
    force: bool = False
    """Replace OUT.png and OUT.pdf when they exist (without it, the command refuses)."""
    config: ConfigLayers = field(default_factory=ConfigLayers)
    """Preset and overrides."""


@dataclass(frozen=True)
class CheckOptions:
    """Check the photos before the expensive run; exit 1 on errors."""

    capture: Annotated[str, Arg(positional=True)]
    """Capture folder."""
    no_features: bool = False
    """Skip the pairwise feature matching (fast)."""
    json: bool = False
    """Print the problems as JSON."""
    config: ConfigLayers = field(default_factory=ConfigLayers)
    """Preset and overrides."""


@command("new", NewOptions, "create a capture folder with a documented capture.toml and a checklist")
def new(options: NewOptions) -> int:
    from pipeline.capture.scaffold import create_capture, take_photos
    from pipeline.imaging.photo_io import PHOTO_SUFFIXES, list_photos

    photos = Path(options.photos) if options.photos else None
    if photos is not None and not list_photos(photos):
        raise ConfigError(f"--photos {photos} holds no photos ({', '.join(PHOTO_SUFFIXES)}): name the folder of photos")
    path = create_capture(Path(options.capture), options.description, options.rig, registry.registered_stages())
    if photos is None:
        print(f"created {path}: read {path / 'README.md'} before the photo session")
        return 0
    taken = take_photos(photos, path / "images")
    print(f"created {path} with the {taken} photos of {photos} in images/: `pipeline run {path}` runs them")
    return 0


@command("board", BoardOptions, "write a printable calibration board (PNG and PDF)")
def board(options: BoardOptions) -> int:
    from pipeline.camera.board import write_printable

    capture = capture_dir(options.capture) if options.capture else None
    config = load_config(schema(registry.registered_stages()), capture, options.config.preset, options.config.set)
    if config["board"].kind == "none":
        raise ConfigError("board.kind = 'none': set it to 'charuco' or 'checkerboard' to print a board")
    folder = Path(options.out).parent
    existing = [str(path) for suffix in (".png", ".pdf") if (path := Path(options.out + suffix)).exists()]
    if existing and not options.force:
        verb = "exist" if len(existing) > 1 else "exists"
        raise ConfigError(f"{' and '.join(existing)} {verb}: name another --out, or add --force to replace them")
    try:
        tempfile.TemporaryFile(dir=folder).close()
    except OSError as error:
        raise ConfigError(
            f"--out {options.out}: cannot write into {folder} ({error.strerror}): "
            "name a file in a folder you can write to"
        ) from None
    try:
        png, pdf = write_printable(config["board"], Path(options.out), options.paper, options.dpi)
    except ValueError as e:
        raise ConfigError(f"{e}") from None
    print(f"wrote {pdf} (print at 100 %) and {png} ({options.dpi} dpi)")
    return 0


@command("check", CheckOptions, "check the photos before the expensive run; exit 1 on errors")
def check(options: CheckOptions) -> int:
    from pipeline.capture.check import as_json, check_capture

    capture = capture_dir(options.capture)
    config = load_config(schema(registry.registered_stages()), capture, options.config.preset, options.config.set)
    problems = check_capture(capture, config, features=not options.no_features)
    errors = sum(p.severity == "error" for p in problems)
    if options.json:
        print(json.dumps({"problems": as_json(problems), "errors": errors}, indent=1))
    else:
        for problem in problems:
            print(problem.line())
        warnings = sum(p.severity == "warning" for p in problems)
        print(f"{errors} error(s), {warnings} warning(s) in {capture}")
    return 1 if errors else 0
