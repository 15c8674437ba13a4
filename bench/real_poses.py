"""Poses on real captures and on a randomised suite of synthetic turntables: photos
placed, how many within a degree, stacked photos, errors against a reference, the
reported uncertainty, self-calibration, time.

    .venv/bin/python -m bench.real_poses [--captures ../shared/captures] [--work /tmp/real-poses]
                                         [--suite 12] [--true-masks] [--only NAME ...] [--write]
    .venv/bin/python -m bench.real_poses --write-from LOG   # the section from a run's printed output

Cases (``--only`` picks some by name):

- Real captures from ``--captures`` (each skipped when absent), every one scored against
  its own reference: ``oxford-dino`` (turntable; Oxford's projective turntable
  reconstruction: turntable angles and centres against reference/cameras.txt, viewing
  directions against reference/cameras_upgraded.txt, see its README; ``oxford-dino-k1-held``
  the same with ``sfm.self_calibrate=false``, distortion held at zero, compared photo by
  photo: whether self-calibration's k1 helps), ``dino-sparse-ring``
  (ring; Middlebury's calibrated cameras), ``dino-sparse-ring-known-intrinsics`` (the
  same with Middlebury's K given as ``calibrate.known_intrinsics``, held fixed, as a user
  with a calibrated rig would run it), ``temple-ring`` (handheld) and
  ``temple-ring-ring`` (ring; Middlebury's calibrated cameras), ``porous-cube`` (handheld,
  76 phone photos with one stray room shot; no reference).
- ``suite-SEED``: synthetic turntables drawn from seeds (``suite_options``): resolution
  256-1024 px; steps of 3-15 degrees, even, jittered or alternating short and long; one
  turn, a turn restarted part-way or a second partial turn; the specimen shifted half-way
  (wobble) or not; a glossy plain or a textured specimen; a dotted, grey or board table; a
  room, studio, white or black backdrop; camera height 10-45 degrees; EXIF focal length or
  not. Each is rendered once into ``--work``. With ``--true-masks`` each runs again as
  ``suite-SEED-true-masks``, its true masks given as the user's (``masks/``): the same
  photos with perfect masks (the outlines fitted and placed, and where features may
  come from), which separates what the masks cost from what the solver does.
- ``twin-NAME`` (``TWINS``): handheld synthetic twins of a small specimen centred on white,
  whose features cover under a third of the frame (a 42 or 20 degree lens, without or with
  the EXIF focal length); each also as ``twin-NAME-start-held``, the intrinsics calibrate
  starts from (EXIF or COLMAP's prior) given as ``calibrate.known_intrinsics`` and held:
  what self-calibration is judged against.
- ``bird``: the bundled sample (handheld rings, the board).

Each becomes a pipeline capture in ``--work`` and runs `pipeline run --until sfm --force
sfm` (the stage always recomputed, so its time is measured; real captures with ``-s
board.kind=none``: no board was photographed). Errors are after
a similarity alignment of the camera centres (Umeyama): the viewing direction, the ray
through the photo's centre pixel (R^T K^-1 [centre, 1], in the reference's K and the
solver's own), and for a turntable or ring the angle about the reference circle's axis
(its median offset removed) and the centres' RMS as a fraction of the circle's radius.
"within 1 deg" counts the photos whose viewing direction is within a degree, over all
photos of the capture, and in brackets those whose optical axis (R^T [0 0 1]) is. Where
the photo looks is fixed by its pixels; its optical axis, on a turntable or ring, is
not: a single circular motion does not determine the principal point (the board on the
table turns about its own normal, which leaves it undetermined too), so the solver holds
it at the photo's centre and turns every camera by the angle between the two rays, an
exchange the photos cannot tell apart (to first order in the field of view). "turn
within 1 deg" counts those whose angle about the circle is (a turntable's or ring's
placement on its circle). "stacked" counts placed photos within 0.1 degrees of another
placed photo's direction whose true directions are more than half a step apart. "angle std" is the
uncertainty the solver reports for each placed photo (sfm.json); "outlines / features"
the standard deviations (pixels) of the outlines' tangency errors and of the features'
reprojection errors at the solution, where the outlines were fitted with the features. "masks": the segmenter
the masks stage used, and for a synthetic capture the masks' mean / least IoU against the
true masks, for a real one their mean / largest coverage of the photo.

temple-ring's reference (reference/templeR_par.txt, Middlebury's K [R t]) fits the photos as
published only when turned by 90 degrees (u' = v, v' = 639 - u); the 16 photos from the
opposite gantry latitude were published turned by 180 degrees, which viewing directions
do not see. dino-sparse-ring's reference fits its photos as given.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from bench.common import ROOT, machine, write_section
from pipeline.camera.model import Pose
from pipeline.formats.cameras import read_cameras, read_views
from pipeline.synthetic.score import score_cameras, score_masks

KNOWN_INTRINSICS = "known_intrinsics.json"
"""Where a case's given intrinsics (``Case.given_intrinsics``) are written, in the capture folder."""
TURN = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
"""The reference camera's axes turned about its optical axis: x' = y, y' = -x."""


@dataclass(frozen=True)
class Case:
    name: str
    source: str
    """'shared:NAME' (a folder of ``--captures``), 'suite:SEED' (a drawn synthetic turntable),
    'twin:NAME' (one of ``TWINS``), 'synth:NAME' (rendered from ``synth``) or 'sample:NAME'."""
    rig: str = "handheld"
    overrides: tuple[str, ...] = field(default_factory=tuple)
    true_masks: bool = False
    """A synthetic capture with its true masks given as the user's (masks/): what its
    poses would be with perfect masks."""
    given_intrinsics: Literal["", "reference", "start"] = ""
    """Intrinsics given as calibrate.known_intrinsics and held: ``reference``, a real
    capture's reference calibration, as a user with a calibrated rig would give it;
    ``start``, the intrinsics calibrate starts from without it (EXIF or COLMAP's prior),
    what self-calibration is judged against."""
    synth: tuple[str, ...] = ()
    """A 'synth:' case's `pipeline synth` arguments."""
    description: str = ""
    """A 'synth:' case's "what" cell."""


REAL = [
    Case("oxford-dino", "shared:oxford-dino", "turntable", ("board.kind=none",)),
    Case("oxford-dino-k1-held", "shared:oxford-dino", "turntable", ("board.kind=none", "sfm.self_calibrate=false")),
    Case("dino-sparse-ring", "shared:dino-sparse-ring", "ring", ("board.kind=none",)),
    Case(
        "dino-sparse-ring-known-intrinsics",
        "shared:dino-sparse-ring",
        "ring",
        ("board.kind=none",),
        given_intrinsics="reference",
    ),
    Case("temple-ring", "shared:temple-ring", "handheld", ("board.kind=none",)),
    Case("temple-ring-ring", "shared:temple-ring", "ring", ("board.kind=none",)),
    Case("porous-cube", "shared:porous-cube", "handheld", ("board.kind=none",)),
]
OTHERS = [Case("bird", "sample:bird")]

_SMALL_ON_WHITE = (
    "--rig handheld --views 37 --width 1000 --height 750 --rings 15 30 --table grey --backdrop white "
    "--texture speckles --calibration-shots 0 --spp 8 --seed 7"
).split()
TWINS = {
    "small-wide": (
        [*_SMALL_ON_WHITE, "--hfov", "42", "--distance", "0.45", "--no-exif-focal"],
        "1000 px, 37 views, speckled bird small on white, 42 deg lens, no EXIF",
    ),
    "small-long": (
        [*_SMALL_ON_WHITE, "--hfov", "20", "--distance", "0.98", "--no-exif-focal"],
        "1000 px, 37 views, speckled bird small on white, 20 deg lens, no EXIF",
    ),
    "small-exif": (
        [*_SMALL_ON_WHITE, "--hfov", "42", "--distance", "0.45"],
        "1000 px, 37 views, speckled bird small on white, 42 deg lens, true focal in EXIF",
    ),
}
"""Handheld synthetic twins of a small specimen centred on white (features on under a
third of the frame): `pipeline synth` arguments and a description. Each runs as it is
(self-calibration) and with the focal length calibrate starts from held."""
TWIN_CASES = [
    case
    for name in TWINS
    for case in (
        Case(f"twin-{name}", f"twin:{name}", overrides=("board.kind=none",)),
        Case(f"twin-{name}-start-held", f"twin:{name}", overrides=("board.kind=none",), given_intrinsics="start"),
    )
]


def suite_options(seed: int) -> tuple[list[str], str]:
    """`pipeline synth` arguments of the suite's capture ``seed``, and a short description."""
    rng = np.random.default_rng(1000 + seed)
    size = int(rng.choice([256, 384, 512, 768, 1024]))
    step = float(rng.uniform(3.0, 15.0))
    steps = str(rng.choice(["even", "jittered", "alternating"]))
    order = str(rng.choice(["one turn", "restart", "second partial turn"]))
    wobble = float(rng.choice([0.0, 0.01], p=[0.6, 0.4]))
    look = str(rng.choice(["glossy plain", "textured"]))
    table = str(rng.choice(["dots", "grey", "board"]))
    backdrop = str(rng.choice(["room", "studio", "white", "dark"]))
    height = float(rng.uniform(10.0, 45.0))
    exif = bool(rng.integers(2))
    extra = float(rng.uniform(0.2, 0.5)) if order == "second partial turn" else 0.0
    views = int(round(360.0 * (1 + extra) / step))
    arguments = [
        "--rig", "turntable", "--views", str(views), "--width", str(size), "--height", str(size),
        "--rings", f"{height:.1f}", "--table", table, "--backdrop", backdrop, "--calibration-shots", "0",
        "--spp", "8", "--seed", str(seed), "--extra-turn", f"{extra:.2f}", "--wobble", str(wobble),
        "--material", "glossy_paint" if look == "glossy plain" else "principled",
        "--texture", "plain" if look == "glossy plain" else "blotches",
    ]  # fmt: skip
    if steps == "jittered":
        arguments += ["--turn-jitter", "0.3"]
    if steps == "alternating":
        arguments += ["--turn-alternation", "2.1"]
    if order == "restart":
        arguments += ["--turn-restart-deg", f"{rng.uniform(8.0, 12.0):.1f}"]
    if not exif:
        arguments.append("--no-exif-focal")
    description = (
        f"{size} px, {views} views, {step:.1f} deg {steps}, {order}{', wobble' if wobble else ''}, {look}, "
        f"{table} table, {backdrop}, {height:.0f} deg high{'' if exif else ', no EXIF'}"
    )
    return arguments, description


# --- references --------------------------------------------------------------------------


def centre_ray(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """The camera-frame direction of the ray through a photo's centre pixel (OpenCV's pixel
    centres): where the photo looks, whatever its principal point."""
    ray = np.linalg.solve(K, [(width - 1) / 2, (height - 1) / 2, 1.0])
    return ray / np.linalg.norm(ray)


@dataclass(frozen=True)
class View:
    """A photo's pose and the camera-frame direction of the ray through its centre pixel."""

    pose: Pose
    centre_ray: np.ndarray


def middlebury_views(par: Path, images: Path, turned: bool) -> dict[str, View]:
    """Middlebury's ``name K R t`` lines, the camera turned by 90 degrees about its optical
    axis when ``turned`` (temple-ring's photos as published; the turn maps the photo's
    centre to the reference frame's)."""
    height, width = cv2.imread(str(next(iter(sorted(images.iterdir()))))).shape[:2]
    if turned:
        width, height = height, width
    views = {}
    for line in par.read_text().splitlines()[1:]:
        if not line.strip():
            continue
        name, *values = line.split()
        numbers = np.array(values, float)
        K, R, t = numbers[:9].reshape(3, 3), numbers[9:18].reshape(3, 3), numbers[18:21]
        ray = centre_ray(K, width, height)
        views[name] = View(Pose(TURN @ R, TURN @ t), TURN @ ray) if turned else View(Pose(R, t), ray)
    return views


def middlebury_intrinsics(par: Path, images: Path) -> dict:
    """The K shared by every line of a Middlebury par file, as calibrate's intrinsics.json
    (Middlebury's pixel origin is the first pixel's centre, as OpenCV's)."""
    matrices = {tuple(line.split()[1:10]) for line in par.read_text().splitlines()[1:] if line.strip()}
    if len(matrices) != 1:
        raise ValueError(f"{par} has {len(matrices)} different K; the capture needs one calibration")
    K = np.array(matrices.pop(), float).reshape(3, 3)
    height, width = cv2.imread(str(next(iter(sorted(images.iterdir()))))).shape[:2]
    return {"width": width, "height": height, "fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}


def oxford_views(path: Path, images: Path) -> dict[str, View]:
    """oxford-dino's ``name fx fy cx cy skew R t`` lines."""
    height, width = cv2.imread(str(next(iter(sorted(images.iterdir()))))).shape[:2]
    views = {}
    for line in path.read_text().splitlines():
        if line.strip():
            name, *values = line.split()
            fx, fy, cx, cy, skew, *numbers = np.array(values, float)
            K = np.array([[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
            pose = Pose(np.reshape(numbers[:9], (3, 3)), np.array(numbers[9:12]))
            views[name] = View(pose, centre_ray(K, width, height))
    return views


def camera_views(path: Path) -> dict[str, View]:
    """A cameras.json's poses with each photo's centre ray."""
    return {
        name: View(pose, centre_ray(intrinsics.K, intrinsics.width, intrinsics.height))
        for name, (intrinsics, pose) in read_views(path).items()
    }


def references(case: Case, captures: Path, capture: Path) -> tuple[dict[str, Pose] | None, dict[str, View] | None]:
    """(centres and angles reference, viewing directions reference); None where there is none."""
    kind, _, name = case.source.partition(":")
    if kind == "shared":
        folder, images = captures / name / "reference", captures / name / "images"
        if name == "oxford-dino":
            circle = {n: v.pose for n, v in oxford_views(folder / "cameras.txt", images).items()}
            return circle, oxford_views(folder / "cameras_upgraded.txt", images)
        par = next(folder.glob("*_par.txt"), None) if folder.is_dir() else None
        views = middlebury_views(par, images, turned=name == "temple-ring") if par else None
        return ({n: v.pose for n, v in views.items()} if views else None), views
    truth = camera_views(capture / "ground_truth" / "cameras.json")
    return {n: v.pose for n, v in truth.items()}, truth


# --- scores -------------------------------------------------------------------------------


def _directions(views: dict[str, View], names: list[str], ray: Literal["centre", "axis"] = "centre") -> np.ndarray:
    """World directions of the photos' centre rays, or of their optical axes."""
    axis = np.array([0.0, 0.0, 1.0])
    return np.array([views[n].pose.R.T @ (views[n].centre_ray if ray == "centre" else axis) for n in names])


def direction_errors(
    estimate: dict[str, View], truth: dict[str, View], ray: Literal["centre", "axis"] = "centre"
) -> dict[str, float]:
    """Per photo, degrees between the aligned and the true viewing direction: the ray through
    the photo's centre, or the optical axis."""
    common = sorted(set(estimate) & set(truth))
    if len(common) < 3:
        return {}
    _, similarity = score_cameras({n: estimate[n].pose for n in common}, {n: truth[n].pose for n in common})
    seen = _directions(estimate, common, ray) @ similarity.R.T
    true = _directions(truth, common, ray)
    return dict(zip(common, np.degrees(np.arccos(np.clip(np.sum(seen * true, axis=1), -1.0, 1.0)))))


def circle_errors(estimate: dict[str, Pose], truth: dict[str, Pose]) -> tuple[np.ndarray, float]:
    """Angle errors (degrees) about the reference circle's axis, the median offset removed,
    and the centres' RMS error as a fraction of the circle's radius, after a similarity
    alignment of the centres."""
    common = sorted(set(estimate) & set(truth))
    if len(common) < 3:
        return np.zeros(0), float("nan")
    _, similarity = score_cameras(estimate, truth)
    true = np.array([truth[n].center for n in common])
    seen = similarity.points(np.array([estimate[n].center for n in common]))
    centre = true.mean(axis=0)
    u, _, normal = np.linalg.svd(true - centre)[2]
    v = np.cross(normal, u)
    radius = float(np.median(np.linalg.norm((true - centre) - np.outer((true - centre) @ normal, normal), axis=1)))

    def angles(points: np.ndarray) -> np.ndarray:
        return np.arctan2((points - centre) @ v, (points - centre) @ u)

    difference = np.angle(np.exp(1j * (angles(seen) - angles(true))))
    offset = np.angle(np.mean(np.exp(1j * difference)))
    errors = np.degrees(np.abs(np.angle(np.exp(1j * (difference - offset)))))
    rms = float(np.sqrt(np.mean(np.sum((seen - true) ** 2, axis=1))))
    return errors, rms / radius


def stacked(estimate: dict[str, View], truth: dict[str, View]) -> int:
    """Placed photos within 0.1 degrees of another's viewing direction whose true
    directions are more than half the median nearest-neighbour step apart."""
    names = sorted(set(estimate) & set(truth))
    if len(names) < 2:
        return 0
    seen, true = _directions(estimate, names), _directions(truth, names)
    seen_angle = np.degrees(np.arccos(np.clip(seen @ seen.T, -1, 1)))
    true_angle = np.degrees(np.arccos(np.clip(true @ true.T, -1, 1)))
    np.fill_diagonal(true_angle, np.inf)
    half_step = 0.5 * float(np.median(true_angle.min(axis=1)))
    np.fill_diagonal(seen_angle, np.inf)
    return int(np.sum(np.any((seen_angle < 0.1) & (true_angle > half_step), axis=1)))


# --- running ------------------------------------------------------------------------------


def _pipeline(*arguments: str) -> list[str]:
    return [str(Path(sys.executable).parent / "pipeline"), "--quiet", *arguments]


def prepare(case: Case, captures: Path, work: Path) -> Path:
    capture = work / case.name
    if (capture / "capture.toml").is_file():
        return capture
    kind, _, name = case.source.partition(":")
    if kind == "shared":
        subprocess.run(_pipeline("new", str(capture), "--rig", case.rig), check=True)
        for photo in sorted((captures / name / "images").iterdir()):
            shutil.copy2(photo, capture / "images" / photo.name)
        if case.given_intrinsics == "reference":
            par = next((captures / name / "reference").glob("*_par.txt"))
            (capture / KNOWN_INTRINSICS).write_text(json.dumps(middlebury_intrinsics(par, capture / "images")))
        return capture
    if kind == "sample":
        shutil.copytree(ROOT / "sample_captures" / name, capture, ignore=shutil.ignore_patterns(".pipeline", "output"))
        return capture
    rendered = work / f"rendered-{name}"
    if not (rendered / "capture.toml").is_file():
        shutil.rmtree(rendered, ignore_errors=True)
        arguments = suite_options(int(name))[0] if kind == "suite" else case.synth or TWINS[name][0]
        subprocess.run(_pipeline("synth", str(rendered), *arguments), check=True)
    shutil.copytree(rendered, capture, ignore=shutil.ignore_patterns(".pipeline", "output"))
    if case.true_masks:
        shutil.copytree(rendered / "ground_truth" / "masks", capture / "masks", dirs_exist_ok=True)
    if case.given_intrinsics == "start":
        overrides = [argument for override in case.overrides for argument in ("-s", override)]
        subprocess.run(_pipeline("run", str(capture), "--until", "calibrate", *overrides), check=True)
        shutil.copy2(capture / "output" / "stages" / "calibrate" / "intrinsics.json", capture / KNOWN_INTRINSICS)
    return capture


def calibration_summary(report: dict) -> str:
    """f and k1 as sfm.json reports them: adjusted or held."""
    found = report.get("circular", {}).get("self_calibration") or next(
        iter(report.get("self_calibration", {}).values()), None
    )
    if not found or "values" not in found:
        return found.get("skipped", "-") if found else "board or not tried"
    values = found["values"]
    return ", ".join(
        f"{name} {values[name]['value']:.4g}{'' if values[name]['adjusted'] else ' (held)'}" for name in ("f", "k1")
    )


def _newest_entry(capture: Path, stage: str) -> Path:
    """The stage's latest cache entry (each case runs once, under one configuration)."""
    entries = (capture / ".pipeline" / "cache" / stage).glob("[!.]*/status.json")
    return max(entries, key=lambda p: p.stat().st_mtime).parent


def mask_summary(capture: Path) -> str:
    """The masks stage's segmenter and, against the truth (synthetic captures), the masks'
    mean and least IoU; for a real capture, their mean and largest coverage."""
    masks_json = _newest_entry(capture, "masks") / "masks.json"
    entries = json.loads(masks_json.read_text())["images"].values()
    status = json.loads((masks_json.parent / "status.json").read_text())
    segmenter = status.get("metrics", {}).get("segmenter") or json.loads(masks_json.read_text())["source"]
    if (capture / "ground_truth" / "masks").is_dir():
        pinhole = _newest_entry(capture, "undistort") / "pinhole.json"
        scores = list(score_masks(capture / "ground_truth", pinhole, masks_json).values())
        return f"{segmenter}: IoU {np.mean(scores):.2f} / {np.min(scores):.2f}"
    coverage = [100 * entry["coverage"] for entry in entries]
    return f"{segmenter}: covers {np.mean(coverage):.0f} / {np.max(coverage):.0f} %"


def run_case(case: Case, captures: Path, work: Path) -> dict:
    """Run sfm on the case and score it: a dict of the table's cells."""
    capture = prepare(case, captures, work)
    command = _pipeline("run", str(capture), "--until", "sfm", "--force", "sfm")
    if case.source.startswith("shared:"):
        command += ["-s", f"capture.rig={case.rig}"]
    for override in case.overrides:
        command += ["-s", override]
    if case.given_intrinsics:
        command += ["-s", f"calibrate.known_intrinsics={KNOWN_INTRINSICS}"]
    started = time.perf_counter()
    log = work / f"{case.name}.log"
    with log.open("w") as stream:
        finished = subprocess.run(command, stdout=stream, stderr=subprocess.STDOUT).returncode == 0
    seconds = time.perf_counter() - started
    photos = len([p for p in (capture / "images").iterdir() if p.is_file()])
    row = {"case": case.name, "photos": photos, "seconds": seconds, "finished": finished}
    if not finished:
        # The run's last error line ("E ..." or "error: ..."), cut before its list of photos.
        lines = [line for line in log.read_text().splitlines() if line.startswith(("E ", "error"))]
        row["error"] = lines[-1].split(". Unregistered")[0].removeprefix("E ")[:160] if lines else "failed"
        return row
    output = capture / "output"
    intrinsics = read_cameras(output / "stages" / "sfm" / "cameras.json")[0]
    views = camera_views(output / "stages" / "sfm" / "cameras.json")
    poses = {name: view.pose for name, view in views.items()}
    key = json.loads((output / "manifest.json").read_text())["stages/sfm/cameras.json"]["key"]
    report = json.loads((capture / ".pipeline" / "cache" / "sfm" / key / "sfm.json").read_text())
    circular = report.get("circular", {})
    row |= {
        "rig": report.get("poses_from", ""),
        "placed": len(poses),
        "by": {k: len(v) for k, v in circular.get("pose_source", {}).items() if v} or {"SfM": len(poses)},
        "calibration": f"f {intrinsics.fx:.4g}, given (held)" if case.given_intrinsics else calibration_summary(report),
        "angle_std": list(circular.get("angle_std_deg", {}).values()),
        "coherence": circular.get("silhouette_coherence") or {},
        "circular": circular,
    }
    row["masks"] = mask_summary(capture)
    circle_truth, direction_truth = references(case, captures, capture)
    if direction_truth is not None:
        errors = direction_errors(views, direction_truth)
        values = np.array(list(errors.values()))
        axis_values = np.array(list(direction_errors(views, direction_truth, "axis").values()))
        row |= {
            "within_1deg": int(np.sum(values <= 1.0)),
            "axis_within_1deg": int(np.sum(axis_values <= 1.0)),
            "direction": (float(np.median(values)), float(values.max())) if len(values) else None,
            "stacked": stacked(views, direction_truth),
            "direction_errors": errors,
        }
    if circle_truth is not None and case.rig in ("turntable", "ring"):
        angle_errors, centre_rms = circle_errors(poses, circle_truth)
        if len(angle_errors):
            row |= {"angle": (float(np.median(angle_errors)), float(angle_errors.max())), "centre": centre_rms}
            row["turn_within_1deg"] = int(np.sum(angle_errors <= 1.0))
    return row


def table_row(row: dict, description: str) -> str:
    def pair(value, unit=" deg") -> str:
        return f"{value[0]:.2f} / {value[1]:.2f}{unit}" if value else "-"

    if not row["finished"]:
        return (
            f"| {row['case']} | {description} | {row['photos']} | failed: {row['error']} |||||||||| "
            f"{row['seconds']:.0f} s |"
        )
    std = np.array(row["angle_std"])
    std_cell = f"{np.median(std):.2f} / {std.max():.2f} deg" if len(std) else "-"
    by = ", ".join(f"{k} {v}" for k, v in row["by"].items())
    centre = f"{100 * row['centre']:.2f} %" if "centre" in row else "-"
    within = f"{row['within_1deg']} ({row['axis_within_1deg']})" if "within_1deg" in row else "-"
    turn_within = str(row.get("turn_within_1deg", "-"))
    coherence = row.get("coherence") or {}
    noises = f"{coherence['tangency_sigma_px']:.2f} / {coherence['feature_sigma_px']:.2f} px" if coherence else "-"
    return (
        f"| {row['case']} | {description} | {row['photos']} | {row['placed']} ({by}) | {within} | {turn_within} | "
        f"{row.get('stacked', '-')} | {pair(row.get('direction'))} | {pair(row.get('angle'))} | {centre} | "
        f"{std_cell} | {noises} | {row['calibration']} | {row['masks']} | {row['seconds']:.0f} s |"
    )


HEADER = (
    "| capture | what | photos | placed (by) | within 1 deg (optical axis) | turn within 1 deg | stacked | "
    "direction error median / max | turn angle error median / max | centres (RMS, % of radius) | "
    "angle std median / max | outlines / features | intrinsics (self-calibration) | masks | sfm |\n"
    "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
)


NOTES = [
    "- oxford-dino's reference is a projective turntable reconstruction: its turn angles and centres are",
    "  exact, its viewing directions (cameras_upgraded.txt) are good to a few degrees in elevation only, so",
    '  its direction and "within 1 deg" columns measure the reference as much as the poses.',
    "- The viewing direction is the ray through the photo's centre pixel; in brackets, the optical axis. A",
    "  single circular motion does not determine the principal point, which the solver holds at the photo's",
    "  centre; the synthetic lens has it about 1 % of the width off, and the real references have their own,",
    "  so optical axes differ by that angle (about 0.6 degrees on the synthetic captures) where the photos agree.",
    '- "placed (by)": features (the ring), group_silhouette (an arc of the ring that matching left apart,',
    "  placed by its outlines at once), board, even_steps, silhouette (a photo alone, by its outline).",
]


def write_real_poses(lines: list[str], summary: list[str], command: str) -> None:
    """The "Real poses" section of docs/benchmarks.md."""
    body = [
        "## Real poses",
        "",
        f"{machine()} Command: `{command}` (synthetic captures are rendered once into the work",
        "folder). Columns: bench/real_poses.py's docstring.",
        "",
        HEADER,
        *lines,
        "",
        *summary,
        "",
        *NOTES,
    ]
    write_section("real-poses", body)


def suite_summary(rows: list[dict], title: str) -> str:
    photos = sum(r["photos"] for r in rows)
    within = sum(r.get("within_1deg", 0) for r in rows)
    axis_within = sum(r.get("axis_within_1deg", 0) for r in rows)
    turn_within = sum(r.get("turn_within_1deg", 0) for r in rows)
    stacked_count = sum(r.get("stacked", 0) for r in rows)
    failed = sum(not r["finished"] for r in rows)
    return (
        f"{title} ({len(rows)} captures, {photos} photos): {within} photos "
        f"({100 * within / photos:.1f} %) placed with their viewing direction within 1 degree ({axis_within}, "
        f"{100 * axis_within / photos:.1f} %, by the optical axis), {turn_within} "
        f"({100 * turn_within / photos:.1f} %) with their turn angle within 1 degree; {stacked_count} stacked, "
        f"{failed} stages failed."
    )


def describe(case: Case) -> str:
    """The table's "what" cell: the rig, or the synthetic capture's description, and what
    the case adds."""
    kind, _, name = case.source.partition(":")
    if kind == "suite":
        description = suite_options(int(name))[1]
    elif kind == "twin":
        description = TWINS[name][1]
    else:
        description = case.description or case.rig
    given = {"": "", "reference": ", reference intrinsics given", "start": ", start focal held"}
    return description + (", true masks" if case.true_masks else "") + given[case.given_intrinsics]


def paired_difference(calibrated: dict[str, float], held: dict[str, float]) -> str:
    """Photo by photo, self-calibrated minus held direction errors: their median with a
    bootstrap 95 % interval (seeded), the Wilcoxon signed-rank test's p, and in how many
    photos self-calibration is the better. The medians of two runs differ by their photos'
    noise; only a difference that the photos' pairs bear out makes one run worse."""
    from scipy.stats import wilcoxon

    common = sorted(set(calibrated) & set(held))
    differences = np.array([calibrated[n] - held[n] for n in common])
    if len(differences) < 6:
        return "too few photos in both to compare"
    resampled = np.random.default_rng(0).choice(differences, (4000, len(differences)))
    low, high = np.percentile(np.median(resampled, axis=1), [2.5, 97.5])
    return (
        f"per photo {np.median(differences):+.2f} ({low:+.2f} to {high:+.2f}), "
        f"p {wilcoxon(differences).pvalue:.2g}, better in {int(np.sum(differences < 0))} of {len(differences)}"
    )


def held_summary(rows: dict[str, dict]) -> str:
    """Each case run again as NAME-k1-held (``sfm.self_calibrate=false``: distortion held
    at zero): its median direction error self-calibrated against held, and their
    photo-by-photo difference (``paired_difference``)."""
    pairs = []
    for name, held in rows.items():
        calibrated = rows.get(name.removesuffix("-k1-held"))
        if not name.endswith("-k1-held") or calibrated is None:
            continue
        if calibrated.get("direction_errors") and held.get("direction_errors"):
            difference = paired_difference(calibrated["direction_errors"], held["direction_errors"])
            pairs.append(
                f"{calibrated['case']} {calibrated['direction'][0]:.2f} against {held['direction'][0]:.2f} "
                f"({calibrated['calibration']}; {difference})"
            )
    return (
        "Self-calibration against distortion held at zero, median direction error (degrees), and self-calibrated "
        "minus held photo by photo (median, its 95 % bootstrap interval, Wilcoxon signed-rank p, photos where "
        f"self-calibration is better): {'; '.join(pairs) or 'no pair run'}."
    )


def twin_summary(rows: dict[str, dict]) -> str:
    """Each twin's median direction error with self-calibration against the start focal
    held, and their photo-by-photo difference (``paired_difference``)."""

    def median(row: dict | None) -> str:
        return f"{row['direction'][0]:.2f}" if row and row.get("direction") else "failed"

    pairs = []
    for name in TWINS:
        calibrated, held = rows.get(f"twin-{name}"), rows.get(f"twin-{name}-start-held")
        if calibrated is None and held is None:
            continue
        text = f"{name} {median(calibrated)} against {median(held)}"
        if calibrated and held and calibrated.get("direction_errors") and held.get("direction_errors"):
            text += f" ({paired_difference(calibrated['direction_errors'], held['direction_errors'])})"
        pairs.append(text)
    return (
        "Small specimens on white, median direction error (degrees) with self-calibration against the focal "
        "length calibrate starts from held, and self-calibrated minus held photo by photo (median, its 95 % "
        f"bootstrap interval, Wilcoxon signed-rank p, photos where self-calibration is better): {'; '.join(pairs)}."
    )


def write_from_log(log: Path) -> None:
    """The "Real poses" section from a run's printed table and summary, its command read
    from the log's first line."""
    printed = log.read_text().splitlines()
    command = printed[0].removeprefix("command: ")
    rows = [line for line in printed if line.startswith("| ") and not line.startswith(("| capture |", "|---"))]
    summary = [
        line
        for line in printed
        if line.startswith(("Randomised suite", "The same with", "Small specimens", "Self-calibration against"))
    ]
    write_real_poses(rows, summary, command)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--captures", type=Path, default=ROOT.parent / "shared" / "captures")
    parser.add_argument("--work", type=Path, default=Path("/tmp/real-poses"))
    parser.add_argument("--suite", type=int, default=12, help="synthetic turntables drawn (seeds 0..N-1)")
    parser.add_argument("--only", nargs="*", default=None)
    parser.add_argument(
        "--true-masks", action="store_true", help="run each synthetic turntable again with its true masks"
    )
    parser.add_argument("--write", action="store_true", help="rewrite docs/benchmarks.md's section")
    parser.add_argument(
        "--write-from",
        type=Path,
        metavar="LOG",
        help="rewrite docs/benchmarks.md's section from what an earlier run printed (its standard output), run nothing",
    )
    args = parser.parse_args()
    if args.write_from is not None:
        write_from_log(args.write_from)
        return
    args.work.mkdir(parents=True, exist_ok=True)
    suite = [Case(f"suite-{seed:02d}", f"suite:{seed}", "turntable") for seed in range(args.suite)]
    if args.true_masks:
        suite += [replace(c, name=f"{c.name}-true-masks", true_masks=True) for c in suite]
    cases = [c for c in REAL + suite + TWIN_CASES + OTHERS if args.only is None or c.name in args.only]
    options = " ".join(o for o in sys.argv[1:] if o != "--write")
    print(f"command: .venv/bin/python -m bench.real_poses {options} --write", flush=True)
    print(HEADER, flush=True)
    lines, suite_rows, true_mask_rows, twin_rows, real_rows = [], [], [], {}, {}
    for case in cases:
        if case.source.startswith("shared:") and not (args.captures / case.source.split(":")[1]).is_dir():
            continue
        kind = case.source.partition(":")[0]
        row = run_case(case, args.captures, args.work)
        lines.append(table_row(row, describe(case)))
        print(lines[-1], flush=True)
        if kind == "suite":
            (true_mask_rows if case.true_masks else suite_rows).append(row)
        if kind == "twin":
            twin_rows[case.name] = row
        if kind == "shared":
            real_rows[case.name] = row
    summary = []
    for rows, title in ((suite_rows, "Randomised suite"), (true_mask_rows, "The same with the true masks")):
        if rows:
            summary.append(suite_summary(rows, title))
            print(summary[-1])
    if twin_rows:
        summary.append(twin_summary(twin_rows))
        print(summary[-1])
    if any(name.endswith("-k1-held") for name in real_rows):
        summary.append(held_summary(real_rows))
        print(summary[-1])
    if args.write:
        write_real_poses(lines, summary, f".venv/bin/python -m bench.real_poses {options} --write")


if __name__ == "__main__":
    main()
