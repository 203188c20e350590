"""`create2`: live wheel odometry from an iRobot Create 2 (the robot base) on its serial cable.

The protocol is the iRobot Create 2 Open Interface (OI) Specification. The driver opens the port
(115200 baud by default, 8N1) and sends Start (128: the OI wakes in Passive mode), Safe (131: the
robot then never sleeps) and Stream (148) [2][43][44]: every 15 ms the robot then sends the
cumulative left and right encoder counts in one frame,

    [19][n-bytes][43][left hi][left lo][44][right hi][right lo][checksum]

where n-bytes counts the bytes from the first packet id to the last data byte and the checksum
makes the 8-bit sum of the whole frame zero. The counts are unsigned 16-bit, high byte first,
wrapping at 65535 -> 0 (and back). `StreamParser` finds frames in the byte stream (resyncing on
noise), `WheelOdometry` integrates the counts into a planar pose, and `Create2` publishes a
nav_msgs/Odometry per frame, stamped with the host's receive time. On close the driver pauses the
stream (150 0) and stops the OI (173): the robot leaves Safe mode (in which it neither charges nor
sleeps) and is back on its own, passive behaviour. POSIX serial ports (Linux, macOS), through pyserial.
"""

from __future__ import annotations

import contextlib
import logging
import math
import termios
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from rover.drivers.serial_port import SerialPort, explain, open_serial
from rover.errors import BadInput
from rover.geometry import quaternion_from_yaw, wrap_angle
from rover.messages import header, make
from rover.operator import COMPLETE, Emit, Out, RunOutcome, Source, Watermark
from rover.pipeline.params import Checked, PositiveFloat, PositiveInt

log = logging.getLogger("rover.create2")

OP_START = 128
"""Start: opens the OI, in Passive mode (sensors only)."""
OP_SAFE = 131
"""Safe mode: the robot obeys commands, keeps its cliff and wheel-drop safety stops, and never sleeps."""
OP_STREAM = 148
"""Stream [number of packets][packet ids...]: send those packets every 15 ms until paused."""
OP_PAUSE_RESUME_STREAM = 150
"""Pause/Resume Stream [0 = pause, 1 = resume], keeping the list of packets."""
OP_STOP = 173
"""Stop: the OI stops (streams too) and no longer answers commands; the robot charges and sleeps again."""

STREAM_HEADER = 19
"""First byte of every stream frame."""
LEFT_ENCODER = 43
RIGHT_ENCODER = 44
"""Packet ids of the cumulative encoder counts (2 bytes, unsigned, high byte first)."""
ENCODER_MODULUS = 65536
"""The counts wrap at 65535 -> 0."""
STREAM_PERIOD_NS = 15_000_000
"""The robot sends a stream frame every 15 ms."""

PACKET_BYTES: dict[int, int] = {
    **dict.fromkeys(range(7, 19), 1),
    19: 2, 20: 2, 21: 1, 22: 2, 23: 2, 24: 1, 25: 2, 26: 2,
    **dict.fromkeys(range(27, 32), 2),
    32: 1, 33: 2, 34: 1, 35: 1, 36: 1, 37: 1, 38: 1,
    **dict.fromkeys(range(39, 45), 2),
    45: 1,
    **dict.fromkeys(range(46, 52), 2),
    52: 1, 53: 1,
    **dict.fromkeys(range(54, 58), 2),
    58: 1,
}  # fmt: skip
"""Data bytes of each single sensor packet of the Create 2 OI (ids 7-58)."""
SIGNED_PACKETS = frozenset({19, 20, 23, 24, 39, 40, 41, 42, 54, 55, 56, 57})
"""Packets whose value is two's complement (distance, angle, current, temperature, requested
velocities and radius, motor currents); every other one is unsigned."""
PACKET_GROUPS: dict[int, range] = {
    0: range(7, 27),
    1: range(7, 17),
    2: range(17, 21),
    3: range(21, 27),
    4: range(27, 35),
    5: range(35, 43),
    6: range(7, 43),
    100: range(7, 59),
    101: range(43, 59),
    106: range(46, 52),
    107: range(54, 59),
}
"""Group packet ids and the single packets they carry, in order."""
MIN_FRAME_BODY_BYTES = 2
"""The smallest n-bytes of a frame: one packet id and one data byte."""

"""Serial read timeout: how long a read waits for the first byte (the loop's idle period)."""
VELOCITY_SPAN_S = 0.045
"""Velocities are the change over at least this much host time (3 stream periods): frames arrive
with host jitter and sometimes several in one read, so a single frame's time step is unreliable."""

SLIP_FRACTION = 0.02
"""1-sigma error of the distance driven, as a fraction of it: an allowance for wheel slip, tyre wear
and the nominal wheel diameter (a few per cent is typical of small differential drives indoors; not
measured on this robot: calibrate `wheel_diameter_m` on its floor to do better)."""
HEADING_SLIP_FRACTION = 0.03
"""1-sigma error of a heading change, as a fraction of the angle turned: an allowance for the
wheels' contact points not being exactly `wheel_base_m` apart and for slip in turns in place."""
HEADING_DRIFT_RAD_PER_M = 0.01
"""1-sigma heading error per metre driven (rad/m): an allowance for unequal wheel diameters, which
curve a straight line."""
UNOBSERVED_VARIANCE = 1e6
"""Variance (m², rad², (m/s)², (rad/s)²) of what wheel odometry does not measure: z, roll, pitch
and their rates. Large, so that a fusing filter ignores them."""


# ----------------------------------------------------------------------------- stream frames


Layout = Literal["fits", "more", "unknown", "misfit"]
"""Whether the packets of a candidate frame fill its n-bytes exactly; "more": bytes still to come;
"unknown": a packet id the OI does not define; "misfit": the packets overrun n-bytes."""


@dataclass
class StreamParser:
    """Finds stream frames in a byte stream fed in arbitrary chunks; pure (no I/O).

    A candidate frame starts at a header byte 19. It is taken when its n-bytes is plausible, its
    packets fill n-bytes exactly and its checksum holds; otherwise the parser skips that one byte
    and searches again, so a 19 inside data or noise cannot make it lose a real frame. A candidate
    is rejected as soon as its bytes show it is not a frame (an unknown packet id, packets that
    overrun n-bytes), so noise holds real frames back only rarely. The outcome never depends on
    where the chunks were cut."""

    bad_checksums: int = 0
    """well-formed candidates (known packets filling n-bytes) whose checksum failed"""
    skipped_bytes: int = 0
    """bytes that were not part of a frame taken"""
    unknown_packets: int = 0
    """candidates rejected at a packet id the OI does not define: noise, or a frame of another
    robot's packets (a Create 2 sends only the packets requested)"""

    def __post_init__(self) -> None:
        self._buffer = bytearray()

    @property
    def pending(self) -> int:
        """Bytes held back: the start of a frame not yet complete."""
        return len(self._buffer)

    def feed(self, chunk: bytes) -> list[dict[int, int]]:
        """The frames completed by `chunk`, each as {packet id: value}."""
        self._buffer += chunk
        return self._scan(final=False)

    def finish(self) -> list[dict[int, int]]:
        """The input ended: the frames held behind a candidate that can no longer complete."""
        frames = self._scan(final=True)
        self.skipped_bytes += len(self._buffer)
        self._buffer.clear()
        return frames

    def _scan(self, final: bool) -> list[dict[int, int]]:
        buf = self._buffer
        frames: list[dict[int, int]] = []
        pos = 0
        while True:
            start = buf.find(STREAM_HEADER, pos)
            if start < 0:
                self.skipped_bytes += len(buf) - pos
                pos = len(buf)
                break
            self.skipped_bytes += start - pos
            pos = start
            layout = self._layout(pos)
            if layout == "more" and not final:
                break
            end = pos + 2 + buf[pos + 1] + 1 if layout == "fits" else 0
            if layout == "fits" and sum(buf[pos:end]) & 0xFF == 0:
                frames.append(decode_packets(bytes(buf[pos + 2 : end - 1])))
                pos = end
                continue
            if layout == "fits":
                self.bad_checksums += 1
            elif layout == "unknown":
                self.unknown_packets += 1
            self.skipped_bytes += 1
            pos += 1
        del buf[:pos]
        return frames

    def _layout(self, pos: int) -> Layout:
        """How the packets of the candidate frame at `pos` fit its n-bytes, as far as bytes are here."""
        buf = self._buffer
        if pos + 1 >= len(buf):
            return "more"
        size = buf[pos + 1]
        if size < MIN_FRAME_BODY_BYTES:
            return "misfit"
        at, body_end = pos + 2, pos + 2 + size
        while at < body_end:
            if at >= len(buf):
                return "more"
            packet = buf[at]
            members = PACKET_GROUPS.get(packet, (packet,) if packet in PACKET_BYTES else ())
            if not members:
                return "unknown"
            at += 1 + sum(PACKET_BYTES[m] for m in members)
        if at > body_end:
            return "misfit"
        return "fits" if body_end < len(buf) else "more"


def decode_packets(body: bytes) -> dict[int, int]:
    """{packet id: value} of a frame body (ids and data, no header, n-bytes or checksum) whose layout
    was checked; a group packet gives the values of its members."""
    values: dict[int, int] = {}
    pos = 0
    while pos < len(body):
        packet = body[pos]
        pos += 1
        for member in PACKET_GROUPS.get(packet, (packet,)):
            size = PACKET_BYTES[member]
            values[member] = int.from_bytes(body[pos : pos + size], "big", signed=member in SIGNED_PACKETS)
            pos += size
    return values


# ----------------------------------------------------------------------------- odometry


@dataclass(frozen=True)
class WheelGeometry:
    """The drive's dimensions, which turn encoder counts into metres."""

    wheel_diameter_m: float = 0.072
    wheel_base_m: float = 0.235
    """distance between the two wheels' contact points"""
    counts_per_rev: float = 508.8

    @property
    def metres_per_count(self) -> float:
        return math.pi * self.wheel_diameter_m / self.counts_per_rev


@dataclass(frozen=True)
class OdometryEstimate:
    """The planar pose since the first frame, and the current velocities."""

    stamp_ns: int
    x_m: float
    y_m: float
    yaw_rad: float
    """in [-pi, pi], counter-clockwise"""
    linear_m_s: float
    """forward speed of the robot's centre (between the wheels)"""
    angular_rad_s: float
    path_m: float
    """distance the centre travelled, forward or back (for the covariance)"""
    turned_rad: float
    """angle turned, either way (for the covariance)"""
    velocity_span_s: float
    """host time the velocities were measured over (0 until two stamps differ)"""


def encoder_delta(previous: int, current: int) -> int:
    """Signed change of a 16-bit wrapping counter, in [-32768, 32767]."""
    return (current - previous + ENCODER_MODULUS // 2) % ENCODER_MODULUS - ENCODER_MODULUS // 2


class WheelOdometry:
    """Integrates cumulative wheel encoder counts into a pose (midpoint rule) and velocities; pure.

    The first update only sets the reference counts and returns None: the pose starts at 0 there.
    A step is assumed to be less than half the counter's range (32768 counts, 14.5 m of wheel travel
    on a Create 2), which at 15 ms per frame holds far beyond any wheel speed."""

    def __init__(self, geometry: WheelGeometry, velocity_span_s: float = VELOCITY_SPAN_S):
        self.geometry = geometry
        self._span_ns = int(velocity_span_s * 1e9)
        self._counts: tuple[int, int] | None = None
        self.x_m = self.y_m = self.yaw_rad = 0.0
        self.path_m = self.turned_rad = 0.0
        self._forward_m = 0.0
        """signed distance the centre travelled (for the velocity)"""
        self._heading_rad = 0.0
        """unwrapped heading (for the angular velocity)"""
        self._history: deque[tuple[int, float, float]] = deque()
        self._velocity = (0.0, 0.0, 0.0)

    def update(self, left_counts: int, right_counts: int, stamp_ns: int) -> OdometryEstimate | None:
        """Advance to these cumulative counts, read at `stamp_ns`."""
        if self._counts is None:
            self._counts = (left_counts, right_counts)
            self._history.append((stamp_ns, 0.0, 0.0))
            return None
        step_m = self.geometry.metres_per_count
        left_m = encoder_delta(self._counts[0], left_counts) * step_m
        right_m = encoder_delta(self._counts[1], right_counts) * step_m
        self._counts = (left_counts, right_counts)
        forward_m = (left_m + right_m) / 2
        turn_rad = (right_m - left_m) / self.geometry.wheel_base_m
        middle = self.yaw_rad + turn_rad / 2
        self.x_m += forward_m * math.cos(middle)
        self.y_m += forward_m * math.sin(middle)
        self.yaw_rad = float(wrap_angle(self.yaw_rad + turn_rad))
        self.path_m += abs(forward_m)
        self.turned_rad += abs(turn_rad)
        self._forward_m += forward_m
        self._heading_rad += turn_rad
        self._update_velocity(stamp_ns)
        linear, angular, span = self._velocity
        return OdometryEstimate(
            stamp_ns, self.x_m, self.y_m, self.yaw_rad, linear, angular, self.path_m, self.turned_rad, span
        )

    def _update_velocity(self, stamp_ns: int) -> None:
        """Velocities over the newest history entry at least VELOCITY_SPAN_S old (or the oldest)."""
        history = self._history
        history.append((stamp_ns, self._forward_m, self._heading_rad))
        while len(history) > 2 and stamp_ns - history[1][0] >= self._span_ns:
            history.popleft()
        then_ns, then_forward, then_heading = history[0]
        if stamp_ns > then_ns:
            span_s = (stamp_ns - then_ns) / 1e9
            self._velocity = (
                (self._forward_m - then_forward) / span_s,
                (self._heading_rad - then_heading) / span_s,
                span_s,
            )


def pose_covariance(estimate: OdometryEstimate, geometry: WheelGeometry) -> np.ndarray:
    """The 6x6 row-major covariance of (x, y, z, roll, pitch, yaw), diagonal.

    x and y: one count's quantization per wheel at each end of the path (the centre is their mean:
    q²/12) plus the slip allowance (SLIP_FRACTION × path)². Yaw: quantization (q²/(3 b²)) plus
    HEADING_SLIP_FRACTION of the angle turned and HEADING_DRIFT_RAD_PER_M of the path, added
    linearly (both are biases, not independent per step). z, roll, pitch: UNOBSERVED_VARIANCE."""
    q, b = geometry.metres_per_count, geometry.wheel_base_m
    xy = q * q / 12 + (SLIP_FRACTION * estimate.path_m) ** 2
    heading_std = HEADING_SLIP_FRACTION * estimate.turned_rad + HEADING_DRIFT_RAD_PER_M * estimate.path_m
    yaw = q * q / (3 * b * b) + heading_std**2
    return np.diag([xy, xy, UNOBSERVED_VARIANCE, UNOBSERVED_VARIANCE, UNOBSERVED_VARIANCE, yaw]).ravel()


def twist_covariance(estimate: OdometryEstimate, geometry: WheelGeometry) -> np.ndarray:
    """The 6x6 row-major covariance of (vx, vy, vz, wx, wy, wz) in the robot frame, diagonal.

    vx and vy (a wheeled robot does not slide sideways but for slip): one count's quantization
    over the velocity span plus (SLIP_FRACTION × speed)². wz: quantization over the span plus
    (HEADING_SLIP_FRACTION × rate)². Before two stamps differ the speeds are unknown:
    UNOBSERVED_VARIANCE. vz, wx, wy: UNOBSERVED_VARIANCE."""
    q, b, span = geometry.metres_per_count, geometry.wheel_base_m, estimate.velocity_span_s
    if span <= 0:
        return np.diag([UNOBSERVED_VARIANCE] * 6).ravel()
    linear = q * q / (12 * span * span) + (SLIP_FRACTION * estimate.linear_m_s) ** 2
    angular = q * q / (3 * b * b * span * span) + (HEADING_SLIP_FRACTION * estimate.angular_rad_s) ** 2
    return np.diag([linear, linear, UNOBSERVED_VARIANCE, UNOBSERVED_VARIANCE, UNOBSERVED_VARIANCE, angular]).ravel()


# ----------------------------------------------------------------------------- the source


@dataclass(frozen=True)
class Create2Params(Checked):
    port: str
    """the serial device of the robot's cable, e.g. /dev/ttyUSB0"""
    baud: PositiveInt = 115200
    """the OI's default rate"""
    wheel_diameter_m: PositiveFloat = 0.072
    wheel_base_m: PositiveFloat = 0.235
    counts_per_rev: PositiveFloat = 508.8
    frame_id: str = "odom"
    child_frame_id: str = "base_link"
    timeout_s: PositiveFloat = 1.0
    """no stream frame for this long means the robot is gone (off, asleep, unplugged, wrong baud)"""


class Create2(Source):
    """Publishes the Create 2's wheel odometry, one message per 15 ms stream frame."""

    live = True

    outputs = {"odom": Out("nav_msgs/msg/Odometry", "wheel odometry from the encoder counts, every 15 ms")}
    Params = Create2Params

    def __init__(
        self, params: Create2Params | None = None, open_port: Callable[[str, str, int], SerialPort] = open_serial
    ):
        if params is None:
            raise BadInput("create2: no serial port given (set params.port)")
        super().__init__(params)
        p: Create2Params = self.params
        self.geometry = WheelGeometry(p.wheel_diameter_m, p.wheel_base_m, p.counts_per_rev)
        self.parser = StreamParser()
        self.odometry = WheelOdometry(self.geometry)
        self.port = open_port("create2", p.port, p.baud)
        self._streaming = False
        self._closed = False
        self._last_stamp_ns = 0
        """the last stamp sent or promised: later frames are never stamped before it"""
        self._counted = (0, 0)

    def run(self, stop: threading.Event) -> Iterator[Emit | Watermark]:
        p: Create2Params = self.params
        try:
            self.port.reset_input_buffer()
            self._streaming = True
            self.port.write(bytes([OP_START, OP_SAFE, OP_STREAM, 2, LEFT_ENCODER, RIGHT_ENCODER]))
        except (OSError, termios.error) as exc:
            log.warning("create2: %s: cannot send the stream request (%s): no odometry", p.port, explain(exc))
            return
        last_frame = time.monotonic()
        while not stop.is_set():
            try:
                chunk = self.port.read(self.port.in_waiting or 1)
            except OSError as exc:
                yield from self._frames(self.parser.finish(), time.time_ns())
                log.warning(
                    "create2: %s: reading the robot failed (%s): the odometry stream ends",
                    p.port,
                    explain(exc),
                )
                return
            now_ns = time.time_ns()
            if chunk:
                frames = self.parser.feed(chunk)
                if frames:
                    last_frame = time.monotonic()
                yield from self._frames(frames, now_ns)
            if time.monotonic() - last_frame > p.timeout_s:
                yield from self._frames(self.parser.finish(), now_ns)
                log.warning(
                    "create2: %s: no stream frame for %g s (robot off or asleep, or not at %d baud?): "
                    "the odometry stream ends",
                    p.port,
                    p.timeout_s,
                    p.baud,
                )
                return
            if not chunk:
                self._last_stamp_ns = max(now_ns, self._last_stamp_ns)
                yield Watermark(self._last_stamp_ns)

    def _frames(self, frames: list[dict[int, int]], now_ns: int) -> Iterator[Emit]:
        """An odometry message per frame with both encoder counts; what the parser skipped is counted.

        Frames are stamped with the receive time; several read at once (the driver was busy) were
        sent one stream period apart, so the earlier ones are stamped that much earlier, never
        before the frame before them."""
        counted = (self.parser.bad_checksums, self.parser.skipped_bytes)
        bad, skipped = (now - before for now, before in zip(counted, self._counted, strict=True))
        self._counted = counted
        self.drop("stream frames with a bad checksum", bad)
        self.drop("bytes outside stream frames (line noise, or frames cut short)", skipped)
        for i, values in enumerate(frames):
            if LEFT_ENCODER not in values or RIGHT_ENCODER not in values:
                self.drop("stream frames without both encoder counts (packets 43 and 44)")
                continue
            sent_ns = now_ns - (len(frames) - 1 - i) * STREAM_PERIOD_NS
            stamp_ns = self._last_stamp_ns = max(sent_ns, self._last_stamp_ns)
            estimate = self.odometry.update(values[LEFT_ENCODER], values[RIGHT_ENCODER], stamp_ns)
            if estimate is not None:
                yield Emit("odom", self.message(estimate))

    def message(self, estimate: OdometryEstimate) -> Any:
        """The nav_msgs/Odometry of an estimate: pose in `frame_id`, twist in `child_frame_id`."""
        p: Create2Params = self.params
        msg = make(
            "nav_msgs/msg/Odometry", header=header(estimate.stamp_ns, p.frame_id), child_frame_id=p.child_frame_id
        )
        pose = msg.pose.pose
        pose.position.x, pose.position.y = estimate.x_m, estimate.y_m
        _, _, qz, qw = quaternion_from_yaw(estimate.yaw_rad)
        pose.orientation.z, pose.orientation.w = float(qz), float(qw)
        msg.pose.covariance = pose_covariance(estimate, self.geometry)
        msg.twist.twist.linear.x = estimate.linear_m_s
        msg.twist.twist.angular.z = estimate.angular_rad_s
        msg.twist.covariance = twist_covariance(estimate, self.geometry)
        return msg

    def close(self, outcome: RunOutcome = COMPLETE) -> None:
        """Pause the stream and stop the OI if `run` started them (the robot is left passive), then close
        the port. The port may be gone (cable pulled): write errors are ignored."""
        if self._closed:
            return
        self._closed = True
        if self._streaming:
            with contextlib.suppress(OSError, termios.error):
                self.port.write(bytes([OP_PAUSE_RESUME_STREAM, 0, OP_STOP]))
                self.port.flush()
        with contextlib.suppress(OSError, termios.error):
            self.port.close()
