"""`rover simulate`: deterministic, physically consistent datasets that the rest of Rover reads like real ones."""

from __future__ import annotations

import json
import math
import signal

import numpy as np
import pytest
from conftest import popen_rover, read_bag, run_rover, stop_while_writing

from rover.datasets.radio import Impairments, backscatter_csi, impair, true_aoa
from rover.datasets.scenario import load_scenario
from rover.datasets.simulate import antenna_positions, simulate
from rover.errors import BadInput, SpecError
from rover.formats.intel5300 import RecordHeader, decode_bfee, encode_record
from rover.formats.wifi import SPEED_OF_LIGHT_M_S, subcarrier_freqs_hz
from rover.geometry import wrap_angle, yaw_from_quaternion
from rover.messages import deserialize

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


def test_cli_round_trip_simulate_info_replay(tmp_path):
    out = tmp_path / "sim.mcap"
    proc = run_rover("simulate", "--seed", "4", "--set", "trajectory.laps=1", "-o", str(out))
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


def test_scenario_mistakes_are_reported():
    with pytest.raises(BadInput, match="unknown scenario 'papr'; did you mean 'paper'"):
        load_scenario("papr")
    with pytest.raises(SpecError, match="unknown key 'sped_m_s' in trajectory; did you mean 'speed_m_s'"):
        load_scenario("paper", {"trajectory.sped_m_s": "1"})
    with pytest.raises(SpecError, match="receiver.range_m: expected float"):
        load_scenario("paper", {"receiver.range_m": "far"})


QUICK = ("--set", "trajectory.laps=1", "--set", "trajectory.speed_m_s=1.0")
"""A 41 s run instead of 180 s: quicker to simulate, and still a moment to write (for the signal tests)."""


def test_an_output_that_is_a_directory_is_one_line_before_any_work(tmp_path, capsys):
    from rover.cli.commands import main

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
    from rover.cli.commands import main

    scenario = tmp_path / "room.yaml"
    scenario.write_text("room: {size_m: [6.0, 4.0]}\n")
    assert main(["simulate", "--scenario", str(scenario), "-o", str(scenario), "--force"]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"rover: error: {scenario}: is also the scenario file; simulating onto it would destroy it"
    ]
    assert scenario.read_text() == "room: {size_m: [6.0, 4.0]}\n"
