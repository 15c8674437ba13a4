"""What a capture's mesh, UV atlas and fitted light allow on its held-out photos: the
ceiling of the held-out PSNR that a texture alone can reach (issue 26, point 4).

For a real capture whose stages up to fit_texture are cached, the
base-colour bitmap is baked (pipeline.fit.bake: per texel the least-squares colour of
the pixels that see it, under fit_texture's light and constants) with the colours
left unbounded, from

- the held-out photo itself (one bake per held-out photo): what the mesh, the atlas's
  texels and the render's filter lose of the very photo the texture came from;
- the training photos (what fit_texture starts from, without the colour's bound);
- every photo, held-out ones included: the training photos' disagreement with the
  held-out photo (the mesh's error, view-dependent light, shadows the light misses)
  added to the first row's losses,
- the N training photos whose cameras are nearest the held-out photo's (``--nearest``,
  each scored on its held-out photo alone): how much of that disagreement comes with
  the camera's place (such a texture is one per view, not one material),

and each is re-rendered in the held-out photo's window (128 px, the presets' fit
windows) and scored as heldout/ is (pipeline.synthetic.score.score_heldout: PSNR over
the eroded specimen mask; in brackets, after an RGB gain matched on the specimen). The
first row bounds what any texture can give with this mesh and light; the gap from the
training photos' row to fit_texture's own figure is the texture fit's, and that from
the first row to the training photos' the geometry's and the light's.

``--view-dependent STRENGTH,...`` adds rows for a colour that depends on the view:
per texel and channel ``c0 + c1 x + c2 y + c3 z``, (x, y, z) the unit direction from
the surface to the camera, solved by least squares from the training photos'
pixels (each pixel's shading and the light's other paths from one render at colour
0 and one at 1, as the bake's first solve) with a ridge of STRENGTH times the
texel's own weight on c1..c3, and evaluated per texel at the direction to the
held-out camera; a row of the constant colour from the same single solve goes with
them (the bake's later rounds are not applied to either). Where the photos disagree
smoothly with the viewpoint (a sheen, a light that moves with the camera) such a
colour predicts a held-out photo between training photos; where they disagree texel
by texel (detail the mesh places a pixel off) it cannot.

``--photographer DISTANCE:RADIUS`` puts a black disk into every view's scene, for the
bakes and the scored renders alike: its radius RADIUS times the camera's distance from
the specimen's centre, DISTANCE times that distance behind the camera, facing the
specimen: an occluder that moves with the camera (the photographer's body, a gantry's
arm), which shades the side of the specimen the camera faces.

Usage: ``.venv/bin/python -m bench.studies.ceiling CAPTURE [-s KEY=VALUE ...] [--nearest 2,4,8]
[--photographer 1:0.5] [--view-dependent 0.1,1]`` with the
overrides its runs used (bench/light.py's REAL), after bin/bootstrap and a
``pipeline run CAPTURE --until fit_texture`` with them. Prints a
Markdown table; rewrites the section ``ceiling-NAME`` of docs/benchmarks.md with
``--write``.
"""

from __future__ import annotations

import argparse
import json
import re
import tempfile
from pathlib import Path

import numpy as np

from bench.common import write_section
from pipeline.fit.bake import bake_bitmap, fill_unseen, pixel_rays, render_view, texels_hit
from pipeline.fit.outputs import write_heldout
from pipeline.fit.views import PhotoGains, Windowing, load_views, read_capture_photos
from pipeline.formats.fit_results import read_fitted_scene
from pipeline.formats.scene_description import SceneDescription
from pipeline.render import materials, mitsuba_variant
from pipeline.render.materials import SPECIMEN
from pipeline.synthetic.score import score_heldout

UNBOUNDED = (0.0, 100.0)
"""The colours' range in these bakes: no texel is cut, so the light's level does not matter."""


def _scored(views: list, texture: np.ndarray | None, key: str, folder: Path) -> dict:
    """``views`` rendered with ``texture`` as their bitmap (None: as loaded), scored."""
    import mitsuba as mi

    if texture is not None:
        for scene in {id(v.scene): v.scene for v in views}.values():
            params = mi.traverse(scene)
            params[key] = mi.TensorXf(texture)
            params.update()
    write_heldout(views, folder)
    return score_heldout(folder)


def photographer_scenes(
    textured: Path, description: SceneDescription, cameras: dict, distance: float, radius: float
) -> dict:
    """Each view's scene (its XML without the sensor) with a black disk behind its camera
    (the module docstring's ``--photographer``)."""
    import mitsuba as mi

    box = mi.load_dict({"type": "ply", "filename": str(textured / "mesh.ply")}).bbox()
    centre = (np.array(box.min) + np.array(box.max)) / 2
    mi.file_resolver().prepend(str(textured))
    scenes = {}
    for name, view in description.views.items():
        camera = np.asarray(cameras[name][1].center, float)
        away = camera - centre
        reach = float(np.linalg.norm(away))
        at = camera + distance * away
        disk = (
            f'<shape type="disk" id="photographer"><transform name="to_world">'
            f'<scale value="{radius * reach} {radius * reach} 1"/>'
            f'<lookat origin="{at[0]} {at[1]} {at[2]}" target="{centre[0]} {centre[1]} {centre[2]}" up="0 0 1"/>'
            '</transform><bsdf type="diffuse" id="photographer_bsdf"><rgb name="reflectance" value="0"/></bsdf></shape>'
        )
        xml = re.sub(r"\s*<sensor .*?</sensor>", "", (textured / view.xml).read_text(), flags=re.S)
        scenes[name] = mi.load_string(xml.replace("</scene>", disk + "</scene>"))
    return scenes


def _texels_and_directions(view, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel of ``view``, the specimen's texel its ray meets (-1: none) and the unit
    direction from that surface point to the camera."""
    texel = texels_hit(view, SPECIMEN, shape).ravel()
    rays, _ = pixel_rays(view.sensor)
    towards_camera = -np.array(rays.d).T
    return texel, towards_camera / np.linalg.norm(towards_camera, axis=1, keepdims=True)


def _linear_in_direction(directions: np.ndarray) -> np.ndarray:
    return np.concatenate([np.ones((len(directions), 1)), directions], axis=1)


def view_dependent_rows(
    training: list, scored: list, key: str, shape: tuple[int, int], strengths: list[float], folder: Path
) -> list[tuple[str, dict]]:
    """The ``--view-dependent`` rows (module docstring): the constant colour, then one
    row per ridge strength."""
    import mitsuba as mi

    texels, terms = shape[0] * shape[1], 4
    scenes = {id(v.scene): v.scene for v in training}
    renders = {}
    for value in (0.0, 1.0):
        for scene in scenes.values():
            params = mi.traverse(scene)
            params[key] = mi.TensorXf(np.full((2, 2, 3), value, np.float32))
            params.update()
        renders[value] = {v.name: render_view(v, 32, i + int(value) * len(training)) for i, v in enumerate(training)}
    # per texel and channel the normal equations: sum D^2 y y^T and sum D (I - S) y
    normal = np.zeros((texels, 3, terms, terms))
    right = np.zeros((texels, 3, terms))
    for view in training:
        texel, direction = _texels_and_directions(view, shape)
        counts = (texel >= 0) & (view.weight.ravel() > 0 if view.weight is not None else True)
        other = renders[0.0][view.name].reshape(-1, 3)[counts]
        shading = renders[1.0][view.name].reshape(-1, 3)[counts] - other
        photo, at, y = view.reference.reshape(-1, 3)[counts], texel[counts], _linear_in_direction(direction[counts])
        for c in range(3):
            for i in range(terms):
                right[:, c, i] += np.bincount(at, shading[:, c] * (photo[:, c] - other[:, c]) * y[:, i], texels)
                for j in range(terms):
                    normal[:, c, i, j] += np.bincount(at, shading[:, c] ** 2 * y[:, i] * y[:, j], texels)
    weight = normal[:, :, 0, 0]
    seen = weight.min(axis=1) > 1e-6 * weight.max()
    constant = np.divide(right[:, :, 0], weight, out=np.zeros((texels, 3)), where=weight > 0)
    texture = fill_unseen(np.clip(constant, *UNBOUNDED), seen, shape).reshape(*shape, 3).astype(np.float32)
    rows = [("the training photos, a constant colour, one solve", _scored(scored, texture, key, folder / "constant"))]
    ridge = np.diag([0.0, 1.0, 1.0, 1.0])
    for strength in strengths:
        system = normal[seen] + strength * weight[seen][..., None, None] * ridge
        coefficients = np.zeros((texels, 3, terms))
        coefficients[seen] = np.linalg.solve(system, right[seen][..., None])[..., 0]
        per_view = {}
        for view in scored:  # each held-out photo with the colour its camera sees
            texel, direction = _texels_and_directions(view, shape)
            hit = texel >= 0
            mean = np.stack([np.bincount(texel[hit], direction[hit, i], texels) for i in range(3)], axis=1)
            length = np.linalg.norm(mean, axis=1, keepdims=True)
            y = _linear_in_direction(np.divide(mean, length, out=np.zeros_like(mean), where=length > 0))
            colour = np.einsum("nck,nk->nc", coefficients, y)  # unseen by this camera: c0 alone
            colour = fill_unseen(np.clip(colour, *UNBOUNDED), seen, shape).reshape(*shape, 3).astype(np.float32)
            per_view[view.name] = _scored([view], colour, key, folder / f"view-dependent-{strength:g}-{view.name}")
        rows.append(
            (f"the training photos, a colour linear in the view direction, ridge {strength:g}", _merged(per_view))
        )
    return rows


def _merged(per_view: dict[str, dict]) -> dict:
    """One row's scores from each held-out photo's own: the means over the photos."""
    return {
        "psnr_db_mean": float(np.mean([s["psnr_db_mean"] for s in per_view.values()])),
        "psnr_gain_db_mean": float(np.mean([s["psnr_gain_db_mean"] for s in per_view.values()])),
        "per_view": {name: s["per_view"][name] for name, s in per_view.items()},
    }


def cached_outputs(capture: Path, until: str, overrides: list[str]) -> dict:
    """Each stage's outputs up to ``until``, all cached (a plan takes no lock: a run
    of later stages may go on beside this)."""
    from pipeline.core.config import load_config
    from pipeline.core.runner import Runner, Selection
    from pipeline.core.sections import schema
    from stages import STAGES

    plan = Runner(capture, STAGES, load_config(schema(STAGES), capture, "standard", overrides)).plan(
        Selection(until=until)
    )
    if missing := [item.stage.name for item in plan if item.entry is None]:
        raise SystemExit(f"{capture}: not cached with these settings: {', '.join(missing)} (pipeline run first)")
    return {item.stage.name: item.entry.outputs for item in plan}


def ceiling(
    capture: Path,
    overrides: list[str],
    keep: Path | None = None,
    nearest: tuple[int, ...] = (),
    photographer: tuple[float, float] | None = None,
    rounds: int | None = None,
    view_dependent: list[float] | None = None,
) -> list[tuple[str, dict]]:
    """(what the texture came from, score_heldout's scores) per row of the module docstring;
    each row's heldout/-like folder kept under ``keep`` when given."""
    import mitsuba as mi

    outputs = cached_outputs(capture, "fit_texture", overrides)
    description, material = read_fitted_scene(outputs["scene"]["description"], outputs["fit_material"]["params"])
    textured = outputs["fit_texture"]["textured_dir"]
    bitmap = textured / "base_color.exr"
    if not bitmap.is_file():
        raise SystemExit(f"{capture.name}: fit_texture kept no bitmap ({textured}): nothing to bake into")
    texture_conf = json.loads((outputs["fit_texture"]["params"]).read_text())
    mitsuba_variant.activate("auto")
    shape = np.array(mi.Bitmap(str(bitmap))).shape[:2]
    key = materials.TEXTURE_SLOTS[description.model].key
    photos = read_capture_photos(
        outputs["sfm"]["cameras"],
        outputs["undistort"]["pinhole"],
        outputs["masks"]["masks_json"],
        PhotoGains.of(material),
    )
    held = set(material.held_out)
    scenes = photographer_scenes(textured, description, photos.cameras, *photographer) if photographer else None
    baked = texture_conf.get("baked", {})
    rounds = rounds or baked.get("rounds", 1)
    # the bake's windows and samples as fit_texture's; the scored windows as heldout/'s
    bake_views = [
        v
        for v, _ in load_views(
            textured, description, photos, Windowing(baked.get("max_size", 512), 2, 32), scenes=scenes
        )
    ]
    for view in bake_views:
        if view.gain is not None:  # a held-out photo in the scene's units
            view.reference = view.reference / view.gain.astype(np.float32)
    scored = [v for v, _ in load_views(textured, description, photos, Windowing(128, 2, 64), names=held, scenes=scenes)]
    rows = []
    with tempfile.TemporaryDirectory() as temporary:
        folder = keep or temporary
        Path(folder).mkdir(parents=True, exist_ok=True)
        rows.append(("fit_texture's texture", _scored(scored, None, key, Path(folder) / "stage")))
        for name in sorted(held):
            alone = [v for v in bake_views if v.name == name]
            texture, _, _ = bake_bitmap(alone, key, SPECIMEN, shape, 32, UNBOUNDED, rounds=rounds)
            scores = _scored([v for v in scored if v.name == name], texture, key, Path(folder) / f"self-{name}")
            rows.append((f"{name} alone (scored on it alone)", scores))
        for slug, label, subset in (
            ("training", "the training photos, unbounded", [v for v in bake_views if v.name not in held]),
            ("every", "every photo, held-out ones too", bake_views),
        ):
            texture, _, _ = bake_bitmap(subset, key, SPECIMEN, shape, 32, UNBOUNDED, rounds=rounds)
            rows.append((label, _scored(scored, texture, key, Path(folder) / slug)))
        training = [v for v in bake_views if v.name not in held]
        for name in sorted(held):
            centre = photos[0][name][1].center
            by_distance = sorted(training, key=lambda v: np.linalg.norm(photos[0][v.name][1].center - centre))
            for count in nearest:
                texture, _, _ = bake_bitmap(by_distance[:count], key, SPECIMEN, shape, 32, UNBOUNDED, rounds=rounds)
                scores = _scored(
                    [v for v in scored if v.name == name], texture, key, Path(folder) / f"near{count}-{name}"
                )
                rows.append((f"the {count} training photos nearest {name} (scored on it alone)", scores))
        if view_dependent:
            rows += view_dependent_rows(training, scored, key, shape, view_dependent, Path(folder))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("capture", type=Path)
    parser.add_argument("-s", "--set", dest="overrides", action="append", default=[])
    parser.add_argument("--write", action="store_true", help="rewrite docs/benchmarks.md's section")
    parser.add_argument("--keep", type=Path, help="keep each row's renders, references and masks here")
    parser.add_argument("--nearest", default="", help="counts of nearest training photos to bake from, e.g. 2,4,8")
    parser.add_argument("--photographer", help="DISTANCE:RADIUS of a black disk behind every camera")
    parser.add_argument("--rounds", type=int, help="the bakes' rounds (default: fit_texture's)")
    parser.add_argument("--view-dependent", help="ridge strengths of a colour linear in the view direction, e.g. 0.1,1")
    args = parser.parse_args()
    nearest = tuple(int(n) for n in args.nearest.split(",") if n)
    photographer = tuple(float(x) for x in args.photographer.split(":")) if args.photographer else None
    strengths = [float(x) for x in args.view_dependent.split(",")] if args.view_dependent else None
    rows = ceiling(args.capture, args.overrides, args.keep, nearest, photographer, args.rounds, strengths)
    lines = [
        f"| texture baked from ({args.capture.name}) | held-out PSNR | per photo |",
        "|---|---|---|",
        *(
            f"| {label} | {s['psnr_db_mean']:.2f} dB ({s['psnr_gain_db_mean']:.2f}) | "
            + ", ".join(f"{n} {v:.2f}" for n, v in sorted(s["per_view"].items()))
            + " |"
            for label, s in rows
        ),
    ]
    print("\n".join(lines))
    if args.write:
        suffix = f"-photographer-{args.photographer}" if args.photographer else ""
        suffix += f"-rounds-{args.rounds}" if args.rounds else ""
        suffix += f"-view-dependent-{args.view_dependent}" if args.view_dependent else ""
        write_section(f"ceiling-{args.capture.name}{suffix}", lines)


if __name__ == "__main__":
    main()
