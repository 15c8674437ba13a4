"""Config sections shared by several stages, mostly written by the user in capture.toml.

A stage's own section is its ``Config`` dataclass; the sections here describe the
capture (rig, board, light) and the machine (Mitsuba variant). A stage lists the
sections, or single settings (``capture.rig``), it reads in ``Stage.shared`` so that
they, and only they, enter its cache key.
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass
from typing import Annotated, Literal, Sequence

from pipeline.core.config import InputFile, Range
from pipeline.core.stage import Stage

Vec3 = tuple[float, float, float]
ENVIRONMENT_MAP_SUFFIXES = (".exr", ".tif", ".tiff", ".png", ".jpg", ".jpeg")
"""What an environment map may be: the photo formats that hold an image, RAW and HEIF
aside (pipeline.imaging.photo_io reads it)."""
RadianceChannel = Annotated[float, Range(0.0, 1e9)]
Radiance = tuple[RadianceChannel, RadianceChannel, RadianceChannel]
"""Linear RGB radiance: no channel below zero (a negative one has no physical meaning,
and the fits would bend the material to make up for it) nor above 1e9. Mitsuba renders
in float32 (at most 3.4e38) and the fits square rendered values and sum them over a
window's pixels: a radiance of 3e38 rendered NaN and ended fit_material on a
non-finite result, while 1e9 squared and summed over a million pixels is 1e24. The
photos are levelled near 1."""
ArucoDictionary = Literal["DICT_4X4_50", "DICT_4X4_100", "DICT_5X5_100", "DICT_6X6_250"]


@dataclass(frozen=True)
class CaptureSection:
    """What was photographed and how."""

    description: str = ""
    """Free text: specimen, date, camera; kept with the results."""
    rig: Literal["handheld", "turntable", "ring"] = "handheld"
    """handheld: the camera moves freely around a still object. turntable: camera and
    light stay fixed while the object turns about one axis; photos are ordered by file
    name. ring: the camera is carried round a still object on one circle (a gantry, a
    robot arm), in any order. Turntable and ring poses are solved as one circular motion."""
    material: Literal["auto", "opaque", "principled", "volumetric"] = "auto"
    """Material model hint. opaque: diffuse/principled without transmission;
    principled: surface translucency (spec_trans, eta); volumetric: rough dielectric
    with a homogeneous medium. auto lets the fitting stages decide."""


@dataclass(frozen=True)
class BoardSection:
    """The printed ChArUco (or checkerboard) board used for calibration and scale."""

    kind: Literal["charuco", "checkerboard", "none"] = "charuco"
    """Pattern type; none when no board was photographed."""
    squares_x: Annotated[int, Range(3, 40)] = 7
    """Squares along the board's width."""
    squares_y: Annotated[int, Range(3, 40)] = 5
    """Squares along the board's height."""
    square_mm: Annotated[float, Range(0.0, None, exclusive_lo=True)] = 30.0
    """Printed side length of one square, in millimetres (measure the print)."""
    marker_mm: Annotated[float, Range(0.0, None, exclusive_lo=True)] = 22.0
    """Printed side length of one ArUco marker, in millimetres (ChArUco only)."""
    dictionary: ArucoDictionary = "DICT_5X5_100"
    """ArUco dictionary the markers come from (ChArUco only)."""

    def validate(self, name: str) -> None:
        from pipeline.core.errors import ConfigError

        if self.kind == "charuco" and self.marker_mm >= self.square_mm:
            raise ConfigError(
                f"{name}.marker_mm = {self.marker_mm} must be smaller than {name}.square_mm = {self.square_mm}"
            )
        markers = self.squares_x * self.squares_y // 2
        available = int(self.dictionary.rsplit("_", 1)[-1])
        if self.kind == "charuco" and markers > available:
            larger = [d for d in typing.get_args(ArucoDictionary) if int(d.rsplit("_", 1)[-1]) >= markers]
            fix = f"set {name}.dictionary = {larger[0]!r}" if larger else "use fewer squares"
            raise ConfigError(
                f"{name}: {self.squares_x} x {self.squares_y} squares hold {markers} markers, but "
                f"{name}.dictionary = {self.dictionary!r} has {available}: {fix}"
            )


@dataclass(frozen=True)
class LightSection:
    """The light rig: an environment plus at most one rectangular area light, given, or
    estimated from the photos along with the material (pipeline.render.light)."""

    model: Literal["auto", "constant", "envmap", "envmap+area", "given"] = "auto"
    """given: the rig below as it is (a measured light; an environment_map always is).
    constant, envmap (a lat-long map), envmap+area (and a softbox on the map's brightest
    lobe): estimated by fit_material, jointly with the material, then kept for texture and
    geometry. auto: each of those, simplest first, and the simplest whose held-out error is
    within ``margin`` of the best is kept."""
    environment_radiance: Radiance = (0.5, 0.5, 0.5)
    """Constant environment radiance (linear RGB), used when environment_map is empty."""
    environment_map: Annotated[str, InputFile(suffixes=ENVIRONMENT_MAP_SUFFIXES)] = ""
    """Path of an equirectangular image (.exr, or .tif, .png, .jpg as pipeline.imaging
    reads photos), relative to the capture folder (a file outside it only from the
    command line); empty for none."""
    area_light: bool = True
    """Whether a rectangular area light (a softbox) is part of the rig."""
    area_position: Vec3 = (0.6, 0.8, 0.6)
    """Centre of the area light in metres, in the frame given by `frame`."""
    area_target: Vec3 = (0.0, 0.0, 0.0)
    """Point the area light faces, in the same frame."""
    area_size: Annotated[float, Range(0.0, None, exclusive_lo=True)] = 0.4
    """Side length of the square area light, in metres."""
    area_radiance: Radiance = (6.0, 6.0, 6.0)
    """Emitted radiance of the area light (linear RGB)."""
    frame: Literal["world", "camera"] = "world"
    """world: the light is fixed in the specimen's frame (handheld capture).
    camera: it stays fixed relative to the camera (turntable capture)."""
    environment_width: Annotated[int, Range(4, 512)] = 32
    """Texels along an estimated envmap's width (its height is half)."""
    smoothness: Annotated[float, Range(0.0, None)] = 1e-3
    """Weight of the prior on differences of neighbouring texels' log radiance."""
    margin: Annotated[float, Range(0.0, 1.0)] = 0.05
    """auto: a richer light model is kept only when it lowers the held-out error by more
    than this fraction."""
    area_distance: Annotated[float, Range(1.0, None)] = 10.0
    """Distance of an estimated softbox from the specimen's centre, in specimen radii."""

    def validate(self, name: str) -> None:
        from pipeline.core.errors import ConfigError

        if self.environment_map and self.model not in ("given", "auto"):
            raise ConfigError(
                f'{name}.environment_map is set, so the light is given: set {name}.model = "given" '
                f'(or "auto"), or empty environment_map to estimate the light'
            )

    @property
    def estimated(self) -> bool:
        """Whether the fit estimates the light (an environment map, when given, wins)."""
        return self.model != "given" and not self.environment_map


@dataclass(frozen=True)
class CamerasSection:
    """Cameras from another tool, instead of calibration and structure-from-motion."""

    source: Annotated[str, InputFile(suffixes=(".bin", ".txt", ".xml"), folder_with=("cameras.bin", "cameras.txt"))] = (
        ""
    )
    """A COLMAP sparse model (its folder, .bin or .txt) or an Agisoft Metashape cameras
    XML export, relative to the capture folder; empty: the pipeline computes the
    cameras. Its intrinsics replace calibrate's and its poses sfm's (moved into the
    pipeline's world frame); see pipeline/formats/external_cameras.py for the
    conventions."""


@dataclass(frozen=True)
class MitsubaSection:
    """How Mitsuba runs on this machine."""

    variant: Literal["auto", "cuda_ad_rgb", "llvm_ad_rgb"] = "auto"
    """auto: cuda_ad_rgb when a CUDA device works, else llvm_ad_rgb. The environment
    variable PIPELINE_MITSUBA_VARIANT overrides this setting."""


SHARED_SECTIONS: dict[str, type] = {
    "capture": CaptureSection,
    "board": BoardSection,
    "light": LightSection,
    "cameras": CamerasSection,
    "mitsuba": MitsubaSection,
}


def schema(stages: Sequence[Stage]) -> dict[str, type]:
    """Every config section: the shared ones, then one per stage."""
    sections = dict(SHARED_SECTIONS)
    for stage in stages:
        if stage.name in sections:
            raise ValueError(f"stage {stage.name} clashes with a shared config section")
        sections[stage.name] = stage.config
    for stage in stages:
        for name in stage.shared:
            section, _, setting = name.partition(".")
            if section not in SHARED_SECTIONS or (
                setting and setting not in {f.name for f in dataclasses.fields(SHARED_SECTIONS[section])}
            ):
                raise ValueError(f"stage {stage.name} shares {name}: no such shared section or setting")
    return sections
