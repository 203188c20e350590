"""`rover simulate`: deterministic, physically consistent datasets that the rest of Rover reads like real ones."""

from __future__ import annotations

import json
import math
import signal

import numpy as np
import pytest
import yaml
from helpers import popen_rover, read_bag, run_rover, stop_while_writing

from rover.datasets.radio import Impairments, backscatter_csi, impair, true_aoa
from rover.datasets.scenario import Receiver, load_scenario
from rover.datasets.scenario_size import MAX_MESSAGES, scenario_size
from rover.datasets.simulate import antenna_positions, chain_jumps, simulate
from rover.errors import BadInput, SpecError
from rover.formats.bag import read_metadata
from rover.formats.intel5300 import RecordHeader, decode_bfee, encode_record
from rover.formats.wifi import SPEED_OF_LIGHT_M_S, phase_jump_step_rad, subcarrier_freqs_hz
from rover.geometry import wrap_angle, yaw_from_quaternion
from rover.messages import deserialize, make
from rover.operators.aoa.operator import Aoa, AoaParams
from rover.testing import run_operator

SHORT = {"trajectory.laps": "1"}


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "short.mcap"
    report = simulate(load_scenario("paper", SHORT), 11, out)
    return out, report


def bartlett(csi: np.ndarray, channel: int, antennas: np.ndarray) -> float:
    grid = np.radians(np.arange(-180.0, 180.0, 0.25))
    u = np.stack([np.cos(grid), np.sin(grid)], axis=1)
    f = subcarrier_freqs_hz(channel)
    steering = np.exp(2j * np.pi * f[:, None, None] * (u @ antennas.T)[None] / SPEED_OF_LIGHT_M_S)
    return float(grid[np.argmax(np.abs(np.einsum("fgm,fm->fg", steering.conj(), csi)).sum(axis=0))])


def test_a_single_path_has_the_design_angle_convention():
    scenario = load_scenario("paper")
    antennas = antenna_positions(scenario)
    tag = np.array([3.0, 2.0])
    for yaw in (0.0, 1.0, -2.5):
        for robot in ([1.0, 1.0], [5.0, 3.0], [2.0, 4.0]):
            xy = np.array([robot])
            csi, _ = backscatter_csi(np.array([4.5, 4.6]), tag, xy, np.array([yaw]), antennas, 165, 149, (9, 5), 0.0)
            truth = true_aoa(tag, xy, np.array([yaw]))[0]
            error = math.degrees(abs(wrap_angle(bartlett(csi[0], 149, antennas) - truth)))
            assert error < 0.5


def test_packed_records_decode_back_within_quantization():
    rng = np.random.default_rng(0)
    scenario = load_scenario("paper")
    antennas = antenna_positions(scenario)
    csi, _ = backscatter_csi(
        np.array([4.5, 4.6]),
        np.array([2.5, 0.25]),
        rng.uniform([1, 1], [8, 4], (50, 2)),
        rng.uniform(-3, 3, 50),
        antennas,
        165,
        149,
        (9, 5),
        0.5,
    )
    peak = rng.uniform(40, 90, 50)
    imp = Impairments(np.zeros(50), np.zeros(50), np.full(50, 200.0), peak, np.zeros(3))
    quantized = impair(csi, imp, rng)
    scaled = csi * (peak / np.maximum(np.abs(csi.real), np.abs(csi.imag)).max(axis=(1, 2)))[:, None, None]
    assert np.abs(quantized.real - scaled.real).max() <= 0.5 + 1e-6
    assert np.abs(quantized.imag - scaled.imag).max() <= 0.5 + 1e-6
    for k in range(50):
        record = encode_record(RecordHeader(k, k, (20, 20, 20), -127, 35, 0b011000, 0x4101), quantized[k][:, :, None])
        np.testing.assert_array_equal(decode_bfee([record], scaled=False).csi[0, :, :, 0], quantized[k])


@pytest.mark.slow
def test_the_same_seed_gives_the_same_bytes(tmp_path, short_run):
    again = tmp_path / "again.mcap"
    simulate(load_scenario("paper", SHORT), 11, again)
    assert again.read_bytes() == short_run[0].read_bytes()
    other = tmp_path / "other.mcap"
    simulate(load_scenario("paper", SHORT), 12, other)
    assert other.read_bytes() != again.read_bytes()


def test_truth_is_consistent_and_tags_are_heard_only_in_range(short_run):
    path, report = short_run
    messages = read_bag(path)
    poses = {s: deserialize(d, "geometry_msgs/msg/PoseStamped") for t, s, d in messages if t == "/groundtruth/pose"}
    (tags_msg,) = [deserialize(d, "rover_msgs/msg/TagArray") for t, _s, d in messages if t == "/groundtruth/tags"]
    tags = {t.id: np.array([t.position.x, t.position.y]) for t in tags_msg.tags}
    first = min(poses)
    assert (poses[first].pose.position.x, poses[first].pose.position.y) == (0.0, 0.0)
    stamps = np.array(sorted(poses))
    aoas = [deserialize(d, "rover_msgs/msg/Aoa") for t, _s, d in messages if t == "/groundtruth/aoa"]
    assert len(aoas) == report.counts["/csi"] > 1000
    for aoa in aoas[::50]:
        stamp = aoa.header.stamp.sec * 10**9 + aoa.header.stamp.nanosec
        pose = poses[stamps[max(np.searchsorted(stamps, stamp) - 1, 0)]].pose
        xy = np.array([pose.position.x, pose.position.y])
        yaw = yaw_from_quaternion(pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w)
        assert np.linalg.norm(tags[aoa.tag_id] - xy) <= 5.0 + 0.05
        expected = true_aoa(tags[aoa.tag_id], xy[None], np.array([yaw]))[0]
        assert abs(wrap_angle(aoa.angle_rad - expected)) < math.radians(3)


def test_the_imu_stands_still_then_turns_a_lap(short_run):
    path, _ = short_run
    imu = [deserialize(d, "sensor_msgs/msg/Imu") for t, _s, d in read_bag(path) if t == "/imu/data"]
    accel = np.array([[m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z] for m in imu])
    gyro_z = np.array([m.angular_velocity.z for m in imu])
    still = accel[:500]
    assert np.allclose(still.mean(axis=0), [0, 0, 9.80665], atol=0.08)
    assert still.std(axis=0).max() < 0.05
    assert abs(np.sum(gyro_z) / 200.0 - 3 * math.pi / 2) < math.radians(5), "a lap turns left at three corners"


QUICK = ("--set", "trajectory.laps=1", "--set", "trajectory.speed_m_s=1.0")
"""A 41 s run instead of 180 s: quicker to simulate, and still a moment to write (for the signal tests)."""


@pytest.mark.slow
def test_cli_round_trip_simulate_info_replay(tmp_path):
    out = tmp_path / "sim.mcap"
    proc = run_rover("simulate", "--seed", "4", *QUICK, "-o", str(out))
    assert proc.returncode == 0, proc.stderr
    info = json.loads(run_rover("info", "--json", str(out)).stdout)
    assert info["simulation"]["scenario"] == "paper" and set(info["simulation"]["direct_to_multipath_db"]) <= {
        "1",
        "2",
        "3",
        "4",
    }
    csi = next(t["count"] for t in info["topics"] if t["name"] == "/csi")
    run = run_rover("run", "--dataset", str(out), "--output", str(tmp_path / "run"), "-v")
    assert run.returncode == 0, run.stderr
    assert f"decode: in frames={csi}; out csi={csi}" in run.stderr, "every simulated record decodes"
    aoas = [
        deserialize(d, "rover_msgs/msg/Aoa")
        for t, _s, d in read_bag(tmp_path / "run" / "results.mcap")
        if t == "/rover/aoa"
    ]
    assert len(aoas) > 300 and {a.tag_id for a in aoas} <= {1, 2, 3, 4}
    assert run_rover("simulate", "-o", str(out)).returncode == 2, "an existing output is kept"


def test_scenario_mistakes_are_reported(tmp_path):
    with pytest.raises(BadInput, match="unknown scenario 'papr'; did you mean 'paper'"):
        load_scenario("papr")
    with pytest.raises(BadInput, match="--set trajectory.sped_m_s: no key 'sped_m_s' in section 'trajectory'; did"):
        load_scenario("paper", {"trajectory.sped_m_s": "1"})
    mine = tmp_path / "mine.yaml"  # in a scenario file: the file's line
    mine.write_text("trajectory:\n  sped_m_s: 1\n")
    with pytest.raises(SpecError, match="unknown key 'sped_m_s' in trajectory; did you mean 'speed_m_s'"):
        load_scenario(str(mine))
    with pytest.raises(SpecError, match="receiver.range_m: expected float"):
        load_scenario("paper", {"receiver.range_m": "far"})


@pytest.mark.parametrize(
    ("setting", "problem"),
    [
        ("room.scatterers=100000", "room.scatterers: must be >= 0 and <= 1000, got 100000"),
        ("room.shadowing_db=1e300", "room.shadowing_db: must be >= 0 and <= 60"),
        ("room.scatterer_reflectivity_m=[1e300,6]", "room.scatterer_reflectivity_m: must be > 0 and <= 10"),
        ("receiver.nlos_attenuation_db=[-1e300,0]", "receiver.nlos_attenuation_db: must be >= 0 and <= 60"),
        ("receiver.snr_db=[-1e300,0]", "receiver.snr_db: must be >= -40 and <= 80"),
    ],
)
def test_radio_values_beyond_physics_are_one_line_naming_the_key(tmp_path, capsys, setting, problem):
    """They used to reach the record encoder as infinite CSI (a traceback: "CSI values must fit in
    int8") or, for the scatterers, an allocation of packets x scatterers paths."""
    from rover.cli.app import main

    out = tmp_path / "out.mcap"
    assert main(["simulate", "--seed", "1", "--set", setting, "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert problem in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_an_output_that_is_a_directory_is_one_line_before_any_work(tmp_path, capsys):
    from rover.cli.app import main

    scenario = tmp_path / "broken.yaml"
    scenario.write_text("room: {size_m: [-1, 4]}\n")  # the output is checked first: this is never read
    assert main(["simulate", "--scenario", str(scenario), "-o", str(tmp_path), "--force"]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"rover: error: {tmp_path}: is a directory; name the file to write, e.g. {tmp_path / 'dataset.mcap'}"
    ]
    assert list(tmp_path.iterdir()) == [scenario]


def test_a_full_disk_is_one_line_naming_the_file_and_leaves_no_partial(tmp_path):
    out = tmp_path / "x.mcap"
    proc = popen_rover("simulate", *QUICK, "-o", str(out), max_file_bytes=200_000)
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 2
    assert stderr.splitlines() == [f"rover: error: {out}: cannot write: File too large"]
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(("signum", "status"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)], ids=["TERM", "INT"])
def test_a_signal_while_writing_leaves_no_partial(tmp_path, signum, status):
    proc = popen_rover("simulate", *QUICK, "-o", str(tmp_path / "x.mcap"))
    assert stop_while_writing(proc, tmp_path / ".x.mcap.partial", signum)[0] == status
    assert list(tmp_path.iterdir()) == []


def test_simulating_onto_the_scenario_file_is_refused(tmp_path, capsys):
    from rover.cli.app import main

    scenario = tmp_path / "room.yaml"
    scenario.write_text("room: {size_m: [6.0, 4.0]}\n")
    assert main(["simulate", "--scenario", str(scenario), "-o", str(scenario), "--force"]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"rover: error: {scenario}: is also the scenario file; simulating onto it would destroy it"
    ]
    assert scenario.read_text() == "room: {size_m: [6.0, 4.0]}\n"


def test_the_size_worked_out_before_simulating_bounds_the_size_simulated(short_run):
    """Duration exactly; the messages bounded from above (every tag heard all the time, the sweep's
    windows counted) and not by much more than half."""
    _out, report = short_run
    size = scenario_size(load_scenario("paper", SHORT))
    assert size.duration_s == pytest.approx(report.duration_s, abs=1e-9)
    assert sum(report.counts.values()) <= size.messages <= 1.5 * sum(report.counts.values())


@pytest.mark.parametrize(
    "setting",
    [
        "trajectory.laps=100000",
        "trajectory.laps=1000000000000",
        "receiver.dwell_s=0.0000001",
        "receiver.dwell_s=1e-300",
        "receiver.dwell_s=1e9",  # one window of a billion seconds: its packets outlast the run
        "imu.rate_hz=20000000",
    ],
)
def test_a_scenario_too_big_for_memory_is_refused_before_anything_is_allocated(tmp_path, capsys, setting):
    from rover.cli.app import main

    out = tmp_path / "big.mcap"
    assert main(["simulate", "-o", str(out), "--set", setting]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith(f"rover: error: scenario paper --set {setting}: the scenario would"), err
    assert f"at most {MAX_MESSAGES:,}" in err[0]
    assert list(tmp_path.iterdir()) == []


# -- the chains' phase jumps (issue 14) -------------------------------------------------------------

TINY = {
    "trajectory.laps": "1",
    "trajectory.waypoints_m": "[[4.0, 0.755], [4.0, 2.5]]",
    "trajectory.stationary_s": "0.5",
    "trajectory.speed_m_s": "0.6",
}
"""a short run of the paper's room: every tag channel heard, many sweeps"""
JUMP_VARIANTS = {
    "none": {"receiver.jumps_per_run": "false"},
    "run": {"receiver.jumps_per_run": "true"},
    "retune": {"receiver.jumps_per_run": "false", "receiver.jumps_per_retune": "1.0"},
}


@pytest.fixture(scope="module")
def jump_runs(tmp_path_factory):
    """The same seed without jumps, with a jump per run, and with one at every retune."""
    root = tmp_path_factory.mktemp("jumps")
    out = {}
    for name, overrides in JUMP_VARIANTS.items():
        path = root / f"{name}.mcap"
        simulate(load_scenario("paper", {**TINY, **overrides}), 1, path)
        messages = read_bag(path)
        frames = [deserialize(d, "rover_msgs/msg/CsiFrame") for t, _s, d in messages if t == "/csi"]
        csi = decode_bfee([bytes(f.bfee) for f in frames], scaled=False).csi[:, :, :, 0]
        jumps = yaml.safe_load(read_metadata(path)["rover.simulation"]["yaml"])["phase_jumps"]
        out[name] = (messages, csi, np.array([f.channel for f in frames]), jumps)
    return out


def chain_signs(csi: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per packet and chain, the sign (+-1) that best maps the reference CSI onto `csi`, and per
    packet the power left over once it is applied, relative to the reference's."""
    sign = np.where(np.real(np.einsum("nfm,nfm->nm", csi, reference.conj())) < 0, -1, 1)
    left = np.sum(np.abs(csi - sign[:, None, :] * reference) ** 2, axis=(1, 2))
    return sign, left / np.sum(np.abs(reference) ** 2, axis=(1, 2))


def test_a_jump_per_run_turns_chains_by_pi_and_changes_nothing_else(jump_runs):
    plain_messages, plain, channels, plain_jumps = jump_runs["none"]
    messages, jumped, jumped_channels, jumps = jump_runs["run"]
    for topic in ("/imu/data", "/odom", "/groundtruth/pose", "/groundtruth/aoa", "/groundtruth/tags"):
        assert [(s, d) for t, s, d in messages if t == topic] == [(s, d) for t, s, d in plain_messages if t == topic]
    assert [s for t, s, _ in messages if t == "/csi"] == [s for t, s, _ in plain_messages if t == "/csi"]
    np.testing.assert_array_equal(jumped_channels, channels)
    assert jumps["per_run"] is True and plain_jumps["per_run"] is False
    tag_channels = {t.channel for t in load_scenario("paper").tags}
    assert set(jumps["run_steps"]) == set(plain_jumps["run_steps"]) == tag_channels
    assert set(np.unique(channels).tolist()) == tag_channels, "every tag is heard in this run"
    sign, left = chain_signs(jumped, plain)
    # the receiver noise is drawn alike but added after the chains' phases, so what is left is the
    # difference of two noises (4 / SNR of the power) and the AGC's rescaling, not just rounding
    snr_db = load_scenario("paper").receiver.snr_db[0]
    assert left.max() < 2 * 4 * 10 ** (-snr_db / 10)
    flipped = 0
    for channel, steps in jumps["run_steps"].items():
        assert len(steps) == 3 and set(steps) <= {0, 1}, "a multiple of pi at 5 GHz"
        assert plain_jumps["run_steps"][channel] == [0, 0, 0]
        mine = channels == channel
        np.testing.assert_array_equal(sign[mine], np.broadcast_to((-1) ** np.array(steps), (mine.sum(), 3)))
        flipped += sum(steps)
    assert flipped > 0, "this seed turns some chain (else the test shows nothing)"


def test_jumps_at_every_retune_change_between_windows_of_a_channel(jump_runs):
    plain_messages, plain, channels, _ = jump_runs["none"]
    _, jumped, _, jumps = jump_runs["retune"]
    assert jumps["per_retune"] == 1.0 and jumps["per_run"] is False
    stamps = np.array([s for t, s, _ in plain_messages if t == "/csi"])
    assert np.all(np.diff(stamps) >= 0)
    # a window: consecutive packets on one channel (the next window of a channel is a sweep later)
    start = np.concatenate([[True], (channels[1:] != channels[:-1]) | (np.diff(stamps) > 100e6)])
    window = np.cumsum(start) - 1
    sign, left = chain_signs(jumped, plain)
    assert left.max() < 2 * 4 * 10 ** (-load_scenario("paper").receiver.snr_db[0] / 10)
    patterns: dict[int, list[tuple[int, ...]]] = {}
    for w in range(window[-1] + 1):
        mine = window == w
        assert len(np.unique(sign[mine], axis=0)) == 1, "the chains hold their phase within a window"
        patterns.setdefault(int(channels[mine][0]), []).append(tuple(sign[mine][0]))
    assert jumps["retunes_redrawn"] >= window[-1] + 1
    for channel, seen in patterns.items():
        assert len(seen) >= 20
        assert len(set(seen)) > 1, f"channel {channel}: the multiples vary between its windows"
        changes = np.mean([a != b for a, b in zip(seen[:-1], seen[1:], strict=True)])
        assert changes > 0.5, "8 equally likely patterns: most retunes change it"


def test_chain_jumps_are_multiples_of_the_channel_step():
    """The jump drawn for each packet: pi steps at 5 GHz, pi/2 at 2.4 GHz (all four levels drawn),
    held all run per channel; per packet, a fresh jump for that packet only."""
    windows = np.repeat(np.arange(40), 5)
    window_channel = np.tile([6, 149], 20)
    levels: dict[int, set[int]] = {6: set(), 149: set()}
    for seed in range(10):
        j = chain_jumps(Receiver(jumps_per_run=True), seed, windows, window_channel, 3)
        assert j.retunes_redrawn == 0 and set(j.run_steps) == {6, 149}
        for channel in (6, 149):
            step = phase_jump_step_rad(channel)
            mine = window_channel[windows] == channel
            multiples = j.phase_rad[mine] / step
            np.testing.assert_allclose(multiples, np.round(multiples), atol=1e-9)
            assert len(np.unique(np.mod(np.round(multiples), 2 * np.pi / step), axis=0)) == 1, "once per run"
            np.testing.assert_array_equal(np.mod(np.round(multiples[0]), round(2 * np.pi / step)), j.run_steps[channel])
            levels[channel] |= set(j.run_steps[channel])
    assert levels == {6: {0, 1, 2, 3}, 149: {0, 1}}
    off = chain_jumps(Receiver(), 3, windows, window_channel, 3)
    assert np.all(off.phase_rad == 0) and all(v == [0, 0, 0] for v in off.run_steps.values())
    packet = chain_jumps(Receiver(jumps_per_packet=1.0), 3, windows, window_channel, 3)
    assert packet.retunes_redrawn == 0 and all(v == [0, 0, 0] for v in packet.run_steps.values())
    steps = np.array([phase_jump_step_rad(int(c)) for c in window_channel[windows]])[:, None]
    levels_of = np.round(2 * np.pi / steps)
    multiples = np.mod(np.round(packet.phase_rad / steps), levels_of)
    within = [len(np.unique(multiples[windows == w], axis=0)) for w in range(40)]
    assert np.mean(np.array(within) > 1) > 0.9, "per packet: the jumps differ within a window"


def test_persistent_steps_happen_at_random_moments_and_stay():
    """Steps at 3 a minute over 20 minutes: about 60 (Poisson), each one chain by one jump step (pi at
    5 GHz, pi/2 at 2.4 GHz), in force from its moment until the next, on every channel alike."""
    t = np.linspace(0.0, 1200.0, 24_000)
    windows = np.arange(len(t)) // 5
    window_channel = np.tile([6, 149], len(t) // 10 + 1)[: windows[-1] + 1]
    j = chain_jumps(Receiver(steps_per_minute=3.0), 4, windows, window_channel, 3, t, 1200.0)
    assert 40 <= len(j.steps) <= 80, len(j.steps)  # 60 expected: 2.6 standard deviations either way
    assert all(c in (0, 1, 2) and s in (-1, 1) for _, c, s in j.steps)
    step = np.array([phase_jump_step_rad(int(c)) for c in window_channel[windows]])[:, None]
    multiples = np.round(j.phase_rad / step).astype(int)
    np.testing.assert_allclose(j.phase_rad, multiples * step, atol=1e-9)
    changes = np.flatnonzero(np.any(np.diff(multiples, axis=0) != 0, axis=1))
    step_times = np.array([time for time, _, _ in j.steps])
    # the state changes only across a step's moment, by that step's chain and sign
    assert all(np.any((step_times > t[k]) & (step_times <= t[k + 1])) for k in changes)
    first_time, first_chain, first_sign = j.steps[0]
    before, after = t < first_time, (t >= first_time) & (t < j.steps[1][0])
    assert np.all(multiples[before] == 0)
    expected = np.zeros(3, int)
    expected[first_chain] = first_sign
    assert np.all(multiples[after] == expected)
    assert chain_jumps(Receiver(), 4, windows, window_channel, 3, t, 1200.0).steps == []


@pytest.mark.parametrize(
    ("setting", "message"),
    [
        ("outptu.x=1", "--set outptu.x: no section 'outptu' in a scenario"),
        ("recever.dwell_s=1", "--set recever.dwell_s: no section 'recever' in a scenario; did you mean 'receiver'?"),
        ("receiver.dwel_s=1", "--set receiver.dwel_s: no key 'dwel_s' in section 'receiver'; did you mean 'dwell_s'?"),
    ],
)
def test_a_set_of_no_section_or_key_of_the_scenario_names_the_set_with_a_did_you_mean(tmp_path, setting, message):
    out = tmp_path / "x.mcap"
    result = run_rover("simulate", "-o", str(out), "--set", setting)
    assert result.returncode == 2 and result.stderr.splitlines() == [f"rover: error: {message}"]
    assert not out.exists()


PAIR = {
    "receiver.array": "positions",
    "receiver.antenna_positions_m": "[[0, 0], [0.0258, 0]]",
    "receiver.phase_offsets_rad": "[0, 0.9]",
}
"""a 2-antenna card, its axis along the robot's heading"""


def test_a_pair_of_antennas_records_two_chains_and_looks_all_around(tmp_path):
    """The Intel 5300 with two antennas: records of two chains, and a rig description whose field
    of view is all around (a collinear array's mirror images are then candidates); four are refused."""
    path = tmp_path / "pair.mcap"
    simulate(load_scenario("paper", {**TINY, **PAIR, "receiver.jumps_per_run": "false"}), 1, path)
    messages = read_bag(path)
    frames = [deserialize(d, "rover_msgs/msg/CsiFrame") for t, _s, d in messages if t == "/csi"]
    records = decode_bfee([bytes(f.bfee) for f in frames[:200]], scaled=False)
    assert set(records.nrx.tolist()) == {2} and records.csi.shape[2] == 2
    rig = yaml.safe_load(read_metadata(path)["rover.setup"]["yaml"])
    assert rig["receiver"]["field_of_view_deg"] == [-180.0, 180.0]
    assert rig["receiver"]["antenna_positions_m"] == [[0.0, 0.0], [0.0258, 0.0]]
    four = {**PAIR, "receiver.antenna_positions_m": "[[0, 0], [0.02, 0], [0, 0.02], [0.02, 0.02]]"}
    four["receiver.phase_offsets_rad"] = "[0, 0, 0, 0]"
    with pytest.raises(BadInput, match="4 antennas: the Intel 5300 has three receive chains, so 2 or 3"):
        simulate(load_scenario("paper", {**TINY, **four}), 1, tmp_path / "four.mcap")
    assert not (tmp_path / "four.mcap").exists()


SQUARE = "[[0, 0], [0.019, 0], [0.019, 0.019], [0, 0.019]]"
"""WiROS's 19 mm square of four antennas"""
NEXMON = {
    "receiver.card": "nexmon",
    "receiver.array": "positions",
    "receiver.antenna_positions_m": SQUARE,
    "receiver.phase_offsets_rad": "[0, 0.9, -1.7, 0.4]",
    "receiver.jumps_per_run": "false",
}


def test_a_nexmon_rig_writes_its_four_chains_decoded_on_the_capture_topic(tmp_path):
    """Each packet is Rover's Csi on /csi/capture (no CSI Tool record): four chains, the 20 MHz
    channel's 50 data subcarriers at its tag's channel, as floats; its angle is the truth's within
    the noise. The Intel 5300's jump models are refused with it, naming them, and so are 9 antennas."""
    path = tmp_path / "nexmon.mcap"
    simulate(load_scenario("paper", {**TINY, **NEXMON}), 1, path)
    messages = read_bag(path)
    assert not [t for t, _s, _d in messages if t == "/csi"]
    packets = [deserialize(d, "rover_msgs/msg/Csi") for t, _s, d in messages if t == "/csi/capture"]
    truth = [deserialize(d, "rover_msgs/msg/Aoa") for t, _s, d in messages if t == "/groundtruth/aoa"]
    assert packets and len(packets) == len(truth)
    first = packets[0]
    assert (first.nrx, first.ntx, len(first.subcarriers), len(first.csi_real)) == (4, 1, 50, 200)
    assert {(p.channel, p.centre_freq_hz) for p in packets} <= {(c, 5e6 * c + 5e9) for c in (149, 153, 157, 161)}
    assert all(p.tag_id == t.tag_id for p, t in zip(packets, truth, strict=True))
    setup = make("rover_msgs/msg/RigSetup", setup_yaml=read_metadata(path)["rover.setup"]["yaml"])
    aoas = [e.msg for e in run_operator(Aoa(AoaParams(burst_packets=20)), {"setup": [setup], "capture": packets})]
    stamp = lambda m: m.header.stamp.sec * 10**9 + m.header.stamp.nanosec  # noqa: E731
    true_at = {(t.tag_id, stamp(t)): t.angle_rad for t in truth}
    los = [a for a in aoas if a.tag_id != 4]  # tag 4 is the paper room's NLOS tag
    errors = [abs(math.degrees(wrap_angle(a.angle_rad - true_at[a.tag_id, stamp(a)]))) for a in los]
    assert len(errors) > 20 and np.median(errors) < 10, errors  # a wrong convention is tens of degrees off
    with pytest.raises(BadInput, match=r"receiver.card nexmon: receiver.jumps_per_run model the Intel 5300's"):
        simulate(load_scenario("paper", {**TINY, **NEXMON, "receiver.jumps_per_run": "true"}), 1, tmp_path / "j.mcap")
    nine = {**NEXMON, "receiver.antenna_positions_m": str([[0.01 * k, 0] for k in range(9)])}
    nine["receiver.phase_offsets_rad"] = str([0] * 9)
    with pytest.raises(BadInput, match="9 antennas: a Nexmon rig here has 2 to 8"):
        simulate(load_scenario("paper", {**TINY, **nine}), 1, tmp_path / "nine.mcap")
    assert not (tmp_path / "j.mcap").exists() and not (tmp_path / "nine.mcap").exists()
