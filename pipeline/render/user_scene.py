"""A scene file as users write it, made ready to fit and to write back.

Scenes come from Blender's Mitsuba add-on, from hand, from other tools: BSDFs
declared once and used through ``<ref id=...>``, objects without ids (Mitsuba
then names them by a memory address that changes on every load), ``<include>``d
files, ``<default>`` values used as ``$name``, dielectrics whose IOR is a material
name, and a render integrator (``path``) that cannot be differentiated.
``normalised`` returns one self-contained tree that Mitsuba loads with stable
``mi.traverse`` keys and that ``scene_xml.write_values`` can write fitted values
into:

==========================  =========================================================
as written                  in the normalised tree
==========================  =========================================================
``<include filename=..>``   the included file's content, inlined (recursively)
relative file names         absolute (``relative_filenames`` turns them back for
                            a file written elsewhere)
a plugin without an id      ``id="<tag>_<n>"``, numbered in document order
``int_ior="bk7"``           the number Mitsuba's IOR table gives the name
``value="$name"``           kept: Mitsuba substitutes the ``<default>``; a fitted
                            value replaces it
==========================  =========================================================

``differentiable_integrator`` swaps a render integrator for its differentiable
counterpart at fit time; the file keeps the one it had. ``reduce_films`` makes
the films of a copy to fit with smaller (pixels are most of a fit's cost on a CPU).

Limitations: the written scene is one file (includes are not written back
separately); ``-D`` command-line parameters of the ``mitsuba`` tool are not
supported, only ``<default>``.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from pipeline.core.errors import PipelineError

PLUGIN_TAGS = ("shape", "bsdf", "medium", "phase", "emitter", "texture", "volume", "sensor", "film", "sampler")
"""Elements that load as Mitsuba objects (and so appear in ``mi.traverse``)."""

DIFFERENTIABLE = {"path": "prb", "volpath": "prbvolpath", "direct": "direct_projective"}
"""Render integrators and the differentiable integrator that computes the same image."""
DIFFERENTIABLE_TYPES = {"prb", "prbvolpath", "direct_projective", "prb_projective", "prb_basic"}


def _filename_attribute(element: ET.Element) -> str | None:
    if element.tag == "include":
        return "filename"
    if element.tag == "string" and element.get("name") == "filename":
        return "value"
    return None


def _inlined(path: Path, chain: tuple[Path, ...] = ()) -> ET.Element:
    """The root of ``path`` with its includes replaced by their content and relative
    file names made absolute."""
    if path in chain:
        raise PipelineError(f"{path} includes itself (through {' -> '.join(p.name for p in chain)})")
    if not path.is_file():
        raise PipelineError(f"{chain[-1] if chain else path}: the scene file {path} does not exist")
    try:
        # Comments kept: the fitted scene is written back from this tree.
        root = ET.parse(path, parser=ET.XMLParser(target=ET.TreeBuilder(insert_comments=True))).getroot()
    except ET.ParseError as error:
        raise PipelineError(f"{path} is not valid XML: {error}") from error
    for element in root.iter():
        attribute = _filename_attribute(element)
        target = element.get(attribute) if attribute else None
        if target and "$" not in target and not Path(target).is_absolute():
            element.set(attribute, str((path.parent / target).resolve()))
    for parent in list(root.iter()):
        for child in list(parent):
            if child.tag == "include":
                included = _inlined(Path(child.get("filename")), (*chain, path))
                position = list(parent).index(child)
                parent.remove(child)
                for offset, grandchild in enumerate(list(included)):
                    parent.insert(position + offset, grandchild)
    return root


def _name_unnamed(root: ET.Element) -> None:
    """Give every plugin without an id one, ``<tag>_<n>``, unique in the file."""
    taken = {e.get("id") for e in root.iter() if e.get("id")}
    counts: dict[str, int] = {}
    for element in root.iter():
        if element.tag in PLUGIN_TAGS and not element.get("id"):
            while True:
                counts[element.tag] = counts.get(element.tag, 0) + 1
                candidate = f"{element.tag}_{counts[element.tag]}"
                if candidate not in taken:
                    break
            element.set("id", candidate)
            taken.add(candidate)


def ior_value(name: str) -> float:
    """The refractive index Mitsuba's table gives a material name ("bk7", "water", ...)."""
    import mitsuba as mi

    try:
        bsdf = mi.load_dict({"type": "dielectric", "int_ior": name, "ext_ior": 1.0})
    except RuntimeError as error:
        raise PipelineError(f"unknown index of refraction '{name}': give a number or a name Mitsuba knows") from error
    return float(np.ravel(np.asarray(mi.traverse(bsdf)["eta"]))[0])


def _ior_numbers(root: ET.Element) -> None:
    for element in root.iter("string"):
        if element.get("name") in ("int_ior", "ext_ior") and "$" not in element.get("value", ""):
            element.tag = "float"
            element.set("value", f"{ior_value(element.get('value')):.9g}")


def normalised(path: Path) -> ET.ElementTree:
    """The scene at ``path`` as one self-contained tree (see the module docstring);
    Mitsuba must be active (IOR names are looked up in its table)."""
    root = _inlined(path.resolve())
    _name_unnamed(root)
    _ior_numbers(root)
    return ET.ElementTree(root)


FILM_DEFAULT_SIZE = (768, 576)
"""Mitsuba's film size when a sensor names none (hdrfilm's width and height)."""
FILM_PIXEL_COUNTS = ("width", "height", "crop_width", "crop_height", "crop_offset_x", "crop_offset_y")
"""A film's integers that count pixels (and scale with it)."""


DEFAULT_FILTER_STDDEV = 0.5
"""Mitsuba's default reconstruction filter: a Gaussian of this standard deviation (px)."""


def _filter_variance(film: ET.Element, defaults: dict[str, str]) -> float | None:
    """The variance (px^2) of the film's reconstruction filter: a Gaussian's, a box's
    (1/12) or a tent's (radius^2 / 6); None for another kind, which is kept as it is."""
    element = film.find("rfilter")
    if element is None:
        return DEFAULT_FILTER_STDDEV**2
    values = {
        child.get("name"): float(_substituted(child.get("value"), defaults))
        for child in element
        if child.get("name") in ("stddev", "radius")
    }
    kind = element.get("type")
    if kind == "gaussian":
        return values.get("stddev", DEFAULT_FILTER_STDDEV) ** 2
    if kind == "box":
        return 1 / 12
    if kind == "tent":
        return values.get("radius", 1.0) ** 2 / 6
    return None


def reduce_films(tree: ET.ElementTree, max_size: int) -> list[tuple[int, int]]:
    """Scale every sensor's film in ``tree`` (in place; a sensor without one gets
    Mitsuba's default film first) so that its longer side has at most ``max_size``
    pixels, crop windows with it; 0 keeps them. Returns each sensor's crop size
    before, in document order (the order of ``scene.sensors()``).

    A reduced film's reconstruction filter becomes the blur of its reference image
    averaged down to it (``cv2.INTER_AREA``): a Gaussian with the variance of a pixel's
    square (1/12 px^2) plus the full film's own filter's, scaled. Mitsuba's default
    (0.5 px at any size) would blur a small film's render past its reference, and the
    fit would answer with sharper highlights, a roughness too low (docs/decisions.md,
    "The fitting loop's stop and schedule"). A filter other than a Gaussian, box or tent
    is kept."""
    defaults = {d.get("name"): d.get("value") for d in tree.getroot().iter("default")}
    sizes = []
    for sensor in tree.getroot().iter("sensor"):
        film = sensor.find("film")
        if film is None:
            film = ET.SubElement(sensor, "film", type="hdrfilm")
        elements = {child.get("name"): child for child in film if child.get("name") in FILM_PIXEL_COUNTS}
        for name, default in zip(("width", "height"), FILM_DEFAULT_SIZE):
            if name not in elements:
                elements[name] = ET.SubElement(film, "integer", name=name, value=str(default))
        pixels = {name: int(_substituted(element.get("value"), defaults)) for name, element in elements.items()}
        sizes.append((pixels.get("crop_width", pixels["width"]), pixels.get("crop_height", pixels["height"])))
        scale = min(1.0, max_size / max(pixels["width"], pixels["height"])) if max_size else 1.0
        for name, element in elements.items():
            element.set("value", str(max(0 if name.startswith("crop_offset") else 1, round(pixels[name] * scale))))
        variance = _filter_variance(film, defaults)
        if scale < 1.0 and variance is not None:
            for old in film.findall("rfilter"):
                film.remove(old)
            rfilter = ET.SubElement(film, "rfilter", type="gaussian")
            ET.SubElement(rfilter, "float", name="stddev", value=repr(float(np.sqrt(1 / 12 + variance * scale**2))))
    return sizes


def _substituted(value: str, defaults: dict[str, str]) -> str:
    """``value`` with a ``$name`` replaced by its ``<default>``."""
    return defaults.get(value[1:], value) if value.startswith("$") else value


def relative_filenames(tree: ET.ElementTree, folder: Path) -> None:
    """Absolute file names made relative to ``folder``, where the tree is written."""
    for element in tree.iter():
        attribute = _filename_attribute(element)
        target = element.get(attribute) if attribute else None
        if target and Path(target).is_absolute():
            element.set(attribute, os.path.relpath(target, folder))


def differentiable_integrator(tree: ET.ElementTree):
    """The integrator to fit with: None when the scene's own is differentiable, else
    the differentiable counterpart of its render integrator, with its max_depth."""
    import mitsuba as mi

    element = tree.getroot().find("integrator")
    kind = element.get("type") if element is not None else "path"  # Mitsuba's default
    if kind in DIFFERENTIABLE_TYPES:
        return None
    if kind not in DIFFERENTIABLE:
        raise PipelineError(
            f"the scene's integrator '{kind}' has no differentiable counterpart: use path, volpath, direct, "
            f"or one of {', '.join(sorted(DIFFERENTIABLE_TYPES))}"
        )
    properties = {"type": DIFFERENTIABLE[kind]}
    for child in element if element is not None else ():
        if child.tag == "integer" and child.get("name") in ("max_depth", "rr_depth"):
            properties[child.get("name")] = int(child.get("value"))
    return mi.load_dict(properties)
