"""An emulated LORD MicroStrain 3DM-GX4-45 behind a pseudo-terminal, for the `microstrain_imu` tests.

The driver opens `MipDevice.port` (the pty's slave) as it would /dev/ttyACM0. A thread plays the
device on the master side: it answers MIP commands (ACK, or NACK when told to), answers "get IMU
data base rate" with 500 Hz, and once the IMU stream is enabled and the device resumed it streams
IMU packets (scaled accelerometer, scaled gyro, GPS correlation timestamp) at 500/decimation Hz of
device time, `speed` times faster on the host's clock, with values from a function of device time.

The MIP encoding here is written from the protocol manual on its own (it does not use the driver's
`mip` module), so the two check each other.
"""

from __future__ import annotations

import os
import select
import struct
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass

BASE_RATE_HZ = 500
"""the IMU base rate of the 3DM-GX4-45"""
WEEK_S = 604800.0
START_TOW_S = 345_600.25
"""GPS time of week of the first sample (a Thursday)"""
START_WEEK = 2290

Vector = tuple[float, float, float]
Values = Callable[[float], tuple[Vector, Vector]]
"""device time since the stream started (s) -> (accel in g, gyro in rad/s), device frame"""


def fletcher(data: bytes) -> bytes:
    """MIP checksum: two running byte sums mod 256, the first sent first."""
    a = b = 0
    for byte in data:
        a = (a + byte) % 256
        b = (b + a) % 256
    return bytes([a, b])


def packet(descriptor_set: int, fields: list[tuple[int, bytes]]) -> bytes:
    """A MIP packet: 0x75 0x65, set, payload length, [length, descriptor, data] fields, checksum."""
    payload = b"".join(bytes([2 + len(data), desc]) + data for desc, data in fields)
    head = bytes([0x75, 0x65, descriptor_set, len(payload)]) + payload
    return head + fletcher(head)


def still(_t: float) -> tuple[Vector, Vector]:
    """A device at rest, z down: the accelerometer reads -1 g on z."""
    return (0.0, 0.0, -1.0), (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Sent:
    """One IMU packet the device sent: its GPS time and values (device frame), and whether corrupted."""

    tow_s: float
    week: int
    accel_g: Vector
    gyro_rad_s: Vector
    corrupted: bool


@dataclass(frozen=True)
class Command:
    """One command field the device received."""

    descriptor_set: int
    descriptor: int
    data: bytes


class MipDevice:
    """The emulated device; use as a context manager (the thread stops and the pty closes on exit).

    Options: `values` (samples as a function of device time); `speed` (host-time pacing factor);
    `burst` (packets written together, when the last is due); `corrupt_every` (the checksum of every
    Nth IMU packet is wrong); `split` (each write, a packet or a burst, in two parts cut at a varying
    byte, with a pause between); `garbage` (bytes written before every IMU packet); `stop_after`
    (IMU packets sent before the stream stops); `vanish` (close the pty once stopped and drained, as
    an unplugged device); `nack` ({(set, descriptor): error code} to refuse); `mute` (commands never
    answered); `streaming` (the device streams from the start, as its saved settings may say, at
    `decimation`)."""

    def __init__(
        self,
        values: Values = still,
        *,
        speed: float = 1.0,
        burst: int = 1,
        corrupt_every: int = 0,
        split: bool = False,
        garbage: bytes = b"",
        stop_after: int | None = None,
        vanish: bool = False,
        nack: dict[tuple[int, int], int] | None = None,
        mute: frozenset[tuple[int, int]] = frozenset(),
        streaming: bool = False,
        decimation: int = 5,
    ):
        self.values = values
        self.speed = speed
        self.burst = burst
        self.corrupt_every = corrupt_every
        self.split = split
        self.garbage = garbage
        self.stop_after = stop_after
        self.vanish_when_stopped = vanish
        self.nack = nack or {}
        self.mute = mute
        self.decimation = decimation
        self.stream_enabled = streaming
        self.resumed = streaming
        self.received: list[Command] = []
        self.bytes_received = 0
        self.sent: list[Sent] = []
        self.vanished = False
        self.changed = threading.Condition()
        self._inbox = bytearray()
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no line editing: the driver's bytes must not come back
        os.set_blocking(self._master, False)
        self.port = os.ttyname(self._slave)
        self._wake_r, self._wake_w = os.pipe()
        self._closing = False
        self._stream_start: float | None = None
        """host monotonic time of the first sample of the current stream"""
        self._next = 0
        """index of the next sample of the current stream"""
        self._thread = threading.Thread(target=self._serve, name="mip-device", daemon=True)
        self._thread.start()

    @property
    def rate_hz(self) -> float:
        return BASE_RATE_HZ / self.decimation

    def __enter__(self) -> MipDevice:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._closing = True
        os.write(self._wake_w, b"x")
        self._thread.join(timeout=5)
        for fd in (self._wake_r, self._wake_w, self._slave):
            os.close(fd)
        if not self.vanished:
            os.close(self._master)

    def wait_for(self, predicate: Callable[[], bool], timeout_s: float = 10.0) -> bool:
        """Wait until `predicate()` holds (checked whenever the device's state changes), at most `timeout_s`."""
        with self.changed:
            return self.changed.wait_for(predicate, timeout_s)

    def _unplug(self) -> None:
        """Vanish: close the master side, so the driver's reads fail (only from the device's thread,
        which is the one using the master)."""
        with self.changed:
            if not self.vanished:
                self.vanished = True
                os.close(self._master)
                self.changed.notify_all()

    # -- the device's thread

    def _serve(self) -> None:
        while not self._closing and not self.vanished:
            timeout = self._until_due()
            try:
                ready, _, _ = select.select([self._master, self._wake_r], [], [], timeout)
            except (OSError, ValueError):
                return
            if self._master in ready:
                try:
                    data = os.read(self._master, 4096)
                except BlockingIOError:
                    data = b""
                except OSError:
                    return
                self._on_bytes(data)
            self._stream_due()

    def _until_due(self) -> float | None:
        """Seconds until the next burst is due, or None when not streaming."""
        if not self._streaming():
            return None
        if self._stream_start is None:
            return 0.0
        return max(0.0, self._due(self._next + self.burst - 1) - time.monotonic())

    def _due(self, k: int) -> float:
        """When sample `k` of the stream is due, on the host's monotonic clock."""
        assert self._stream_start is not None
        return self._stream_start + k / self.rate_hz / self.speed

    def _streaming(self) -> bool:
        stopped = self.stop_after is not None and len(self.sent) >= self.stop_after
        return self.stream_enabled and self.resumed and not stopped

    def _on_bytes(self, data: bytes) -> None:
        with self.changed:
            self.bytes_received += len(data)
            self.changed.notify_all()
        self._inbox += data
        while True:
            start = self._inbox.find(b"\x75\x65")
            if start < 0:
                del self._inbox[: max(0, len(self._inbox) - 1)]
                return
            del self._inbox[:start]
            if len(self._inbox) < 4 or len(self._inbox) < 6 + self._inbox[3]:
                return
            end = 6 + self._inbox[3]
            raw = bytes(self._inbox[:end])
            if fletcher(raw[:-2]) != raw[-2:]:
                del self._inbox[:1]
                continue
            del self._inbox[:end]
            self._on_packet(raw[2], raw[4:-2])

    def _on_packet(self, descriptor_set: int, payload: bytes) -> None:
        replies: list[tuple[int, bytes]] = []
        pos = 0
        while pos + 2 <= len(payload):
            length, desc = payload[pos], payload[pos + 1]
            data = payload[pos + 2 : pos + length]
            pos += max(length, 2)
            with self.changed:
                self.received.append(Command(descriptor_set, desc, data))
                self.changed.notify_all()
            if (descriptor_set, desc) in self.mute:
                continue
            error = self.nack.get((descriptor_set, desc), 0)
            replies.append((0xF1, bytes([desc, error])))
            if not error:
                replies += self._obey(descriptor_set, desc, data)
        if replies:
            self._write(packet(descriptor_set, replies))

    def _obey(self, descriptor_set: int, desc: int, data: bytes) -> list[tuple[int, bytes]]:
        """Carry out an accepted command; its reply fields beyond the ACK."""
        if (descriptor_set, desc) == (0x01, 0x02):  # set to idle
            self.resumed = False
            self._stream_start = None
        elif (descriptor_set, desc) == (0x01, 0x06):  # resume
            self.resumed = True
        elif (descriptor_set, desc) == (0x0C, 0x06):  # get IMU data base rate
            return [(0x83, struct.pack(">H", BASE_RATE_HZ))]
        elif (descriptor_set, desc) == (0x0C, 0x08) and data[:1] == b"\x01":  # IMU message format, use new
            entries = [struct.unpack_from(">BH", data, 2 + 3 * i) for i in range(data[1])]
            self.decimation = entries[0][1]
        elif (descriptor_set, desc) == (0x0C, 0x11) and data[:2] == b"\x01\x01":  # IMU stream on/off
            self.stream_enabled = data[2] == 1
        return []

    def _stream_due(self) -> None:
        if not self._streaming():
            return
        now = time.monotonic()
        if self._stream_start is None:
            self._stream_start, self._next = now, 0
        while (
            self._streaming() and self._stream_start + (self._next + self.burst - 1) / self.rate_hz / self.speed <= now
        ):
            count = self.burst
            if self.stop_after is not None:
                count = min(count, self.stop_after - len(self.sent))
            self._write(b"".join(self._sample(self._next + i) for i in range(count)))
            self._next += count
        if self.stop_after is not None and len(self.sent) >= self.stop_after and self.vanish_when_stopped:
            self._drained()
            self._unplug()

    def _sample(self, k: int) -> bytes:
        t = k / self.rate_hz
        accel, gyro = self.values(t)
        tow = START_TOW_S + t
        fields = [
            (0x04, struct.pack(">3f", *accel)),
            (0x05, struct.pack(">3f", *gyro)),
            (0x12, struct.pack(">dHH", tow, START_WEEK, 0x0007)),
        ]
        raw = packet(0x80, fields)
        corrupted = bool(self.corrupt_every) and (len(self.sent) + 1) % self.corrupt_every == 0
        if corrupted:
            raw = raw[:-1] + bytes([raw[-1] ^ 0x5A])
        as_sent = struct.unpack(">3f", struct.pack(">3f", *accel)), struct.unpack(">3f", struct.pack(">3f", *gyro))
        with self.changed:
            self.sent.append(Sent(tow, START_WEEK, as_sent[0], as_sent[1], corrupted))
            self.changed.notify_all()
        return self.garbage + raw

    def _write(self, data: bytes) -> None:
        """Write all of `data` (in two parts with a pause when splitting), unless closing."""
        if self.split and len(data) > 1:
            cut = 1 + len(self.sent) % (len(data) - 1)
            parts = [data[:cut], data[cut:]]
        else:
            parts = [data]
        for i, part in enumerate(parts):
            if i:
                time.sleep(0.002)  # pacing: lets the driver read the first part on its own
            view = memoryview(part)
            while view and not self._closing and not self.vanished:
                try:
                    n = os.write(self._master, view)
                    view = view[n:]
                except BlockingIOError:
                    select.select([], [self._master], [], 0.05)
                except OSError:
                    return

    def _drained(self, timeout_s: float = 5.0) -> None:
        """Wait until the driver has read everything written: a vanishing pty discards unread input.

        Polling the slave makes the kernel hand what the pty still buffers to the line discipline
        first (n_tty_poll flushes the pending input), so "not readable" means "all read"."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not self._closing:
            readable, _, _ = select.select([self._slave], [], [], 0)
            if not readable:
                return
            time.sleep(0.001)
