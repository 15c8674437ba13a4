"""What a fit stage writes beside its scene: held-out renders, texture files, the
log and its plot (file names in pipeline.formats.scene_folder)."""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np

from pipeline.core.errors import require_finite
from pipeline.fit import engine
from pipeline.formats.scene_folder import LOG_JSONL, LOSS_PNG, heldout_files, write_log
from pipeline.imaging.photo_io import to_uint8, write_image
from pipeline.render import materials

HELDOUT_SPP = 1024
"""Samples per pixel of the held-out renders written and scored: enough that their PSNR
measures the scene, not Monte Carlo noise (a glossy fit under an environment map still
gains several dB from 128 to 1024 spp; a diffuse one is converged by 256)."""


def write_heldout(views: list[engine.FitView], folder: Path) -> None:
    """Each view's render at HELDOUT_SPP (fixed seeds), its reference and the pixels scored;
    and to look at, the reference, the render and their absolute difference (four times
    brighter) as sRGB PNGs."""
    import mitsuba as mi

    folder.mkdir()
    for index, view in enumerate(views):
        seed = 10_000 + index
        render = mi.render(view.scene, sensor=view.sensor, integrator=view.integrator, spp=HELDOUT_SPP, seed=seed)
        # a held-out photo's known gain: the render as the photo's exposure shows it
        image = np.asarray(render, dtype=np.float32) * np.float32(1.0 if view.gain is None else view.gain)
        render_path, reference_path, mask_path = heldout_files(folder, view.name)
        write_image(render_path, image)
        write_image(reference_path, view.reference)
        cv2.imwrite(str(mask_path), (view.weight > 0).astype(np.uint8) * 255)
        pictures = {"reference": view.reference, "render": image, "difference": 4 * np.abs(image - view.reference)}
        for kind, picture in pictures.items():
            cv2.imwrite(str(folder / f"{view.name}.{kind}.png"), to_uint8(np.clip(picture, 0, 1))[..., ::-1])


def write_texture_files(folder: Path, slot: materials.TextureSlot, texture: np.ndarray) -> None:
    """The texture's data file (what the scene loads) and a PNG to look at, in ``folder``."""
    import mitsuba as mi

    require_finite(texture, str(folder / slot.parameter))
    name = slot.parameter
    if slot.kind == "bitmap":
        # float32, not write_image's half: the scene loads this file as the
        # starting point of the optimisation, which needs full precision.
        mi.Bitmap(np.ascontiguousarray(texture, dtype=np.float32)).write(str(folder / f"{name}.exr"))
        cv2.imwrite(str(folder / f"{name}.png"), to_uint8(texture)[..., ::-1])
        return
    write_volume_grid(folder / f"{name}.vol", texture)
    columns = int(np.ceil(np.sqrt(texture.shape[0])))
    slices = [texture[z] for z in range(texture.shape[0])]
    slices += [np.zeros_like(slices[0])] * (columns * columns - len(slices))
    rows = [np.concatenate(slices[r * columns : (r + 1) * columns], axis=1) for r in range(columns)]
    cv2.imwrite(str(folder / f"{name}.png"), to_uint8(np.concatenate(rows, axis=0)[::-1])[..., ::-1])


def write_volume_grid(path: Path, grid: np.ndarray) -> None:
    """``grid`` (z, y, x, channels) in Mitsuba's .vol format (version 3, float32, the
    unit box), written without Mitsuba: a stage may write its starting texture before
    it has chosen a Mitsuba variant, which ``mi.VolumeGrid`` needs."""
    depth, height, width, channels = grid.shape
    header = struct.pack("<3sBi4i6f", b"VOL", 3, 1, width, height, depth, channels, 0, 0, 0, 1, 1, 1)
    path.write_bytes(header + np.ascontiguousarray(grid, dtype="<f4").tobytes())


def write_fit_log(folder: Path, log: list[dict]) -> None:
    """log.jsonl and loss.png of a fit into ``folder``."""
    write_log(folder / LOG_JSONL, log)
    engine.plot_loss(log, folder / LOSS_PNG)
