import numpy as np

from pipeline.synthetic.set_pieces import PLATE_DOT, PLATE_INK, dot_centres, dotted_plate


def test_the_plate_is_white_exactly_where_a_texel_lies_within_a_dots_radius():
    """dotted_plate draws each dot only in the columns (radii) it can reach: the same
    texels as testing every texel of the disk against every dot."""
    size, dots, radius = 256, 12, 0.05
    u = (np.arange(size) + 0.5) / size
    r, phi = np.meshgrid(u, 2 * np.pi * u)
    x, y = r * np.cos(phi), r * np.sin(phi)
    within = np.zeros((size, size), bool)
    for cx, cy in dot_centres(7, dots, radius):
        within |= np.hypot(x - cx, y - cy) < radius
    plate = dotted_plate(7, dots, radius, size)
    assert within.any() and np.array_equal(plate, np.where(within, PLATE_DOT, PLATE_INK).astype(np.float32))
