"""`create2`: the stream parser on hand-written frames, the odometry integrator, and the driver against
an emulated robot behind a pty (tests/create2_device.py), called as a function and through `rover run`."""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from create2_device import Create2Device, SentFrame, constant, standing
from helpers import read_bag, run_rover
from scripted_port import ScriptedPort

from rover.drivers.create2 import (
    Create2,
    Create2Params,
    StreamParser,
    WheelGeometry,
    WheelOdometry,
    encoder_delta,
)
from rover.errors import BadInput
from rover.messages import deserialize, stamp_ns
from rover.operator import Emit
from rover.pipeline.params import ParamValueError

GEOMETRY = WheelGeometry(wheel_diameter_m=0.072, wheel_base_m=0.235, counts_per_rev=508.8)
STEP_M = math.pi * 0.072 / 508.8
"""Wheel travel per encoder count."""
WHEEL_RADIUS_M = 0.036
T0_NS = 1_700_000_000_000_000_000
DEADLINE_S = 10.0
"""The longest a test lets the driver run."""

SPEC_EXAMPLE = bytes([19, 5, 29, 2, 25, 13, 0, 163])
"""The OI spec's stream example: packet 29 (cliff front left signal, 2 bytes) = 2 * 256 + 25 = 537 and
packet 13 (virtual wall, 1 byte) = 0; 19 + 5 + 29 + 2 + 25 + 13 + 0 + 163 = 256."""
ENCODERS_A = bytes([19, 6, 43, 0x01, 0x02, 44, 0xFF, 0xFE, 144])
"""left 258, right 65534: 19 + 6 + 43 + 1 + 2 + 44 + 255 + 254 = 624 = 2 * 256 + 112, and 112 + 144 = 256."""
ENCODERS_B = bytes([19, 6, 43, 0x13, 0x13, 44, 0x06, 0x13, 81])
"""19s in the data: left 0x1313 = 4883, right 0x0613 = 1555; the bytes before the checksum sum to 175,
and 175 + 81 = 256."""


def test_frames_sum_to_zero():
    for frame in (SPEC_EXAMPLE, ENCODERS_A, ENCODERS_B):
        assert sum(frame) % 256 == 0


# ----------------------------------------------------------------------------- parser


def test_the_specs_stream_example_and_encoder_frames():
    parser = StreamParser()
    assert parser.feed(SPEC_EXAMPLE + ENCODERS_A + ENCODERS_B) == [
        {29: 537, 13: 0},
        {43: 258, 44: 65534},
        {43: 4883, 44: 1555},
    ]
    assert (parser.bad_checksums, parser.skipped_bytes, parser.unknown_packets, parser.pending) == (0, 0, 0, 0)


def test_a_frame_split_at_any_byte_or_two_comes_out_whole():
    data = ENCODERS_A + SPEC_EXAMPLE + ENCODERS_B
    whole = StreamParser().feed(data)
    for i in range(len(data) + 1):
        for j in range(i, len(data) + 1):
            parser = StreamParser()
            frames = parser.feed(data[:i]) + parser.feed(data[i:j]) + parser.feed(data[j:])
            assert frames == whole, (i, j)
            assert parser.skipped_bytes == 0 and parser.pending == 0
    parser = StreamParser()
    assert [f for b in data for f in parser.feed(bytes([b]))] == whole


def test_noise_with_headers_in_it_is_skipped_and_counted():
    # Headers with n-bytes 19 (its first packet, group 0, overruns it), 0, 1 and 2 (packet 19 has 2 data
    # bytes: it overruns too), and a 19 just before a real header.
    noise = bytes([0, 19, 19, 0, 255, 19, 1, 7, 19, 2, 19])
    parser = StreamParser()
    frames = parser.feed(noise + ENCODERS_A + noise + ENCODERS_B + noise + SPEC_EXAMPLE + ENCODERS_A)
    assert frames == [{43: 258, 44: 65534}, {43: 4883, 44: 1555}, {29: 537, 13: 0}, {43: 258, 44: 65534}]
    assert parser.skipped_bytes == 3 * len(noise)
    assert parser.bad_checksums == 0 and parser.pending == 0


def test_a_frame_behind_a_plausible_false_header_waits_for_more_bytes():
    """The last 19 of the noise starts a candidate with n-bytes 19 (the real header) whose first packet,
    group 5, fits: only the bytes after the spec's frame can tell it is none."""
    parser = StreamParser()
    assert parser.feed(bytes([19, 2, 19]) + SPEC_EXAMPLE) == []
    assert parser.feed(ENCODERS_A) == [{29: 537, 13: 0}, {43: 258, 44: 65534}]
    assert parser.skipped_bytes == 3


def test_bad_checksums_are_counted_and_the_next_frame_is_found():
    bad_a = ENCODERS_A[:-1] + bytes([ENCODERS_A[-1] ^ 0x01])
    bad_b = ENCODERS_B[:-1] + bytes([ENCODERS_B[-1] + 1])
    parser = StreamParser()
    frames = parser.feed(ENCODERS_A + bad_a + ENCODERS_B + bad_b + bad_a + SPEC_EXAMPLE)
    assert frames == [{43: 258, 44: 65534}, {43: 4883, 44: 1555}, {29: 537, 13: 0}]
    assert parser.bad_checksums == 3
    assert parser.skipped_bytes == 3 * 9


def test_a_long_false_frame_holds_frames_back_until_the_input_ends():
    """[19][250][7] could start a frame 253 bytes long (packet 7, then packet 6 of 52 bytes, ...): the
    parser waits for more bytes, and when the input ends (`finish`) it gives up on that frame and finds
    the real ones behind it."""
    parser = StreamParser()
    assert parser.feed(bytes([19, 250, 7]) + ENCODERS_A + ENCODERS_B) == []
    assert parser.pending == 3 + 18
    assert parser.finish() == [{43: 258, 44: 65534}, {43: 4883, 44: 1555}]
    assert parser.skipped_bytes == 3 and parser.pending == 0


def test_group_packets_and_signed_values():
    # Group 2 = packets 17 (IR, 1 byte), 18 (buttons, 1), 19 (distance, signed 2: -10 mm), 20 (angle,
    # signed 2: 90 deg); its bytes sum to 784 = 3 * 256 + 16, so the checksum is 240.
    group2 = bytes([19, 7, 2, 0xA1, 0x04, 0xFF, 0xF6, 0x00, 0x5A, 240])
    assert StreamParser().feed(group2) == [{17: 0xA1, 18: 0x04, 19: -10, 20: 90}]


def test_an_unknown_packet_id_is_no_frame():
    """The OI defines no packet 99: the candidate is rejected there, without waiting for its end."""
    unknown = bytes([19, 200, 43, 0x00, 0x05, 99, 0x07])
    parser = StreamParser()
    assert parser.feed(unknown + ENCODERS_A) == [{43: 258, 44: 65534}]
    assert parser.unknown_packets == 1 and parser.skipped_bytes == len(unknown)


# ----------------------------------------------------------------------------- odometry


def test_counts_deltas_wrap_both_ways():
    assert encoder_delta(65530, 4) == 10
    assert encoder_delta(3, 65533) == -6
    assert encoder_delta(0, 32767) == 32767
    assert encoder_delta(0, 32768) == -32768
    assert encoder_delta(100, 100) == 0


def test_straight_line():
    """5 wheel revolutions (2544 counts) in two steps: 5 * pi * 0.072 m forward, at that distance per 0.2 s."""
    odometry = WheelOdometry(GEOMETRY)
    assert odometry.update(1000, 2000, T0_NS) is None
    odometry.update(1000 + 1272, 2000 + 1272, T0_NS + 100_000_000)
    last = odometry.update(1000 + 2544, 2000 + 2544, T0_NS + 200_000_000)
    assert last is not None
    assert last.x_m == pytest.approx(5 * math.pi * 0.072, abs=1e-12)
    assert last.y_m == 0 and last.yaw_rad == 0
    assert last.linear_m_s == pytest.approx(5 * math.pi * 0.072 / 0.2)
    assert last.angular_rad_s == 0
    assert last.stamp_ns == T0_NS + 200_000_000


def test_one_revolution_is_the_wheels_circumference():
    odometry = WheelOdometry(WheelGeometry(wheel_diameter_m=0.072, wheel_base_m=0.235, counts_per_rev=500.0))
    odometry.update(0, 0, T0_NS)
    last = odometry.update(500, 500, T0_NS + 10**9)
    assert last is not None and last.x_m == pytest.approx(math.pi * 0.072)


def test_turn_in_place():
    """Opposite counts: yaw = 2 d / wheel base, with d each wheel's distance; the centre stays put."""
    odometry = WheelOdometry(GEOMETRY)
    odometry.update(0, 0, T0_NS)
    last = odometry.update(65536 - 200, 200, T0_NS + 500_000_000)
    assert last is not None
    d = 200 * STEP_M
    assert last.yaw_rad == pytest.approx(2 * d / 0.235)
    assert last.x_m == pytest.approx(0, abs=1e-12) and last.y_m == pytest.approx(0, abs=1e-12)
    assert last.angular_rad_s == pytest.approx(2 * d / 0.235 / 0.5)
    assert last.linear_m_s == pytest.approx(0, abs=1e-12)
    assert last.turned_rad == pytest.approx(2 * d / 0.235) and last.path_m == pytest.approx(0, abs=1e-12)


def test_wrap_around_forward_and_backward_are_small_steps():
    odometry = WheelOdometry(GEOMETRY)
    odometry.update(65530, 65530, T0_NS)
    forward = odometry.update(4, 4, T0_NS + 15_000_000)
    assert forward is not None and forward.x_m == pytest.approx(10 * STEP_M)
    back = odometry.update(65534, 65534, T0_NS + 30_000_000)
    assert back is not None and back.x_m == pytest.approx(4 * STEP_M)
    assert back.path_m == pytest.approx(16 * STEP_M)
    assert back.yaw_rad == 0


def test_a_counter_clockwise_circle_comes_back_to_its_start():
    """Right wheel faster: the robot turns left (y > 0 on the way), and a full circle closes."""
    odometry = WheelOdometry(GEOMETRY)
    odometry.update(0, 0, T0_NS)
    radius_m, steps = 0.5, 400
    per_step_rad = 2 * math.pi / steps
    left = right = 0.0
    estimates = []
    for k in range(1, steps + 1):
        left += (radius_m - 0.235 / 2) * per_step_rad / STEP_M
        right += (radius_m + 0.235 / 2) * per_step_rad / STEP_M
        estimate = odometry.update(round(left) % 65536, round(right) % 65536, T0_NS + k * 15_000_000)
        assert estimate is not None
        estimates.append(estimate)
    assert max(e.y_m for e in estimates) == pytest.approx(2 * radius_m, abs=0.005)
    assert estimates[steps // 4].x_m == pytest.approx(radius_m, abs=0.005)
    last = estimates[-1]
    assert math.hypot(last.x_m, last.y_m) < 0.002
    assert abs(last.yaw_rad) < 0.002
    assert last.turned_rad == pytest.approx(2 * math.pi, abs=0.002)


def test_velocities_span_frames_that_arrive_together():
    """Frames with one stamp (the driver stamps a batch no earlier than what it promised): the velocity is
    measured over a span of host time, never over 0 s."""
    odometry = WheelOdometry(GEOMETRY)
    odometry.update(0, 0, T0_NS)
    for k in range(1, 10):
        stamp = T0_NS + (k // 2) * 30_000_000  # two frames per read, 30 ms apart
        estimate = odometry.update(10 * k, 10 * k, stamp)
        assert estimate is not None
        if k > 1:
            assert estimate.linear_m_s == pytest.approx(10 * STEP_M / 0.015, rel=0.5)


# ----------------------------------------------------------------------------- the driver, on an emulated robot


def params(device: Create2Device, **changes: Any) -> Create2Params:
    return Create2Params(port=device.path, **changes)


def collect(source: Create2, count: int | None = None) -> list[Any]:
    """The messages `run` yields until it ends, or the first `count`; fails after DEADLINE_S."""
    stop, expired = threading.Event(), threading.Event()

    def expire() -> None:
        expired.set()
        stop.set()

    watchdog = threading.Timer(DEADLINE_S, expire)
    watchdog.start()
    messages = []
    try:
        for item in source.run(stop):
            if isinstance(item, Emit):
                assert item.port == "odom"
                messages.append(item.msg)
                if count is not None and len(messages) >= count:
                    break
    finally:
        watchdog.cancel()
    assert not expired.is_set(), f"the driver still ran after {DEADLINE_S} s"
    return messages


def expected_x(frames: list[SentFrame]) -> list[float]:
    """x of each frame after the first, for a straight drive (both wheels alike)."""
    return [encoder_delta(frames[0].left, f.left) * STEP_M for f in frames[1:]]


def xs(messages: list[Any]) -> list[float]:
    return [m.pose.pose.position.x for m in messages]


def test_the_driver_starts_the_stream_and_leaves_the_robot_passive():
    with Create2Device(standing) as device:
        source = Create2(params(device))
        assert device.received == []
        assert len(collect(source, count=3)) == 3
        assert device.received == [128, 131, 148, 2, 43, 44]
        assert device.mode == "safe" and device.streaming
        source.close()
        assert device.wait_for(lambda d: len(d.received) >= 9)
        assert device.received == [128, 131, 148, 2, 43, 44, 150, 0, 173]
        assert device.commands[-2:] == [(150, 0), (173,)]
        assert device.mode == "off" and not device.streaming
        source.close()  # a second close does nothing, and does not raise on the closed port


def test_a_steady_drive_gives_the_pose_and_speed():
    """Both wheels at 5 rad/s (0.18 m/s), in real time so that host stamps measure the speed."""
    with Create2Device(constant(5.0, 5.0)) as device:
        source = Create2(params(device))
        before = time.time_ns()
        messages = collect(source, count=30)
        source.close()
        frames = device.good_frames()[:31]
    assert xs(messages) == pytest.approx(expected_x(frames), abs=1e-12)
    assert xs(messages)[-1] == pytest.approx(0.18 * frames[-1].time_s, abs=2 * STEP_M)
    speeds = sorted(m.twist.twist.linear.x for m in messages[3:])
    assert speeds[len(speeds) // 2] == pytest.approx(0.18, rel=0.05)
    for m in messages:
        assert (m.header.frame_id, m.child_frame_id) == ("odom", "base_link")
        assert m.pose.pose.position.y == 0 and m.pose.pose.orientation.w == 1
        assert m.twist.twist.angular.z == 0
        assert m.pose.covariance[0] > 0 and m.pose.covariance[0] == m.pose.covariance[7]
        assert m.pose.covariance[14] == m.pose.covariance[21] == m.pose.covariance[28] == 1e6
        assert 0 < m.pose.covariance[35] < 1e-3
        assert m.twist.covariance[0] > 0 and m.twist.covariance[14] == 1e6
    stamps = [stamp_ns(m) for m in messages]
    assert stamps == sorted(stamps) and before <= stamps[0] <= time.time_ns()
    assert source.drops == {}


def test_frames_with_a_bad_checksum_are_dropped_and_counted():
    """Every 4th checksum is wrong: those 10 frames are dropped (and their 9 bytes each skipped), the
    other 30 delivered; then the cable is pulled and the stream ends."""
    with Create2Device(constant(4.0, 4.0), speed=4, corrupt_every=4, stop_after=40, vanish=True) as device:
        source = Create2(params(device))
        messages = collect(source)
        source.close()
        good = device.good_frames()
    assert len(good) == 30
    assert xs(messages) == pytest.approx(expected_x(good), abs=1e-12)
    assert source.drops == {
        "stream frames with a bad checksum": 10,
        "bytes outside stream frames (line noise, or frames cut short)": 10 * 9,
    }


def test_split_frames_and_noise_lose_no_frame():
    noise = bytes([19, 19, 2, 19, 1, 0xFF, 0, 19])
    with Create2Device(
        constant(-3.0, -3.0), speed=4, split_seed=7, garbage=noise, stop_after=40, vanish=True
    ) as device:
        source = Create2(params(device))
        messages = collect(source)
        source.close()
    assert len(device.sent) == 40 and device.overflowed == 0
    assert xs(messages) == pytest.approx(expected_x(device.sent), abs=1e-12)
    assert xs(messages)[-1] < 0
    assert source.drops == {"bytes outside stream frames (line noise, or frames cut short)": 40 * len(noise)}


def test_counts_that_wrap_during_the_drive():
    with Create2Device(constant(6.0, 6.0), speed=4, start_counts=(65500, 65520), stop_after=20, vanish=True) as device:
        source = Create2(params(device))
        messages = collect(source)
        source.close()
    assert device.sent[0].left > 65000 and device.sent[-1].left < 1000
    assert xs(messages) == pytest.approx(expected_x(device.sent), abs=1e-12)
    assert all(m.pose.pose.position.y == 0 for m in messages)


def test_a_vanished_robot_ends_the_stream_with_a_warning(caplog):
    with Create2Device(constant(2.0, 2.0), speed=4, stop_after=20, vanish=True) as device:
        source = Create2(params(device, timeout_s=5.0))
        with caplog.at_level(logging.WARNING, logger="rover.create2"):
            messages = collect(source)
        source.close()
        assert device.wait_for(lambda d: d.vanished)
        assert device.received == [128, 131, 148, 2, 43, 44]  # nobody left to read Pause and Stop
    assert len(messages) == 19
    (record,) = caplog.records
    assert record.levelname == "WARNING"
    assert record.getMessage().startswith(f"create2: {device.path}: reading the robot failed (")
    assert record.getMessage().endswith("): the odometry stream ends")


def test_silence_past_the_timeout_ends_the_stream(caplog):
    with Create2Device(constant(2.0, 2.0), stop_after=5) as device:
        source = Create2(params(device, timeout_s=0.5))
        began = time.monotonic()
        with caplog.at_level(logging.WARNING, logger="rover.create2"):
            messages = collect(source)
        ended = time.monotonic() - began
        source.close()
        assert device.wait_for(lambda d: d.received[-1:] == [173])
        assert device.received == [128, 131, 148, 2, 43, 44, 150, 0, 173]
    assert len(messages) == 4
    assert 0.5 < ended < 3.0
    assert [r.getMessage() for r in caplog.records] == [
        f"create2: {device.path}: no stream frame for 0.5 s (robot off or asleep, or not at 115200 baud?): "
        "the odometry stream ends"
    ]


def test_a_port_that_cannot_be_opened_is_bad_input(tmp_path):
    missing = tmp_path / "ttyUSB9"
    with pytest.raises(BadInput, match=rf"^create2: cannot open serial port {missing}: No such file or directory$"):
        Create2(Create2Params(port=str(missing)))
    with pytest.raises(BadInput, match=rf"^create2: cannot open serial port {tmp_path}: Is a directory$"):
        Create2(Create2Params(port=str(tmp_path)))
    plain = tmp_path / "plain"
    plain.write_bytes(b"")
    with pytest.raises(BadInput, match=rf"^create2: cannot open serial port {plain}: not a serial port"):
        Create2(Create2Params(port=str(plain)))


def test_geometry_must_be_positive():
    with pytest.raises(ParamValueError, match="wheel_base_m"):
        Create2Params(port="/dev/ttyUSB0", wheel_base_m=0.0)
    with pytest.raises(ParamValueError, match="timeout_s"):
        Create2Params(port="/dev/ttyUSB0", timeout_s=-1.0)


def test_frames_without_both_encoder_counts_are_dropped(caplog):
    port = ScriptedPort([ENCODERS_A, SPEC_EXAMPLE, ENCODERS_B[:4], ENCODERS_B[4:]])
    opener: Callable[[str, str, int], ScriptedPort] = lambda _driver, _port, _baud: port  # noqa: E731
    source = Create2(Create2Params(port="/dev/fake"), open_port=opener)
    with caplog.at_level(logging.WARNING, logger="rover.create2"):
        (message,) = collect(source)
    source.close()  # the port is gone: the write fails, quietly
    assert port.closed and bytes(port.written) == bytes([128, 131, 148, 2, 43, 44])
    reference = WheelOdometry(GEOMETRY)
    reference.update(258, 65534, T0_NS)
    expected = reference.update(4883, 1555, T0_NS + 1)
    assert expected is not None
    assert (message.pose.pose.position.x, message.pose.pose.position.y) == (expected.x_m, expected.y_m)
    assert source.drops == {"stream frames without both encoder counts (packets 43 and 44)": 1}
    assert "create2: /dev/fake: reading the robot failed (read failed: [Errno 5] Input/output error)" in caplog.text


# ----------------------------------------------------------------------------- through `rover run`


def test_rover_run_records_the_drive_until_the_robot_vanishes(tmp_path: Path):
    """The robot sends 100 frames, then its cable is pulled: the run ends by itself (status 0) with one
    warning, and the recording has the 99 poses of the drive (the first frame is the reference). The
    driver's Pause and Stop at close find no robot any more: the emulator saw only the start sequence."""
    wheel_rad_s = 4.0
    with Create2Device(constant(wheel_rad_s, wheel_rad_s), speed=2, stop_after=100, vanish=True) as device:
        pipeline = tmp_path / "robot.yaml"
        pipeline.write_text(f"""\
name: robot
operators:
  base:   {{uses: create2, params: {{port: "{device.path}", timeout_s: 5.0}}}}
  record: {{uses: recorder, inputs: {{odom: base/odom}}, params: {{out: out}}}}
""")
        proc = run_rover("run", str(pipeline), cwd=tmp_path, timeout=60)
        assert device.wait_for(lambda d: d.vanished)
        assert device.received == [128, 131, 148, 2, 43, 44]
        sent = list(device.sent)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.count("WARNING") == 1
    assert f"rover: WARNING: create2: {device.path}: reading the robot failed (" in proc.stderr
    recorded = read_bag(tmp_path / "out" / "results.mcap")
    assert {topic for topic, _, _ in recorded} == {"/odom"}
    odom = [deserialize(payload, "nav_msgs/msg/Odometry") for _, _, payload in recorded]
    assert len(odom) == 99
    assert xs(odom) == pytest.approx(expected_x(sent), abs=1e-12)
    assert xs(odom)[-1] == pytest.approx(wheel_rad_s * WHEEL_RADIUS_M * sent[-1].time_s, abs=2 * STEP_M)
    assert [log_ns for _, log_ns, _ in recorded] == [stamp_ns(m) for m in odom]


def test_rover_run_names_a_port_that_is_not_there(tmp_path: Path):
    missing = tmp_path / "ttyUSB9"
    pipeline = tmp_path / "robot.yaml"
    pipeline.write_text(f"""\
name: robot
operators:
  base:   {{uses: create2, params: {{port: "{missing}"}}}}
  record: {{uses: recorder, inputs: {{odom: base/odom}}, params: {{out: out}}}}
""")
    proc = run_rover("run", str(pipeline), cwd=tmp_path, timeout=60)
    assert proc.returncode == 2
    assert proc.stderr == f"rover: error: create2: cannot open serial port {missing}: No such file or directory\n"
