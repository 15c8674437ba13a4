"""pipeline.core.errors.require_finite and the result writers that call it: a NaN or
infinity is never written silently into params.json, a scene file or a texture."""

import numpy as np
import pytest

from pipeline.core.errors import NonFiniteOutput, require_finite
from pipeline.formats.fit_results import FittedValues
from pipeline.render import scene_xml


def test_finite_results_pass_and_a_nan_anywhere_is_named_by_its_key():
    require_finite({"params": {"eta": [1.4]}, "held_out": ["a.jpg"], "validation_mse": None, "kept": True}, "p")
    with pytest.raises(NonFiniteOutput, match=r"params.json: params: base_color\[1\] is not finite"):
        require_finite({"params": {"base_color": [[0.5], [float("nan")]]}}, "params.json")
    with pytest.raises(NonFiniteOutput, match="texture is not finite"):
        require_finite(np.array([[0.1, np.inf]], np.float32), "texture")


def test_writers_refuse_non_finite_values(tmp_path):
    fitted = FittedValues(model="opaque", params={}, bounds={}, held_out=[], details={"validation_mse": float("inf")})
    with pytest.raises(NonFiniteOutput, match="validation_mse"):
        fitted.write(tmp_path / "params.json")
    assert not (tmp_path / "params.json").exists()
    root = scene_xml.new_scene()
    shape = scene_xml.plugin(root, "shape", {"type": "sphere", "id": "specimen"})
    scene_xml.plugin(shape, "bsdf", {"type": "principled", "id": "specimen_bsdf", "roughness": 0.5})
    path = scene_xml.write(root, tmp_path / "scene.xml")
    with pytest.raises(NonFiniteOutput, match="specimen.bsdf.roughness.value"):
        scene_xml.set_values(path, {"specimen.bsdf.roughness.value": [float("nan")]}, tmp_path / "out.xml")
