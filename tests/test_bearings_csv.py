"""Bearings from another front end as a CSV (rover.formats.bearings_csv): times to the nanosecond as
written, rows sorted by time, a spreadsheet's byte-order mark accepted. (Refused rows: test_replay.)"""

from __future__ import annotations

import math

import numpy as np

from rover.formats.bearings_csv import HEADER, read_bearings


def test_times_are_read_to_the_nanosecond_as_written_and_rows_sorted_by_them(tmp_path):
    """A float holds 1.7e9 s only to about 120 ns: 1700000000.000000001 and 1.7e9 would be one time."""
    path = tmp_path / "b.csv"
    path.write_text(
        f"{HEADER}\n1700000000.000000001,1,30,5\n1.7e9,2,-40,4\n 1700000000.5 ,3,1,1\n1700000000.1234567891,4,0,2\n"
    )
    b = read_bearings(path)
    assert b.stamp_ns.tolist() == [1_700_000_000_000_000_000, 1_700_000_000_000_000_001, 1_700_000_000_123_456_789,
                                   1_700_000_000_500_000_000]  # fmt: skip
    assert b.tag.tolist() == [2, 1, 4, 3]
    assert np.allclose(np.degrees(b.angle_rad), [-40, 30, 0, 1]) and math.isclose(math.degrees(b.std_rad[0]), 4)


def test_a_byte_order_mark_before_the_header_is_no_error(tmp_path):
    path = tmp_path / "b.csv"
    path.write_bytes(f"\ufeff{HEADER}\n10.5,1,30,5\n".encode())
    assert read_bearings(path).stamp_ns.tolist() == [10_500_000_000]
