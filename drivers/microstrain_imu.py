"""`microstrain_imu`: live IMU samples from a LORD MicroStrain 3DM-GX4-45 on a serial port (MIP protocol).

With `configure` (the default) the driver sets the device up as the 3DM-GX4-45 Data Communications
Protocol manual describes: set to idle, read the IMU base rate, set the IMU message format to the
scaled accelerometer (0x80, 0x04), scaled gyro (0x80, 0x05) and GPS correlation timestamp (0x80, 0x12)
at `rate_hz`, enable the IMU stream and resume. Each command waits for its ACK. Without it, the
driver only listens to what the device already streams.

Every IMU packet with both vectors becomes a sensor_msgs/Imu in REP-103 axes (x forward, y left,
z up): the device's frame is x forward, y right, z down, a half turn about x away. Accelerations are
converted from g to m/s^2, angular rates are rad/s already. Orientation is not measured
(orientation_covariance[0] = -1); the other covariances come from the datasheet noise densities.

Stamps are on the host clock, spaced as the device's own timestamps: stamp = device time + offset,
where the offset is the least (host receive time - device time) seen so far, i.e. the latency of
the least-delayed packet. A read that brings several packets at once gives all of them the offset
the newest one implies, so a burst keeps its spacing. The offset is re-anchored (forgotten and taken
afresh) when the device time goes backwards, or jumps against the host clock by more than
`REANCHOR_S` between two packets (the device's clock was set). Stamps are kept strictly increasing
and never before a watermark already sent; watermarks, sent while no bytes come, run `timeout_s`
behind the host clock (a packet delayed even more is stamped just after the last one). A packet
without a timestamp is stamped when received. A run that begins more than `timeout_s` after the
device was set up (its host waited for the others) discards what the device sent meanwhile.

The stream ends, with one warning, when the port fails (unplugged device) or the device says
nothing for `timeout_s` while streaming. On close a configured device is set back to idle.
"""

from __future__ import annotations

import logging
import math
import struct
import termios
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from rover.drivers.mip import MipParser, Packet, encode
from rover.drivers.serial_port import SerialPort, explain, open_serial
from rover.errors import BadInput
from rover.messages import header, make
from rover.operator import COMPLETE, Emit, Out, RunOutcome, Source, Watermark
from rover.pipeline.params import Checked, PositiveFloat, PositiveInt

log = logging.getLogger("rover.microstrain_imu")

BASE_SET = 0x01
CMD_SET_IDLE = 0x02
CMD_RESUME = 0x06
SET_3DM = 0x0C
CMD_GET_IMU_BASE_RATE = 0x06
CMD_IMU_MESSAGE_FORMAT = 0x08
CMD_DATA_STREAM = 0x11
REPLY_IMU_BASE_RATE = 0x83
FUNCTION_USE_NEW = 0x01
STREAM_IMU = 0x01
"""device selector of the IMU stream in the enable/disable continuous data stream command"""
STREAM_ENABLE = 0x01
ACK_NACK = 0xF1
"""the ACK/NACK reply field, the same in every command set: [echoed command descriptor, error code]"""

IMU_SET = 0x80
SCALED_ACCEL = 0x04
SCALED_GYRO = 0x05
GPS_TIMESTAMP = 0x12
VECTOR = struct.Struct(">3f")
TIMESTAMP = struct.Struct(">dHH")
"""GPS time of week (s), GPS week, valid flags"""
BASE_RATE = struct.Struct(">H")
DECIMATION = struct.Struct(">BH")
"""one entry of the IMU message format: data descriptor, rate decimation"""
MAX_DECIMATION = 0xFFFF

NACK_ERRORS = {
    1: "unknown command",
    2: "checksum invalid",
    3: "parameter invalid",
    4: "command failed",
    5: "command timeout",
    6: "unknown descriptor set",
}
"""the MIP ACK/NACK error codes"""

STANDARD_GRAVITY_M_S2 = 9.80665
"""1 g, the unit of the scaled accelerometer vector"""
WEEK_NS = 7 * 24 * 3600 * 1_000_000_000

ACCEL_NOISE_DENSITY_G_PER_SQRT_HZ = 100e-6
"""Accelerometer noise density of the 3DM-GX4-45, 100 ug/sqrt(Hz) (LORD MicroStrain 3DM-GX4-45 datasheet,
accelerometer specifications)."""
GYRO_NOISE_DENSITY_DEG_S_PER_SQRT_HZ = 0.005
"""Gyroscope noise density of the 3DM-GX4-45, 0.005 deg/s/sqrt(Hz) (same datasheet, gyroscope
specifications)."""

REANCHOR_S = 3.0
"""a device-time step that differs from the host-time step by more than this re-anchors the stamps"""


def accel_variance_m2_s4(rate_hz: float) -> float:
    """Per-axis variance of one accelerometer sample, (m/s^2)^2: noise density squared times the
    bandwidth of a sample stream at `rate_hz` (its Nyquist frequency)."""
    return (ACCEL_NOISE_DENSITY_G_PER_SQRT_HZ * STANDARD_GRAVITY_M_S2) ** 2 * rate_hz / 2


def gyro_variance_rad2_s2(rate_hz: float) -> float:
    """Per-axis variance of one gyro sample, (rad/s)^2, likewise."""
    return math.radians(GYRO_NOISE_DENSITY_DEG_S_PER_SQRT_HZ) ** 2 * rate_hz / 2


def device_to_rep103(x: float, y: float, z: float) -> tuple[float, float, float]:
    """A vector of the device frame (x forward, y right, z down) in REP-103 axes (x forward, y left,
    z up): a half turn about x."""
    return x, -y, -z


@dataclass(frozen=True)
class MicrostrainParams(Checked):
    port: str
    """The serial port of the device (/dev/ttyACM0, or a udev link to it)."""
    baud: PositiveInt = 115200
    rate_hz: PositiveFloat = 100.0
    """IMU sample rate: the device's base rate (500 Hz on the GX4-45) divided by a whole number."""
    configure: bool = True
    """Set the message format and start the stream; false: only listen to what the device sends."""
    frame_id: str = "imu_link"
    timeout_s: PositiveFloat = 1.0
    """How long a command waits for its reply, and how long a streaming device may stay silent."""


@dataclass(frozen=True)
class Sample:
    """One IMU packet, decoded: device-frame vectors and the device time (None without a timestamp)."""

    accel_g: tuple[float, float, float]
    gyro_rad_s: tuple[float, float, float]
    device_ns: int | None


def decode_sample(packet: Packet) -> Sample | None:
    """The vectors and time of an IMU data packet; None when it lacks either vector."""
    accel, gyro = packet.field(SCALED_ACCEL), packet.field(SCALED_GYRO)
    if accel is None or gyro is None or len(accel) != VECTOR.size or len(gyro) != VECTOR.size:
        return None
    device_ns = None
    stamp = packet.field(GPS_TIMESTAMP)
    if stamp is not None and len(stamp) == TIMESTAMP.size:
        tow_s, week, _flags = TIMESTAMP.unpack(stamp)
        if math.isfinite(tow_s):
            device_ns = week * WEEK_NS + round(tow_s * 1e9)
    ax, ay, az = VECTOR.unpack(accel)
    gx, gy, gz = VECTOR.unpack(gyro)
    return Sample((ax, ay, az), (gx, gy, gz), device_ns)


class DeviceClock:
    """Host-clock stamps for device times: device time + the least latency seen (see the module doc)."""

    def __init__(self, reanchor_ns: int = round(REANCHOR_S * 1e9)) -> None:
        self.reanchor_ns = reanchor_ns
        self.offset_ns: int | None = None
        self.floor_ns = 0
        """stamps must come after this: the last stamp or watermark"""
        self.reanchors = 0
        self._last: tuple[int, int] | None = None
        """(device time, host time) of the last timed packet"""

    def stamps(self, device_ns: list[int | None], host_ns: int) -> list[int]:
        """Stamps for the packets of one read, received at `host_ns`, in order."""
        segments: list[list[tuple[int, int]]] = [[]]
        """(index, device time) of the timed packets, cut where the clock re-anchors"""
        for i, d in enumerate(device_ns):
            if d is None:
                continue
            if self._last is not None and self._jumped(d, host_ns):
                segments.append([])
            segments[-1].append((i, d))
            self._last = (d, host_ns)
        out = [host_ns] * len(device_ns)
        for k, segment in enumerate(segments):
            if not segment:
                continue
            if k > 0:
                self.offset_ns = None
                self.reanchors += 1
            least = min(host_ns - d for _, d in segment)
            self.offset_ns = least if self.offset_ns is None else min(self.offset_ns, least)
            for i, d in segment:
                out[i] = d + self.offset_ns
        for i, stamp in enumerate(out):
            out[i] = self.floor_ns = max(stamp, self.floor_ns + 1)
        return out

    def _jumped(self, device_ns: int, host_ns: int) -> bool:
        assert self._last is not None
        last_device, last_host = self._last
        step = device_ns - last_device
        return step <= 0 or abs(step - (host_ns - last_host)) > self.reanchor_ns

    def watermark(self, host_ns: int, lag_ns: int) -> int:
        """A promise for an idle moment: no later stamp is before it (later stamps are kept after it)."""
        self.floor_ns = max(self.floor_ns, host_ns - lag_ns)
        return self.floor_ns


OpenPort = Callable[[str, str, int], SerialPort]


class MicrostrainImu(Source):
    """Publishes the IMU samples of a 3DM-GX4-45, in SI units and REP-103 axes."""

    live = True

    outputs = {"imu": Out("sensor_msgs/msg/Imu", "accelerometer and gyro samples; orientation unknown")}
    Params = MicrostrainParams

    def __init__(self, params: MicrostrainParams | None = None, open_port: OpenPort = open_serial):
        if params is None or not params.port:
            raise BadInput("microstrain_imu: no serial port given (params.port)")
        super().__init__(params)
        p: MicrostrainParams = self.params
        self._who = f"microstrain_imu: {p.port}"
        self.parser = MipParser()
        self.clock = DeviceClock()
        self.rate_hz = p.rate_hz
        self.configured = False
        self._pending: list[Packet] = []
        """data packets read with the last command's reply, for `run`"""
        self._pending_ns = 0
        self._configured_at = time.monotonic()
        """when the device was set up (or opened): a run starting much later discards the backlog"""
        self.port = open_port("microstrain_imu", p.port, p.baud)
        if p.configure:
            try:
                self._configure()
            except BaseException:
                self.port.close()
                raise
        self._accel_cov = np.diag([accel_variance_m2_s4(self.rate_hz)] * 3).ravel()
        self._gyro_cov = np.diag([gyro_variance_rad2_s2(self.rate_hz)] * 3).ravel()

    def _configure(self) -> None:
        """Idle, read the base rate, set the message format, enable the IMU stream, resume."""
        self._command("set to idle", BASE_SET, CMD_SET_IDLE)
        reply = self._command("get IMU data base rate", SET_3DM, CMD_GET_IMU_BASE_RATE)
        rate = reply.field(REPLY_IMU_BASE_RATE)
        if rate is None or len(rate) != BASE_RATE.size or BASE_RATE.unpack(rate)[0] == 0:
            raise BadInput(f"{self._who}: the reply to 'get IMU data base rate' carries no base rate")
        (base_hz,) = BASE_RATE.unpack(rate)
        decimation = self._decimation(base_hz)
        entries = b"".join(DECIMATION.pack(d, decimation) for d in (SCALED_ACCEL, SCALED_GYRO, GPS_TIMESTAMP))
        self._command("IMU message format", SET_3DM, CMD_IMU_MESSAGE_FORMAT, bytes((FUNCTION_USE_NEW, 3)) + entries)
        self._command(
            "enable IMU data stream", SET_3DM, CMD_DATA_STREAM, bytes((FUNCTION_USE_NEW, STREAM_IMU, STREAM_ENABLE))
        )
        self._command("resume", BASE_SET, CMD_RESUME)
        self.configured = True
        self._configured_at = time.monotonic()
        log.info("%s: streaming at %g Hz (base rate %d Hz / %d)", self._who, self.rate_hz, base_hz, decimation)

    def _decimation(self, base_hz: int) -> int:
        """The rate decimation for `rate_hz`; a warning naming the rate used when the base rate does not divide."""
        wanted = self.params.rate_hz
        decimation = min(MAX_DECIMATION, max(1, round(base_hz / wanted)))
        self.rate_hz = base_hz / decimation
        if not math.isclose(self.rate_hz, wanted, rel_tol=1e-9):
            nearby = sorted({base_hz / d for d in range(max(1, decimation - 1), decimation + 2)}, reverse=True)
            log.warning(
                "%s: rate_hz %g is not the base rate %d Hz divided by a whole number: streaming at %g Hz "
                "(decimation %d); rates near it: %s Hz",
                self._who,
                wanted,
                base_hz,
                self.rate_hz,
                decimation,
                ", ".join(f"{r:g}" for r in nearby),
            )
        return decimation

    def _command(self, name: str, descriptor_set: int, descriptor: int, data: bytes = b"") -> Packet:
        """Send one command and wait for its ACK (data packets on the way are kept for `run`)."""
        p: MicrostrainParams = self.params
        what = f"'{name}' (0x{descriptor_set:02X}, 0x{descriptor:02X})"
        try:
            self.port.write(encode(descriptor_set, [(descriptor, data)]))
        except OSError as exc:
            raise BadInput(f"{self._who}: cannot send {what}: {explain(exc)}") from None
        deadline = time.monotonic() + p.timeout_s
        self._pending = []
        while time.monotonic() < deadline:
            try:
                chunk = self._read()
            except OSError as exc:
                raise BadInput(f"{self._who}: reading the reply to {what} failed: {explain(exc)}") from None
            packets = self.parser.feed(chunk)
            for i, packet in enumerate(packets):
                ack = packet.field(ACK_NACK) if packet.descriptor_set == descriptor_set else None
                if ack is None or len(ack) != 2 or ack[0] != descriptor:
                    continue
                if ack[1]:
                    meaning = NACK_ERRORS.get(ack[1], "unknown error")
                    raise BadInput(f"{self._who}: the device refused {what}: error {ack[1]} ({meaning})")
                self._pending = [q for q in packets[i + 1 :] if q.descriptor_set == IMU_SET]
                self._pending_ns = time.time_ns()
                return packet
        raise BadInput(
            f"microstrain_imu: no reply to {what} within {p.timeout_s:g} s: is a 3DM-GX4 on {p.port} at {p.baud} baud?"
        )

    def _read(self) -> bytes:
        """What the port has: waits up to POLL_S for a first byte, then takes whatever else is there."""
        waiting = self.port.in_waiting
        data = self.port.read(waiting or 1)
        if data and (more := self.port.in_waiting):
            data += self.port.read(more)
        return data

    def run(self, stop: threading.Event) -> Iterator[Emit | Watermark]:
        p: MicrostrainParams = self.params
        lag_ns = round(p.timeout_s * 1e9)
        streaming = p.configure
        heard = time.monotonic()
        """when the last IMU sample arrived: bytes of anything else do not keep the stream alive"""
        warned_silent = False
        if time.monotonic() - self._configured_at > p.timeout_s:
            self._discard_backlog()
        elif self._pending:
            yield from self._emit(self._pending, self._pending_ns)
        self._pending = []
        while not stop.is_set():
            try:
                chunk = self._read()
            except OSError as exc:
                log.warning("%s: the device went away: %s; end of its stream", self._who, explain(exc))
                return
            host_ns = time.time_ns()
            emitted = list(self._emit(self.parser.feed(chunk), host_ns)) if chunk else []
            self._count_stream_drops()
            if emitted:
                heard, streaming = time.monotonic(), True
                yield from emitted
                continue
            silent_s = time.monotonic() - heard
            if silent_s >= p.timeout_s and streaming:
                log.warning("%s: silent for %.1f s: the device went away: end of its stream", self._who, silent_s)
                return
            if silent_s >= p.timeout_s and not warned_silent:
                log.warning("%s: no IMU sample received yet: is the device streaming? (configure is off)", self._who)
                warned_silent = True
            yield Watermark(self.clock.watermark(time.time_ns(), lag_ns))

    def _discard_backlog(self) -> None:
        """Forget what the device sent while the run had not begun (the other hosts were awaited,
        possibly minutes): stamped now, it would be packed into the first instants of the run."""
        try:
            self.port.reset_input_buffer()
        except (OSError, termios.error) as exc:
            log.debug("%s: could not discard the input buffer: %s", self._who, exc)
        self._pending = []
        self.parser = MipParser()

    def _count_stream_drops(self) -> None:
        """Bring the drop counts up to the parser's (it counts from the start)."""
        for reason, total in (
            ("MIP packets with a bad checksum", self.parser.bad_checksums),
            ("bytes of garbage between MIP packets", self.parser.skipped_bytes),
            ("MIP packets whose fields do not add up", self.parser.bad_fields),
        ):
            self.drop(reason, total - self.drops[reason])

    def _emit(self, packets: list[Packet], host_ns: int) -> Iterator[Emit]:
        samples = []
        for packet in packets:
            if packet.descriptor_set != IMU_SET:
                self.drop("MIP packets that are not IMU data")
            elif (sample := decode_sample(packet)) is None:
                self.drop("IMU packets without both the scaled accelerometer and gyro vectors")
            else:
                samples.append(sample)
        if not samples:
            return
        stamps = self.clock.stamps([s.device_ns for s in samples], host_ns)
        for sample, stamp in zip(samples, stamps, strict=True):
            yield Emit("imu", self._message(sample, stamp), stamp)

    def _message(self, sample: Sample, stamp: int) -> Any:
        accel = device_to_rep103(*(a * STANDARD_GRAVITY_M_S2 for a in sample.accel_g))
        gyro = device_to_rep103(*sample.gyro_rad_s)
        orientation_cov = np.zeros(9)
        orientation_cov[0] = -1.0
        return make(
            "sensor_msgs/msg/Imu",
            header=header(stamp, self.params.frame_id),
            orientation_covariance=orientation_cov,
            angular_velocity=make("geometry_msgs/msg/Vector3", x=gyro[0], y=gyro[1], z=gyro[2]),
            angular_velocity_covariance=self._gyro_cov.copy(),
            linear_acceleration=make("geometry_msgs/msg/Vector3", x=accel[0], y=accel[1], z=accel[2]),
            linear_acceleration_covariance=self._accel_cov.copy(),
        )

    def close(self, outcome: RunOutcome = COMPLETE) -> None:
        """Set a configured device back to idle (best effort: it may be gone), then close the port."""
        if self.configured:
            try:
                self.port.write(encode(BASE_SET, [(CMD_SET_IDLE, b"")]))
            except OSError as exc:
                log.debug("%s: could not set the device to idle: %s", self._who, explain(exc))
            self.configured = False
        try:
            self.port.close()
        except OSError as exc:
            log.debug("%s: closing the port: %s", self._who, explain(exc))
