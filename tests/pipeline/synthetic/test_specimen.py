"""The synthetic specimen's albedo pattern."""

import numpy as np

from pipeline.synthetic.specimen import BLOTCH_SCALE, blotch_colours


def _edges_along_a_line(scale: float) -> int:
    """Light-dark changes of the pattern along 20 cm of a straight line."""
    points = np.column_stack([np.linspace(0.0, 0.2, 4000), np.full(4000, 0.01), np.full(4000, 0.02)])
    colours = blotch_colours(points, np.array([0.5, 0.4, 0.3]), seed=3, scale=scale)
    light = colours.mean(axis=1) > 0.4
    return int(np.count_nonzero(light[1:] != light[:-1]))


def test_speckles_are_the_blotches_at_a_third_of_the_size():
    blotches, speckles = _edges_along_a_line(BLOTCH_SCALE), _edges_along_a_line(BLOTCH_SCALE / 3)
    assert blotches >= 5
    assert 2.0 < speckles / blotches < 4.5


def test_the_pattern_stays_within_the_unit_range():
    points = np.random.default_rng(0).uniform(-0.05, 0.05, (1000, 3))
    colours = blotch_colours(points, np.array([0.9, 0.05, 0.5]), seed=1, scale=BLOTCH_SCALE / 3)
    assert colours.min() >= 0.0 and colours.max() <= 1.0
