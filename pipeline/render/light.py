"""The light of a capture estimated from its photos: the models a fit chooses from,
their fitted parameters, the scene files rewritten with a light, and the irradiance
a light casts.

============  ==============================================  ==================================
model         emitters (ids)                                  fitted (pipeline.fit.variables)
============  ==============================================  ==================================
constant      ``constant`` environment (environment)          nothing (its level is measured)
envmap        ``envmap``, a lat-long map of W x W/2 texels    every texel, as log radiance with a
              (environment)                                   smoothness prior on the logarithms
envmap+area   the envmap, and a square ``area`` light         the texels and the softbox's
              (softbox) on the map's brightest lobe           radiance
============  ==============================================  ==================================

The light is fixed to the world for a handheld capture and rides with the camera
for a turntable (``frame``, as pipeline.render.capture_scene places it): there the
specimen turns under a still light, and each photo sees it from another side.

Scale and colour: a light's scale and colour trade off exactly against a diffuse
albedo's, so they are not fitted. The scene stage measures a level: the uniform
radiance at which a surface of known albedo renders like the photos (the board's
print, its colour too, when the photos show it; else the specimen as if it had its
starting material, in grey: the camera's white balance taken as right). What that
measures is the irradiance on the surface it was measured on, so the map keeps it:
each channel's mean radiance weighted by how much each texel lights that surface
(``level_weights``: the board faces up; the specimen's faces as the cameras saw
them) stays at its start (pipeline.fit.variables.FitParameter.mean_weights), and
texels that surface never sees (below the board) do not count. With the board,
radiance and albedos are absolute (in the photos' linear units); without, albedos
are relative to that guess, and what is measured is the light's distribution over
directions, the softbox's share, and the materials' other parameters (roughness,
transmission, eta, ...). A guessed level can be too dim for the specimen's brightest
spots, whose colour would have to exceed 1: fit_texture then raises the light (and
lowers the table's albedo) until its baked colours fit (pipeline.fit.bake), so an
albedo is never above 1 and the level is the lowest that allows it.

Limitations: the softbox's position and size come from the envmap's lobe (its
direction and solid angle, at ``area_distance`` times the specimen's radius) and
are not refined by gradients; the map's 2 pi seam is not smoothed across.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np

from pipeline.camera.model import Pose
from pipeline.core.errors import PipelineError
from pipeline.core.sections import LightSection
from pipeline.formats.scene_folder import SPECIMEN_XML
from pipeline.imaging.photo_io import read_photo, write_image
from pipeline.render import capture_scene, scene_xml
from pipeline.render.parameters import FitParameter, Layout

LightModel = Literal["constant", "envmap", "envmap+area"]
LIGHT_MODELS: tuple[LightModel, ...] = ("constant", "envmap", "envmap+area")
"""Simplest first: the order in which `auto` tries them."""
ENVIRONMENT_FILE = "environment.exr"
LIGHT_IDS = ("environment", "softbox")
SPECIMEN_LEVEL = "specimen (grey)"
"""scene.json's ``level_from`` when no surface of known reflectance set the level."""
RESCALED = {
    "environment.scale": 1,
    "environment.radiance.value": 1,
    "softbox.emitter.radiance.value": 1,
    "ground.bsdf.reflectance.value": -1,
}
"""``mi.traverse`` keys a change of the light's level multiplies (1) or divides (-1):
the emitters, and the table's albedo, which the photos fix only as a product with it."""


@dataclass(frozen=True)
class AreaLight:
    position: tuple[float, float, float]
    """Centre, in the light's frame (world, or the camera's coordinates)."""
    target: tuple[float, float, float]
    size: float
    radiance: tuple[float, float, float]


@dataclass(frozen=True)
class EstimatedLight:
    """A light of one model, as a fit starts or ends it."""

    model: LightModel
    frame: Literal["world", "camera"]
    environment: np.ndarray
    """(h, w, 3) lat-long radiance; for ``constant`` (1, 1, 3)."""
    area: AreaLight | None = None

    def section(self) -> LightSection:
        """As a [light] section, for pipeline.render.capture_scene.lights."""
        area = self.area
        return LightSection(
            environment_radiance=tuple(float(v) for v in self.environment.reshape(-1, 3).mean(axis=0)),
            environment_map=ENVIRONMENT_FILE if self.model != "constant" else "",
            area_light=area is not None,
            area_position=area.position if area else LightSection.area_position,
            area_target=area.target if area else LightSection.area_target,
            area_size=area.size if area else LightSection.area_size,
            area_radiance=area.radiance if area else LightSection.area_radiance,
            frame=self.frame,
        )

    def scaled(self, factor) -> EstimatedLight:
        """Every radiance times ``factor`` (a number, or one per colour channel)."""
        factor = np.broadcast_to(np.asarray(factor, np.float32), 3)
        area = self.area and replace(self.area, radiance=tuple(float(v) for v in factor * self.area.radiance))
        return replace(self, environment=self.environment * factor, area=area)

    def summary(self) -> dict:
        """For the stage's JSON."""
        summary = {
            "model": self.model,
            "frame": self.frame,
            "environment_mean": [float(v) for v in self.environment.reshape(-1, 3).mean(axis=0)],
        }
        if self.model != "constant":
            summary["environment_map"] = ENVIRONMENT_FILE
            summary["environment_texels"] = list(self.environment.shape[:2])
        if self.area is not None:
            summary["area"] = {
                "position": list(self.area.position),
                "target": list(self.area.target),
                "size": self.area.size,
                "radiance": list(self.area.radiance),
            }
        return summary


def start(model: LightModel, frame: str, level: np.ndarray, width: int) -> EstimatedLight:
    """A uniform light of radiance ``level`` (RGB) in ``model``'s form (an area light is
    added later, from a fitted envmap's lobe: with_area)."""
    shape = (1, 1) if model == "constant" else (width // 2, width)
    environment = np.broadcast_to(np.asarray(level, np.float32), (*shape, 3)).copy()
    return EstimatedLight("envmap" if model == "envmap+area" else model, frame, environment)


def parameters(light: EstimatedLight, smoothness: float, measured_on: Surface | None) -> list[FitParameter]:
    """The fitted parameters of ``light``'s model (names prefixed ``light_``); the map's
    level on ``measured_on`` (the surface the scene stage measured it on) is kept, or
    left to the loss when None (a surface of known reflectance in it: the board)."""
    if light.model == "constant":
        return []  # its level and colour are the start's
    height, width = light.environment.shape[:2]
    weights = None if measured_on is None else level_weights(height, width, light.frame, measured_on)
    environment = FitParameter(
        "light_environment",
        "environment.data",
        1e-6,
        1e6,
        log=True,
        learning_rate=0.1,
        smoothness=smoothness,
        smooth_logarithm=True,
        mean_weights=None if weights is None else tuple(float(w) for w in weights.ravel()),
        layout=envmap_layout(height, width),
    )
    if light.area is None:
        return [environment]
    area = FitParameter(
        "light_area_radiance", "softbox.emitter.radiance.value", 1e-6, 1e6, log=True, learning_rate=0.05
    )
    return [environment, area]


def envmap_layout(height: int, width: int) -> Layout:
    """Mitsuba's envmap stores W + 2 columns: the last texel column first and the first
    one last, for wrapping; the latent holds the W real ones."""
    rows, columns, channels = np.meshgrid(np.arange(height), np.arange(width), np.arange(3), indexing="ij")
    take = (rows * (width + 2) + columns + 1) * 3 + channels
    rows, padded, channels = np.meshgrid(np.arange(height), np.arange(width + 2), np.arange(3), indexing="ij")
    give = (rows * width + (padded - 1) % width) * 3 + channels
    return Layout((height, width, 3), tuple(int(i) for i in take.ravel()), tuple(int(i) for i in give.ravel()))


def fitted(light: EstimatedLight, values: dict[str, np.ndarray]) -> EstimatedLight:
    """``light`` with a fit's values (pipeline.fit.engine.FitResult: plain values flat,
    textures as arrays)."""
    if "light_environment" not in values:
        return light
    environment = np.asarray(values["light_environment"], np.float32).reshape(light.environment.shape)
    area = light.area
    if area is not None:
        area = replace(area, radiance=tuple(float(v) for v in values["light_area_radiance"]))
    return replace(light, environment=environment, area=area)


def check_environment_map(path: Path, setting: str) -> None:
    """Refuse an environment map whose pixels are no radiance: unreadable, NaN or
    infinite (read_photo says which), or negative."""
    negative = int(np.count_nonzero((read_photo(path).pixels < 0).any(axis=-1)))
    if negative:
        raise PipelineError(
            f"{setting}: {negative} pixel(s) of {path} are negative, which is no radiance: clamp them to 0 in the file"
        )


def from_section(section: LightSection, environment: np.ndarray | None = None) -> EstimatedLight:
    """A [light] rig (a known light) in this module's form: ``environment`` the map of
    its environment_map (loaded by the caller), else its constant radiance."""
    area = None
    if section.area_light:
        area = AreaLight(section.area_position, section.area_target, section.area_size, section.area_radiance)
    constant = np.asarray(section.environment_radiance, np.float32).reshape(1, 1, 3)
    environment = constant if environment is None else np.asarray(environment, np.float32)
    model: LightModel = "constant" if environment.shape[:2] == (1, 1) else "envmap"
    return EstimatedLight("envmap+area" if area and model == "envmap" else model, section.frame, environment, area)


def read(summary: dict, scene_dir: Path) -> EstimatedLight:
    """The light a fit chose, from its summary (EstimatedLight.summary, in fit_material's
    params.json) and the environment map in ``scene_dir``."""
    if summary.get("environment_map"):
        environment = read_photo(scene_dir / summary["environment_map"]).pixels
    else:
        environment = np.asarray(summary["environment_mean"], np.float32).reshape(1, 1, 3)
    area = summary.get("area")
    if area is not None:
        area = AreaLight(tuple(area["position"]), tuple(area["target"]), area["size"], tuple(area["radiance"]))
    return EstimatedLight(summary["model"], summary["frame"], environment, area)


def write(light: EstimatedLight, scene_dir: Path, view_files: dict[str, str], poses: dict[str, Pose]) -> None:
    """Put ``light`` into scene.xml and every photo's scene file of ``scene_dir``
    (``view_files``: by photo name; the environment map written beside them), in place
    of the lights they had."""
    section = light.section()
    environment_file = None
    if light.model != "constant":
        write_image(scene_dir / ENVIRONMENT_FILE, light.environment.astype(np.float32))
        environment_file = ENVIRONMENT_FILE
    first = sorted(view_files)[0]
    files = [("scene.xml", first)] + [(xml, name) for name, xml in sorted(view_files.items())]
    for filename, photo in files:
        path = scene_dir / filename
        tree = ET.parse(path)
        root = tree.getroot()
        for element in [e for e in root if e.get("id") in LIGHT_IDS]:
            root.remove(element)
        capture_scene.lights(root, section, poses[photo], environment_file)
        ET.indent(root)
        tree.write(path, encoding="unicode", xml_declaration=True)


def rescale_scenes(scenes: list, factor: float) -> None:
    """Multiply the light of every distinct scene in ``scenes`` by ``factor`` (RESCALED)."""
    import mitsuba as mi

    for scene in {id(s): s for s in scenes}.values():
        params = mi.traverse(scene)
        for key in [k for k in RESCALED if k in params]:
            params[key] = params[key] * factor ** RESCALED[key]
        params.update()


def rescale_files(
    scene_dir: Path, chosen: dict, factor: float, view_files: dict[str, str], poses: dict[str, Pose]
) -> dict:
    """The light fit_material chose (``chosen``: its summary; the map in ``scene_dir``)
    times ``factor`` in every scene file of ``scene_dir`` (write), and the table's
    albedo in its specimen file divided by it; the new light's summary."""
    scaled = read(chosen, scene_dir).scaled(factor)
    write(scaled, scene_dir, view_files, poses)
    specimen = scene_dir / SPECIMEN_XML
    for bsdf in [b for b in ET.parse(specimen).iter("bsdf") if b.get("id") == capture_scene.GROUND_BSDF]:
        albedo = [float(v) / factor for v in next(bsdf.iter("rgb")).get("value").replace(",", " ").split()]
        scene_xml.set_values(specimen, {"ground.bsdf.reflectance.value": albedo}, specimen)
    return scaled.summary()


def directions(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Each texel's direction in the map's own frame and its solid angle. Mitsuba's
    envmap maps u = atan2(x, -z) / 2 pi and v = acos(y) / pi, with column centres at
    (c + 0.5) / w but rows at r / (h - 1): the first and last rows sit on the poles."""
    theta = np.arange(height) / (height - 1) * np.pi
    phi = (np.arange(width) + 0.5) / width * 2 * np.pi
    edges = np.clip((np.arange(height + 1) - 0.5) / (height - 1) * np.pi, 0, np.pi)
    band = np.cos(edges[:-1]) - np.cos(edges[1:])
    theta, phi = np.meshgrid(theta, phi, indexing="ij")
    local = np.stack([np.sin(phi) * np.sin(theta), np.cos(theta), -np.cos(phi) * np.sin(theta)], -1)
    solid_angle = np.broadcast_to((2 * np.pi / width) * band[:, None], theta.shape)
    return local, solid_angle


@dataclass(frozen=True)
class Surface:
    """Where a light's level was measured, as the light sees it: unit normals (n, 3) in
    the light's frame, each with the weight of its part in the measurement."""

    normals: np.ndarray
    weights: np.ndarray


def measured_surface(level_from: str, mesh, poses: dict[str, Pose], frame: str, faces: int = 2000) -> Surface:
    """The surface the scene stage measured the level on (scene.json's ``level_from``):
    the board, facing up (+z of the world); or the specimen (``mesh``, in world
    coordinates): up to ``faces`` of its faces, each as often as a camera faces it,
    weighted by its area as that camera sees it (occlusion ignored). With a light that
    rides with the camera, each photo's normals in its camera's coordinates."""
    if level_from == "board":
        up = (np.array([[0.0, 0.0, 1.0]]), np.ones(1))
        seen = {name: up for name in poses}
    else:
        chosen = np.random.default_rng(0).choice(len(mesh.faces), min(faces, len(mesh.faces)), replace=False)
        centres, normals, areas = mesh.triangles_center[chosen], mesh.face_normals[chosen], mesh.area_faces[chosen]
        seen = {}
        for name, pose in poses.items():
            towards = pose.center - centres
            facing = np.einsum("ij,ij->i", normals, towards) / np.linalg.norm(towards, axis=1)
            seen[name] = (normals[facing > 0], areas[facing > 0] * facing[facing > 0])
    rotations = {name: np.eye(3) if frame == "world" else pose.R for name, pose in poses.items()}
    return Surface(
        np.concatenate([normals @ rotations[name].T for name, (normals, _) in seen.items()]),
        np.concatenate([weights for normals, weights in seen.values()]),
    )


def level_weights(height: int, width: int, frame: str, surface: Surface) -> np.ndarray:
    """(height, width) weights summing to 1: each texel's share of the irradiance on
    ``surface`` under a uniform map (its solid angle times its mean cosine with the
    surface's normals), so that a uniform map's weighted mean is its radiance."""
    weights = np.zeros(height * width)
    for chunk in range(0, len(surface.normals), 4096):  # (normals, texels) at a time
        part = slice(chunk, chunk + 4096)
        weights += surface.weights[part] @ _texel_shares(surface.normals[part], height, width, frame)
    return (weights / weights.sum()).reshape(height, width)


def _texel_shares(normals: np.ndarray, height: int, width: int, frame: str, above: bool = False) -> np.ndarray:
    """(n, texels): what each texel of a map in ``frame`` gives, per unit radiance, to the
    irradiance on surfaces facing ``normals`` (solid angle times cosine); ``above``: only
    texels above the horizon (+z of the light's frame)."""
    local, solid_angle = directions(height, width)
    texel_directions = local.reshape(-1, 3) @ map_to_frame(frame).T
    solid_angle = solid_angle.ravel() * (texel_directions[:, 2] > 0 if above else 1.0)
    return np.clip(normals @ texel_directions.T, 0, None) * solid_angle


def map_to_frame(frame: str) -> np.ndarray:
    """Rotation from the map's frame to the light's (world, or the camera's coordinates)."""
    return capture_scene.environment_to_world(frame, Pose(np.eye(3), np.zeros(3)))[:3, :3]


def specimen_sphere(vertices: np.ndarray, light: LightSection, poses: dict[str, Pose]) -> tuple[np.ndarray, float]:
    """(centre in the light's frame, the softbox's distance) for with_area: the centre of
    the specimen's bounding box (in the first photo's camera coordinates when the light
    rides with the camera) and ``light.area_distance`` times the radius about it."""
    centre = (vertices.min(axis=0) + vertices.max(axis=0)) / 2
    radius = float(np.max(np.linalg.norm(vertices - centre, axis=1)))
    if light.frame == "camera":
        pose = poses[sorted(poses)[0]]
        centre = pose.R @ centre + pose.t
    return centre, light.area_distance * radius


def with_area(light: EstimatedLight, centre: np.ndarray, distance: float) -> EstimatedLight:
    """The envmap's brightest lobe (texels above half the peak's luminance within 45
    degrees of it) as a square softbox at ``distance`` from ``centre`` (in the light's
    frame) subtending the lobe's solid angle, with the lobe's radiance above the rest of
    the map; the lobe's texels fall to the rest's median."""
    environment = light.environment
    height, width = environment.shape[:2]
    local, solid_angle = directions(height, width)
    luminance = environment @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    peak = np.unravel_index(int(np.argmax(luminance)), luminance.shape)
    near = local @ local[peak] > np.cos(np.radians(45))
    lobe = near & (luminance > 0.5 * luminance[peak])
    rest = np.median(environment[~lobe], axis=0)
    weights = solid_angle[lobe]
    lobe_radiance = np.clip((environment[lobe] * weights[:, None]).sum(axis=0) / weights.sum() - rest, 1e-4, None)
    direction = map_to_frame(light.frame) @ ((local[lobe] * weights[:, None]).sum(axis=0))
    direction /= np.linalg.norm(direction)
    size = distance * float(np.sqrt(weights.sum()))
    position = np.asarray(centre, float) + distance * direction
    cleared = environment.copy()
    cleared[lobe] = rest
    area = AreaLight(
        tuple(float(v) for v in position),
        tuple(float(v) for v in centre),
        size,
        tuple(float(v) for v in lobe_radiance),
    )
    return replace(light, model="envmap+area", environment=cleared, area=area)


def irradiance(light: EstimatedLight, normals: np.ndarray, point: np.ndarray, above: bool = False) -> np.ndarray:
    """(n, 3) RGB irradiance at ``point`` on surfaces facing ``normals`` (n, 3), in the
    light's frame, with nothing in the way: the environment summed over its texels (a
    constant one over a fine grid), the softbox as a small patch. ``above``: only light
    arriving from above (+z: what a table leaves of a world-fixed light)."""
    environment = light.environment
    if environment.shape[:2] == (1, 1):
        environment = np.broadcast_to(environment, (129, 256, 3))
    shares = _texel_shares(normals, *environment.shape[:2], light.frame, above)
    result = shares @ environment.reshape(-1, 3)
    if light.area is not None:
        area = light.area
        offset = np.asarray(area.position) - np.asarray(point)
        distance = np.linalg.norm(offset)
        towards = offset / distance
        facing = np.asarray(area.target) - np.asarray(area.position)
        emitted = max(0.0, float(-towards @ facing) / np.linalg.norm(facing)) * area.size**2 / distance**2
        result = result + np.clip(normals @ towards, 0, None)[:, None] * emitted * np.asarray(area.radiance)
    return result


def render_unit_light(scene_file: Path):
    """``scene_file`` loaded with its lights replaced by a unit constant environment: its
    renders measure the level at which the scene looks like the photos."""
    import mitsuba as mi

    tree = ET.parse(scene_file)
    root = tree.getroot()
    for element in [e for e in root if e.get("id") in LIGHT_IDS]:
        root.remove(element)
    scene_xml.plugin(root, "emitter", {"type": "constant", "id": "environment", "radiance": (1.0, 1.0, 1.0)})
    unit = scene_file.with_name(f".unit-{scene_file.name}")
    scene_xml.write(root, unit)
    try:
        return mi.load_file(str(unit))
    finally:
        unit.unlink()
