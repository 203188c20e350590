"""Per-chain phase calibration (`rover calibrate`): synthetic CSI with known offsets, the real LGTM
captures (a transmitter at labelled angles, ten repeats each), a simulated dataset, and the CLI."""

from __future__ import annotations

import contextlib
import functools
import io
import math
import re
import tempfile
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers import T0_NS, reference_data
from hypothesis import given
from hypothesis import strategies as st
from test_cli_contract import FUZZ, _mutated, assert_contract, run_cli, text_or_bytes

from rover.cli.app import main
from rover.datasets.scenario import load_scenario
from rover.errors import BadInput
from rover.formats.bag import BagWriter
from rover.formats.intel5300 import read_dat, split_records
from rover.formats.rig import rig_from_text
from rover.formats.wifi import SPEED_OF_LIGHT_M_S, SUBCARRIER_SPACING_HZ, SUBCARRIERS_20MHZ, subcarrier_freqs_hz
from rover.messages import header, make
from rover.operators.aoa.calibration import compare, estimate_offsets, jump_step_rad, reduce_offsets

LGTM_ULA = np.array([[0.0, 0.0], [0.0, -0.1], [0.0, -0.2]])
"""LGTM's laptop array in the robot frame: antenna 1 leftmost, so a positive angle puts it nearest."""
LGTM_CHANNEL = 64
LGTM_ANGLES_DEG = (0, 10, -10, 20, -20)
D = 0.0258
TRIANGLE = np.array([[0.0, 0.0], [D, 0.0], [D / 2, -D * math.sqrt(3) / 2]])
SUBCARRIERS = len(SUBCARRIERS_20MHZ)
SIGMAS = 5.0
"""Estimates are held to this many standard errors of the mean."""
CALIBRATION_BUDGET_DEG = load_scenario("paper").receiver.calibration_error_deg
"""The calibration error the paper scenario (and so the estimator's tuning) assumes: repeated
calibrations that disagree by more than this are not good enough to use."""
RIG = (
    "receiver:\n  antenna_positions_m: [[0.0, 0.0], [0.0, -0.1], [0.0, -0.2]]\n"
    "excitation: {channel: 64}  # required by the rig format for now\n"
)


def synthesize(antennas, channel, angles_rad, offsets_rad, snr_db, seed):
    """Raw CSI (P, 30, M) of one plane wave per packet, as the card reports it: the steering vector
    at each subcarrier's frequency, the chains' offsets exp(+j phi), a random sampling-time offset
    and common phase per packet, and complex Gaussian noise at `snr_db` per subcarrier."""
    rng = np.random.default_rng(seed)
    angles = np.asarray(angles_rad, dtype=float)
    u = np.stack([np.cos(angles), np.sin(angles)], axis=-1)  # (P, 2)
    lead_m = u @ antennas.T  # (P, M): how much nearer the source each antenna is
    f = subcarrier_freqs_hz(channel)
    h = np.exp(2j * np.pi * f[None, :, None] * lead_m[:, None, :] / SPEED_OF_LIGHT_M_S)
    sto_s = rng.uniform(-50e-9, 150e-9, len(angles))
    h = h * np.exp(-2j * np.pi * (SUBCARRIERS_20MHZ * SUBCARRIER_SPACING_HZ)[None, :, None] * sto_s[:, None, None])
    h = h * np.exp(1j * rng.uniform(-np.pi, np.pi, len(angles)))[:, None, None]
    h = h * np.exp(1j * np.asarray(offsets_rad))[None, None, :]
    sigma = math.sqrt(10 ** (-snr_db / 10) / 2)
    return h + sigma * (rng.standard_normal(h.shape) + 1j * rng.standard_normal(h.shape))


def standard_error_rad(snr_db: float, packets: int) -> float:
    """Standard error of a chain's offset: a subcarrier's phase difference between two chains has
    variance 1/snr, the 30 subcarriers of a packet average it, the packets average that."""
    return math.sqrt(10 ** (-snr_db / 10) / SUBCARRIERS / packets)


def wrapped(a):
    return np.angle(np.exp(1j * np.asarray(a)))


# --- synthetic CSI -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("antennas", "channel", "angle_deg"),
    [(TRIANGLE, 149, 130.0), (TRIANGLE, 6, -60.0), (LGTM_ULA, 64, 20.0), (LGTM_ULA, 64, -20.0)],
)
def test_recovers_the_offsets_modulo_the_jump_step(antennas, channel, angle_deg):
    rng = np.random.default_rng(channel)
    phi = rng.uniform(-np.pi, np.pi, 3)  # chain 1 too: only differences are observable
    packets, snr_db = 300, 15.0
    csi = synthesize(antennas, channel, np.full(packets, math.radians(angle_deg)), phi, snr_db, seed=1)
    cal = estimate_offsets(csi, antennas, channel, math.radians(angle_deg))
    step = math.pi if channel > 14 else math.pi / 2
    assert cal.jump_step_rad == step
    assert cal.offsets_rad[0] == 0.0 and cal.packets == packets and cal.outliers == 0
    bound = SIGMAS * standard_error_rad(snr_db, packets)
    assert np.all(np.abs(wrapped(cal.offsets_rad - (phi - phi[0]))) < bound)  # no jump here: the session's own
    assert np.all(np.abs(reduce_offsets(cal.reduced_rad - (phi - phi[0]), step)) < bound)
    assert np.all((cal.reduced_rad >= -step / 2) & (cal.reduced_rad < step / 2))
    per_packet_deg = math.degrees(math.sqrt(10 ** (-snr_db / 10) / SUBCARRIERS))
    assert np.all(np.abs(cal.spread_deg[1:] - per_packet_deg) < 0.2 * per_packet_deg)


def test_the_known_angle_matters():
    """Dividing out the wrong direction (the angle's sign flipped) gives wrong offsets: the sign
    convention of the steering vector is in the estimate."""
    phi = np.array([0.0, 0.7, -2.1])
    csi = synthesize(LGTM_ULA, 64, np.full(200, math.radians(20)), phi, 20.0, seed=2)
    right = estimate_offsets(csi, LGTM_ULA, 64, math.radians(20))
    wrong = estimate_offsets(csi, LGTM_ULA, 64, math.radians(-20))
    assert np.all(np.abs(reduce_offsets(right.reduced_rad - phi, math.pi)) < math.radians(1))
    assert np.any(np.abs(reduce_offsets(wrong.reduced_rad - phi, math.pi)) > math.radians(10))


def test_an_angle_per_packet():
    """A transmitter that moves: each packet divided by its own direction."""
    phi = np.array([0.0, -1.2, 2.5])
    angles = np.linspace(-math.pi, math.pi, 400, endpoint=False)
    csi = synthesize(TRIANGLE, 157, angles, phi, 20.0, seed=3)
    cal = estimate_offsets(csi, TRIANGLE, 157, angles)
    assert np.all(np.abs(wrapped(cal.offsets_rad - phi)) < SIGMAS * standard_error_rad(20.0, 400))


def test_packets_from_another_direction_are_left_out():
    """A tenth of the packets from a second transmitter would pull a plain mean by degrees."""
    phi = np.array([0.0, 1.1, -0.4])
    good = synthesize(LGTM_ULA, 64, np.full(450, math.radians(10)), phi, 20.0, seed=4)
    other = synthesize(LGTM_ULA, 64, np.full(50, math.radians(-35)), phi, 20.0, seed=5)
    csi = np.concatenate([good, other])[np.random.default_rng(6).permutation(500)]
    cal = estimate_offsets(csi, LGTM_ULA, 64, math.radians(10))
    assert 50 <= cal.outliers <= 55
    assert np.all(np.abs(wrapped(cal.offsets_rad - phi)) < SIGMAS * standard_error_rad(20.0, cal.packets))


@pytest.mark.parametrize(("channel", "shift"), [(64, [0, 1, 0]), (64, [0, 1, 1]), (6, [0, 3, 2]), (149, [0, 0, 0])])
def test_compare_finds_the_jumps_between_two_sessions(channel, shift):
    step = jump_step_rad(channel)
    phi = np.array([0.0, 2.0, -0.5])
    a = estimate_offsets(synthesize(TRIANGLE, channel, np.zeros(200), phi, 20.0, 7), TRIANGLE, channel, 0.0)
    later = phi + step * np.array(shift)
    b = estimate_offsets(synthesize(TRIANGLE, channel, np.zeros(200), later, 20.0, 8), TRIANGLE, channel, 0.0)
    jumps = compare(b, a)
    assert jumps.multiples.tolist() == shift
    assert np.all(np.abs(jumps.residual_rad) < SIGMAS * math.sqrt(2) * standard_error_rad(20.0, 200))
    assert np.all(np.abs(reduce_offsets(b.reduced_rad - a.reduced_rad, step)) < math.radians(1))


def test_jump_step_and_bad_input():
    assert jump_step_rad(36) == jump_step_rad(165) == math.pi
    assert jump_step_rad(1) == jump_step_rad(14) == math.pi / 2
    csi = synthesize(TRIANGLE, 149, np.zeros(5), np.zeros(3), 20.0, 9)
    for call in (
        lambda: jump_step_rad(15),
        lambda: estimate_offsets(csi[:, :20], TRIANGLE, 149, 0.0),
        lambda: estimate_offsets(csi, TRIANGLE[:2], 149, 0.0),
        lambda: estimate_offsets(csi, TRIANGLE, 149, np.zeros(4)),
        lambda: estimate_offsets(csi, TRIANGLE, 149, math.nan),
        lambda: estimate_offsets(csi[:1], TRIANGLE, 149, 0.0),
        lambda: estimate_offsets(np.zeros_like(csi), TRIANGLE, 149, 0.0),
        lambda: compare(estimate_offsets(csi, TRIANGLE, 149, 0.0), estimate_offsets(csi, TRIANGLE, 153, 0.0)),
    ):
        with pytest.raises(BadInput):
            call()


# --- the real LGTM captures ----------------------------------------------------------------------


def lgtm_path(angle_deg: int, test: int) -> Path:
    label = f"neg-{-angle_deg}" if angle_deg < 0 else str(angle_deg)
    return reference_data() / "csi" / "lgtm" / f"lgtm-monitor.dat--1m-{label}-degrees--laptop-1--test-{test}.dat"


def lgtm_calibration(angle_deg: int, test: int):
    records = read_dat(lgtm_path(angle_deg, test))
    return estimate_offsets(records.csi[:, :, :3, 0], LGTM_ULA, LGTM_CHANNEL, math.radians(angle_deg))


def circular_std_modulo_deg(values_rad: np.ndarray, step: float, axis: int = 0) -> np.ndarray:
    """Circular standard deviation of angles known modulo `step` (scaled to a full turn and back)."""
    r = np.abs(np.exp(1j * np.asarray(values_rad) * 2 * math.pi / step).mean(axis=axis))
    return np.degrees(np.sqrt(-2 * np.log(np.minimum(r, 1.0)))) * step / (2 * math.pi)


def test_lgtm_repeats_agree_modulo_pi_and_their_jumps_are_found():
    """The 20-degree set-up (the one the data's README quotes), its ten repeats calibrated with the
    label: the same offsets modulo pi; the session's own offsets differ by pi on some chains."""
    cals = [lgtm_calibration(20, test) for test in range(1, 11)]
    reduced = np.array([c.reduced_rad for c in cals])
    across = circular_std_modulo_deg(reduced, math.pi)
    assert np.all(across < CALIBRATION_BUDGET_DEG), across
    jumps = [compare(c, cals[0]) for c in cals[1:]]
    assert all(np.all(np.abs(np.degrees(j.residual_rad)) < CALIBRATION_BUDGET_DEG) for j in jumps)
    shifted = np.array([j.multiples for j in jumps])
    assert shifted.any(), "the README reports pi jumps between these repeats"
    raw_gap = np.abs(wrapped(np.array([c.offsets_rad - cals[0].offsets_rad for c in cals[1:]])))
    assert np.all((raw_gap > math.pi / 2) == (shifted == 1))
    assert all(c.packets > 0.99 * (c.packets + c.outliers) for c in cals)


def test_lgtm_offsets_follow_the_antennas_through_a_permutation_change():
    """0-degree test 4 switches antenna selection mid-capture (antenna_sel 6 and 9): calibrated per
    selection, after the CSI Tool's permutation, both give the same offsets, so the offsets belong
    to the permuted antenna index (what `phase_offsets_rad` lists), not to the RF chain."""
    records = read_dat(lgtm_path(0, 4))
    by_selection = [
        estimate_offsets(records.csi[records.antenna_sel == sel, :, :3, 0], LGTM_ULA, LGTM_CHANNEL, 0.0)
        for sel in (6, 9)
    ]
    assert min(c.packets for c in by_selection) > 300
    gap = np.degrees(compare(*by_selection).residual_rad)
    assert compare(*by_selection).multiples.tolist() == [0, 0, 0]
    assert np.all(np.abs(gap) < CALIBRATION_BUDGET_DEG)


def test_a_frame_takes_the_one_true_angle_of_its_stamp_and_channel():
    """A frame matches an angle of the same stamp and channel; a frame of channel 0 takes the angle's
    channel when there is exactly one; an ambiguous or missing angle leaves the frame out."""
    from rover.operators.aoa.calibration import match_truth

    stamps = [10, 20, 30, 40, 50]
    channels = [36, 0, 0, 40, 36]
    angles = {10: [(36, 0.1), (40, 0.2)], 20: [(44, 0.3)], 30: [(36, 0.4), (40, 0.5)], 40: [(36, 0.6)]}
    assert match_truth(stamps, channels, angles) == ([0, 1], [36, 44], [0.1, 0.3])


# --- a simulated dataset -------------------------------------------------------------------------


@pytest.mark.slow
def test_simulated_dataset_gives_the_true_offsets_per_channel(simulated):
    """Without wall reflections the only errors are noise and quantization: each tag channel's
    calibration equals the scenario's true offsets modulo pi (the simulator shifts chains by pi
    per channel), within standard errors."""
    from rover.cli.calibrate import _calibrate_dataset

    path = simulated("paper", 1, "trajectory.laps=1", "room.wall_reflection=0")
    truth = np.array(load_scenario("paper").receiver.phase_offsets_rad)
    cals = [c for _, c in _calibrate_dataset(path, None)]
    assert sorted(c.channel for c in cals) == sorted(t.channel for t in load_scenario("paper").tags)
    for c in cals:
        error = reduce_offsets(c.reduced_rad - (truth - truth[0]), math.pi)
        standard_error = np.radians(c.spread_deg) / math.sqrt(c.packets)
        assert np.all(np.abs(error[1:]) < SIGMAS * standard_error[1:]), (c.channel, np.degrees(error))


# --- the command line ----------------------------------------------------------------------------


def run(*args: str) -> tuple[int, str, list[str]]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = main(["-q", *args])
    return status, out.getvalue(), err.getvalue().splitlines()


@pytest.fixture
def rig_file(tmp_path) -> Path:
    path = tmp_path / "rig.yaml"
    path.write_text(RIG)
    return path


def test_cli_calibrates_a_log_and_writes_the_setup_block(tmp_path, rig_file):
    log = lgtm_path(20, 2)
    out = tmp_path / "calibration.yaml"
    args = [str(log), "--setup", str(rig_file), "--angle-deg", "20", "--channel", "64", "--out", str(out)]
    status, stdout, err = run("calibrate", *args)
    assert status == 0, err
    expected = lgtm_calibration(20, 2)
    written = yaml.safe_load(out.read_text())["receiver"]["phase_offsets_rad"]
    assert list(written) == [64]
    assert np.allclose(written[64], expected.offsets_rad, atol=1e-4)
    assert "phase_offsets_rad: {64: [0.0000, " in stdout
    rig = rig_from_text(RIG.replace("receiver:\n", "receiver:\n  phase_offsets_rad: " + str(written) + "\n"))
    assert np.allclose(rig.phase_offsets(64), expected.offsets_rad, atol=1e-4)

    before = out.read_bytes()
    status, _, err = run("calibrate", *args)
    assert status == 2 and len(err) == 1 and "exists" in err[0] and str(out) in err[0]
    assert out.read_bytes() == before
    status, _, err = run("calibrate", *args, "--force")
    assert status == 0, err


def test_cli_several_logs_print_their_jumps(rig_file):
    logs = [str(lgtm_path(20, test)) for test in (1, 2, 3)]
    status, stdout, err = run("calibrate", *logs, "--setup", str(rig_file), "--angle-deg", "20", "--channel", "64")
    assert status == 0, err
    cals = [lgtm_calibration(20, test) for test in (1, 2, 3)]
    for later in (1, 2):
        line = next(row for row in stdout.splitlines() if row.startswith(Path(logs[later]).name + " vs "))
        printed = [int(k) for k in re.findall(r"chain (\d) by 180 deg", line)]
        assert printed == [k + 1 for k in np.flatnonzero(compare(cals[later], cals[0]).multiples)]
    assert len(stdout.splitlines()) == 1 + 3 + 2 + 1 + 2  # header, rows, jumps, blank, block


def test_cli_takes_the_channel_from_the_setup(tmp_path):
    rig = tmp_path / "rig.yaml"
    rig.write_text(RIG.replace("receiver:\n", "receiver:\n  channel: 64\n"))
    status, stdout, err = run("calibrate", str(lgtm_path(-20, 1)), "--setup", str(rig), "--angle-deg", "-20")
    assert status == 0, err
    expected = lgtm_calibration(-20, 1).offsets_rad
    assert f"{{64: [{', '.join(f'{v:.4f}' for v in expected)}]}}" in stdout


def lgtm_dataset(path: Path, angle_deg: float | None, packets: int | None = None) -> Path:
    """The 20-degree test 2 capture (its first `packets` records) as a dataset: its records as /csi
    frames on channel 64, with their true angle on /groundtruth/aoa (none when `angle_deg` is None),
    and the rig as metadata."""
    records = split_records(lgtm_path(20, 2).read_bytes())[0][:packets]
    with BagWriter(path, metadata={"rover.setup": {"yaml": RIG}}) as bag:
        for k, bfee in enumerate(records):
            stamp = T0_NS + k * 1_000_000
            frame = make(
                "rover_msgs/msg/CsiFrame",
                header=header(stamp, "base_link"),
                channel=64,
                bfee=np.frombuffer(bfee, dtype=np.uint8),
            )
            bag.write("/csi", frame, stamp)
            if angle_deg is not None:
                aoa = make(
                    "rover_msgs/msg/Aoa",
                    header=header(stamp, "base_link"),
                    channel=64,
                    angle_rad=math.radians(angle_deg),
                )
                bag.write("/groundtruth/aoa", aoa, stamp)
    return path


def test_cli_dataset_with_ground_truth_equals_the_log(tmp_path):
    out = tmp_path / "cal.yaml"
    status, _, err = run("calibrate", str(lgtm_dataset(tmp_path / "lgtm.mcap", 20)), "--out", str(out))
    assert status == 0, err
    written = yaml.safe_load(out.read_text())["receiver"]["phase_offsets_rad"]
    assert np.allclose(written[64], lgtm_calibration(20, 2).offsets_rad, atol=1e-4)


def test_cli_bad_input_is_one_line_and_status_2(tmp_path, rig_file):
    log = str(lgtm_path(20, 1))
    no_truth = str(lgtm_dataset(tmp_path / "no-truth.mcap", None))
    out = tmp_path / "cal.yaml"
    cases = {
        "missing.dat": ["calibrate", str(tmp_path / "missing.dat"), "--setup", str(rig_file), "--angle-deg", "0"],
        "--angle-deg": ["calibrate", log, "--setup", str(rig_file), "--channel", "64"],
        "--setup": ["calibrate", log, "--angle-deg", "20", "--channel", "64"],
        "--channel": ["calibrate", log, "--setup", str(rig_file), "--angle-deg", "20"],
        "/groundtruth/aoa": ["calibrate", no_truth],
        "once per log": ["calibrate", log, log, "--setup", str(rig_file), "--channel", "64"]
        + [a for v in ("1", "2", "3") for a in ("--angle-deg", v)],
    }
    for named, args in cases.items():
        status, _, err = run(*args, "--out", str(out))
        assert status == 2, (named, err)
        assert len(err) == 1 and named in err[0] and "Traceback" not in err[0], (named, err)
        assert not out.exists() and not any(p.name.startswith(".") for p in tmp_path.iterdir())


@functools.cache
def small_inputs() -> tuple[bytes, bytes]:
    """A short real log (the first 60 records of a capture) and the same as a dataset with ground truth."""
    data = lgtm_path(20, 2).read_bytes()
    log = b"".join(len(r).to_bytes(2, "big") + r for r in split_records(data)[0][:60])
    with tempfile.TemporaryDirectory() as folder:
        return log, lgtm_dataset(Path(folder) / "d.mcap", 20, 60).read_bytes()


@FUZZ
@given(data=st.data())
def test_cli_contract_on_any_log_or_dataset(data):
    """Any bytes, or a real log or dataset cut short or with bytes overwritten: status 0, or 2 with
    one line naming the file, nothing left behind."""
    log, dataset = small_inputs()
    which = data.draw(st.sampled_from(["c.dat", "d.mcap"]))
    content = data.draw(st.one_of(text_or_bytes, _mutated(log if which == "c.dat" else dataset)))
    options = ["--setup", "rig.yaml", "--angle-deg", "20", "--channel", "64"] if which == "c.dat" else []
    status, lines, left = run_cli(
        lambda d: [
            "calibrate",
            str(d / which),
            *[str(d / o) if o == "rig.yaml" else o for o in options],
            "--out",
            str(d / "o.yaml"),
        ],
        {which: content, "rig.yaml": RIG.encode()},
    )
    assert_contract(status, lines, left, which)
    assert status == 0 or len(lines) == 1


def test_a_log_name_holding_a_dataset_with_log_options_is_one_line_naming_it():
    """Found by the fuzz: a .dat whose bytes are an MCAP file is a dataset, and --angle-deg is refused naming it."""
    status, lines, left = run_cli(
        lambda d: ["calibrate", str(d / "c.dat"), "--angle-deg", "20", "--out", str(d / "o.yaml")],
        {"c.dat": b"\x89MCAP0\r\n"},
    )
    assert_contract(status, lines, left, "c.dat")
    assert status == 2 and len(lines) == 1
