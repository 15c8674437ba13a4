"""pipeline.fit.variables: a base colour fitted as its diffuse weight beside spec_trans
(FitParameter.times_complement_of), on a traversed principled BSDF, without rendering."""

from dataclasses import replace

import numpy as np
import pytest

from pipeline.core.errors import PipelineError
from pipeline.fit.variables import MaterialVariables
from pipeline.render.materials import diffuse_weight_fitted, fit_parameters, refit_parameters
from pipeline.render.parameters import FitParameter

BASE_COLOR = FitParameter("base_color", "ball.bsdf.base_color.value", 0.001, 1.0, learning_rate=0.05)
SPEC_TRANS = FitParameter("spec_trans", "ball.bsdf.spec_trans.value", 0.0, 1.0)
ROUGHNESS = FitParameter("roughness", "ball.bsdf.roughness.value", 0.001, 1.0, log=True)


def _variables(mi, parameters, base_color=(0.6, 0.4, 0.2), spec_trans=0.25):
    scene = mi.load_dict(
        {
            "type": "scene",
            "ball": {
                "type": "sphere",
                "bsdf": {
                    "type": "principled",
                    "id": "ball_bsdf",
                    "base_color": {"type": "rgb", "value": list(base_color)},
                    "roughness": 0.3,
                    "spec_trans": spec_trans,
                    "eta": 1.4,
                },
            },
        }
    )
    params = mi.traverse(scene)
    variables = MaterialVariables(parameters, {id(scene): params}, [])
    variables.register(1.0)
    return variables, params, id(scene)


def test_the_base_colour_beside_spec_trans_is_fitted_as_its_diffuse_weight(mi):
    variables, params, key = _variables(mi, diffuse_weight_fitted([BASE_COLOR, ROUGHNESS, SPEC_TRANS]))
    assert np.allclose(np.ravel(variables.optimizer["base_color"]), np.array([0.6, 0.4, 0.2]) * 0.75, atol=1e-6)
    variables.apply(key)
    assert np.allclose(np.ravel(params[BASE_COLOR.key]), [0.6, 0.4, 0.2], atol=1e-6)
    snapshot = variables.snapshot()
    assert np.allclose(snapshot["base_color"], [0.6, 0.4, 0.2], atol=1e-6)
    assert np.allclose(snapshot["roughness"], [0.3], atol=1e-6)

    variables.restore(
        {"base_color": np.array([0.2, 0.3, 0.4]), "roughness": np.array([0.5]), "spec_trans": np.array([0.6])}
    )
    assert np.allclose(np.ravel(variables.optimizer["base_color"]), np.array([0.2, 0.3, 0.4]) * 0.4, atol=1e-6)
    assert np.allclose(variables.snapshot()["base_color"], [0.2, 0.3, 0.4], atol=1e-6)


def test_spec_trans_steps_with_the_diffuse_weight_held(mi):
    """A loss that sees only the diffuse weight gives spec_trans no gradient: it moves
    along the valley instead of across it; the base colour's gradient is the weight's."""
    import drjit as dr

    variables, params, key = _variables(mi, diffuse_weight_fitted([BASE_COLOR, SPEC_TRANS]))
    variables.apply(key)
    diffuse_weight = params[BASE_COLOR.key] * (1 - params[SPEC_TRANS.key])
    dr.backward(dr.sum(diffuse_weight))
    assert abs(float(np.ravel(dr.grad(variables.optimizer["spec_trans"]))[0])) < 1e-6
    assert np.allclose(np.ravel(dr.grad(variables.optimizer["base_color"])), 1.0, atol=1e-5)


def test_the_base_colour_stays_inside_its_bounds_when_spec_trans_moves(mi):
    variables, params, key = _variables(
        mi, diffuse_weight_fitted([BASE_COLOR, SPEC_TRANS]), base_color=(0.9, 0.9, 0.9), spec_trans=0.1
    )
    variables.optimizer["spec_trans"] = type(variables.optimizer["spec_trans"])(0.7)
    variables.clamp()
    variables.apply(key)
    assert np.all(np.ravel(params[BASE_COLOR.key]) <= 1.0 + 1e-6)
    assert np.all(variables.snapshot()["base_color"] <= 1.0 + 1e-6)
    # spec_trans at 1: the weight is held at 0, and the colour stays finite
    variables.optimizer["spec_trans"] = type(variables.optimizer["spec_trans"])(1.0)
    variables.clamp()
    variables.apply(key)
    assert np.all(np.isfinite(np.ravel(params[BASE_COLOR.key])))


def test_only_the_models_that_fit_spec_trans_fit_the_diffuse_weight():
    principled = {p.name: p for p in fit_parameters("principled")}
    assert principled["base_color"].times_complement_of == "spec_trans"
    assert all(p.times_complement_of is None for p in fit_parameters("opaque") + fit_parameters("volumetric"))
    texture = {p.name: p for p in refit_parameters("principled", {"base_color": (0.001, 1.0)}, (0.01, 0.0))}
    assert texture["base_color"].key.endswith(".data") and texture["base_color"].times_complement_of == "spec_trans"
    alone = refit_parameters("principled", {"base_color": (0.001, 1.0)}, (0.01, 0.0), constants=False)
    assert alone[0].times_complement_of is None


def test_a_complement_of_a_parameter_not_fitted_is_refused(mi):
    with pytest.raises(PipelineError, match="times_complement_of"):
        _variables(mi, [replace(BASE_COLOR, times_complement_of="metallic"), SPEC_TRANS])
