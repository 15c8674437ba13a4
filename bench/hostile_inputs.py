"""Hostile inputs, faults and signals, each run by the real CLI in a process of its own
under a watchdog: the cases of issue 53 and further ones of the same kinds.

    .venv/bin/python -m bench.hostile_inputs [--work /tmp/hostile] [--only NAME ...] [--write]

A tiny synthetic capture (6 views of 96x72 px) is rendered once and run to masks. Each
case copies it with its cache and output/, spoils the copy, runs a command and records
the exit code, the seconds, the message (the last line of stderr), whether a traceback
or a stack dump appeared, and whether the good run's output/ survived. A case passes when
the exit code and message are the expected ones, nothing was dumped, the output survived,
and the watchdog (120 s) did not fire. Disk-full cases run on a small tmpfs (root only;
they are skipped where mounting fails). ``--write`` regenerates docs/benchmarks.md's
section.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from bench.common import CLI, finish, synthetic_capture, write_section
from bench.common import ROOT as REPOSITORY

WATCHDOG_S = 120
SECTION = "## Hostile inputs, faults and signals (issues 53 and 101)"
HOLD_LOCK = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    from pipeline.core.lock import CaptureLock
    with CaptureLock(Path(sys.argv[1]), "bench holder"):
        print("held", flush=True)
        time.sleep(float(sys.argv[2]))
    """
)
SCENE = """<scene version="3.0.0">
  <integrator type="path" id="integrator"><integer name="max_depth" value="3"/></integrator>
  <emitter type="constant" id="sky"><rgb name="radiance" value="1, 1, 1"/></emitter>
  <shape type="sphere" id="ball"><bsdf type="diffuse" id="paint"><rgb name="reflectance" value="0.5, 0.5, 0.5"/></bsdf></shape>
  <sensor type="perspective" id="camera">
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm" id="film"><integer name="width" value="16"/><integer name="height" value="16"/></film>
    <sampler type="independent" id="sampler"><integer name="sample_count" value="4"/></sampler>
  </sensor>
</scene>
"""


@dataclass
class Case:
    name: str
    kind: str
    """hang, silently wrong, lost, traceback, message, signal, disk full"""
    origin: str
    """"issue" (one of issue 53's cases) or "new" (one of ours)"""
    spoil: Callable[[Path], None]
    argv: list[str]
    """After `pipeline`; CAPTURE stands for the spoilt copy."""
    code: int
    message: str
    """Expected in stdout or stderr."""
    signal_after: tuple[int, str] | None = None
    """(signal, what to wait for: "lock" held by another process, or a number of seconds)."""
    check: Callable[[Path], str | None] | None = None
    """Returns what is wrong with the capture afterwards, or None."""
    on_tmpfs_kb: int = 0
    """Run on a tmpfs this much larger than the capture (disk-full cases)."""
    result: dict = field(default_factory=dict)


# --- spoilers ---------------------------------------------------------------------------


def nothing(capture: Path) -> None:
    pass


def first_photo(capture: Path) -> Path:
    return sorted((capture / "images").glob("*.jpg"))[0]


def replace_photo(capture: Path, name: str, pixels: np.ndarray, channels_alpha: int = -1) -> None:
    import OpenImageIO as oiio

    first_photo(capture).unlink()
    spec = oiio.ImageSpec(
        pixels.shape[1], pixels.shape[0], pixels.shape[2], oiio.FLOAT if pixels.dtype.kind == "f" else oiio.UINT8
    )
    if channels_alpha >= 0:
        spec.alpha_channel = channels_alpha
    out = oiio.ImageOutput.create(str(capture / "images" / name))
    assert out.open(str(capture / "images" / name), spec) and out.write_image(pixels) and out.close()


def alpha_photo(capture: Path, channels: int = 4) -> None:
    pixels = np.full((72, 96, channels), 200, np.uint8)
    pixels[..., -1] = 128
    replace_photo(capture, "view_000.png", pixels, channels - 1)


def exr_photo(value: float) -> Callable[[Path], None]:
    def spoil(capture: Path) -> None:
        pixels = np.full((72, 96, 3), 0.25, np.float32)
        pixels[10, 10:13] = value
        replace_photo(capture, "view_000.exr", pixels)

    return spoil


def same_size_and_mtime(capture: Path) -> None:
    """`cp -p` of another photo of the same size: here the same bytes with two swapped."""
    photo = first_photo(capture)
    stamp = photo.stat()
    data = bytearray(photo.read_bytes())
    middle = len(data) // 2
    data[middle], data[middle + 1] = data[middle + 1], data[middle] ^ 0x10
    photo.write_bytes(bytes(data))
    os.utime(photo, ns=(stamp.st_atime_ns, stamp.st_mtime_ns))


def edit_output(capture: Path) -> None:
    manifest = json.loads((capture / "output" / "manifest.json").read_text())
    name = sorted(manifest)[0]
    path = capture / "output" / name
    path.write_bytes(path.read_bytes() + b" ")


def fifo(relative: str) -> Callable[[Path], None]:
    def spoil(capture: Path) -> None:
        path = capture / relative
        if path.exists():
            path.unlink()
        path.parent.mkdir(parents=True, exist_ok=True)
        os.mkfifo(path)

    return spoil


def add_file(relative: str, data: bytes = b"not a photo") -> Callable[[Path], None]:
    return lambda capture: (
        (capture / relative).parent.mkdir(parents=True, exist_ok=True) or (capture / relative).write_bytes(data)
    )


def rename_photos(*names: str) -> Callable[[Path], None]:
    def spoil(capture: Path) -> None:
        for photo, name in zip(sorted((capture / "images").glob("*.jpg")), names):
            photo.rename(photo.with_name(name))

    return spoil


def byo(mesh_damage: str) -> Callable[[Path], None]:
    """Cameras and mesh "from another tool" (tests/support/byo_capture.py), the mesh damaged."""

    def spoil(capture: Path) -> None:
        import trimesh

        sys.path.insert(0, str(REPOSITORY))
        from tests.support.byo_capture import byo_capture

        shutil.rmtree(capture / "external", ignore_errors=True)
        staging = capture.with_name(capture.name + "-byo")
        byo_capture(capture, staging)
        shutil.move(staging / "external", capture / "external")
        shutil.rmtree(staging)
        mesh = trimesh.load(capture / "ground_truth" / "mesh.ply", process=False)
        vertices, faces = np.array(mesh.vertices), np.array(mesh.faces)
        if mesh_damage == "nan":
            vertices[::7] = np.nan
        elif mesh_damage == "far":
            vertices = vertices * 1e30
        elif mesh_damage == "faces":
            faces[0, 0] = len(vertices) + 10
        if mesh_damage == "empty":
            (capture / "bad.ply").write_bytes(b"")
        elif mesh_damage == "faces":
            lines = [
                "ply",
                "format ascii 1.0",
                f"element vertex {len(vertices)}",
                "property float x",
                "property float y",
                "property float z",
                f"element face {len(faces)}",
                "property list uchar int vertex_indices",
                "end_header",
            ]
            lines += [" ".join(map(str, v)) for v in vertices] + ["3 " + " ".join(map(str, f)) for f in faces]
            (capture / "bad.ply").write_text("\n".join(lines) + "\n")
        else:
            trimesh.Trimesh(vertices, faces, process=False).export(capture / "bad.ply")

    return spoil


def scene_folder(reference_value: float | None) -> Callable[[Path], None]:
    """A scene for `pipeline fit` and one reference image (with a spoilt pixel)."""

    def spoil(capture: Path) -> None:
        from pipeline.imaging.photo_io import write_image

        (capture / "fit").mkdir()
        (capture / "fit" / "scene.xml").write_text(SCENE)
        (capture / "fit" / "refs").mkdir()
        pixels = np.full((16, 16, 3), 0.3, np.float32)
        if reference_value is not None:
            pixels[3, 3] = reference_value
        write_image(capture / "fit" / "refs" / "ref.exr", pixels)

    return spoil


def output_link_elsewhere(capture: Path) -> None:
    target = capture.parent / f"{capture.name}-elsewhere"
    target.mkdir()
    (target / "mine.txt").write_text("keep")
    shutil.rmtree(capture / "output")
    (capture / "output").symlink_to(target)


def target_kept(capture: Path) -> str | None:
    mine = capture.parent / f"{capture.name}-elsewhere" / "mine.txt"
    return None if mine.is_file() and mine.read_text() == "keep" else "the link's target was changed"


def output_complete(capture: Path) -> str | None:
    manifest = json.loads((capture / "output" / "manifest.json").read_text())
    for record in manifest.values():
        for rel, (size, digest) in record["contents"].items():
            path = capture / "output" / rel
            if not path.is_file() or hashlib.sha256(path.read_bytes()).hexdigest() != digest:
                return f"output/{rel} is not what the manifest says"
    return None


BACKGROUND: list[subprocess.Popen] = []
"""Processes a spoiler started (a fit holding --out), killed when the case ends."""


def fit_argv(out: str = "CAPTURE/fit_out", iterations: int = 3) -> list[str]:
    """`pipeline fit` on scene_folder's scene into ``out``."""
    return [
        "fit",
        "CAPTURE/fit/scene.xml",
        "--references",
        "CAPTURE/fit/refs",
        "--params",
        "reflectance",
        "--bound",
        "reflectance=0:1",
        "--iterations",
        str(iterations),
        "--still-threshold",
        "0",
        "--spp",
        "2",
        "--out",
        out,
    ]


def fit_running(capture: Path) -> None:
    """scene_folder's scene, and a long fit of it into CAPTURE/fit_out, running."""
    scene_folder(None)(capture)
    argv = [a.replace("CAPTURE", str(capture)) for a in fit_argv(iterations=1_000_000)]
    BACKGROUND.append(subprocess.Popen([sys.executable, "-c", CLI, *argv], cwd=REPOSITORY, stderr=subprocess.DEVNULL))
    lock = capture / "fit_out" / ".fit.lock"
    deadline = time.time() + 60
    while not (lock.is_file() and lock.read_text()) and time.time() < deadline:
        time.sleep(0.1)


def fit_interrupted(capture: Path) -> str | None:
    params = capture / "fit_out" / "params.json"
    if not params.is_file() or not json.loads(params.read_text()).get("interrupted"):
        return "no params.json marked interrupted"
    return None if (capture / "fit_out" / "scene.xml").is_file() else "no fitted scene"


def traversing_manifest(capture: Path) -> None:
    victim = capture.parent / "victim"
    victim.mkdir(exist_ok=True)
    (victim / "f.txt").write_text("abc")
    manifest = capture / "output" / "manifest.json"
    records = json.loads(manifest.read_text())
    name = sorted(records)[0]
    records[name]["contents"]["../../victim/f.txt"] = [3, "0" * 64]
    manifest.write_text(json.dumps(records))


def victim_untouched(capture: Path) -> str | None:
    found = sorted(p.name for p in (capture.parent / "victim").iterdir())
    return None if found == ["f.txt"] else f"written beside the capture: {found}"


def cache_status(change: Callable[[dict], dict]) -> Callable[[Path], None]:
    """The masks stage's cache entry's status.json, changed (valid JSON, wrong shape)."""

    def spoil(capture: Path) -> None:
        for status in (capture / ".pipeline" / "cache" / "masks").glob("*/status.json"):
            status.write_text(json.dumps(change(json.loads(status.read_text()))))

    return spoil


def add_to_cache(capture: Path) -> None:
    for entry in (capture / ".pipeline" / "cache" / "masks").glob("*/status.json"):
        (entry.parent / "stray.txt").write_text("put here by hand")


def many_files(count: int) -> Callable[[Path], None]:
    def spoil(capture: Path) -> None:
        for index in range(count):
            (capture / "images" / f"notes_{index:05d}.txt").write_text("x")

    return spoil


def readable_outputs(capture: Path) -> str | None:
    mask = os.umask(0)
    os.umask(mask)
    wrong = [
        p.relative_to(capture).as_posix()
        for p in (capture / "output").rglob("*")
        if p.is_file() and p.stat().st_mode & 0o777 != 0o666 & ~mask
    ]
    return f"{len(wrong)} files not {oct(0o666 & ~mask)}, e.g. {wrong[0]}" if wrong else output_complete(capture)


def fill_disk(leave_kb: int) -> Callable[[Path], None]:
    def spoil(capture: Path) -> None:
        free = shutil.disk_usage(capture).free
        with (capture / "filler.bin").open("wb") as filler:
            filler.write(b"\0" * max(free - leave_kb * 1024, 0))

    return spoil


def cases() -> list[Case]:
    until_undistort = ["run", "CAPTURE", "--until", "undistort"]
    until_masks = ["run", "CAPTURE", "--until", "masks"]
    byo_mesh = ["run", "CAPTURE", "--until", "mesh", "-s", "cameras.source='external'", "-s", "mesh.source='bad.ply'"]
    fit = fit_argv()
    return [
        # issue 53's cases
        Case("mesh-non-finite", "hang", "issue", byo("nan"), byo_mesh, 1, "vertices are NaN or infinite"),
        Case(
            "envmap-fifo",
            "hang",
            "issue",
            fifo("room.exr"),
            [*until_masks, "-s", "light.environment_map='room.exr'"],
            2,
            "is a FIFO, not a file",
        ),
        Case("alpha-photo", "silently wrong", "issue", alpha_photo, until_undistort, 1, "is partly transparent"),
        Case(
            "negative-radiance",
            "silently wrong",
            "issue",
            nothing,
            [*until_masks, "-s", "light.area_radiance=[6, -1, 6]"],
            2,
            "is out of range",
        ),
        Case(
            "cp-p-photo",
            "silently wrong",
            "issue",
            same_size_and_mtime,
            until_undistort,
            0,
            "input changed: images/view_000.jpg",
        ),
        Case(
            "edited-output",
            "silently wrong",
            "issue",
            edit_output,
            until_masks,
            0,
            "was edited after it was published",
            check=output_complete,
        ),
        Case(
            "heic-photo",
            "silently wrong",
            "issue",
            add_file("images/IMG_0001.HEIC"),
            ["check", "CAPTURE", "--no-features"],
            1,
            "cannot read this HEIF file",
        ),
        Case(
            "psd-photo",
            "silently wrong",
            "new",
            add_file("images/IMG_0002.PSD"),
            ["check", "CAPTURE", "--no-features"],
            0,
            "IMG_0002.PSD: not a photo the pipeline reads",
        ),
        Case(
            "fit-nan-reference",
            "silently wrong",
            "issue",
            scene_folder(float("nan")),
            [*fit, "--out", "CAPTURE/fitted"],
            1,
            "NaN or infinite",
        ),
        Case(
            "rm-cache-then-report",
            "lost",
            "issue",
            lambda c: shutil.rmtree(c / ".pipeline"),
            ["report", "CAPTURE"],
            0,
            "report.html",
            check=output_complete,
        ),
        Case(
            "fit-out-inside-a-file",
            "lost",
            "issue",
            lambda c: (scene_folder(None)(c), (c / "afile").write_text("x")),
            [*fit, "--out", "CAPTURE/afile/out"],
            2,
            "cannot be written (Not a directory)",
        ),
        Case(
            "ctrl-c-waiting-for-lock",
            "traceback",
            "issue",
            nothing,
            until_masks,
            130,
            "interrupted",
            signal_after=(signal.SIGINT, "lock"),
        ),
        Case(
            "sigterm-waiting-for-lock",
            "traceback",
            "issue",
            nothing,
            until_masks,
            143,
            "interrupted",
            signal_after=(signal.SIGTERM, "lock"),
        ),
        Case(
            "huge-charuco",
            "traceback",
            "issue",
            nothing,
            [
                "board",
                "--out",
                "CAPTURE/board",
                "-s",
                "board.squares_x=40",
                "-s",
                "board.squares_y=40",
                "-s",
                "board.square_mm=5",
                "-s",
                "board.marker_mm=3",
                "--paper",
                "A3",
            ],
            2,
            "markers, but board.dictionary",
        ),
        Case(
            "board-out-inside-a-file",
            "traceback",
            "issue",
            add_file("afile"),
            ["board", "--out", "CAPTURE/afile/board"],
            2,
            "cannot write into",
        ),
        Case(
            "photo-ids-collide",
            "message",
            "issue",
            rename_photos("a b.jpg", "a_b.jpg"),
            until_undistort,
            1,
            "would get the same camera id",
        ),
        Case(
            "batch-workers-exit",
            "traceback",
            "issue",
            nothing,
            ["batch", "CAPTURE", "--until", "masks", "--report", "CAPTURE/batch.json"],
            0,
            "1 of 1 capture(s) succeeded",
        ),
        Case(
            "disk-full-undistort",
            "disk full",
            "issue",
            lambda c: (shutil.rmtree(c / ".pipeline" / "cache" / "undistort"), fill_disk(24)(c)),
            until_undistort,
            1,
            "is full",
            on_tmpfs_kb=4096,
        ),
        Case(
            "disk-full-report",
            "disk full",
            "issue",
            fill_disk(0),
            ["report", "CAPTURE"],
            1,
            "the previous guide and report were kept",
            on_tmpfs_kb=4096,
        ),
        # further cases of the same kinds
        Case(
            "fifo-photo",
            "hang",
            "new",
            fifo("images/view_fifo.jpg"),
            [*until_undistort, "--force", "undistort"],
            0,
            "view_fifo.jpg is not a photo the pipeline reads",
        ),
        Case(
            "fifo-capture-toml",
            "hang",
            "new",
            fifo("capture.toml"),
            until_masks,
            2,
            "capture.toml is a FIFO, not a file",
        ),
        Case(
            "fifo-camera-file",
            "hang",
            "new",
            fifo("cams.txt"),
            [*until_masks, "-s", "cameras.source='cams.txt'"],
            2,
            "is a FIFO, not a file",
        ),
        Case(
            "fifo-mesh-source",
            "hang",
            "new",
            lambda c: (byo("none")(c), fifo("bad.ply")(c)),
            byo_mesh,
            2,
            "is a FIFO, not a file",
        ),
        Case(
            "fifo-background-plate",
            "hang",
            "new",
            fifo("background/plate.jpg"),
            [*until_undistort, "--force", "undistort"],
            0,
            "plate.jpg is not a photo the pipeline reads",
        ),
        Case("mesh-far-away", "hang", "new", byo("far"), byo_mesh, 1, "its outline overlaps the masks by"),
        Case("mesh-bad-face-index", "traceback", "new", byo("faces"), byo_mesh, 1, "mesh.source = 'bad.ply'"),
        Case("mesh-empty-file", "message", "new", byo("empty"), byo_mesh, 1, "mesh.source = 'bad.ply'"),
        Case(
            "dangling-photo-link",
            "silently wrong",
            "new",
            lambda c: (c / "images" / "gone.jpg").symlink_to(c / "nowhere.jpg"),
            [*until_undistort, "--force", "undistort"],
            0,
            "gone.jpg is not a photo the pipeline reads",
        ),
        Case(
            "empty-photo",
            "message",
            "new",
            lambda c: first_photo(c).write_bytes(b""),
            until_undistort,
            1,
            "cannot read this image",
        ),
        Case(
            "grey-alpha-photo",
            "silently wrong",
            "new",
            lambda c: alpha_photo(c, 2),
            until_undistort,
            1,
            "is partly transparent",
        ),
        Case("exr-nan-photo", "silently wrong", "new", exr_photo(float("nan")), until_undistort, 1, "NaN or infinite"),
        Case("exr-inf-photo", "silently wrong", "new", exr_photo(float("inf")), until_undistort, 1, "NaN or infinite"),
        Case(
            "unicode-ids-collide",
            "message",
            "new",
            rename_photos("é.jpg", "è.jpg"),
            until_undistort,
            1,
            "would get the same camera id",
        ),
        Case("dollar-photo-name", "message", "new", rename_photos("$HOME.jpg"), until_undistort, 0, "ran"),
        Case(
            "capture-toml-folder",
            "traceback",
            "new",
            lambda c: (c / "capture.toml").unlink() or (c / "capture.toml").mkdir(),
            until_masks,
            2,
            "capture.toml is a folder, not a file",
        ),
        Case(
            "capture-toml-utf16",
            "message",
            "new",
            lambda c: (c / "capture.toml").write_bytes((c / "capture.toml").read_text().encode("utf-16")),
            until_masks,
            2,
            "capture.toml: invalid TOML",
        ),
        Case(
            "cache-folder-is-a-file",
            "traceback",
            "new",
            lambda c: shutil.rmtree(c / ".pipeline") or (c / ".pipeline").write_text("x"),
            until_masks,
            2,
            ".pipeline is a file",
        ),
        Case(
            "lock-is-a-folder",
            "traceback",
            "new",
            lambda c: (c / ".pipeline" / "lock").unlink() or (c / ".pipeline" / "lock").mkdir(),
            until_masks,
            1,
            "is a folder, not the pipeline's lock file",
        ),
        Case(
            "hash-memo-is-a-folder",
            "traceback",
            "new",
            lambda c: (c / ".pipeline" / "file_hashes.json").unlink() or (c / ".pipeline" / "file_hashes.json").mkdir(),
            until_masks,
            0,
            "file_hashes.json is not a file",
        ),
        Case(
            "output-links-elsewhere",
            "lost",
            "new",
            output_link_elsewhere,
            until_masks,
            0,
            "published",
            check=target_kept,
        ),
        Case(
            "removed-output-file",
            "lost",
            "new",
            lambda c: (c / "output" / sorted(json.loads((c / "output" / "manifest.json").read_text()))[0]).unlink(),
            until_masks,
            0,
            "was removed after it was published",
            check=output_complete,
        ),
        Case(
            "user-notes-in-output",
            "lost",
            "new",
            add_file("output/notes.txt", b"mine"),
            [*until_masks, "-s", "masks.max_hole_fraction=0.5"],
            0,
            "stage(s) ran",
            check=lambda c: None if (c / "output" / "notes.txt").read_bytes() == b"mine" else "notes.txt lost",
        ),
        Case(
            "radiance-beyond-float32",
            "silently wrong",
            "new",
            nothing,
            [*until_masks, "-s", "light.area_radiance=[1e39, 1, 1]"],
            2,
            "is out of range",
        ),
        Case(
            "radiance-nan",
            "silently wrong",
            "new",
            nothing,
            [*until_masks, "-s", "light.environment_radiance=[1, nan, 1]"],
            2,
            "is not a finite number",
        ),
        Case(
            "preset-path",
            "message",
            "new",
            nothing,
            [*until_masks, "--preset", "../../etc/passwd"],
            2,
            "unknown preset",
        ),
        Case(
            "fit-out-is-references",
            "lost",
            "new",
            scene_folder(None),
            [*fit, "--out", "CAPTURE/fit/refs"],
            2,
            "is inside --references",
        ),
        Case(
            "fit-out-overwrites-scene",
            "lost",
            "new",
            scene_folder(None),
            [*fit, "--out", "CAPTURE/fit"],
            2,
            "would overwrite the scene being fitted",
        ),
        Case(
            "fit-empty-references",
            "message",
            "new",
            lambda c: (scene_folder(None)(c), (c / "fit" / "refs" / "ref.exr").unlink()),
            [*fit, "--out", "CAPTURE/fitted"],
            1,
            "holds 0 reference images",
        ),
        Case(
            "fit-broken-xml",
            "message",
            "new",
            lambda c: (scene_folder(None)(c), (c / "fit" / "scene.xml").write_text("<scene version='3.0.0'><shape")),
            [*fit, "--out", "CAPTURE/fitted"],
            1,
            "scene.xml",
        ),
        Case(
            "fit-sigterm",
            "signal",
            "new",
            scene_folder(None),
            [*fit[:-4], "--iterations", "100000", "--spp", "2", "--still-threshold", "0", "--out", "CAPTURE/fitted"],
            143,
            "interrupted",
            signal_after=(signal.SIGTERM, "12"),
        ),
        Case(
            "sighup-waiting-for-lock",
            "signal",
            "new",
            nothing,
            until_masks,
            129,
            "interrupted",
            signal_after=(signal.SIGHUP, "lock"),
        ),
        Case(
            "ctrl-c-json",
            "signal",
            "new",
            nothing,
            [*until_masks, "--json"],
            130,
            '"exit_code": 130',
            signal_after=(signal.SIGINT, "lock"),
        ),
        Case(
            "ctrl-c-during-check",
            "signal",
            "new",
            nothing,
            ["check", "CAPTURE"],
            130,
            "interrupted",
            signal_after=(signal.SIGINT, "1"),
        ),
        Case(
            "disk-full-in-masks",
            "disk full",
            "new",
            fill_disk(2),
            [*until_masks, "-s", "masks.max_hole_fraction=0.5"],
            1,
            "is full",
            on_tmpfs_kb=8192,
        ),
        *round_four_cases(until_masks),
    ]


def round_four_cases(until_masks: list[str]) -> list[Case]:
    """Issue 101's families: lost work, crashes from damaged state or settings the
    configuration accepts, silent or misleading results (the studio's are studio_cases)."""
    republish = [*until_masks, "-s", "masks.max_hole_fraction=0.5"]
    return [
        Case(
            "fit-ctrl-c-keeps-best",
            "lost",
            "round four",
            scene_folder(None),
            fit_argv(iterations=1_000_000),
            130,
            "the best state so far is written to",
            signal_after=(signal.SIGINT, "10"),
            check=fit_interrupted,
        ),
        Case(
            "fit-sigterm-keeps-best",
            "lost",
            "round four",
            scene_folder(None),
            fit_argv(iterations=1_000_000),
            143,
            "the best state so far is written to",
            signal_after=(signal.SIGTERM, "10"),
            check=fit_interrupted,
        ),
        Case("fit-same-out", "lost", "round four", fit_running, fit_argv(), 1, "is in use by pid"),
        Case(
            "board-overwrite",
            "lost",
            "round four",
            add_file("board.png", b"printed already"),
            ["board", "--out", "CAPTURE/board"],
            2,
            "add --force to replace them",
            check=lambda c: None if (c / "board.png").read_bytes() == b"printed already" else "board.png replaced",
        ),
        Case(
            "manifest-leaves-output",
            "lost",
            "round four",
            traversing_manifest,
            republish,
            0,
            "manifest.json is damaged",
            check=victim_untouched,
        ),
        Case(
            "status-json-wrong-shape",
            "crash",
            "round four",
            cache_status(lambda status: status | {"contents": 5}),
            until_masks,
            0,
            "damaged status.json",
        ),
        Case(
            "status-json-outside-entry",
            "crash",
            "round four",
            cache_status(lambda status: status | {"outputs": {"masks": "../../../../etc"}}),
            ["status", "CAPTURE"],
            0,
            "damaged status.json",
        ),
        Case(
            "kernel-file-dry-run",
            "hang",
            "round four",
            nothing,
            ["run", "CAPTURE", "--dry-run", "-s", "light.environment_map='/proc/kmsg'"],
            2,
            "a file the kernel makes up (proc)",
        ),
        Case(
            "bound-infinite",
            "crash",
            "round four",
            scene_folder(None),
            [*fit_argv(), "--bound", "reflectance=0:inf"],
            1,
            "is not finite",
        ),
        Case(
            "from-after-until",
            "silently wrong",
            "round four",
            nothing,
            ["run", "CAPTURE", "--from", "masks", "--until", "calibrate"],
            2,
            "is not upstream of --until",
        ),
        Case(
            "negative-reference",
            "silently wrong",
            "round four",
            scene_folder(-0.5),
            fit_argv(),
            1,
            "pixel(s) are negative",
        ),
        Case("file-added-to-cache", "silently wrong", "round four", add_to_cache, until_masks, 0, "was added"),
        Case(
            "outputs-readable",
            "silently wrong",
            "round four",
            nothing,
            republish,
            0,
            "stage(s) ran",
            check=readable_outputs,
        ),
        Case(
            "check-5000-non-photos",
            "silently wrong",
            "round four",
            many_files(5000),
            ["check", "CAPTURE", "--no-features"],
            0,
            "more files are not photos the pipeline reads",
        ),
    ]


# --- the studio ---------------------------------------------------------------------------

STUDIO_REQUESTS = [
    # (name, kind, path, body (None: GET), headers, with the token, expected status)
    ("studio-foreign-host-run", "security", "api/capture/run", {}, {"Host": "attacker.example"}, True, 403),
    ("studio-foreign-host-session", "security", "api/session", None, {"Host": "attacker.example"}, True, 403),
    ("studio-foreign-host-output", "security", "output/manifest.json", None, {"Host": "attacker.example"}, True, 403),
    ("studio-cross-origin-stop", "security", "api/capture/stop", {}, {"Origin": "http://attacker.example"}, True, 403),
    ("studio-cross-site-fetch", "security", "api/capture/stop", {}, {"Sec-Fetch-Site": "cross-site"}, True, 403),
    ("studio-no-token-stop", "security", "api/capture/stop", {}, {}, False, 403),
    ("studio-no-token-session", "security", "api/session", None, {}, False, 403),
    ("studio-no-token-photo", "security", "api/capture/photos", None, {}, False, 403),
    ("studio-body-2mb", "security", "api/capture/run", b"x" * (2 << 20), {}, True, (413, 0)),
    ("studio-chunked-body", "security", "api/capture/run", b"{}", {"Transfer-Encoding": "chunked"}, True, (411, 0)),
    (
        "studio-page-file-outside",
        "security",
        "api/capture/run",
        {"preset": "draft", "set": ["light.environment_map=/etc/shadow"]},
        {},
        True,
        400,
    ),
    ("studio-get-changes-nothing", "security", "api/capture/stages?preset=draft", None, {}, True, 200),
    ("studio-malformed-json", "crash", "api/capture/run", b"{", {}, True, 400),
    ("studio-run-set-not-list", "crash", "api/capture/run", {"preset": "draft", "set": "a"}, {}, True, 400),
    ("studio-run-preset-number", "crash", "api/capture/run", {"preset": 5}, {}, True, 400),
    ("studio-run-extra-key", "crash", "api/capture/run", {"nonsense": 1}, {}, True, 400),
    ("studio-since-negative", "crash", "api/capture/run?since=-1", None, {}, True, 400),
    ("studio-photo-outside", "crash", "api/capture/photo/..%2F..%2Fcapture.toml", None, {}, True, (400, 404)),
    ("studio-output-outside", "crash", "output/..%2Fcapture.toml", None, {}, True, 400),
    ("studio-preview-no-view", "crash", "api/capture/fit-preview/render", None, {}, True, 400),
    ("studio-unknown-route", "crash", "api/capture/nothing", None, {}, True, 404),
]


def studio_request(url: str, path: str, body, headers: dict, token: bool) -> tuple[int, str]:
    """(status, the answer's text) of one request to the studio at ``url`` (printed, with
    its token); status 0 where the studio closed the connection before answering (a
    body it would not read). A "Transfer-Encoding: chunked" header sends the body so."""
    import http.client
    from urllib.parse import urlsplit

    base, _, query = url.partition("?")
    address = urlsplit(base)
    sent = {"X-Studio-Token": query.removeprefix("token=")} if token else {}
    data = None if body is None else body if isinstance(body, bytes) else json.dumps(body).encode()
    if data is not None:
        sent["Content-Type"] = "application/json"
    chunked = headers.get("Transfer-Encoding") == "chunked"
    sent |= {name: value for name, value in headers.items() if name != "Transfer-Encoding"}
    connection = http.client.HTTPConnection(address.hostname, address.port, timeout=60)
    try:
        connection.request(
            "GET" if data is None else "POST",
            "/" + path,
            body=iter([data]) if chunked else data,
            headers=sent,
            encode_chunked=chunked,
        )
        answer = connection.getresponse()
        return answer.status, answer.read().decode(errors="replace")
    except (ConnectionResetError, BrokenPipeError):
        return 0, "the studio closed the connection"
    finally:
        connection.close()


def start_studio(args: list[str]) -> tuple[subprocess.Popen, str, list[str]]:
    """`pipeline studio ARGS` on a free port: the process, the address it printed, its log."""
    process = subprocess.Popen(
        [sys.executable, "-c", CLI, "studio", *args, "--no-browser"], cwd=REPOSITORY, stderr=subprocess.PIPE, text=True
    )
    lines = []
    for line in process.stderr:
        lines.append(line)
        if "studio at " in line:
            return process, line.split("studio at ")[1].split()[0], lines
    raise RuntimeError("the studio did not start:\n" + "".join(lines))


def studio_cases(base: Path, work: Path) -> list[Case]:
    """Requests a hostile page or client makes of a capture's studio, then Ctrl-C during a
    fit and SIGTERM during a run: each a row of the same table (exit: the HTTP status)."""
    folder = work / "studio"
    shutil.rmtree(folder, ignore_errors=True)
    capture = Path(shutil.copytree(base, folder / "capture", symlinks=True))
    rows = []
    process, url, _ = start_studio([str(capture)])
    try:
        for name, kind, path, body, headers, token, expected in STUDIO_REQUESTS:
            started = time.time()
            status, text = studio_request(url, path, body, headers, token)
            accepted = expected if isinstance(expected, tuple) else (expected,)
            case = Case(name, kind, "round four", nothing, [], accepted[0], "")
            sent = body if isinstance(body, bytes) else json.dumps(body or {}).encode()
            echoed = len(sent) > 1000 and sent[:1000].decode(errors="replace") in text
            case.result = {
                "code": status,
                "seconds": round(time.time() - started, 1),
                "message": text[:160],
                "dumped": "Traceback" in text or echoed,
                "hung": False,
                "survived": "yes",
                "passed": status in accepted and "Traceback" not in text and not echoed,
            }
            rows.append(case)
        described = json.loads(studio_request(url, "api/session", None, {}, True)[1])
        looked = next(case for case in rows if case.name == "studio-get-changes-nothing")
        looked.result["passed"] &= described["preset"] == "standard"  # the GET of draft's table changed nothing
    finally:
        process.terminate()
        process.wait(120)
    rows.append(_studio_signal_case(capture, "studio-sigterm-during-run", signal.SIGTERM))
    scene = folder / "scene"
    scene.mkdir()
    scene_folder(None)(scene)
    rows.append(_studio_fit_ctrl_c(scene, folder / "fit_out"))
    return rows


def _studio_signal_case(capture: Path, name: str, signum: int) -> Case:
    """A run started from the page, then ``signum`` to the studio: the run must end and
    release the capture's lock."""
    from pipeline.core.lock import holder

    case = Case(name, "lost", "round four", nothing, [], 0, "")
    process, url, lines = start_studio([str(capture)])
    started = time.time()
    studio_request(url, "api/capture/run", {"preset": "standard", "set": ["masks.max_hole_fraction=0.4"]}, {}, True)
    while holder(capture) is None and time.time() - started < 60:
        time.sleep(0.1)
    process.send_signal(signum)
    try:
        code = process.wait(WATCHDOG_S)
        hung = False
    except subprocess.TimeoutExpired:
        process.kill()
        code, hung = process.wait(), True
    lines += process.stderr.readlines()
    left = holder(capture)
    case.result = {
        "code": code,
        "seconds": round(time.time() - started, 1),
        "message": (lines[-1].strip() if lines else "")[:160],
        "dumped": any("Traceback" in line for line in lines),
        "hung": hung,
        "survived": "yes" if left is None else f"lock held by {left}",
        "passed": code == 0 and not hung and left is None,
    }
    return case


def _studio_fit_ctrl_c(scene_capture: Path, out: Path) -> Case:
    """A fit started from the page, then one Ctrl-C: the fit's best state must be written."""
    case = Case("studio-ctrl-c-during-fit", "lost", "round four", nothing, [], 0, "")
    args = [str(scene_capture / "fit" / "scene.xml"), "--references", str(scene_capture / "fit" / "refs")]
    process, url, lines = start_studio([*args, "--out", str(out)])
    started = time.time()
    session = json.loads(studio_request(url, "api/session", None, {}, True)[1])
    first = next(row["key"] for row in session["parameters"] if row["fittable"])
    form = {
        "params": [first],
        "bounds": {first: [0, 1]},
        "settings": {"iterations": 1_000_000, "still_threshold": 0},
    }
    studio_request(url, "api/fit/start", form, {}, True)
    while studio_request(url, "api/fit/state", None, {}, True)[1].count('"iteration"') < 5:
        assert time.time() - started < WATCHDOG_S and process.poll() is None
        time.sleep(0.2)
    process.send_signal(signal.SIGINT)
    try:
        code, hung = process.wait(WATCHDOG_S), False
    except subprocess.TimeoutExpired:
        process.kill()
        code, hung = process.wait(), True
    lines += process.stderr.readlines()
    params = out / "params.json"
    written = params.is_file() and json.loads(params.read_text())["stopped"].startswith("stopped by the user")
    case.result = {
        "code": code,
        "seconds": round(time.time() - started, 1),
        "message": (lines[-1].strip() if lines else "")[:160],
        "dumped": any("Traceback" in line or "interrupted twice" in line for line in lines),
        "hung": hung,
        "survived": "yes" if written else "no params.json",
        "passed": code == 0 and not hung and written,
    }
    return case


# --- running ------------------------------------------------------------------------------


def base_capture(work: Path) -> Path:
    return synthetic_capture(work / "base", 6, (96, 72), 4, 3, "--until", "masks")


def _mount_tmpfs(folder: Path, kilobytes: int) -> bool:
    folder.mkdir(parents=True, exist_ok=True)
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={kilobytes}k", "tmpfs", str(folder)], capture_output=True
    )
    return done.returncode == 0


def _size_kb(folder: Path) -> int:
    """What ``folder`` takes on a tmpfs, which stores files in whole 4 KB pages."""
    files = [p for p in folder.rglob("*") if p.is_file() and not p.is_symlink()]
    return sum(-(-p.stat().st_size // 4096) * 4 for p in files) + 16


def _wait_for_lock_message(process: subprocess.Popen, lines: list[str]) -> None:
    while process.poll() is None:
        line = process.stderr.readline()
        lines.append(line)
        if "waiting for it to finish" in line:
            return


def run_case(case: Case, base: Path, work: Path) -> dict:
    folder = work / case.name
    subprocess.run(["umount", str(folder)], capture_output=True)
    shutil.rmtree(folder, ignore_errors=True)
    if case.on_tmpfs_kb and not _mount_tmpfs(folder, _size_kb(base) + case.on_tmpfs_kb):
        return {"skipped": "no tmpfs (mount needs root)"}
    folder.mkdir(parents=True, exist_ok=True)
    capture = folder / "capture"
    shutil.copytree(base, capture, symlinks=True)
    case.spoil(capture)
    argv = [a.replace("CAPTURE", str(capture)) for a in case.argv]
    holder = None
    if case.signal_after and case.signal_after[1] == "lock":
        holder = subprocess.Popen(
            [sys.executable, "-c", HOLD_LOCK, str(capture), "60"], stdout=subprocess.PIPE, text=True, cwd=REPOSITORY
        )
        holder.stdout.readline()
    started = time.time()
    process = subprocess.Popen(
        [sys.executable, "-c", CLI, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPOSITORY
    )
    early: list[str] = []
    if case.signal_after:
        signum, when = case.signal_after
        if when == "lock":
            _wait_for_lock_message(process, early)
        else:
            time.sleep(float(when))
        process.send_signal(signum)
    out, err, hung = finish(process, WATCHDOG_S)
    seconds = time.time() - started
    if holder is not None:
        holder.kill()
    for background in BACKGROUND:
        background.kill()
        background.wait()
    BACKGROUND.clear()
    err = "".join(early) + err
    (work / f"{case.name}.stderr.txt").write_text(err)  # for a case that fails
    text = out + err
    lines = [line for line in text.splitlines() if line.strip()]
    dumped = any(word in text for word in ("Traceback", "stack trace", "*** Aborted", "malloc"))
    survived = case.check(capture) if case.check else None
    if case.check is None and (capture / "output" / "manifest.json").is_file() and not case.on_tmpfs_kb:
        survived = output_complete(capture)
    message = next((line for line in reversed(lines) if case.message in line), lines[-1] if lines else "")
    passed = not hung and process.returncode == case.code and case.message in text and not dumped and survived is None
    if case.on_tmpfs_kb:
        subprocess.run(["umount", str(folder)], capture_output=True)
    return {
        "code": process.returncode,
        "seconds": round(seconds, 1),
        "message": message.strip().replace(str(capture), "CAPTURE")[:160],
        "dumped": dumped,
        "hung": hung,
        "survived": survived or "yes",
        "passed": passed,
    }


def write_table(rows: list[Case], command: str) -> None:
    lines = [
        SECTION,
        "",
        f"Machine: the 2-core development VM (no GPU). Command: `.venv/bin/python {command}`. Each case runs the",
        "real CLI in its own process under a 120 s watchdog on a copy of a 6-view 96x72 px synthetic",
        "capture run to masks; disk-full cases on a tmpfs a little larger than the capture. The studio's",
        "rows are requests to `pipeline studio` on that capture (exit: the HTTP status), then SIGTERM during a",
        "run from the page and Ctrl-C during a fit from the page (exit: the studio's).",
        "\"output kept\" is whether the good run's output/ still matches its manifest (or the case's own check).",
        "",
        "| case | kind | from | exit | s | message | dump | output kept | pass |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for case in rows:
        r = case.result
        if "skipped" in r:
            lines.append(f"| {case.name} | {case.kind} | {case.origin} | - | - | skipped: {r['skipped']} | - | - | - |")
            continue
        message = r["message"].replace("|", "\\|")
        lines.append(
            f"| {case.name} | {case.kind} | {case.origin} | {r['code']} | {r['seconds']} | {message} | "
            f"{'yes' if r['dumped'] else 'no'} | {r['survived']} | {'yes' if r['passed'] else '**no**'} |"
        )
    ran = [c for c in rows if "passed" in c.result]
    passed = sum(c.result["passed"] for c in ran)
    origins = {origin: sum(c.origin == origin for c in ran) for origin in dict.fromkeys(c.origin for c in ran)}
    counted = ", ".join(f"{n} {origin}" for origin, n in origins.items())
    lines += ["", f"{passed} of {len(ran)} cases pass ({counted}: issue 53's, further ones, issue 101's).", ""]
    write_section("hostile-inputs", lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", default="/tmp/hostile")
    parser.add_argument("--only", nargs="*", default=[])
    parser.add_argument("--write", action="store_true", help="rewrite docs/benchmarks.md's section")
    args = parser.parse_args()
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    base = base_capture(work)
    chosen = [c for c in cases() if not args.only or c.name in args.only]
    for case in chosen:
        case.result = run_case(case, base, work)
        print(case.name, json.dumps(case.result), flush=True)
    if not args.only or "studio" in args.only:
        for case in studio_cases(base, work):
            chosen.append(case)
            print(case.name, json.dumps(case.result), flush=True)
    if args.write:
        write_table(chosen, "-m bench.hostile_inputs " + " ".join(sys.argv[1:]).replace(" --write", ""))
    return 0 if all(c.result.get("passed", True) for c in chosen) else 1


if __name__ == "__main__":
    sys.exit(main())
