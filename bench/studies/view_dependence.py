"""Whether a capture's photos see the same surface differently from different places
(issue 26, point 4): fit_texture's scene re-rendered for every training photo, each
render matched to its photo by an RGB gain, and the ratio photo / render (both blurred
by a 2 px Gaussian within the eroded specimen mask) read per pixel with the surface
normal and the direction to the camera.

The normals are clustered (k-means on the unit sphere, ``--faces`` clusters; pixels
within 18 degrees of their cluster's mean count), and per cluster the median ratio is
binned by the camera's azimuth about the normal, measured from the horizontal tangent
(``normal x up``; for a vertical face -90 degrees is the camera straight in front and
above, 0 and -180 grazing to either side). One light and one texture give every
photo the same ratio, up to noise: a face whose ratio swings with the azimuth is seen
differently from different places (light that moves with the camera, such as the
photographer's shadow, or a reflectance the model lacks), which no texture fixes.
Each cell: the median ratio, the camera's median angle from the normal and the
photos in the bin (bins with fewer than 300 pixels are left out).

``--camera-frame DEGREE`` asks whether that difference is light fixed to the camera (an
occluder that moves with it, such as the photographer): the logarithm of each training
photo's blurred ratio is fitted, by least squares over every pixel, as a polynomial of
degree DEGREE in the surface normal expressed in that photo's camera coordinates (and,
as the control, in the world's); each held-out photo's render is multiplied by the
exponential of that polynomial, and its PSNR after an RGB gain matched on the specimen
is printed before and after, with the share of the training log-ratio's variance the
polynomial explains.

Usage: ``.venv/bin/python -m bench.studies.view_dependence CAPTURE [-s KEY=VALUE ...] [--camera-frame 3]`` with
the overrides its runs used (bench/light.py's REAL), after bin/bootstrap and a
``pipeline run CAPTURE --until fit_texture`` with them. Prints a Markdown table;
rewrites the section ``view-dependence-NAME`` of docs/benchmarks.md with ``--write``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from bench.common import write_section
from bench.studies.ceiling import cached_outputs
from pipeline.fit.bake import pixel_rays
from pipeline.fit.loop import matched_gain
from pipeline.fit.views import PhotoGains, Windowing, load_views, read_capture_photos
from pipeline.formats.fit_results import read_fitted_scene
from pipeline.render import mitsuba_variant

BINS_DEG = np.arange(-180, 181, 30)
"""Azimuth bins about a face's normal."""
FACE_COS = np.cos(np.radians(18.0))
"""A pixel counts for its cluster when its normal is this close to the cluster's mean."""
MIN_PIXELS = 300
"""Fewest pixels in a reported bin."""


def rendered_views(capture: Path, overrides: list[str], names: str = "training") -> list[dict]:
    """fit_texture's scene rendered (128 px windows, 64 spp) for the ``names`` photos
    (training or held_out): per photo its name, photo, render, the specimen pixels that
    count (eroded by 2 px), the surface normal per pixel and the camera's rotation."""
    import mitsuba as mi

    outputs = cached_outputs(capture, "fit_texture", overrides)
    description, material = read_fitted_scene(outputs["scene"]["description"], outputs["fit_material"]["params"])
    textured = outputs["fit_texture"]["textured_dir"]
    photos = read_capture_photos(
        outputs["sfm"]["cameras"],
        outputs["undistort"]["pinhole"],
        outputs["masks"]["masks_json"],
        PhotoGains.of(material),
    )
    mitsuba_variant.activate("auto")
    held = set(material.held_out)
    chosen = held if names == "held_out" else set(description.views) - held
    views = load_views(textured, description, photos, Windowing(128, 2, 64), names=chosen)
    rendered = []
    for view, _ in views:
        render = np.asarray(mi.render(view.scene, sensor=view.sensor, integrator=view.integrator, spp=64, seed=1))
        rays, (height, width) = pixel_rays(view.sensor)
        hit = view.scene.ray_intersect(rays)
        inside = (view.weight > 0) & np.array(hit.is_valid()).reshape(height, width)
        inside = cv2.erode(inside.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        if inside.sum() < MIN_PIXELS:
            continue
        rendered.append(
            {
                "name": view.name,
                "photo": view.reference,
                "render": render,
                "inside": inside,
                "normal": np.array(hit.sh_frame.n).T.reshape(height, width, 3),
                "to_camera": -np.array(rays.d).T.reshape(height, width, 3),
                "rotation": photos[0][view.name][1].R,
            }
        )
    return rendered


def blurred_ratio(view: dict) -> np.ndarray:
    """Photo over the gain-matched render, both blurred by 2 px within the pixels that count."""
    inside = view["inside"]
    gain = matched_gain(view["render"], view["render"], view["photo"], inside[..., None], 3)
    blurred_photo = cv2.GaussianBlur(view["photo"].mean(-1) * inside, (0, 0), 2)
    blurred_render = cv2.GaussianBlur((view["render"] * gain).mean(-1) * inside, (0, 0), 2)
    return blurred_photo / np.maximum(blurred_render, 1e-4)


def pixel_samples(views: list[dict]) -> np.ndarray:
    """(n, 8): per specimen pixel of every view its normal, the unit vector to the
    camera, the ratio photo / gain-matched render, and the photo's index."""
    samples = []
    for index, view in enumerate(views):
        inside, count = view["inside"], int(view["inside"].sum())
        columns = [view["normal"][inside], view["to_camera"][inside], blurred_ratio(view)[inside][:, None]]
        samples.append(np.concatenate([*columns, np.full((count, 1), index)], 1))
    return np.concatenate(samples)


def monomials(normals: np.ndarray, degree: int) -> np.ndarray:
    """(n, terms): every monomial of the normals' coordinates up to ``degree``."""
    x, y, z = normals.T
    powers = [(i, j, k) for i in range(degree + 1) for j in range(degree + 1 - i) for k in range(degree + 1 - i - j)]
    return np.stack([x**i * y**j * z**k for i, j, k in powers], axis=1)


def camera_frame_fit(training: list[dict], held_out: list[dict], degree: int) -> list[str]:
    """Per frame (camera, world): the training log-ratio's variance explained by a
    polynomial of the normal in that frame, and each held-out photo's gain-matched
    PSNR before and after its render is multiplied by it (the module docstring)."""
    ratios = [blurred_ratio(view) for view in training]
    lines = []
    for frame in ("camera", "world"):

        def normals(view: dict) -> np.ndarray:
            return view["normal"] @ view["rotation"].T if frame == "camera" else view["normal"]

        rows, targets = [], []
        for view, ratio in zip(training, ratios):
            usable = view["inside"] & np.isfinite(ratio) & (ratio > 0.2) & (ratio < 5.0)
            rows.append(monomials(normals(view)[usable], degree))
            targets.append(np.log(ratio[usable]))
        rows, targets = np.concatenate(rows), np.concatenate(targets)
        scale = np.abs(rows).max(axis=0)  # columns of one magnitude: a well-posed solve
        coefficients = np.linalg.lstsq(rows / scale, targets, rcond=None)[0] / scale
        explained = 1 - np.var(targets - rows @ coefficients) / np.var(targets)
        scores = []
        for view in held_out:
            inside = view["inside"]
            factor = np.exp(monomials(normals(view).reshape(-1, 3), degree) @ coefficients).reshape(inside.shape)
            for render in (view["render"], view["render"] * factor[..., None]):
                gain = matched_gain(render, render, view["photo"], inside[..., None], 3)
                error = np.mean(np.square(render * gain - view["photo"])[inside])
                scores.append(-10 * np.log10(error))
        before, after = np.mean(scores[0::2]), np.mean(scores[1::2])
        per_photo = ", ".join(f"{b:.2f} -> {a:.2f}" for b, a in zip(scores[0::2], scores[1::2]))
        lines.append(f"| {frame} | {degree} | {explained:.1%} | {before:.2f} -> {after:.2f} dB | {per_photo} |")
    return lines


def face_table(samples: np.ndarray, faces: int) -> list[tuple[np.ndarray, int, list[str]]]:
    """Per normal cluster (largest first): its mean normal, its photos, and a cell per
    azimuth bin (the module docstring)."""
    normal, to_camera, ratio, photo = samples[:, :3], samples[:, 3:6], samples[:, 6], samples[:, 7]
    valid = np.isfinite(ratio) & (ratio > 0.2) & (ratio < 5.0)
    normal, to_camera, ratio, photo = normal[valid], to_camera[valid], ratio[valid], photo[valid]
    rng = np.random.default_rng(0)
    means = normal[rng.choice(len(normal), faces, replace=False)]
    for _ in range(30):
        label = np.argmax(normal @ means.T, axis=1)
        means = np.stack([normal[label == k].mean(0) if (label == k).any() else means[k] for k in range(faces)])
        means /= np.linalg.norm(means, axis=1, keepdims=True)
    label = np.argmax(normal @ means.T, axis=1)
    rows = []
    for k in np.argsort(-np.bincount(label, minlength=faces)):
        on_face = (label == k) & (normal @ means[k] > FACE_COS)
        if on_face.sum() < MIN_PIXELS:
            continue
        axis = means[k]
        tangent = np.cross(axis, [0.0, 0.0, 1.0])
        if np.linalg.norm(tangent) < 0.3:  # a horizontal face: azimuth from the x axis
            tangent = np.cross(axis, [1.0, 0.0, 0.0])
        tangent /= np.linalg.norm(tangent)
        bitangent = np.cross(axis, tangent)
        seen = to_camera[on_face]
        azimuth = np.degrees(np.arctan2(seen @ bitangent, seen @ tangent))
        tilt = np.degrees(np.arccos(np.clip(seen @ axis, -1.0, 1.0)))
        cells = []
        for low, high in zip(BINS_DEG[:-1], BINS_DEG[1:]):
            in_bin = (azimuth >= low) & (azimuth < high)
            if in_bin.sum() < MIN_PIXELS:
                cells.append("")
                continue
            photos = len(np.unique(photo[on_face][in_bin]))
            cells.append(f"{np.median(ratio[on_face][in_bin]):.2f} ({np.median(tilt[in_bin]):.0f}°, {photos})")
        rows.append((axis, len(np.unique(photo[on_face])), cells))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("capture", type=Path)
    parser.add_argument("-s", "--set", dest="overrides", action="append", default=[])
    parser.add_argument("--faces", type=int, default=6, help="normal clusters")
    parser.add_argument("--write", action="store_true", help="rewrite docs/benchmarks.md's section")
    parser.add_argument("--camera-frame", type=int, metavar="DEGREE", help="fit light fixed to the camera instead")
    args = parser.parse_args()
    training = rendered_views(args.capture, args.overrides)
    if args.camera_frame is not None:
        lines = [
            "| normal in the frame of | degree | training variance explained | held-out PSNR, gain-matched | per photo |",
            "|---|---|---|---|---|",
            *camera_frame_fit(training, rendered_views(args.capture, args.overrides, "held_out"), args.camera_frame),
        ]
        print("\n".join(lines))
        if args.write:
            write_section(f"camera-frame-{args.capture.name}", lines)
        return
    rows = face_table(pixel_samples(training), args.faces)
    centres = [f"{(low + high) // 2}°" for low, high in zip(BINS_DEG[:-1], BINS_DEG[1:])]
    lines = [
        f"| normal ({args.capture.name}) | photos | " + " | ".join(centres) + " |",
        "|---|---|" + "---|" * len(centres),
        *(
            f"| {' '.join(f'{c:.2f}' for c in axis)} | {photos} | " + " | ".join(cells) + " |"
            for axis, photos, cells in rows
        ),
    ]
    print("\n".join(lines))
    if args.write:
        write_section(f"view-dependence-{args.capture.name}", lines)


if __name__ == "__main__":
    main()
