"""The window's epochs: their bearings stacked into padded rows."""

from __future__ import annotations

import numpy as np

from rover.operators.slam.epoch import padded_rows


def test_blocks_of_several_widths_are_stacked_row_by_row_and_filled_out():
    blocks = [np.array([[1.0, 2.0], [3.0, 4.0]]), np.zeros((0, 3)), np.array([[5.0]]), np.array([[6.0, 7.0, 8.0]])]
    out = padded_rows(blocks, 4, np.nan)
    expected = np.array(
        [[1, 2, np.nan, np.nan], [3, 4, np.nan, np.nan], [5, np.nan, np.nan, np.nan], [6, 7, 8, np.nan]]
    )
    np.testing.assert_array_equal(out, expected)


def test_integer_blocks_stay_integers_and_no_blocks_give_no_rows():
    out = padded_rows([np.array([[2, 0]]), np.array([[1]])], 3, -1)
    assert out.dtype.kind == "i"
    np.testing.assert_array_equal(out, [[2, 0, -1], [1, -1, -1]])
    assert padded_rows([], 3, np.nan).shape == (0, 3)
