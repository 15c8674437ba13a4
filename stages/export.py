"""Stage export: the fitted specimen as glTF 2.0 (binary .glb) for Blender and three.js.

The mesh is fit_geometry's (with its UVs and the vertex normals Mitsuba shades it
with), turned from the pipeline's world (metres, z up) to glTF's (metres, y up). The
material is a glTF metallic-roughness material (metallic 0) with these extensions:

===========  ===============================================================================
model        glTF material
===========  ===============================================================================
opaque       baseColor (texture when fit_texture kept one), roughness = Disney roughness
             (both perceptual: GGX alpha = roughness^2); KHR_materials_ior from
             ``specular`` (F0 = 0.08 specular, ior = (1 + sqrt F0) / (1 - sqrt F0))
principled   as opaque, plus KHR_materials_transmission (spec_trans), KHR_materials_ior
             (eta) and, when spec_trans > 0, KHR_materials_volume with the mean chord
             4 V / A as thicknessFactor and no attenuation (a clear solid, as
             Mitsuba refracts into it, not glTF's default thin wall)
volumetric   roughness = sqrt(alpha), KHR_materials_transmission 1, KHR_materials_ior
             (eta), KHR_materials_volume: absorption sigma_a = sigma_t (1 - albedo) as
             attenuationColor exp(-sigma_a d) at attenuationDistance d, the specimen's
             mean chord 4 V / A, which is also the thicknessFactor
===========  ===============================================================================

Limitations: glTF's ratified extensions have no scattering medium, so the
volumetric model's scattering (its albedo) is lost and only its absorption is
kept; a grid-volume albedo texture is exported as its mean.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
import trimesh
from PIL import Image

from pipeline import logger
from pipeline.core.config import Range
from pipeline.core.stage import Stage, StageInputs, StageResult
from pipeline.formats.fit_results import FittedValues
from pipeline.formats.scene_folder import MESH_PLY, texture_png

# glTF is y up: x stays, y becomes z, z becomes -y.
Z_UP_TO_Y_UP = np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]], dtype=float)


@dataclass(frozen=True)
class Config:
    """glTF export (the material mapping is fixed, see the module docstring)."""

    max_texture_size: Annotated[int, Range(16, None)] = 2048
    """Longer side of the embedded base-colour image; larger ones are downscaled
    (2048 is what WebGL on phones reliably takes)."""


def gltf_material(model: str, values: dict[str, list[float]], thickness: float) -> tuple[dict, dict]:
    """(pbrMetallicRoughness, extensions) of the glTF material for the fitted values."""
    if model == "volumetric":
        sigma_a = values["sigma_t"][0] * (1.0 - np.clip(values["albedo"], 0.0, 1.0))
        pbr = {
            "baseColorFactor": [1.0, 1.0, 1.0, 1.0],
            "metallicFactor": 0.0,
            "roughnessFactor": float(np.sqrt(values["alpha"][0])),
        }
        extensions = {
            "KHR_materials_transmission": {"transmissionFactor": 1.0},
            "KHR_materials_ior": {"ior": values["eta"][0]},
            "KHR_materials_volume": {
                "thicknessFactor": thickness,
                "attenuationDistance": thickness,
                "attenuationColor": [float(c) for c in np.exp(-sigma_a * thickness)],
            },
        }
        return pbr, extensions
    pbr = {
        "baseColorFactor": [*map(float, values["base_color"]), 1.0],
        "metallicFactor": 0.0,
        "roughnessFactor": values["roughness"][0],
    }
    if model == "opaque":
        reflectance = np.sqrt(0.08 * values["specular"][0])
        return pbr, {"KHR_materials_ior": {"ior": float((1 + reflectance) / (1 - reflectance))}}
    extensions = {
        "KHR_materials_transmission": {"transmissionFactor": values["spec_trans"][0]},
        "KHR_materials_ior": {"ior": values["eta"][0]},
    }
    if values["spec_trans"][0] > 0:
        # Mitsuba's principled transmission refracts into a solid; glTF's is thin-walled
        # unless a volume gives it a thickness (clear: no attenuation).
        extensions["KHR_materials_volume"] = {"thicknessFactor": thickness}
    return pbr, extensions


def _image(path: Path, max_size: int) -> Image.Image:
    image = Image.open(path)
    image.thumbnail((max_size, max_size))
    return image


def specimen_glb(
    mesh: trimesh.Trimesh, model: str, values: dict[str, list[float]], texture: Image.Image | None
) -> bytes:
    """The specimen (a mesh in the pipeline's world, with its UVs and vertex normals) as
    a binary glTF with the fitted material (see the module docstring)."""
    watertight = trimesh.Trimesh(mesh.vertices, mesh.faces)
    watertight.merge_vertices()
    thickness = float(4 * abs(watertight.volume) / watertight.area)
    pbr, extensions = gltf_material(model, values, thickness)
    uv = getattr(mesh.visual, "uv", None)
    texture = texture if uv is not None else None
    if texture is not None:
        pbr["baseColorFactor"] = [1.0, 1.0, 1.0, 1.0]  # glTF multiplies the texture by it
    material_visual = trimesh.visual.material.PBRMaterial(
        name="specimen",
        baseColorFactor=pbr["baseColorFactor"],
        metallicFactor=pbr["metallicFactor"],
        roughnessFactor=pbr["roughnessFactor"],
        baseColorTexture=texture,
    )
    # The scene's PLY UVs put v = 0 on the image's first row, as glTF does;
    # trimesh's exporter flips v on the way out, so hand it the flipped value.
    turned = mesh.copy()
    turned.visual = trimesh.visual.TextureVisuals(
        uv=None if uv is None else np.column_stack([uv[:, 0], 1.0 - uv[:, 1]]), material=material_visual
    )
    turned.apply_transform(Z_UP_TO_Y_UP)

    def add_extensions(tree: dict) -> None:
        for entry in tree["materials"]:
            entry.setdefault("extensions", {}).update(extensions)
        tree["extensionsUsed"] = sorted(set(tree.get("extensionsUsed", [])) | set(extensions))

    return trimesh.exchange.gltf.export_glb(
        trimesh.Scene({"specimen": turned}), include_normals=True, tree_postprocessor=add_extensions
    )


def main(conf: Config, inputs: StageInputs, out_dir: Path) -> StageResult:
    scene_dir = inputs.upstream["fit_geometry"]["geometry_dir"]
    # The final scene's values: a kept texture's mean stands in the textured
    # parameter's place (a volume's albedo has no glTF texture).
    fitted = FittedValues.read(inputs.upstream["fit_geometry"]["params"])
    # The PLY's vertex normals are the ones Mitsuba shades with: the glb carries them
    # (turned with the mesh), so that viewers shade it smooth as the renders are.
    mesh = trimesh.load(scene_dir / MESH_PLY, force="mesh", process=False)
    image_path = texture_png(scene_dir, "base_color")
    texture = _image(image_path, conf.max_texture_size) if image_path is not None else None
    folder = out_dir / "export"
    folder.mkdir()
    glb = folder / "specimen.glb"
    glb.write_bytes(specimen_glb(mesh, fitted.model, dict(fitted.params), texture))
    logger.info("glTF: %s, %d triangles", glb.name, len(mesh.faces))
    return StageResult({"glb": glb}, {"triangles": len(mesh.faces), "textured": image_path is not None})


STAGE = Stage(
    name="export",
    version=5,
    config=Config,
    main=main,
    needs=("fit_geometry.geometry_dir", "fit_geometry.params"),
    outputs=("glb",),
    exports=("glb",),
    result=("model", "glb"),
)
