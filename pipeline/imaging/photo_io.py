"""Reading photos the way the pipeline needs them, through OpenImageIO and LibRaw.

Every reader returns linear-radiance float32 RGB, upright (EXIF orientation
applied), whatever the file: 8-bit JPEG or PNG and 16-bit TIFF are sRGB-encoded
unless their metadata says linear; EXR and float TIFF are linear. Camera RAW files
(DNG, CR2, CR3, NEF, ARW, ...) are developed by LibRaw (rawpy) straight to linear
sRGB primaries: black level subtracted, scaled by the white level, the camera's
as-shot white balance applied, no tone curve, no brightening, so a value of 1 is the
sensor's clipping point. The white balance, levels and exposure are recorded in the
photo's metadata (``raw:*`` and the EXIF names). Where a RAW file and a JPEG share a
name (RAW+JPEG shooting), the RAW is read and the JPEG left out. HEIC/HEIF (phones)
is decoded by libheif (pillow-heif), its 8 or 10 bits taken through the sRGB curve
and from the primaries its colour profile names (Display P3 on most phones) to linear
sRGB primaries; libheif turns the pixels upright.
"""

from __future__ import annotations

import errno
import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import OpenImageIO as oiio
import rawpy

from pipeline import logger
from pipeline.core.errors import PipelineError

FREE_MARGIN_BYTES = 16 << 20
"""Free space below which a failed image write is put down to a full disk."""
RAW_SUFFIXES = (".dng", ".cr2", ".cr3", ".crw", ".nef", ".nrw", ".arw", ".orf", ".rw2", ".raf", ".pef", ".srw", ".3fr")
"""Camera RAW formats, read through LibRaw."""
HEIF_SUFFIXES = (".heic", ".heif", ".hif")
"""High-efficiency image files (phones), read through libheif."""
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".exr", *RAW_SUFFIXES, *HEIF_SUFFIXES)
EXIF_NAMES = {
    "Make": "Make",
    "Model": "Model",
    "FocalLength": "Exif:FocalLength",
    "FocalLengthIn35mmFilm": "Exif:FocalLengthIn35mmFilm",
    "FocalPlaneXResolution": "Exif:FocalPlaneXResolution",
    "FocalPlaneYResolution": "Exif:FocalPlaneYResolution",
    "FocalPlaneResolutionUnit": "Exif:FocalPlaneResolutionUnit",
    "ExposureTime": "ExposureTime",
    "FNumber": "FNumber",
    "ISOSpeedRatings": "Exif:ISOSpeedRatings",
}
"""EXIF tags a HEIF file's metadata is read for, by PIL's name -> OpenImageIO's."""
SRGB_PRIMARIES = ((0.64, 0.33), (0.30, 0.60), (0.15, 0.06), (0.3127, 0.3290))
Encoding = Literal["auto", "srgb", "linear"]


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    linear = np.clip(linear, 0.0, 1.0)
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(linear, 1 / 2.4) - 0.055)


def srgb_decode(encoded: np.ndarray) -> np.ndarray:
    return np.where(encoded <= 0.04045, encoded / 12.92, np.power((encoded + 0.055) / 1.055, 2.4)).astype(encoded.dtype)


def to_uint8(linear: np.ndarray) -> np.ndarray:
    """8-bit sRGB for feature matching, previews and PNG masks."""
    return np.round(srgb_encode(linear) * 255).astype(np.uint8)


def gray_uint8(linear: np.ndarray) -> np.ndarray:
    return np.round(srgb_encode(linear.mean(axis=-1)) * 255).astype(np.uint8)


def is_raw(path: Path) -> bool:
    return path.suffix.lower() in RAW_SUFFIXES


def photo_files(paths: list[Path]) -> list[Path]:
    """The photos among ``paths``, sorted: files with a photo suffix, less each one that
    has a RAW twin (same folder and name, RAW+JPEG shooting): the RAW is the photo."""
    photos = sorted(p for p in paths if p.is_file() and p.suffix.lower() in PHOTO_SUFFIXES)
    raw = {p.with_suffix("") for p in photos if is_raw(p)}
    twins = [p for p in photos if not is_raw(p) and p.with_suffix("") in raw]
    if twins:
        logger.info("%d photo(s) have a RAW twin, which is read instead (%s, ...)", len(twins), twins[0].name)
    return [p for p in photos if p not in twins]


UNREAD_NAMED = 5
"""Files a warning about unread files names one by one; the rest are counted."""


def folder_entries(folder: Path) -> list[Path]:
    """What sits directly in ``folder`` ([] when it does not exist); one that cannot be
    listed is a user error naming it, never "no photos"."""
    if not folder.is_dir():
        return []
    try:
        return list(folder.iterdir())
    except PermissionError as error:
        raise PipelineError(
            f"{folder} cannot be read ({error.strerror}): give yourself permission to list it (chmod u+rx)"
        ) from None


def list_photos(folder: Path) -> list[Path]:
    """The photos directly in ``folder`` (``photo_files``); [] when it does not exist."""
    return photo_files(folder_entries(folder))


def unsupported_files(folder: Path) -> list[Path]:
    """What sits directly in ``folder`` and is not a photo the pipeline reads (PSD, XMP
    sidecars, a FIFO named .jpg...), sorted; hidden files are left out."""
    return sorted(
        p
        for p in folder_entries(folder)
        if not p.name.startswith(".") and not p.is_dir() and not (p.is_file() and p.suffix.lower() in PHOTO_SUFFIXES)
    )


def warn_unread(folder: Path, what: str = "photo") -> None:
    """Warn about ``unsupported_files(folder)``, which the stage reading ``folder`` leaves
    out: the first few by name, then how many more, so that a folder of thousands of
    other files gives a few lines, not thousands."""
    unread = unsupported_files(folder)
    for path in unread[:UNREAD_NAMED]:
        logger.warning(
            "%s is not a %s the pipeline reads (it reads %s): left out; convert it or move it away",
            path,
            what,
            ", ".join(PHOTO_SUFFIXES),
        )
    if len(unread) > UNREAD_NAMED:
        logger.warning(
            "%d more files in %s are not %ss the pipeline reads: left out", len(unread) - UNREAD_NAMED, folder, what
        )


@dataclass
class Photo:
    pixels: np.ndarray
    """Linear RGB, float32, (height, width, 3), upright."""
    metadata: dict[str, object]
    """EXIF and format attributes as OpenImageIO names them (``Make``, ``Exif:FocalLength``...)."""
    encoding: Literal["srgb", "linear"]
    """How the file's values were decoded."""
    bits: int
    """Bits per channel in the file."""

    @property
    def size(self) -> tuple[int, int]:
        return self.pixels.shape[1], self.pixels.shape[0]


def _raw_metadata(path: Path, raw: rawpy.RawPy) -> dict[str, object]:
    """EXIF read by OpenImageIO from the RAW's TIFF structure where it has one (DNG, CR2,
    NEF...), completed by LibRaw's own reading and the development's levels."""
    image = oiio.ImageInput.open(str(path))
    metadata: dict[str, object] = {}
    if image is not None:  # the attributes of the first image: often the preview's size, not kept
        metadata = {a.name: a.value for a in image.spec().extra_attribs if not a.name.startswith(("oiio:", "tiff:"))}
        image.close()
    metadata.pop("Orientation", None)  # LibRaw turns the pixels upright itself
    other = raw.other
    for name, value in (
        ("Exif:FocalLength", other.focal_length),
        ("ExposureTime", other.shutter_speed),  # seconds
        ("Exif:ISOSpeedRatings", other.iso_speed),
        ("FNumber", other.aperture),
    ):
        if value and name not in metadata:
            metadata[name] = float(value)
    balance = np.asarray(raw.camera_whitebalance[:3], dtype=float)
    if balance[1] > 0:
        metadata["raw:WhiteBalance"] = [float(v) for v in balance / balance[1]]
    metadata["raw:BlackLevel"] = [float(v) for v in raw.black_level_per_channel]
    metadata["raw:WhiteLevel"] = float(raw.white_level)
    return metadata


def _raw_size(raw: rawpy.RawPy) -> tuple[int, int]:
    """The developed image's upright (width, height)."""
    sizes = raw.sizes
    return (sizes.height, sizes.width) if sizes.flip in (5, 6) else (sizes.width, sizes.height)


@contextmanager
def _open_raw(path: Path) -> Iterator[rawpy.RawPy]:
    """The RAW file opened by LibRaw; its errors (here or while unpacking) are the user's."""
    try:
        with rawpy.imread(str(path)) as raw:
            yield raw
    except (rawpy.LibRawError, OSError) as error:
        raise PipelineError(
            f"{path}: cannot read this RAW file ({error}); remove it, or replace it by a TIFF from your RAW converter"
        ) from error


def _rgb_to_xyz(primaries) -> np.ndarray:
    """The linear RGB -> XYZ matrix of red, green, blue and white chromaticities (x, y)."""
    columns = np.array([[x / y, 1.0, (1 - x - y) / y] for x, y in primaries[:3]]).T
    x, y = primaries[3]
    white = np.array([x / y, 1.0, (1 - x - y) / y])
    return columns * np.linalg.solve(columns, white)


def _open_heif(path: Path):
    import pillow_heif

    try:
        return pillow_heif.open_heif(str(path), convert_hdr_to_8bit=False)
    except (ValueError, RuntimeError, OSError) as error:
        raise PipelineError(f"{path}: cannot read this HEIF file ({error}); remove it or export it as JPEG") from error


def _heif_metadata(heif) -> dict[str, object]:
    from PIL import Image

    exif = Image.Exif()
    if heif.info.get("exif"):
        exif.load(heif.info["exif"])
    tags = {**dict(exif.items()), **dict(exif.get_ifd(0x8769).items())}  # IFD0 and the Exif IFD
    names = {Image.ExifTags.TAGS.get(tag, ""): value for tag, value in tags.items()}
    metadata: dict[str, object] = {}
    for name, attribute in EXIF_NAMES.items():
        if name in names and names[name] not in (None, ""):
            value = names[name]
            metadata[attribute] = str(value).strip("\x00 ") if isinstance(value, str) else float(value)
    return metadata


def _heif_to_srgb_primaries(heif) -> np.ndarray | None:
    """The matrix from the file's linear primaries to sRGB's, None when they are sRGB's."""
    nclx = heif.info.get("nclx_profile") or {}
    if "color_primary_red_x" in nclx:
        primaries = tuple(
            (nclx[f"color_primary_{c}_x"], nclx[f"color_primary_{c}_y"]) for c in ("red", "green", "blue", "white")
        )
        if np.allclose(primaries, SRGB_PRIMARIES, atol=2e-3):
            return None
        return np.linalg.solve(_rgb_to_xyz(SRGB_PRIMARIES), _rgb_to_xyz(primaries))
    if heif.info.get("icc_profile"):
        return _icc_to_srgb_primaries(heif.info["icc_profile"])
    return None


def _icc_to_srgb_primaries(icc: bytes) -> np.ndarray | None:
    """The matrix of a matrix-shaper ICC profile (its rXYZ, gXYZ, bXYZ, D50-adapted) to
    linear sRGB; None for sRGB itself or a profile without those tags."""
    import struct

    count = struct.unpack(">I", icc[128:132])[0]
    tags = {}
    for index in range(count):
        signature, offset, size = struct.unpack(">4sII", icc[132 + 12 * index : 144 + 12 * index])
        tags[signature] = icc[offset : offset + size]
    if not all(t in tags for t in (b"rXYZ", b"gXYZ", b"bXYZ")):
        return None
    columns = np.array(
        [[v / 65536 for v in struct.unpack(">3i", tags[t][8:20])] for t in (b"rXYZ", b"gXYZ", b"bXYZ")]
    ).T
    # Bradford-adapted sRGB in the profile connection space (D50), as ICC's sRGB profile holds it.
    srgb_d50 = np.array(
        [[0.4360747, 0.3850649, 0.1430804], [0.2225045, 0.7168786, 0.0606169], [0.0139322, 0.0971045, 0.7141733]]
    )
    if np.allclose(columns, srgb_d50, atol=2e-3):
        return None
    return np.linalg.solve(srgb_d50, columns)


def _read_heif(path: Path, reduce: int) -> Photo:
    heif = _open_heif(path)
    bits = int(heif.info.get("bit_depth", 8))
    pixels = np.asarray(heif, dtype=np.float32)[..., :3] / np.float32(2**bits - 1 if bits <= 8 else 65535)
    pixels = srgb_decode(np.clip(pixels, np.float32(0.0), np.float32(1.0)))
    to_srgb = _heif_to_srgb_primaries(heif)
    if to_srgb is not None:
        pixels = np.maximum(pixels @ to_srgb.T.astype(np.float32), np.float32(0.0))
    height, width = pixels.shape[0] // reduce, pixels.shape[1] // reduce
    pixels = pixels[: height * reduce, : width * reduce].reshape(height, reduce, width, reduce, 3).mean(axis=(1, 3))
    return Photo(np.ascontiguousarray(pixels, dtype=np.float32), _heif_metadata(heif), "srgb", bits)


def read_metadata(path: Path) -> tuple[dict[str, object], tuple[int, int]]:
    """(attributes, upright (width, height)) without decoding the pixels."""
    if path.suffix.lower() in HEIF_SUFFIXES:
        heif = _open_heif(path)
        return _heif_metadata(heif), heif.size
    if is_raw(path):
        with _open_raw(path) as raw:
            return _raw_metadata(path, raw), _raw_size(raw)
    image = oiio.ImageInput.open(str(path))
    if image is None:
        raise PipelineError(f"{path}: cannot read this image ({oiio.geterror()}); remove or replace it")
    spec = image.spec()
    image.close()
    metadata = {attribute.name: attribute.value for attribute in spec.extra_attribs}
    width, height = spec.width, spec.height
    if int(metadata.get("Orientation", 1)) in (5, 6, 7, 8):  # rotated by 90 degrees
        width, height = height, width
    return metadata, (width, height)


STRIP_ROWS = 64
"""Scanlines decoded at a time: memory for a photo stays that strip plus the result."""


def _orient(pixels: np.ndarray, orientation: int) -> np.ndarray:
    """Pixels as stored -> upright, for EXIF orientations 1-8."""
    if orientation in (5, 6, 7, 8):
        pixels = np.swapaxes(pixels, 0, 1)  # transpose: 5 as is, the others one flip more
        flips = {5: (), 6: (1,), 7: (0, 1), 8: (0,)}[orientation]
    else:
        flips = {1: (), 2: (1,), 3: (0, 1), 4: (0,)}.get(orientation, ())
    return np.flip(pixels, flips) if flips else pixels


def read_photo(path: Path, encoding: Encoding = "auto", reduce: int = 1) -> Photo:
    """Decode ``path`` to upright linear RGB, box-filtered down by the integer factor
    ``reduce`` while decoding: scanlines are read a strip at a time, so a huge photo is
    never held whole at full size. A file OpenImageIO cannot read is a user error."""
    if is_raw(path):
        return _read_raw(path, reduce)
    if path.suffix.lower() in HEIF_SUFFIXES:
        return _read_heif(path, reduce)
    unassociated = oiio.ImageSpec()
    unassociated.attribute("oiio:UnassociatedAlpha", 1)  # colour as stored, not multiplied by alpha
    image = oiio.ImageInput.open(str(path), unassociated)
    if image is None:
        raise PipelineError(f"{path}: cannot read this image ({oiio.geterror()}); remove or replace it")
    spec = image.spec()
    metadata = {attribute.name: attribute.value for attribute in spec.extra_attribs}
    width, height = spec.width // reduce * reduce, spec.height // reduce * reduce
    alpha = spec.alpha_channel
    channels = min(alpha if alpha > 0 else spec.nchannels, 3)
    is_float = spec.format.basetype in (oiio.HALF, oiio.FLOAT, oiio.DOUBLE)
    colour_space = str(metadata.get("oiio:ColorSpace", "")).lower()
    if encoding == "auto":
        encoding = "linear" if is_float or colour_space.startswith("lin") else "srgb"
    step = max(STRIP_ROWS // reduce, 1) * reduce
    strips = []
    for y in range(spec.y, spec.y + height, step):
        rows = min(step, spec.y + height - y)
        read = max(channels, alpha + 1)
        strip = image.read_scanlines(0, 0, y, y + rows, 0, 0, read, oiio.FLOAT)
        if strip is None or image.has_error:
            error = image.geterror()
            image.close()
            raise PipelineError(f"{path}: the image data is damaged ({error}); remove or replace it")
        strip = np.asarray(strip, dtype=np.float32).reshape(rows, spec.width, read)[:, :width]
        if alpha >= 0 and np.any(strip[..., alpha] < 1.0):
            image.close()
            raise PipelineError(
                f"{path} is partly transparent (an alpha channel below 1): the pipeline reads colour, not "
                "transparency. Save the photo without alpha, and if the alpha outlines the specimen, save it "
                "as the photo's mask in masks/ (same name, .png)"
            )
        strip = strip[..., :channels]
        if is_float and not np.isfinite(strip).all():
            bad = int(np.count_nonzero(~np.isfinite(strip).all(axis=-1)))
            image.close()
            raise PipelineError(
                f"{path}: {bad} pixel(s) in rows {y}-{y + rows - 1} are NaN or infinite, which no render can match: "
                "fix them in the file (e.g. replace them by their neighbours) or leave the file out"
            )
        if encoding == "srgb":
            strip = srgb_decode(np.clip(strip, np.float32(0.0), np.float32(1.0)))
        if reduce > 1:
            strip = strip.reshape(rows // reduce, reduce, width // reduce, reduce, channels).mean(axis=(1, 3))
        strips.append(strip)
    image.close()
    pixels = _orient(np.concatenate(strips), int(metadata.get("Orientation", 1)))
    pixels = np.repeat(pixels[..., :1], 3, axis=2) if channels < 3 else pixels
    return Photo(np.ascontiguousarray(pixels), metadata, encoding, spec.format.size() * 8)


def _read_raw(path: Path, reduce: int) -> Photo:
    """Develop a RAW file to linear sRGB primaries (see the module docstring)."""
    with _open_raw(path) as raw:
        metadata = _raw_metadata(path, raw)
        width, height = _raw_size(raw)
        # Half size takes each 2x2 Bayer block as one pixel: no demosaicing where the
        # caller reduces by an even factor anyway.
        half = reduce % 2 == 0
        developed = raw.postprocess(
            gamma=(1, 1),
            no_auto_bright=True,
            output_bps=16,
            use_camera_wb=True,
            output_color=rawpy.ColorSpace.sRGB,
            half_size=half,
            highlight_mode=rawpy.HighlightMode.Clip,
            adjust_maximum_thr=0.0,  # LibRaw would take a bright photo's maximum as white
        )
    pixels = developed.astype(np.float32) / np.float32(65535)
    step = reduce // 2 if half else reduce
    height, width = height // reduce, width // reduce
    pixels = pixels[: height * step, : width * step].reshape(height, step, width, step, 3).mean(axis=(1, 3))
    return Photo(np.ascontiguousarray(pixels), metadata, "linear", 16)


def write_image(path: Path, pixels: np.ndarray, attributes: dict[str, object] | None = None) -> Path:
    """Write uint8 (PNG, JPEG) or float (EXR, stored as half) pixels through OpenImageIO."""
    pixels = np.ascontiguousarray(pixels)
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    height, width, channels = pixels.shape
    is_float = pixels.dtype.kind == "f"
    spec = oiio.ImageSpec(width, height, channels, oiio.HALF if is_float else oiio.UINT8)
    if is_float:
        spec.attribute("compression", "zips")
    for name, value in (attributes or {}).items():
        spec.attribute(name, value)
    out = oiio.ImageOutput.create(str(path))
    if out is None or not out.open(str(path), spec) or not out.write_image(pixels) or not out.close():
        reason = oiio.geterror() or (out.geterror() if out is not None else "")
        # OpenImageIO does not pass on errno; a full disk is what leaves its reason empty.
        if shutil.disk_usage(path.parent).free < pixels.nbytes + FREE_MARGIN_BYTES:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        raise OSError(errno.EIO, f"could not write {path}: {reason or 'no reason given'}", str(path))
    return path


def camera_setting(metadata: dict[str, object], size: tuple[int, int]) -> str:
    """What must match for two photos to share intrinsics: camera body, zoom, image size.

    Photos without EXIF share one setting per image size.
    """
    body = " ".join(str(metadata[k]).strip() for k in ("Make", "Model") if metadata.get(k)) or "unknown camera"
    focal = metadata.get("Exif:FocalLength")
    zoom = f", f={float(focal):.2f} mm" if focal else ""
    return f"{body}{zoom}, {size[0]}x{size[1]}"
