"""`rover aoa` and operators/aoa/bare_log.py: AoA on a bare CSI Tool log, on the real LGTM captures."""

from __future__ import annotations

import contextlib
import io
import math

import numpy as np
import pytest
from helpers import reference_data

from rover.cli.app import main
from rover.formats.intel5300 import read_dat
from rover.formats.rig import rig_from_text
from rover.operators.aoa.bare_log import log_bursts, log_stamps_ns

LGTM_RIG = "receiver:\n  antenna_positions_m: [[0, 0], [0, -0.1], [0, -0.2]]\n  channel: 64\n"


def rover(*argv: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            status = main(list(argv))
        except SystemExit as exc:  # argparse's usage errors
            status = int(exc.code or 0)
    return status, out.getvalue(), err.getvalue()


def test_log_stamps_unwrap_the_nics_clock():
    low = np.array([2**32 - 2_000, 2**32 - 1_000, 500, 1_500, 2**32 - 10, 5], dtype=np.uint32)
    assert log_stamps_ns(low).tolist() == [
        0,
        1_000_000,
        2_500_000,
        3_500_000,
        2**32 * 1000 * 2 - 2**32 * 1000 + 1_990_000,
        2**32 * 1000 + 2_005_000,
    ]


def test_bursts_of_a_capture_hold_every_jump_combination():
    """A ULA's three chains: four combinations of pi jumps, each a candidate unless two coincide."""
    path = reference_data() / "csi" / "lgtm" / "lgtm-monitor.dat--1m-20-degrees--laptop-1--test-1.dat"
    records = read_dat(path)
    bursts = log_bursts(records, rig_from_text(LGTM_RIG), 64, 100)
    assert sum(b.packets for b in bursts) == int(np.sum(records.nrx == 3))
    assert all(1 <= len(b.candidate_angles_rad) <= 4 and b.chosen == -1 for b in bursts)
    assert all(b.angle_rad == b.candidate_angles_rad[0] for b in bursts)
    assert all(abs(math.degrees(a)) <= 90.0 + 1e-9 for b in bursts for a in b.candidate_angles_rad)  # in front


@pytest.mark.slow
def test_rover_aoa_runs_on_every_lgtm_capture(tmp_path):
    setup = tmp_path / "rig.yaml"
    setup.write_text(LGTM_RIG)
    captures = sorted((reference_data() / "csi" / "lgtm").glob("*.dat"))
    assert len(captures) == 50
    for path in captures:
        status, out, err = rover("-q", "aoa", str(path), "--setup", str(setup), "--burst", "200")
        assert status == 0, (path.name, err)
        assert "bursts of 200 packets" in out
    csv = tmp_path / "out.csv"
    assert rover("-q", "aoa", str(captures[0]), "--setup", str(setup), "--csv", str(csv))[0] == 0
    rows = csv.read_text().splitlines()
    assert rows[0].startswith("time_s,packets,angle_deg") and len(rows) > 2


@pytest.mark.parametrize(
    "rig, extra, message",
    [
        ("receiver:\n  antenna_positions_m: [[0, 0], [0, -0.1], [0, -0.2]]\n", [], "give --channel N"),
        (LGTM_RIG, ["--calibration", "missing.yaml"], "missing.yaml"),
        (LGTM_RIG, ["--channel", "999"], "999 is not a WiFi channel"),
        (LGTM_RIG, ["--burst", "2"], "a whole number of packets from 3"),
    ],
)
def test_bad_input_is_one_line_and_status_2(tmp_path, rig, extra, message):
    """One error line naming the problem (argparse's own come after its usage lines)."""
    setup = tmp_path / "rig.yaml"
    setup.write_text(rig)
    path = reference_data() / "csi" / "lgtm" / "lgtm-monitor.dat--1m-0-degrees--laptop-1--test-1.dat"
    status, _out, err = rover("-q", "aoa", str(path), "--setup", str(setup), *extra)
    lines = err.strip().splitlines()
    assert status == 2 and message in lines[-1] and sum("error" in line for line in lines) == 1, err


def test_a_calibration_file_of_the_wrong_shape_is_one_line(tmp_path):
    setup, calibration = tmp_path / "rig.yaml", tmp_path / "cal.yaml"
    setup.write_text(LGTM_RIG)
    calibration.write_text("receiver: [1, 2]\n")
    path = reference_data() / "csi" / "lgtm" / "lgtm-monitor.dat--1m-0-degrees--laptop-1--test-1.dat"
    status, _out, err = rover("-q", "aoa", str(path), "--setup", str(setup), "--calibration", str(calibration))
    assert status == 2 and "no receiver.phase_offsets_rad" in err and len(err.strip().splitlines()) == 1, err


def test_a_log_cut_while_being_written_is_read_to_its_cut_and_says_so(tmp_path):
    from helpers import run_rover

    setup = tmp_path / "rig.yaml"
    setup.write_text(LGTM_RIG)
    whole = sorted((reference_data() / "csi" / "lgtm").glob("*.dat"))[0]
    cut = tmp_path / "cut.dat"
    cut.write_bytes(whole.read_bytes()[:-50])
    proc = run_rover("aoa", str(cut), "--setup", str(setup), "--burst", "200")
    assert proc.returncode == 0, proc.stderr
    about_the_cut = [line for line in proc.stderr.splitlines() if str(cut) in line]
    assert about_the_cut == [
        f"rover: WARNING: {cut}: 1 record(s) cut short or corrupt and 0 byte(s) of garbage skipped "
        "(a log cut while being written ends with a cut record)"
    ]
    assert f"{len(read_dat(whole).nrx) - 1} records" in proc.stdout
