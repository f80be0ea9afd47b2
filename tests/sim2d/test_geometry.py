"""Tests of the can world's geometry (sim2d/geometry.py): positions, fields, masks."""

import math

import numpy as np
from effect_networks.sim2d import geometry, materials
from hypothesis import given
from hypothesis import strategies as st


def field(row: int, column: int) -> int:
    return row * geometry.N_COLUMNS + column


def test_constants():
    assert (
        geometry.N_CANS == 10 and geometry.N_FIELDS == 195 == geometry.N_COLUMNS * geometry.N_ROWS
    )
    assert (geometry.N_COLUMNS, geometry.N_ROWS) == (15, 13)
    assert geometry.ANGLES == ((7.0, 0.0), (7.0, -4.0), (7.0, 4.0))
    assert geometry.ANGLE_NAMES == ("0deg", "30deg", "-30deg")
    assert materials.BALL_MASS == 2.0
    assert math.isclose(geometry.PYRAMID_WIDTH, 0.54) and math.isclose(
        geometry.PYRAMID_HEIGHT, 0.64
    )


def test_can_positions_rows_gaps_and_support():
    p = geometry.can_positions()
    assert p.shape == (10, 2)
    rows = [[0, 1, 2, 3], [4, 5, 6], [7, 8], [9]]
    for r, members in enumerate(rows):
        np.testing.assert_allclose(p[members, 1], geometry.CAN_HEIGHT * (r + 0.5))
        # neighbours in a row: 2 cm between their faces
        np.testing.assert_allclose(np.diff(p[members, 0]), geometry.CAN_WIDTH + geometry.GAP)
    assert math.isclose(p[0, 0] - geometry.CAN_WIDTH / 2, geometry.PYRAMID_X)
    assert math.isclose(p[3, 0] + geometry.CAN_WIDTH / 2, geometry.PYRAMID_X + 0.54)
    for i, below in enumerate(geometry.SUPPORTERS):
        if below is None:
            assert i < 4
            continue
        # centred over the gap between its two supporters, resting on them
        assert math.isclose(p[i, 0], p[list(below), 0].mean())
        assert math.isclose(p[i, 1] - p[below[0], 1], geometry.CAN_HEIGHT)
    # the named groups are the pyramid's edges
    assert geometry.NEAR_FLANK == (0, 4, 7, 9) and geometry.FAR_FLANK == (3, 6, 8, 9)
    assert geometry.TOP_THREE == (7, 8, 9)
    assert np.all(np.diff(p[list(geometry.NEAR_FLANK), 0]) > 0)
    assert np.all(np.diff(p[list(geometry.FAR_FLANK), 0]) < 0)


def test_field_centres_grid():
    c = geometry.field_centres()
    assert c.shape == (195, 2)
    assert np.all(c[:, 0] > geometry.PYRAMID_X) and np.all(c[:, 0] < geometry.PYRAMID_X + 0.54)
    assert np.all(c[:, 1] > 0) and np.all(c[:, 1] < 0.64)
    np.testing.assert_allclose(c[field(0, 0)], [geometry.PYRAMID_X + 0.018, 0.32 / 13])
    np.testing.assert_allclose(
        c[field(12, 14)], [geometry.PYRAMID_X + 0.54 - 0.018, 0.64 - 0.32 / 13]
    )
    # field = row * 15 + column: columns vary x, rows vary z
    np.testing.assert_allclose(c[field(5, 3)], [c[field(0, 3), 0], c[field(5, 0), 1]])


@given(st.sets(st.integers(0, 9)))
def test_mask_round_trip(members):
    mask = geometry.cans_to_mask(members)
    assert geometry.mask_to_cans(mask) == tuple(sorted(members))
    assert geometry.n_cans(mask) == len(members)
