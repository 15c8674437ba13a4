"""Stage fit_material with a fit small enough for a test: on a small synthetic bird, and on
the bundled bird where the board (the light's level, white balance) takes part."""

import json

import numpy as np
import pytest

from pipeline.synthetic.score import score_heldout, score_material
from tests.support.tiny_fits import TINY_FIT, TINY_TEXTURE
from tests.support.toy_stages import run_python

pytestmark = pytest.mark.slow


def test_fit_material_moves_base_colour_toward_the_truth_within_bounds(run_stages, small_bird, mi):
    outputs = run_stages(small_bird, "fit_material", *TINY_FIT)["fit_material"]
    params = json.loads(outputs["params"].read_text())
    truth = json.loads((small_bird / "ground_truth" / "material.json").read_text())
    start = np.array([0.5, 0.5, 0.5])
    fitted = np.array(params["params"]["base_color"])
    target = np.array(truth["base_color_mean"])  # a constant fit to the textured bird
    assert np.abs(fitted - target).max() < np.abs(start - target).max()
    for name, (lower, upper) in params["bounds"].items():
        assert all(lower - 1e-6 <= v <= upper + 1e-6 for v in params["params"][name])
    assert len(params["held_out"]) == 2 and params["validation_mse"] is not None
    errors = score_material(params, truth)
    assert set(errors) >= {"base_color_abs_error", "roughness_abs_error", "spec_trans_abs_error", "eta_abs_error"}
    heldout = score_heldout(outputs["heldout"])
    assert heldout["views"] == 2 and np.isfinite(heldout["psnr_db_mean"])
    # The fitted scene renders as-is and carries the fitted values.
    fitted_scene = mi.traverse(mi.load_file(str(outputs["scene"])))
    np.testing.assert_allclose(np.ravel(fitted_scene["specimen.bsdf.base_color.value"]), fitted, rtol=1e-5)
    log = [json.loads(line) for line in (outputs["fitted_dir"] / "log.jsonl").read_text().splitlines()]
    assert len(log) == params["iterations"] and "validation_error" in log[3]


def test_white_balance_writes_centred_gains_by_which_the_views_divide_their_photos(run_stages, small_bird, mi):
    """With the light estimated, the gains' mean is moved into it: the gains are centred
    and the scene as written, times a photo's gain, renders like the photo."""
    from dataclasses import replace

    from pipeline.fit.loop import matched_gain
    from pipeline.fit.views import PhotoGains, Windowing, load_views, read_capture_photos
    from pipeline.formats.fit_results import MaterialFit
    from pipeline.formats.scene_description import SceneDescription

    overrides = (*TINY_FIT, "fit_material.white_balance=true", "light.model=constant")
    outputs = run_stages(small_bird, "fit_material", *overrides)
    params = json.loads(outputs["fit_material"]["params"].read_text())
    gains = params["photo_gains"]
    assert set(gains).isdisjoint(params["held_out"]) and len(gains) >= 3
    logarithms = np.log(np.array(list(gains.values())))
    assert logarithms.shape[1] == 3 and np.all(np.isfinite(logarithms))
    np.testing.assert_allclose(logarithms.mean(axis=0), 0.0, atol=1e-5)  # centred: the light took the level
    # the photo whose gain is farthest from 1, so that a render matched to it without its
    # gain would be off by more than the check below allows
    name = max(gains, key=lambda photo: np.abs(np.log(gains[photo])).max())
    assert np.abs(np.log(gains[name])).max() > 0.2
    photos = read_capture_photos(
        outputs["sfm"]["cameras"], outputs["undistort"]["pinhole"], outputs["masks"]["masks_json"]
    )
    description = SceneDescription.read(outputs["scene"]["description"])
    folder = outputs["fit_material"]["fitted_dir"]
    plain, divided = (
        load_views(folder, description, replace(photos, gains=given), Windowing(32, 0, 4), names={name})[0][0]
        for given in (None, PhotoGains({name: [2.0, 4.0, 0.5]}, params["gain_channels"]))
    )
    np.testing.assert_allclose(divided.reference * [2.0, 4.0, 0.5], plain.reference, rtol=1e-5)
    # held out, a photo's render is matched to it by a gain of as many channels, within
    # the range of the training photos' gains
    assert params["gain_channels"] == 3 and (plain.heldout_gain, divided.heldout_gain) == (0, 3)
    assert divided.heldout_gain_range == (0.5, 4.0)
    # the scene as written renders a training photo divided by its gain (on the pixels
    # its gain was matched on: the specimen's, as this capture has no board)
    assert description.board_print is None
    with_gains = replace(photos, gains=PhotoGains.of(MaterialFit.read(outputs["fit_material"]["params"])))
    fitted = load_views(folder, description, with_gains, Windowing(48, 2, 4), names={name})[0][0]
    render = np.asarray(mi.render(fitted.scene, sensor=fitted.sensor, integrator=fitted.integrator, spp=64))
    matched = matched_gain(render, render, fitted.reference, fitted.weight[..., None], 3)
    np.testing.assert_allclose(matched, 1.0, rtol=0.1)


def test_fit_material_rejects_bounds_of_unknown_parameters(run_stages, small_bird):
    from pipeline.core.errors import PipelineError

    with pytest.raises(PipelineError, match="alpha, not parameters of the principled model"):
        run_stages(small_bird, "fit_material", *TINY_FIT, 'fit_material.bounds=["alpha=0.1:0.5"]')


KILLED_IN_FIT = """
import os, signal
from pathlib import Path
import pipeline.fit.checkpoint as checkpoint
from pipeline.core.config import load_config
from pipeline.core.runner import Runner, Selection
from pipeline.core.sections import schema
from stages import STAGES

save = checkpoint.Checkpoint.save
def save_then_die(self, optimizer, arrays, record):
    save(self, optimizer, arrays, record)
    if record["iteration"] == 5:
        os.kill(os.getpid(), signal.SIGKILL)
checkpoint.Checkpoint.save = save_then_die
checkpoint.CHECKPOINT_EVERY_S = 0.0
capture = Path(CAPTURE)
config = load_config(schema(STAGES), capture, "standard", OVERRIDES)
Runner(capture, STAGES, config).run(Selection(until="fit_material"))
"""


def test_a_fit_killed_midway_resumes_where_it_was(run_stages, small_bird, caplog):
    overrides = [*TINY_FIT, "fit_material.seed=11"]  # a key no other test computes
    run_stages(small_bird, "scene")
    script = KILLED_IN_FIT.replace("CAPTURE", repr(str(small_bird))).replace("OVERRIDES", repr(overrides))
    killed = run_python(script, timeout=300)
    assert killed.returncode == -9, killed.stderr[-2000:]
    outputs = run_stages(small_bird, "fit_material", *overrides)["fit_material"]
    assert "at iteration 5" in caplog.text and "resuming a fit" in caplog.text
    log = [json.loads(line) for line in (outputs["fitted_dir"] / "log.jsonl").read_text().splitlines()]
    assert [e["iteration"] for e in log] == list(range(1, 9))
    assert not list((small_bird / ".pipeline" / "checkpoints").glob("fit_material-*"))  # removed once committed


def test_an_estimated_light_is_chosen_by_held_out_error_and_written_into_the_scene(run_stages, small_bird, mi):
    """light.model = auto: each light model fitted with the material, the simplest within
    the margin of the best kept, and every candidate's error and time reported."""
    from pipeline.formats.scene_description import SceneDescription

    overrides = (*TINY_FIT, "light.model=auto")
    stages = run_stages(small_bird, "fit_material", *overrides)
    outputs = stages["fit_material"]
    params = json.loads(outputs["params"].read_text())
    report = params["light"]
    assert [c["model"] for c in report["candidates"]] == ["constant", "envmap", "envmap+area"]
    errors = {c["model"]: c["validation_mse"] for c in report["candidates"]}
    assert all(c["seconds"] > 0 and c["validation_mse"] < c["start_validation_mse"] for c in report["candidates"])
    chosen = report["chosen"]["model"]
    assert errors[chosen] <= min(errors.values()) * 1.05
    simpler = list(errors)[: list(errors).index(chosen)]
    assert all(errors[m] > min(errors.values()) * 1.05 for m in simpler)
    # The level stays where the scene stage measured it (no board here: the specimen).
    assert report["level_from"] == SceneDescription.read(stages["scene"]["description"]).light.level_from
    assert params["validation_mse"] == errors[chosen]
    # The material's parameters only in "params"; the scene renders with the chosen light.
    assert set(params["params"]) == {"base_color", "roughness", "spec_trans", "eta"}
    keys = set(mi.traverse(mi.load_file(str(outputs["scene"]))).keys())
    assert ("environment.data" in keys) == (chosen != "constant")
    assert ("softbox.emitter.radiance.value" in keys) == (chosen == "envmap+area")
    for name in params["held_out"]:
        for kind in ("reference", "render", "difference"):
            assert (outputs["heldout"] / f"{name}.{kind}.png").is_file()


def test_a_material_model_left_open_is_chosen_by_held_out_error_and_carried_downstream(run_stages, small_bird, mi):
    """capture.material = auto: fit_material fits principled, then opaque from it, then
    volumetric only when principled beat opaque by more than model_margin; keeps the
    simplest within the margin of the best (margin 0: the best), then checks twice the
    path depth. The scene files, params.json and fit_texture follow the choice."""
    from dataclasses import replace

    from pipeline.formats.fit_results import MaterialFit
    from pipeline.formats.scene_description import SceneDescription

    overrides = (*TINY_FIT, "capture.material=auto", "fit_material.model_margin=0", *TINY_TEXTURE)
    outputs = run_stages(small_bird, "fit_texture", *overrides, "fit_texture.texture=off")
    description = SceneDescription.read(outputs["scene"]["description"])
    assert description.model_choice == ["opaque", "principled", "volumetric"]
    assert description.model == "principled" and set(description.integrators) == set(description.model_choice)
    params = json.loads(outputs["fit_material"]["params"].read_text())
    choice = params["model_choice"]
    errors = {c["model"]: c["validation_mse"] for c in choice["candidates"]}
    climbed = errors["principled"] < errors["opaque"]
    assert list(errors) == ["opaque", "principled", *(["volumetric"] if climbed else [])]
    assert all(c["seconds"] > 0 for c in choice["candidates"])
    expected = min(errors, key=errors.get)
    assert choice["chosen"] == params["model"] == expected
    names = {
        "opaque": {"base_color", "roughness", "specular"},
        "principled": {"base_color", "roughness", "spec_trans", "eta"},
        "volumetric": {"alpha", "eta", "albedo", "sigma_t"},
    }
    assert set(params["params"]) == names[expected]
    # The depth: the chosen model's own, or twice it when a deeper refit won.
    depth = choice["depth"]
    own = description.integrators[expected].max_depth
    assert depth["max_depth"] == own and depth["deeper_validation_mse"] > 0
    deeper = {c["model"]: c["validation_mse"] for c in depth.get("candidates", [])}
    assert not deeper or list(deeper) == [f"max_depth {own}", f"max_depth {2 * own}"]
    chosen_depth = 2 * own if deeper and deeper[f"max_depth {2 * own}"] < deeper[f"max_depth {own}"] else own
    assert MaterialFit.read(outputs["fit_material"]["params"]).integrator == replace(
        description.integrators[expected], max_depth=chosen_depth
    )
    assert params["validation_mse"] == (deeper[f"max_depth {chosen_depth}"] if deeper else errors[expected])
    scene = mi.load_file(str(outputs["fit_material"]["scene"]))
    assert f"max_depth = {chosen_depth}" in str(scene.integrator())
    values = mi.traverse(scene)
    # Both surface models are Mitsuba's principled BSDF: opaque sets its specular, principled its eta.
    assert ("specimen.bsdf.specular" in values.keys()) == (expected == "opaque")
    assert ("specimen.bsdf.spec_trans.value" in values.keys()) == (expected != "volumetric")
    assert ("specimen.interior_medium.sigma_t.value.value" in values.keys()) == (expected == "volumetric")
    texture = json.loads(outputs["fit_texture"]["params"].read_text())
    assert texture["model"] == expected and set(texture["params"]) == names[expected]
