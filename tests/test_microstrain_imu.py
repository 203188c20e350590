"""`microstrain_imu` against an emulated 3DM-GX4-45 on a pseudo-terminal (tests/mip_device.py), and once
through the real CLI into a recording."""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from itertools import pairwise

import pytest
from helpers import read_bag, run_rover
from mip_device import Command, MipDevice, Sent
from scripted_port import ScriptedPort

from rover.drivers.microstrain_imu import (
    DeviceClock,
    MicrostrainImu,
    MicrostrainParams,
    accel_variance_m2_s4,
    gyro_variance_rad2_s2,
)
from rover.drivers.mip import encode
from rover.errors import BadInput
from rover.messages import deserialize, stamp_ns
from rover.operator import Emit, Watermark

G = 9.80665
DEADLINE_S = 10.0
"""the longest a test waits for the driver or the emulator"""
NOBODY = 65534
"""the user id and group id of `nobody`"""
GARBAGE = b"\x75\x00junk\x65"
"""bytes between packets, with a first sync byte and a second that are not a sync"""


def moving(t: float) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """Values that change with device time, so each sample is told apart."""
    return (0.1 + t, 0.2, -1.0 + 0.5 * math.sin(t)), (0.01, -0.02 * t, 0.03)


def take(source: MicrostrainImu, n: int | None = None) -> tuple[list[Emit], bool]:
    """Run the source until it sent `n` messages (or to its end when None): (messages, ended by itself).
    A deadline stops a run that would hang."""
    stop = threading.Event()
    timer = threading.Timer(DEADLINE_S, stop.set)
    timer.start()
    out: list[Emit] = []
    ended = True
    try:
        for item in source.run(stop):
            if isinstance(item, Emit):
                out.append(item)
                if len(out) == n:
                    ended = False
                    break
    finally:
        timer.cancel()
    return out, ended and not stop.is_set()


def stamps_of(items: list[Emit]) -> list[int]:
    return [stamp_ns(i.msg) for i in items]


def expected(sent: Sent) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """What a sample becomes: SI units, REP-103 axes (a half turn about x)."""
    ax, ay, az = (a * G for a in sent.accel_g)
    gx, gy, gz = sent.gyro_rad_s
    return (ax, -ay, -az), (gx, -gy, -gz)


def vectors(msg) -> tuple[tuple[float, ...], tuple[float, ...]]:
    a, w = msg.linear_acceleration, msg.angular_velocity
    return (a.x, a.y, a.z), (w.x, w.y, w.z)


def assert_matches(messages: list, sent: list[Sent]) -> None:
    assert len(messages) == len(sent)
    for msg, s in zip(messages, sent, strict=True):
        got, want = vectors(msg), expected(s)
        for g, w in zip(got[0] + got[1], want[0] + want[1], strict=True):
            assert g == pytest.approx(w, rel=1e-12, abs=1e-12)


@pytest.fixture
def source_of():
    """Builds sources and closes them at the end of the test."""
    made: list[MicrostrainImu] = []

    def build(port: str, **params) -> MicrostrainImu:
        op = MicrostrainImu(MicrostrainParams(port=port, **params))
        made.append(op)
        return op

    yield build
    for op in made:
        op.close()


def test_samples_decode_to_si_units_in_rep103_axes(source_of):
    with MipDevice(lambda t: ((0.1, 0.2, -1.0), (0.01, 0.02, -0.03))) as device:
        items, _ = take(source_of(device.port), 5)
    for item in items:
        msg = item.msg
        (ax, ay, az), (gx, gy, gz) = vectors(msg)
        assert (ax, ay, az) == pytest.approx((0.980665, -1.96133, 9.80665), rel=1e-6)
        assert (gx, gy, gz) == pytest.approx((0.01, -0.02, 0.03), rel=1e-6)
        assert msg.header.frame_id == "imu_link"
        assert item.stamp_ns == stamp_ns(msg)
        assert list(msg.orientation_covariance) == [-1.0] + [0.0] * 8
        accel_var, gyro_var = accel_variance_m2_s4(100.0), gyro_variance_rad2_s2(100.0)
        assert list(msg.linear_acceleration_covariance) == [accel_var, 0, 0, 0, accel_var, 0, 0, 0, accel_var]
        assert list(msg.angular_velocity_covariance) == [gyro_var, 0, 0, 0, gyro_var, 0, 0, 0, gyro_var]
    # 100 ug/sqrt(Hz) and 0.005 deg/s/sqrt(Hz) over a 50 Hz bandwidth
    assert accel_var == pytest.approx((100e-6 * G) ** 2 * 50)
    assert gyro_var == pytest.approx((0.005 * math.pi / 180) ** 2 * 50)


def test_every_sample_arrives_in_order_with_its_values(source_of):
    with MipDevice(moving, speed=5.0) as device:
        items, _ = take(source_of(device.port), 25)
        assert_matches([i.msg for i in items], device.sent[:25])


def test_the_device_is_configured_as_the_manual_says_and_idled_at_close(source_of):
    with MipDevice() as device:
        source = source_of(device.port, rate_hz=50.0)
        configured = [
            Command(0x01, 0x02, b""),  # set to idle
            Command(0x0C, 0x06, b""),  # get IMU data base rate
            # IMU message format: use new, 3 descriptors: accel, gyro, GPS timestamp, each at 500 / 10
            Command(0x0C, 0x08, bytes.fromhex("01 03 04 000A 05 000A 12 000A")),
            Command(0x0C, 0x11, bytes.fromhex("01 01 01")),  # enable the IMU stream
            Command(0x01, 0x06, b""),  # resume
        ]
        assert device.received == configured
        items, _ = take(source, 3)
        assert device.rate_hz == 50.0 and len(items) == 3
        source.close()
        assert device.wait_for(lambda: len(device.received) == 6)
        assert device.received == [*configured, Command(0x01, 0x02, b"")]


def test_a_rate_the_base_rate_does_not_divide_is_rounded_with_a_warning(source_of, caplog):
    with MipDevice() as device:
        source = source_of(device.port, rate_hz=120.0)
        assert device.decimation == 4
        assert source.rate_hz == 125.0
    assert "rate_hz 120 is not the base rate 500 Hz divided by a whole number: streaming at 125 Hz" in caplog.text
    assert "rates near it: 166.667, 125, 100 Hz" in caplog.text


def test_a_refused_command_is_one_line_naming_it():
    with MipDevice(nack={(0x0C, 0x08): 3}) as device, pytest.raises(BadInput) as err:
        MicrostrainImu(MicrostrainParams(port=device.port))
    assert str(err.value) == (
        f"microstrain_imu: {device.port}: the device refused 'IMU message format' (0x0C, 0x08): "
        "error 3 (parameter invalid)"
    )


def test_no_reply_fails_within_the_timeout():
    with MipDevice(mute=frozenset({(0x01, 0x02)})) as device:
        started = time.monotonic()
        with pytest.raises(BadInput) as err:
            MicrostrainImu(MicrostrainParams(port=device.port, timeout_s=0.3))
        waited = time.monotonic() - started
    assert str(err.value) == (
        f"microstrain_imu: no reply to 'set to idle' (0x01, 0x02) within 0.3 s: "
        f"is a 3DM-GX4 on {device.port} at 115200 baud?"
    )
    assert 0.3 <= waited < 1.0


def test_packets_split_anywhere_and_garbage_between_them_lose_nothing(source_of):
    with MipDevice(moving, speed=5.0, split=True, garbage=GARBAGE, stop_after=30) as device:
        source = source_of(device.port)
        items, _ = take(source, 30)
        assert_matches([i.msg for i in items], device.sent)
    assert source.drops == {"bytes of garbage between MIP packets": 30 * len(GARBAGE)}


def test_packets_with_a_bad_checksum_are_dropped_and_counted(source_of):
    with MipDevice(moving, speed=5.0, corrupt_every=5, stop_after=50, vanish=True) as device:
        source = source_of(device.port)
        items, ended = take(source)
        assert ended
        assert_matches([i.msg for i in items], [s for s in device.sent if not s.corrupted])
    assert len(items) == 40
    assert source.drops == {"MIP packets with a bad checksum": 10}


def test_a_vanishing_device_ends_the_stream_with_a_warning(source_of, caplog):
    with MipDevice(moving, speed=5.0, stop_after=20, vanish=True) as device:
        items, ended = take(source_of(device.port))
        assert ended and device.vanished
        assert_matches([i.msg for i in items], device.sent)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1
    assert warnings[0].startswith(f"microstrain_imu: {device.port}: the device went away: ")
    assert warnings[0].endswith("; end of its stream")


def test_a_device_that_falls_silent_ends_the_stream_after_the_timeout(source_of, caplog):
    with MipDevice(moving, speed=5.0, stop_after=10) as device:
        source = source_of(device.port, timeout_s=0.3)
        items, ended = take(source)
        assert device.wait_for(lambda: len(device.sent) == 10)
    assert ended and len(items) == 10
    assert f"microstrain_imu: {device.port}: silent for 0." in caplog.text


@pytest.mark.parametrize(
    ("make_path", "reason"),
    [
        (lambda tmp: tmp / "ttyACM9", "No such file or directory"),
        (lambda tmp: tmp, "Is a directory"),
    ],
)
def test_a_port_that_cannot_be_opened_is_bad_input_naming_it(tmp_path, make_path, reason):
    path = make_path(tmp_path)
    with pytest.raises(BadInput) as err:
        MicrostrainImu(MicrostrainParams(port=str(path)))
    assert str(err.value) == f"microstrain_imu: cannot open serial port {path}: {reason}"


def test_a_file_that_is_not_a_serial_port_is_bad_input_naming_it(tmp_path):
    path = tmp_path / "notatty"
    path.write_bytes(b"")
    with pytest.raises(BadInput, match=f"^microstrain_imu: cannot open serial port {path}: .*ioctl"):
        MicrostrainImu(MicrostrainParams(port=str(path)))


def opening_error(port: str) -> str:
    """The BadInput that opening `port` gives, as an unprivileged user (a forked child drops root's
    rights first: root opens any file)."""
    if os.geteuid() != 0:
        with pytest.raises(BadInput) as err:
            MicrostrainImu(MicrostrainParams(port=port))
        return str(err.value)
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: report the error on the pipe, never return into pytest
        message = "opened"
        try:
            os.setgid(NOBODY)
            os.setuid(NOBODY)
            MicrostrainImu(MicrostrainParams(port=port))
        except BadInput as exc:
            message = str(exc)
        except Exception as exc:
            message = repr(exc)
        finally:
            os.write(write_end, message.encode())
            os._exit(0)
    os.close(write_end)
    with os.fdopen(read_end, "rb") as pipe:
        message = pipe.read().decode()
    os.waitpid(pid, 0)
    return message


def test_a_port_without_permission_is_bad_input_naming_it():
    with MipDevice() as device:
        os.chmod(device.port, 0)
        message = opening_error(device.port)
    assert message == f"microstrain_imu: cannot open serial port {device.port}: Permission denied"


def test_stamps_follow_the_device_clock_when_packets_come_in_bursts(source_of):
    """Four packets written at once every 40 ms: stamped 10 ms apart, not all at the receive time."""
    with MipDevice(moving, burst=4) as device:
        started = time.time_ns()
        items, _ = take(source_of(device.port), 40)
        ended = time.time_ns()
    stamps = stamps_of(items)
    steps = [b - a for a, b in pairwise(stamps)]
    assert all(0 < s <= 10_000_001 for s in steps), steps
    exact = [s for s in steps if abs(s - 10_000_000) <= 1_000]
    assert len(exact) >= 0.6 * len(steps), steps
    assert started < stamps[0] and stamps[-1] <= ended


def test_without_configure_the_driver_only_listens(source_of):
    with MipDevice(lambda t: ((0.0, 0.0, -1.0), (0.0, 0.0, 0.5)), streaming=True) as device:
        source = source_of(device.port, configure=False)
        items, _ = take(source, 10)
        source.close()
        # anything the driver wrote would reach the device before this ping
        fd = os.open(device.port, os.O_RDWR | os.O_NOCTTY)
        try:
            os.write(fd, encode(0x01, [(0x01, b"")]))
            assert device.wait_for(lambda: device.received != [])
        finally:
            os.close(fd)
        assert device.received == [Command(0x01, 0x01, b"")]
    assert len(items) == 10
    assert all(vectors(i.msg) == ((0.0, 0.0, G), (0.0, 0.0, -0.5)) for i in items)


def test_packets_without_both_vectors_or_of_other_sets_are_dropped():
    accel = (0x04, bytes.fromhex("3F800000 00000000 00000000"))
    gyro = (0x05, bytes.fromhex("00000000 3F800000 00000000"))
    port = ScriptedPort([encode(0x80, [accel]), b"", encode(0x81, [accel, gyro]), encode(0x80, [accel, gyro])])
    before = time.time_ns()
    source = MicrostrainImu(MicrostrainParams(port="canned", configure=False), open_port=lambda *_: port)
    items = list(source.run(threading.Event()))
    source.close()
    emits = [i for i in items if isinstance(i, Emit)]
    # a read that brings no usable sample is idle time too: a watermark, so readers are never stalled
    assert [type(i) for i in items] == [Watermark, Watermark, Emit]  # the last two chunks come in one read
    assert len(emits) == 1 and vectors(emits[0].msg) == ((G, 0.0, 0.0), (0.0, -1.0, 0.0))
    assert before <= stamps_of(emits)[0] <= time.time_ns()  # no timestamp: stamped when received
    assert source.drops == {
        "IMU packets without both the scaled accelerometer and gyro vectors": 1,
        "MIP packets that are not IMU data": 1,
    }
    assert port.written == b""


def test_the_device_clock_keeps_device_spacing_and_re_anchors_on_jumps():
    clock = DeviceClock(reanchor_ns=2_000_000_000)
    ms = 1_000_000
    # a burst of three received at once: spaced as the device says, the newest at the receive time
    assert clock.stamps([0, 10 * ms, 20 * ms], 1000 * ms) == [980 * ms, 990 * ms, 1000 * ms]
    # later, slower: the least latency so far still holds
    assert clock.stamps([30 * ms], 1015 * ms) == [1010 * ms]
    # faster than ever: the offset follows
    assert clock.stamps([40 * ms], 1018 * ms) == [1018 * ms]
    # the device clock was set back: stamps start afresh from the receive time, still increasing
    assert clock.stamps([-5000 * ms, -4990 * ms], 1030 * ms) == [1020 * ms, 1030 * ms]
    assert clock.reanchors == 1
    # a jump forward by far more than the host clock moved: re-anchored too
    assert clock.stamps([60_000 * ms], 1040 * ms) == [1040 * ms]
    assert clock.reanchors == 2
    # no device time: the receive time, kept after the last stamp
    assert clock.stamps([None], 1040 * ms) == [1040 * ms + 1]
    # a watermark is a floor for what follows
    assert clock.watermark(2000 * ms, 500 * ms) == 1500 * ms
    assert clock.stamps([60_010 * ms], 1045 * ms) == [1500 * ms + 1]


def test_a_live_pipeline_records_what_the_device_sent(tmp_path):
    """`rover run` with the device feeding a recorder: the device stops after 200 samples and is
    unplugged, the run ends by itself, and the recording holds every sample."""
    with MipDevice(moving, speed=4.0, stop_after=200, vanish=True) as device:
        pipeline = tmp_path / "imu.yaml"
        pipeline.write_text(f"""\
name: imu_live
operators:
  imu:    {{uses: microstrain_imu, params: {{port: "{device.port}", rate_hz: 100}}}}
  record: {{uses: recorder, inputs: {{imu: imu/imu}}, params: {{out: out}}}}
""")
        proc = run_rover("run", str(pipeline), cwd=tmp_path, timeout=60)
        assert proc.returncode == 0, proc.stderr
        assert device.vanished
    assert "Traceback" not in proc.stderr
    assert f"rover: WARNING: microstrain_imu: {device.port}: the device went away" in proc.stderr
    recorded = read_bag(tmp_path / "out" / "results.mcap")
    assert {topic for topic, _, _ in recorded} == {"/imu"}
    messages = [deserialize(data, "sensor_msgs/msg/Imu") for _, _, data in recorded]
    assert_matches(messages, device.sent)
    stamps = [stamp for _, stamp, _ in recorded]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
