"""Options of `pipeline synth`, apart from the renderer so the CLI starts fast."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

from pipeline.core.config import Range


@dataclass(frozen=True)
class SynthOptions:
    """Options of `pipeline synth`."""

    views: Annotated[int, Range(2, 400)] = 30
    """Number of photos of the specimen."""
    rings: tuple[float, ...] = (18.0, 42.0)
    """Camera elevations in degrees; views are spread over these rings (one ring for a turntable)."""
    width: Annotated[int, Range(32, 4096)] = 560
    """Photo width in pixels."""
    height: Annotated[int, Range(32, 4096)] = 420
    """Photo height in pixels."""
    hfov: Annotated[float, Range(10.0, 120.0)] = 42.0
    """Horizontal field of view of the lens in degrees (before distortion)."""
    distortion: tuple[float, float, float, float, float] = (-0.09, 0.035, 0.0008, -0.0005, 0.0)
    """Lens distortion (k1, k2, p1, p2, k3), OpenCV's model; the default is a mild phone lens."""
    distance: Annotated[float, Range(0.05, 5.0)] = 0.36
    """Camera distance from the bird's centre in metres."""
    spp: Annotated[int, Range(1, 4096)] = 64
    """Samples per pixel of the specimen renders."""
    material: Literal["principled", "volumetric", "glossy_paint"] = "principled"
    """principled: Disney BSDF with specular transmission; volumetric: rough dielectric
    boundary around a homogeneous scattering medium; glossy_paint: an opaque painted
    figurine (principled, no transmission, low roughness: highlights that move over it)."""
    texture: Literal["blotches", "speckles", "plain"] = "blotches"
    """blotches: mottled base colour that gives feature points; speckles: the same pattern
    at a third of the size, for a specimen small in the frame; plain: a low-texture specimen.
    Principled and glossy_paint only: the volumetric specimen is a homogeneous medium, untextured."""
    table: Literal["board", "dots", "grey"] = "board"
    """What the specimen stands on: board, the capture's ChArUco board printed on a grey plate;
    dots, a dark plate with sparse white dots (a turntable without a board); grey, a plain
    grey plate."""
    backdrop: Literal["studio", "room", "white", "dark"] = "studio"
    """What is seen behind the specimen: studio, the constant environment (a plain grey
    surround); room, a textured room (an environment map that also lights the scene), still
    while a turntable turns; white, photos cut out on white (everything but the specimen
    replaced by white, as a matting tool leaves them); dark, a studio hung with black cloth:
    the surround nearly black, the softbox the only light."""
    exif_focal: bool = True
    """Write the focal length into the photos' EXIF; False: a camera or tool that strips it."""
    rig: Literal["handheld", "turntable"] = "handheld"
    """handheld: camera moves, light fixed in the world; turntable: the object turns."""
    turn_jitter: Annotated[float, Range(0.0, 0.9)] = 0.0
    """Turntable only: random unevenness of the steps, as a fraction of the mean step."""
    turn_alternation: Annotated[float, Range(1.0, 4.0)] = 1.0
    """Turntable only: every second step is this many times longer than the one before (a
    table turned by hand in short and long steps); 1: no alternation."""
    turn_restart_deg: Annotated[float, Range(0.0, 90.0)] = 0.0
    """Turntable only: half-way through the photos the table goes back by this many degrees
    (a capture restarted part-way): file order is not turning order there."""
    extra_turn: Annotated[float, Range(0.0, 1.0)] = 0.0
    """Turntable only: the photos cover one turn and this fraction of a second one."""
    wobble: Annotated[float, Range(0.0, 0.1)] = 0.0
    """Turntable only: the specimen shifts on the table half-way through the photos, so that
    the camera's height above it changes by this fraction of the camera's distance: the
    photos no longer lie on one circle."""
    set_views: tuple[int, ...] = ()
    """Turntable only: the photos shot in several sets (rings), this many in each, in file
    order (they sum to ``views``); empty: one set. Set k's camera stands at elevation
    ``rings[k]`` (the last ring where fewer are given); each set turns once (plus
    ``extra_turn``) from where the one before ended, less its ``set_restarts_deg``."""
    set_distances: tuple[float, ...] = ()
    """Turntable sets only: each set's camera distance as a multiple of ``distance`` (1
    where not given): a tripod moved nearer or farther."""
    set_rolls_deg: tuple[float, ...] = ()
    """Turntable sets only: each set's camera turned about its optical axis by this many
    degrees (0 where not given): a tripod head re-levelled."""
    set_restarts_deg: tuple[float, ...] = ()
    """Turntable sets only: each set starts this many degrees back from where the set
    before it ended (the first set's value is not used; 0 where not given)."""
    sets_turned_over: tuple[int, ...] = ()
    """Turntable sets only: the numbers (1 = the first) of the sets shot with the specimen
    turned over on the table (turned 180 degrees about a horizontal axis through its
    centre): its underside up."""
    specimen: Literal["bird", "vase"] = "bird"
    """bird: the procedural bird figurine; vase: a body of revolution about the table's
    axis, its outline the same from every side of a turn (features alone can fix its
    angle)."""
    calibration_shots: Annotated[int, Range(0, 100)] = 12
    """Number of ChArUco board photos written to calibration/."""
    background_plates: bool = False
    """Also render every view without the specimen into background/, as plates shot from a
    tripod at each camera position."""
    noise: Annotated[float, Range(0.0, 10.0)] = 1.0
    """Sensor noise level: 1 is a good camera at base ISO, 0 disables noise."""
    jpeg_quality: Annotated[int, Range(50, 100)] = 92
    """JPEG quality of the written photos."""
    seed: int = 0
    """Seed for the texture, camera jitter, turntable steps and noise."""
