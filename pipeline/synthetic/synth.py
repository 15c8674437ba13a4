"""``pipeline synth``: render a capture whose every unknown is known.

A procedural bird (pipeline.synthetic.specimen) stands on a turntable plate printed with
the capture's ChArUco board, under an environment plus one area light. Views sit
on elevation rings around it. Each view is rendered as an ideal pinhole image
with Mitsuba, then bent by OpenCV radial-tangential distortion, given shot and
read noise, encoded to sRGB and written as an 8-bit JPEG with EXIF, as a camera
would. Also written: ``calibration/`` (board shots with the same camera),
``capture.toml`` (what a user would write) and ``ground_truth/`` (intrinsics,
poses, mesh, material, light, board placement and true masks).

Turntable captures (``--rig turntable``) keep camera and light fixed while the
object turns: in the object's frame the camera circles one ring and the light
travels with it. ``--turn-jitter`` makes the steps uneven like a hand-turned table,
``--turn-alternation`` alternates short and long steps, ``--turn-restart-deg`` turns the
table back half-way, ``--extra-turn`` adds part of a second turn and ``--wobble`` shifts
the specimen half-way, as real turntable captures do. ``--set-views`` shoots the turn in
several sets, each with its own camera (``--rings``, ``--set-distances``,
``--set-rolls-deg``), restart (``--set-restarts-deg``) and, with ``--sets-turned-over``,
the specimen turned over; ``--specimen vase`` is a body of revolution whose outline
cannot tell the table's angle.
``--table`` and ``--backdrop`` build the hard cases of real captures: a plate with
sparse dots instead of the board, a still textured room (an environment map, which
also lights the scene: written to ``ground_truth/room.exr``), photos cut out on white,
a dark studio lit by the softbox alone.
"""

from __future__ import annotations

import json
import math
import tomllib
from dataclasses import asdict, replace
from pathlib import Path

import cv2
import numpy as np
import trimesh

from pipeline import logger
from pipeline.camera.board import board_image, board_to_world
from pipeline.camera.model import Intrinsics, Pose, Similarity, distortion_maps, pinhole_render_size
from pipeline.core import progress
from pipeline.core.config import toml_section
from pipeline.core.errors import PipelineError
from pipeline.core.sections import BoardSection, CaptureSection, LightSection
from pipeline.formats.cameras import write_cameras
from pipeline.geometry.atlas import mitsuba_mesh
from pipeline.imaging.photo_io import to_uint8, write_image
from pipeline.render import mitsuba_variant
from pipeline.render.capture_scene import environment_to_world
from pipeline.synthetic import set_pieces
from pipeline.synthetic.options import SynthOptions
from pipeline.synthetic.specimen import BLOTCH_SCALE, bird_mesh, blotch_colours, vase_mesh

SENSOR_WIDTH_MM = 6.4
"""Sensor width written to EXIF, so that focal length in mm is meaningful."""

BIRD_CENTRE = np.array([0.0, 0.0, 0.045])


# Ground-truth materials: translucent but distinguishable, inside the fitting bounds.
PRINCIPLED_TRUTH = {
    "model": "principled",
    "base_color": [0.72, 0.46, 0.22],
    "roughness": 0.35,
    "spec_trans": 0.45,
    "eta": 1.45,
    # Mitsuba derives `specular` from eta (specular = F0 / 0.08) and rejects both
    # at once; recorded for comparison with fits that use `specular`.
    "specular": ((1.45 - 1) / (1.45 + 1)) ** 2 / 0.08,
}
GLOSSY_PAINT_TRUTH = {
    "model": "opaque",
    "base_color": [0.60, 0.12, 0.08],
    "roughness": 0.12,
    "specular": 0.5,
}
VOLUMETRIC_TRUTH = {
    "model": "volumetric",
    "alpha": 0.12,
    "eta": 1.40,
    "albedo": [0.90, 0.72, 0.50],
    "sigma_t": 180.0,
}

TRUTHS = {"principled": PRINCIPLED_TRUTH, "volumetric": VOLUMETRIC_TRUTH, "glossy_paint": GLOSSY_PAINT_TRUTH}
PLATE_RADIUS = 0.2
"""Radius of the turntable plate, metres."""


DARK_SURROUND = (0.01, 0.01, 0.01)
"""The environment's radiance with ``--backdrop dark``: black cloth round a softbox."""


def lens_intrinsics(options: SynthOptions) -> Intrinsics:
    """The synthetic camera: ``options``' size and field of view, its lens distortion."""
    f = options.width / 2 / math.tan(math.radians(options.hfov) / 2)
    # Principal point a little off centre, as in real cameras.
    return Intrinsics(
        width=options.width,
        height=options.height,
        fx=f,
        fy=f,
        cx=(options.width - 1) / 2 + 0.011 * options.width,
        cy=(options.height - 1) / 2 - 0.008 * options.height,
        dist=list(options.distortion),
    )


def specimen_poses(options: SynthOptions, rng: np.random.Generator) -> list[Pose]:
    """The cameras of ``options``' views: on its rings (jittered) or, for a turntable,
    one ring in the object's frame. ``synthesize`` draws them first from
    ``np.random.default_rng(options.seed)``."""
    if options.rig == "turntable" and options.set_views:
        return _set_poses(options, rng)
    if options.rig == "turntable":
        steps = 1.0 + options.turn_jitter * rng.uniform(-1, 1, options.views)
        steps[1::2] *= options.turn_alternation
        turns = 1.0 + options.extra_turn
        azimuths = np.concatenate([[0.0], np.cumsum(steps[:-1])]) * 2 * np.pi * turns / steps.sum()
        second_half = np.arange(options.views) >= options.views // 2
        azimuths[second_half] -= math.radians(options.turn_restart_deg)
        elevation = math.radians(options.rings[0])
        return [
            Pose.look_at(
                BIRD_CENTRE
                + options.distance * _direction(a, elevation)
                + [0.0, 0.0, options.wobble * options.distance * shifted],
                BIRD_CENTRE,
            )
            for a, shifted in zip(azimuths, second_half)
        ]
    poses = []
    rings = options.rings
    for i in range(options.views):
        ring = i % len(rings)
        index_on_ring = i // len(rings)
        count_on_ring = len(range(ring, options.views, len(rings)))
        azimuth = 2 * np.pi * (index_on_ring + 0.5 * ring) / count_on_ring + rng.normal(0, 0.05)
        elevation = math.radians(rings[ring] + rng.normal(0, 2.0))
        distance = options.distance * rng.uniform(0.92, 1.08)
        target = BIRD_CENTRE + rng.normal(0, 0.006, 3)
        poses.append(
            Pose.look_at(BIRD_CENTRE + distance * _direction(azimuth, elevation), target, roll_deg=rng.normal(0, 3.0))
        )
    return poses


def _direction(azimuth: float, elevation: float) -> np.ndarray:
    """The unit vector from the specimen towards a camera at ``azimuth`` and ``elevation`` (radians)."""
    return np.array(
        [math.cos(azimuth) * math.cos(elevation), math.sin(azimuth) * math.cos(elevation), math.sin(elevation)]
    )


def _nth(values: tuple[float, ...], k: int, default: float) -> float:
    return values[k] if k < len(values) else default


def _set_poses(options: SynthOptions, rng: np.random.Generator) -> list[Pose]:
    """A turntable's cameras in several sets (``options.set_views``), in the table's
    frame: each set one turn of its own steps, from where the set before ended less its
    restart, at its own elevation, distance and roll."""
    poses: list[Pose] = []
    start = 0.0
    for k, count in enumerate(options.set_views):
        steps = 1.0 + options.turn_jitter * rng.uniform(-1, 1, count)
        steps[1::2] *= options.turn_alternation
        steps *= 2 * np.pi * (1.0 + options.extra_turn) / steps.sum()
        if k:
            start -= math.radians(_nth(options.set_restarts_deg, k, 0.0))
        azimuths = start + np.concatenate([[0.0], np.cumsum(steps[:-1])])
        start = float(azimuths[-1])
        elevation = math.radians(options.rings[min(k, len(options.rings) - 1)])
        distance = options.distance * _nth(options.set_distances, k, 1.0)
        poses += [
            Pose.look_at(
                BIRD_CENTRE + distance * _direction(a, elevation),
                BIRD_CENTRE,
                roll_deg=_nth(options.set_rolls_deg, k, 0.0),
            )
            for a in azimuths
        ]
    return poses


def turned_over(options: SynthOptions) -> list[bool]:
    """Per view, whether the specimen lies turned over in its set."""
    counts = options.set_views or (options.views,)
    return [k + 1 in options.sets_turned_over for k, count in enumerate(counts) for _ in range(count)]


def _turn_over(mesh: trimesh.Trimesh) -> Similarity:
    """The specimen turned over: 180 degrees about the x axis through its bounding box's
    centre (its underside up, in the same box), from its own frame to the table's."""
    R = np.diag([1.0, -1.0, -1.0])
    centre = mesh.bounds.mean(axis=0)
    return Similarity(1.0, R, centre - R @ centre)


def _check_sets(options: SynthOptions) -> None:
    if not options.set_views:
        return
    if options.rig != "turntable":
        raise PipelineError("set_views: sets are shot on a turntable; give --rig turntable or leave --set-views out")
    if sum(options.set_views) != options.views or min(options.set_views) < 2:
        raise PipelineError(
            f"set_views {list(options.set_views)}: each set needs 2 photos or more, and they must sum to "
            f"views ({options.views}); give --views {sum(options.set_views)}"
        )


def _calibration_poses(count: int, board_size: tuple[float, float], rng) -> list[Pose]:
    """Board shots from varied angles and distances, the board filling much of the frame."""
    poses = []
    for _ in range(count):
        tilt = math.radians(rng.uniform(0, 40))
        azimuth = rng.uniform(0, 2 * np.pi)
        distance = rng.uniform(0.26, 0.40)
        direction = np.array([math.sin(tilt) * math.cos(azimuth), math.sin(tilt) * math.sin(azimuth), math.cos(tilt)])
        target = np.array([rng.uniform(-0.25, 0.25) * board_size[0], rng.uniform(-0.25, 0.25) * board_size[1], 0.0])
        poses.append(
            Pose.look_at(target + distance * direction, target, up=(0.0, 1.0, 0.0), roll_deg=rng.uniform(-30, 30))
        )
    return poses


def material_plugins(material: dict, textured: bool) -> tuple[dict, dict | None, dict]:
    """(bsdf, interior medium or None, integrator) for a ground-truth material.

    Only what the model needs: no medium for the surface models, and the
    vertex-colour texture only when the specimen has one.
    """
    if material["model"] in ("principled", "opaque"):
        colour = (
            {"type": "mesh_attribute", "name": "vertex_color"}
            if textured
            else {"type": "rgb", "value": material["base_color"]}
        )
        bsdf = {"type": "principled", "id": "specimen_material", "base_color": colour}
        if material["model"] == "principled":
            bsdf |= {"roughness": material["roughness"], "spec_trans": material["spec_trans"], "eta": material["eta"]}
        else:
            bsdf |= {"roughness": material["roughness"], "specular": material["specular"]}
        return bsdf, None, {"type": "path", "max_depth": 10}
    bsdf = {
        "type": "roughdielectric",
        "id": "specimen_material",
        "alpha": material["alpha"],
        "int_ior": material["eta"],
        "ext_ior": 1.0,
    }
    medium = {
        "type": "homogeneous",
        "id": "specimen_medium",
        "albedo": {"type": "rgb", "value": material["albedo"]},
        "sigma_t": material["sigma_t"],
    }
    return bsdf, medium, {"type": "volpath", "max_depth": 32}


class _Studio:
    """The synthetic photo studio: scenes, the lens, and the sensor."""

    def __init__(self, options: SynthOptions, board: BoardSection, light: LightSection):
        import mitsuba as mi

        self.mi = mi
        self.options = options
        self.light = light
        self.intrinsics = lens_intrinsics(options)
        self.render_size = pinhole_render_size(self.intrinsics)
        self.maps = distortion_maps(self.intrinsics, self.render_size)
        self.noise_rng = np.random.default_rng(options.seed + 1)
        self.renders = 1000 * options.seed
        # Printed paper: ink reflects ~4 %, paper ~80 %.
        reflectance = 0.04 + 0.76 * board_image(board).astype(np.float32) / 255.0
        # Mitsuba's rectangle maps the bitmap's first row to local y = -1; the board's
        # top edge must sit at +y (see board_to_world), so the rows are flipped.
        reflectance = np.ascontiguousarray(reflectance[::-1])
        self.board_texture = mi.Bitmap(np.repeat(reflectance[..., None], 3, axis=2))
        self.board_half = (board.squares_x * board.square_mm / 2000, board.squares_y * board.square_mm / 2000)
        plate = {"type": "rgb", "value": 0.25}
        if options.table == "dots":
            dots = set_pieces.dotted_plate(options.seed + 11)
            plate = {"type": "bitmap", "bitmap": mi.Bitmap(np.repeat(dots[..., None], 3, axis=2)), "raw": True}
        self.plate = {"type": "diffuse", "id": "plate", "reflectance": plate}
        self.room = set_pieces.room_map(options.seed + 12) if options.backdrop == "room" else None

    def specimen_shape(
        self,
        mesh: trimesh.Trimesh,
        albedo: np.ndarray | None,
        bsdf: dict,
        medium: dict | None = None,
        emitter: dict | None = None,
    ):
        """The specimen as a Mitsuba mesh; BSDF, medium and emitter bind at construction."""
        mi = self.mi
        props = mi.Properties()
        props["bsdf"] = mi.load_dict(bsdf)
        if medium is not None:
            props["interior"] = mi.load_dict(medium)
        if emitter is not None:
            props["emitter"] = mi.load_dict(emitter)
        shape = mitsuba_mesh(mesh, "specimen", props)
        if albedo is not None:
            # Float attribute, not PLY colours: no 8-bit quantisation or colour-space guess.
            shape.add_attribute("vertex_color", 3, mi.Float(albedo.astype(np.float32).ravel()))
        return shape

    def scene(
        self, pose: Pose, spp: int, integrator: dict, specimen=None, black_props: bool = False, board_only: bool = False
    ) -> dict:
        """Board, turntable, rig and the specimen when given, seen from ``pose``; with
        ``board_only`` just the board (the calibration shots add their own light)."""
        mi = self.mi
        render_w, render_h = self.render_size
        black = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}}
        paper = {
            "type": "diffuse",
            "id": "board_paper",
            "reflectance": {"type": "bitmap", "bitmap": self.board_texture, "raw": True},
        }
        scene = {
            "type": "scene",
            "integrator": integrator,
            "camera": {
                "type": "perspective",
                "fov": math.degrees(2 * math.atan(render_w / 2 / self.intrinsics.fx)),
                "fov_axis": "x",
                "near_clip": 0.01,
                "to_world": mi.ScalarTransform4f(pose.mitsuba_to_world().tolist()),
                "sampler": {"type": "independent", "sample_count": spp},
                "film": {"type": "hdrfilm", "width": render_w, "height": render_h, "pixel_format": "rgb"},
            },
        }
        if board_only or self.options.table == "board":
            scene["board"] = {
                "type": "rectangle",
                "to_world": mi.ScalarTransform4f().scale([self.board_half[0], self.board_half[1], 1.0]),
                "bsdf": black if black_props else paper,
            }
        if board_only:
            return scene
        scene["turntable"] = {
            "type": "disk",
            "to_world": mi.ScalarTransform4f().translate([0, 0, -0.001]).scale(PLATE_RADIUS),
            "bsdf": black if black_props else self.plate,
        }
        if specimen is not None:
            scene["specimen"] = specimen
        if not black_props:
            scene.update(self.lights(pose))
        return scene

    def lights(self, pose: Pose) -> dict:
        mi, light = self.mi, self.light
        lights: dict = {
            "environment": {"type": "constant", "radiance": {"type": "rgb", "value": list(light.environment_radiance)}}
        }
        if self.room is not None:
            lights["environment"] = {
                "type": "envmap",
                "bitmap": mi.Bitmap(self.room),
                "to_world": mi.ScalarTransform4f(environment_to_world(light.frame, pose).tolist()),
            }
        if not light.area_light:
            return lights
        position, target = np.array(light.area_position), np.array(light.area_target)
        up = np.array([0.0, 0.0, 1.0])
        if light.frame == "camera":
            position = pose.R.T @ (position - pose.t)
            target = pose.R.T @ (target - pose.t)
            up = -pose.R[1]
        half = light.area_size / 2
        lights["softbox"] = {
            "type": "rectangle",
            "to_world": mi.ScalarTransform4f().look_at(origin=position.tolist(), target=target.tolist(), up=up.tolist())
            @ mi.ScalarTransform4f().scale([half, half, 1.0]),
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": list(light.area_radiance)}},
        }
        return lights

    def render(self, scene: dict) -> np.ndarray:
        """Render a pinhole image and bend it through the lens: linear, distorted.

        Every render gets its own sampler seed: with one seed, Monte Carlo noise is
        the same pattern at the same pixels in every photo, a "texture" that stays
        put in the image while the scene moves, which SIFT matches (fixed-pattern
        noise that real sensors have far less of)."""
        self.renders += 1
        image = np.asarray(self.mi.render(self.mi.load_dict(scene), seed=self.renders), dtype=np.float32)
        return cv2.remap(image, *self.maps, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def photo(self, linear: np.ndarray, coverage: np.ndarray | None = None) -> np.ndarray:
        """Shot and read noise in linear space, then 8-bit sRGB, as a camera writes it;
        with ``coverage`` (the specimen's share of each pixel) cut out on white."""
        if self.options.noise > 0:
            electrons_at_white = 4000.0 / self.options.noise
            variance = np.clip(linear, 0, None) / electrons_at_white + (0.0015 * self.options.noise) ** 2
            linear = linear + self.noise_rng.normal(size=linear.shape) * np.sqrt(variance)
        if coverage is not None:
            linear = coverage[..., None] * linear + (1 - coverage[..., None])
        return to_uint8(linear)

    def write_jpeg(self, path: Path, pixels: np.ndarray) -> None:
        width, height = self.intrinsics.width, self.intrinsics.height
        focal_mm = self.intrinsics.fx * SENSOR_WIDTH_MM / width
        # The 35 mm equivalent is defined on the diagonal (CIPA DC-008): 43.27 mm.
        sensor_diagonal_mm = SENSOR_WIDTH_MM * math.hypot(width, height) / width
        pixels_per_cm = width / (SENSOR_WIDTH_MM / 10)
        focal = {
            "Exif:FocalLength": float(focal_mm),
            "Exif:FocalLengthIn35mmFilm": int(round(focal_mm * 43.27 / sensor_diagonal_mm)),
            "Exif:FocalPlaneXResolution": float(pixels_per_cm),
            "Exif:FocalPlaneYResolution": float(pixels_per_cm),
            "Exif:FocalPlaneResolutionUnit": 3,  # centimetres
        }
        write_image(
            path,
            pixels,
            {
                "Make": "pipeline-synth",
                "Model": "SynthCam 1",
                **(focal if self.options.exif_focal else {}),
                "compression": f"jpeg:{self.options.jpeg_quality}",
            },
        )


def default_light(options: SynthOptions) -> LightSection:
    """The rig's light: a softbox fixed in the world, or riding with a turntable's camera;
    given (the synthetic capture knows it; ``-s light.model=auto`` makes the fit estimate it)."""
    if options.rig == "turntable":
        # Camera frame: x right, y down, z forward; softbox up and to the right, aimed at the bird.
        return LightSection(
            model="given",
            environment_radiance=(0.3, 0.3, 0.3),
            area_position=(0.25, -0.30, 0.05),
            area_target=(0.0, 0.0, options.distance),
            area_size=0.3,
            area_radiance=(10.0, 10.0, 10.0),
            frame="camera",
        )
    return LightSection(
        model="given",
        environment_radiance=(0.3, 0.3, 0.3),
        area_position=(0.30, 0.35, 0.50),
        area_target=(0.0, 0.0, 0.04),
        area_size=0.3,
        area_radiance=(10.0, 10.0, 10.0),
    )


def _capture_toml(options: SynthOptions, board: BoardSection, light: LightSection) -> str:
    capture = CaptureSection(
        f"synthetic {options.specimen}, {options.material} material, seed {options.seed}",
        options.rig,
        TRUTHS[options.material]["model"],
    )
    if options.table != "board" and options.calibration_shots == 0:
        board = replace(board, kind="none")  # no board anywhere in the capture
    lines = ["# Written by `pipeline synth`: what a user would write for this capture."]
    for name, section in (("capture", capture), ("board", board), ("light", light)):
        lines += toml_section(name, section, documented=False) + [""]
    text = "\n".join(lines)
    tomllib.loads(text)  # what we write must parse
    return text


def synthesize(out_dir: Path, options: SynthOptions, board: BoardSection = BoardSection()) -> Path:
    """Render a complete synthetic capture into ``out_dir``; returns ``out_dir``."""
    # Longer than 60 lines: one pass writing the capture's folders in order (photos,
    # plates, board shots, capture.toml, ground truth), each a call or two.
    if out_dir.exists() and any(out_dir.iterdir()):
        raise PipelineError(f"{out_dir} is not empty: choose a new folder for the synthetic capture")
    mitsuba_variant.activate()
    light = default_light(options)
    if options.backdrop == "room":
        light = replace(light, environment_map="ground_truth/room.exr")
    if options.backdrop == "dark":
        light = replace(light, environment_radiance=DARK_SURROUND)
    _check_sets(options)
    rng = np.random.default_rng(options.seed)
    mesh = bird_mesh() if options.specimen == "bird" else vase_mesh()
    material = dict(TRUTHS[options.material])
    textured = options.texture != "plain" and options.material != "volumetric"
    scale = BLOTCH_SCALE / 3 if options.texture == "speckles" else BLOTCH_SCALE
    albedo = blotch_colours(mesh.vertices, np.array(material["base_color"]), options.seed, scale) if textured else None
    if albedo is not None:
        material["base_color_mean"] = albedo.mean(axis=0).tolist()
    poses = specimen_poses(options, rng)
    flips = turned_over(options)
    flip = _turn_over(mesh)
    studio = _Studio(options, board, light)

    images, calibration, truth = out_dir / "images", out_dir / "calibration", out_dir / "ground_truth"
    for folder in (images, calibration, truth / "masks"):
        folder.mkdir(parents=True)

    bsdf, medium, integrator = material_plugins(material, textured)
    # Keyed by whether the specimen lies turned over: the mesh as it stands on the table.
    placed = {False: mesh} | ({True: mesh.copy().apply_transform(flip.matrix())} if any(flips) else {})
    specimens = {turned: studio.specimen_shape(shape, albedo, bsdf, medium) for turned, shape in placed.items()}
    silhouettes = {
        turned: studio.specimen_shape(
            shape,
            None,
            {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}},
            emitter={"type": "area", "radiance": {"type": "rgb", "value": 1.0}},
        )
        for turned, shape in placed.items()
    }
    names = [f"view_{i:03d}.jpg" for i in range(len(poses))]
    for name, pose, turned in progress.track(list(zip(names, poses, flips)), "rendering views"):
        linear = studio.render(studio.scene(pose, options.spp, integrator, specimens[turned]))
        coverage = studio.render(
            studio.scene(pose, 16, {"type": "path", "max_depth": 1}, silhouettes[turned], black_props=True)
        )
        cut_out = np.clip(coverage[..., 0], 0, 1) if options.backdrop == "white" else None
        studio.write_jpeg(images / name, studio.photo(linear, cut_out))
        cv2.imwrite(
            str(truth / "masks" / name.replace(".jpg", ".png")), ((coverage[..., 0] > 0.5) * 255).astype(np.uint8)
        )
        if options.background_plates:
            (out_dir / "background").mkdir(exist_ok=True)
            plate = studio.photo(studio.render(studio.scene(pose, options.spp, integrator)))
            studio.write_jpeg(out_dir / "background" / name, plate)

    board_size = (2 * studio.board_half[0], 2 * studio.board_half[1])
    calibration_env = {"type": "direct", "emitter_samples": 1, "bsdf_samples": 1}
    calibration_poses = _calibration_poses(options.calibration_shots, board_size, rng)
    for i, pose in enumerate(progress.track(calibration_poses, "rendering calibration shots")):
        scene = studio.scene(pose, 16, calibration_env, board_only=True)
        scene["environment"] = {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}}
        studio.write_jpeg(calibration / f"board_{i:02d}.jpg", studio.photo(studio.render(scene)))

    # The truth is in the specimen's frame: x_camera = R (R_flip x + t_flip) + t.
    in_specimen_frame = [
        Pose(pose.R @ flip.R, pose.R @ flip.t + pose.t) if turned else pose for pose, turned in zip(poses, flips)
    ]
    write_cameras(truth / "cameras.json", studio.intrinsics, dict(zip(names, in_specimen_frame)))
    exported = mesh.copy()
    if albedo is not None:
        srgb = to_uint8(albedo)
        exported.visual.vertex_colors = np.c_[srgb, np.full(len(srgb), 255, np.uint8)]
    exported.export(truth / "mesh.ply")
    (truth / "material.json").write_text(
        json.dumps({**material, "texture": "vertex colours of mesh.ply (sRGB)" if textured else None}, indent=1)
    )
    (truth / "light.json").write_text(json.dumps(asdict(light), indent=1))
    if studio.room is not None:
        write_image(truth / "room.exr", studio.room)
    (truth / "board.json").write_text(
        json.dumps({**asdict(board), "board_to_world": board_to_world(board).tolist()}, indent=1)
    )
    (truth / "synth.json").write_text(
        json.dumps(
            {"options": asdict(options), "calibration_poses": [p.to_json() for p in calibration_poses]}, indent=1
        )
    )
    (out_dir / "capture.toml").write_text(_capture_toml(options, board, light))
    logger.info("wrote %d views and %d calibration shots to %s", len(poses), len(calibration_poses), out_dir)
    return out_dir
