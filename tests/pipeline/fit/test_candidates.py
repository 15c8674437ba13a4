"""pipeline.fit.candidates: the rule every choice by evidence follows."""

import pytest

from pipeline.fit.candidates import Candidate, choose, improves
from pipeline.fit.engine import FitResult
from pipeline.formats.scene_description import Integrator


def _candidate(model: str, error: float | None, depth: int = 8) -> Candidate:
    result = FitResult({}, 1, error, "iterations", start_validation_error=1.0)
    integrator = Integrator(type="path", max_depth=depth, differentiable="prb")
    return Candidate(model, None, integrator, result, ["view_002"], 2.0)


def test_the_simplest_within_the_margin_of_the_best_wins():
    ladder = [_candidate("opaque", 0.0104), _candidate("principled", 0.0100), _candidate("volumetric", 0.0060)]
    assert choose(ladder, 0.05, "material")[0].model == "volumetric"
    assert choose(ladder[:2], 0.05, "material")[0].model == "opaque"  # 4 % worse: within 5 %
    winner, why = choose(ladder[:2], 0.03, "material")
    assert winner.model == "principled" and "principled" in why and "3%" in why


def test_without_held_out_errors_the_last_candidate_is_kept_and_said_why():
    assert choose([_candidate("opaque", None), _candidate("principled", None)], 0.05, "material")[1] == (
        "no held-out photos"
    )
    assert choose([_candidate("principled", 0.1)], 0.05, "material")[1] == "the only material candidate fitted"


@pytest.mark.parametrize(
    ("richer", "simpler", "margin", "climbs"),
    [
        (0.0090, 0.0100, 0.05, True),
        (0.0096, 0.0100, 0.05, False),
        (0.0110, 0.0100, 0.0, False),
        (None, 0.01, 0.0, False),
    ],
)
def test_a_ladder_climbs_only_when_the_last_rung_improved_by_more_than_the_margin(richer, simpler, margin, climbs):
    assert improves(_candidate("principled", richer), _candidate("opaque", simpler), margin) is climbs


def test_candidates_name_themselves_by_what_is_chosen_and_summarise_their_fit():
    deep = _candidate("principled", 0.01, depth=16)
    assert (deep.name("material"), deep.name("depth"), deep.name("light")) == ("principled", "max_depth 16", "given")
    assert deep.summary("depth") == {
        "model": "max_depth 16",
        "validation_mse": 0.01,
        "start_validation_mse": 1.0,
        "seconds": 2.0,
    }
