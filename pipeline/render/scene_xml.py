"""Mitsuba 3 scene XML, written with xml.etree (Mitsuba has no dict-to-XML writer).

Every element the pipeline writes has an id, so that ``mi.traverse`` keys stay
stable (``specimen.bsdf.roughness.value``). ``set_values`` writes fitted numbers
back into any scene file whose parameters are plain values, and swaps a plain
value for a texture or volume element (fit_texture).
"""

from __future__ import annotations

import math
import os
import re
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Sequence

import numpy as np

from pipeline.camera.model import Intrinsics, Pose
from pipeline.core.errors import PipelineError, require_finite


def _number(value: float) -> str:
    return f"{float(value):.9g}"


def _property(parent: ET.Element, name: str, value) -> ET.Element:
    """``<float>``, ``<integer>``, ``<rgb>``, ``<string>`` or ``<boolean>`` by the value's type."""
    if isinstance(value, bool):
        return ET.SubElement(parent, "boolean", name=name, value="true" if value else "false")
    if isinstance(value, int):
        return ET.SubElement(parent, "integer", name=name, value=str(value))
    if isinstance(value, float):
        return ET.SubElement(parent, "float", name=name, value=_number(value))
    if isinstance(value, str):
        return ET.SubElement(parent, "string", name=name, value=value)
    values = [float(v) for v in value]
    if len(values) != 3:
        raise ValueError(f"{name}: expected a number or an RGB triple, got {value!r}")
    return ET.SubElement(parent, "rgb", name=name, value=" ".join(_number(v) for v in values))


def plugin(parent: ET.Element, tag: str, properties: dict, name: str | None = None) -> ET.Element:
    """``<tag type=... id=...>`` with its properties; ``properties`` holds "type",
    optionally "id", and name -> value."""
    attributes = {"type": properties["type"]}
    if name is not None:
        attributes["name"] = name
    if "id" in properties:
        attributes["id"] = properties["id"]
    element = ET.SubElement(parent, tag, attributes)
    for key, value in properties.items():
        if key not in ("type", "id"):
            _property(element, key, value)
    return element


def new_scene() -> ET.Element:
    return ET.Element("scene", version="3.0.0")


def write(root: ET.Element, path: Path, comment: str | None = None) -> Path:
    if comment:
        # "--" may not occur in an XML comment; names users chose can hold it.
        root.insert(0, ET.Comment(" " + re.sub(r"-(?=-)", "- ", comment).rstrip("-") + " "))
    ET.indent(root)
    ET.ElementTree(root).write(path, encoding="unicode", xml_declaration=True)
    return path


def transform_matrix(parent: ET.Element, matrix: np.ndarray) -> None:
    """``<transform name="to_world">`` holding a 4x4 matrix."""
    transform = ET.SubElement(parent, "transform", name="to_world")
    ET.SubElement(transform, "matrix", value=" ".join(_number(v) for v in np.asarray(matrix).ravel()))


def sensor_properties(
    intrinsics: Intrinsics,
    pose: Pose,
    spp: int,
    near_clip: float,
    crop: tuple[int, int, int, int] | None = None,
    sample_border: bool = False,
    rfilter: dict | None = None,
) -> dict:
    """A perspective sensor reproducing a pinhole camera with square pixels, as a
    ``mi.load_dict`` dict (``to_world`` a 4x4 nested list): focal length as
    horizontal field of view, principal point as Mitsuba's offsets (a fraction of
    the film, positive moving the image content left/up; Mitsuba puts pixel
    centres at +0.5, OpenCV at 0). ``crop`` = (x, y, width, height) renders only
    that window of the full image. ``sample_border`` lets geometry that moves across
    the window's edge be differentiated (projective integrators want it). ``rfilter``:
    the film's reconstruction filter as a ``mi.load_dict`` dict (for load_sensor only:
    the XML writer takes no nested plugin); None: Mitsuba's default Gaussian."""
    if abs(intrinsics.fx - intrinsics.fy) > 1e-3 * intrinsics.fx:
        raise PipelineError(
            f"a camera has fx = {intrinsics.fx:.2f} and fy = {intrinsics.fy:.2f}: Mitsuba's "
            "perspective sensor needs square pixels (rerun undistort and sfm)"
        )
    film = {"type": "hdrfilm", "width": int(intrinsics.width), "height": int(intrinsics.height), "pixel_format": "rgb"}
    if sample_border:
        film["sample_border"] = True
    if rfilter is not None:
        film["rfilter"] = rfilter
    if crop is not None:
        film.update(zip(("crop_offset_x", "crop_offset_y", "crop_width", "crop_height"), map(int, crop)))
    return {
        "type": "perspective",
        "fov_axis": "x",
        "fov": math.degrees(2 * math.atan(intrinsics.width / 2 / intrinsics.fx)),
        "principal_point_offset_x": (intrinsics.width / 2 - (intrinsics.cx + 0.5)) / intrinsics.width,
        "principal_point_offset_y": (intrinsics.height / 2 - (intrinsics.cy + 0.5)) / intrinsics.height,
        "near_clip": float(near_clip),
        "to_world": pose.mitsuba_to_world().tolist(),
        "sampler": {"type": "independent", "sample_count": int(spp)},
        "film": film,
    }


def load_sensor(properties: dict):
    """The Mitsuba sensor of ``sensor_properties`` (the active variant)."""
    import mitsuba as mi

    return mi.load_dict({**properties, "to_world": mi.ScalarTransform4f(properties["to_world"])})


SENSOR_PREFIX = "photo-"
"""Starts every sensor's id, so that no photo's name can take the id of one of the
scene's own objects (a photo named softbox.jpg)."""


def sensor_id(name: str) -> str:
    """A sensor's id Mitsuba's parser takes as it is, from a photo's name: the parser
    substitutes ``$name`` in every attribute (with no way to escape a ``$``), and
    parameter keys are split at dots, so every other character becomes ``_``. Two
    names this maps to one id are refused where photos enter (undistort)."""
    return SENSOR_PREFIX + re.sub(r"[^A-Za-z0-9_-]", "_", name)


def sensor(parent: ET.Element, name: str, properties: dict) -> ET.Element:
    """``<sensor>`` from ``sensor_properties``, its id made from the photo's ``name``."""
    element = plugin(
        parent,
        "sensor",
        {
            "type": "perspective",
            "id": sensor_id(name),
            **{k: v for k, v in properties.items() if k not in ("type", "to_world", "sampler", "film")},
        },
    )
    transform_matrix(element, np.asarray(properties["to_world"]))
    plugin(element, "sampler", properties["sampler"])
    plugin(element, "film", properties["film"])
    return element


def area_light(
    parent: ET.Element,
    light_id: str,
    position: Sequence[float],
    target: Sequence[float],
    up: Sequence[float],
    size: float,
    radiance: Sequence[float],
) -> ET.Element:
    """A square softbox of side ``size`` at ``position`` facing ``target``."""
    direction = np.asarray(target, float) - np.asarray(position, float)
    up = np.asarray(up, float)
    if np.linalg.norm(np.cross(direction, up)) < 1e-6 * np.linalg.norm(direction):
        up = np.array([0.0, 1.0, 0.0]) if abs(direction[1]) < 0.9 * np.linalg.norm(direction) else np.array([1.0, 0, 0])
    shape = ET.SubElement(parent, "shape", type="rectangle", id=light_id)
    transform = ET.SubElement(shape, "transform", name="to_world")
    ET.SubElement(transform, "scale", value=f"{_number(size / 2)} {_number(size / 2)} 1")
    ET.SubElement(
        transform,
        "lookat",
        origin=" ".join(map(_number, position)),
        target=" ".join(map(_number, target)),
        up=" ".join(map(_number, up)),
    )
    plugin(shape, "emitter", {"type": "area", "id": f"{light_id}_emitter", "radiance": tuple(radiance)})
    return shape


def include(parent: ET.Element, filename: str) -> ET.Element:
    """``<include>`` of another scene file (a path relative to the including file)."""
    return ET.SubElement(parent, "include", filename=filename)


def _element_ids(tree: ET.ElementTree) -> dict[str, ET.Element]:
    """Plugin elements by id; a ``<ref id=...>`` names another element, it is not one."""
    return {e.get("id"): e for e in tree.iter() if e.get("id") and e.tag != "ref"}


def _child(element: ET.Element, part: str, by_id: dict[str, ET.Element]) -> ET.Element | None:
    """The child plugin that ``mi.traverse`` names ``part`` under ``element``: by its
    name or id (through a ``<ref>``), else the one child of that tag."""
    for child in element:
        if part in (child.get("name"), child.get("id")):
            return by_id.get(child.get("id"), child) if child.tag == "ref" else child
    by_tag = [child for child in element if child.tag == part]  # a shape's nested "bsdf", "emitter"
    return by_tag[0] if len(by_tag) == 1 else None


def _property_of(by_id: dict[str, ET.Element], key: str, path: Path) -> tuple[ET.Element, float]:
    """The element holding ``mi.traverse`` key ``key`` (``<id>.<child>...<property>[.value]``)
    and the factor from Mitsuba's value to the file's. The element with the first part
    as id is walked down the middle parts (children by name or id, ``<ref>``s followed);
    where that walk fails, its whole subtree is searched for the property named by the
    last part that is not ``value``."""
    parts = [p for p in key.split(".") if p != "value"]
    owner = by_id.get(parts[0])
    if owner is None:
        raise PipelineError(f"{path}: no element with id '{parts[0]}' for parameter {key}")
    for part in parts[1:-1]:
        owner = _child(owner, part, by_id) if owner is not None else None
    scope = owner.iter() if owner is not None else by_id[parts[0]].iter()
    if owner is None:
        owner = by_id[parts[0]]
    matches = [e for e in scope if e.get("name") == parts[-1] and e.tag != "ref"]
    factor = 1.0
    if not matches and parts[-1] == "eta":
        # Dielectrics are written with int_ior / ext_ior; Mitsuba exposes their ratio.
        matches = [e for e in owner.iter() if e.get("name") == "int_ior"]
        exterior = [float(e.get("value")) for e in owner.iter() if e.get("name") == "ext_ior" and e.tag == "float"]
        factor = exterior[0] if exterior else 1.000277
    if len(matches) != 1 or matches[0].tag not in ("float", "rgb", "spectrum"):
        raise PipelineError(
            f"{path}: cannot write {key}: its property '{parts[-1]}' under id "
            f"'{parts[0]}' is not one plain value (a texture, or an IOR given by name)"
        )
    return matches[0], factor


def writable(tree: ET.ElementTree, key: str) -> bool:
    """Whether ``write_values`` can write ``mi.traverse`` key ``key`` into ``tree``: a
    plain value the file holds (not a default Mitsuba adds, such as the BSDF of an
    area light's shape)."""
    try:
        _property_of(_element_ids(tree), key, Path("scene"))
    except PipelineError:
        return False
    return True


def set_values(
    path: Path, values: dict[str, Sequence[float]], out: Path, textures: dict[str, ET.Element] | None = None
) -> Path:
    """Copy the scene at ``path`` to ``out`` with fitted values written in (file names
    it refers to are made relative to ``out``'s folder). Keys are ``mi.traverse``
    keys of plain values (see ``_property_of``). ``textures`` maps such keys to a
    ``<texture>`` or ``<volume>`` element that takes the value's place (its file
    names relative to ``out``)."""
    return write_values(ET.parse(path), path, values, out, textures)


def write_values(
    tree: ET.ElementTree,
    path: Path,
    values: dict[str, Sequence[float]],
    out: Path,
    textures: dict[str, ET.Element] | None = None,
) -> Path:
    """``set_values`` on a parsed scene ``tree`` read from ``path``."""
    by_id = _element_ids(tree)
    parents = {child: parent for parent in tree.iter() for child in parent}
    for key, value in values.items():
        element, factor = _property_of(by_id, key, path)
        numbers = [factor * float(v) for v in np.ravel(value)]
        require_finite(numbers, f"{out}: {key}")
        if element.tag == "float":
            element.set("value", _number(numbers[0]))
        else:
            element.tag = "rgb"
            element.set("value", " ".join(_number(v) for v in (numbers * 3 if len(numbers) == 1 else numbers)))
    if out.parent.resolve() != path.parent.resolve():
        # Files the scene refers to stay where they are: relative names are
        # rewritten relative to the new file.
        for element in tree.iter():
            if element.get("name") == "filename" or element.tag == "include":
                attribute = "value" if element.tag == "string" else "filename"
                target = element.get(attribute)
                if target and not Path(target).is_absolute() and (path.parent / target).exists():
                    element.set(attribute, os.path.relpath(path.parent / target, out.parent))
    for key, texture in (textures or {}).items():
        element, _ = _property_of(by_id, key, path)
        parent = parents[element]
        texture.set("name", element.get("name"))
        parent.insert(list(parent).index(element), texture)
        parent.remove(element)
    ET.indent(tree.getroot())
    tree.write(out, encoding="unicode", xml_declaration=True)
    return out
