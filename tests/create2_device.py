"""An iRobot Create 2 behind a pty, for the `create2` driver's tests.

It speaks the Open Interface as the Create 2 OI Specification describes it, independently of the
driver (nothing is imported from it): opcodes are read with their data bytes and recorded; Start
(128) opens the OI, Stream (148) [n][ids] starts a frame every 15 ms of emulated time,
Pause/Resume (150) [0|1] pauses and resumes it, Stop (173) closes the OI. Frames are
[19][n-bytes][id][data]...[checksum], the checksum making the 8-bit sum of the frame zero; the
encoder counts (packets 43, 44: unsigned 16-bit, high byte first, wrapping at 65536) come from a
function of emulated time giving the wheels' angles. Faults on demand: corrupted checksums, frames
cut into parts written apart, noise between frames, silence or a vanished device after K frames.
"""

from __future__ import annotations

import fcntl
import math
import os
import random
import select
import struct
import termios
import threading
import time
import tty
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

COUNTS_PER_REV = 508.8
"""Encoder counts per wheel revolution of a Create 2."""
STREAM_PERIOD_S = 0.015
"""The robot sends a stream frame every 15 ms."""
HEADER = 19
START, SAFE, FULL, STREAM, QUERY_LIST, PAUSE_RESUME, STOP = 128, 131, 132, 148, 149, 150, 173
FIXED_DATA_BYTES = {PAUSE_RESUME: 1, 137: 4, 145: 4, 146: 4}
"""Data bytes of the opcodes with a fixed count that tests may send (others: none, or a list)."""
PACKET_BYTES = {7: 1, 35: 1, 43: 2, 44: 2}
"""The sensor packets this robot can stream, and their data bytes."""
OI_MODES = {"off": 0, "passive": 1, "safe": 2, "full": 3}
IDLE_POLL_S = 0.05
"""How long the device thread waits for a command when it has nothing to send."""
DRAIN_POLL_S = 0.005
DRAIN_SETTLE_S = 0.2
DRAIN_SETTLE_POLLS = 10
DRAIN_LIMIT_S = 3.0
"""Before vanishing, the device waits (at most DRAIN_LIMIT_S) until the slave side has held no
unread byte for DRAIN_SETTLE_S and DRAIN_SETTLE_POLLS looks in a row: the kernel hands written
bytes to the slave side a little later (a worker thread), later still on a loaded machine."""

Wheels = Callable[[float], tuple[float, float]]
"""Emulated time (s since the stream started) -> (left, right) wheel angle (rad, forward positive)."""


def standing(_t: float) -> tuple[float, float]:
    return 0.0, 0.0


def constant(left_rad_s: float, right_rad_s: float) -> Wheels:
    """Wheels turning at constant rates."""
    return lambda t: (left_rad_s * t, right_rad_s * t)


def counts(angle_rad: float, offset: int = 0) -> int:
    """The cumulative count of a wheel at this angle, as the robot reports it (wrapped to 16 bits)."""
    return (round(angle_rad / (2 * math.pi) * COUNTS_PER_REV) + offset) % 65536


def encode_frame(packets: list[tuple[int, int]], corrupt: bool = False) -> bytes:
    """A stream frame carrying (packet id, value) pairs; with `corrupt`, its checksum is off by one."""
    body = bytearray()
    for packet, value in packets:
        size = PACKET_BYTES[packet]
        body.append(packet)
        body += (value % (1 << (8 * size))).to_bytes(size, "big")
    frame = bytes([HEADER, len(body)]) + bytes(body)
    checksum = (-sum(frame) + (1 if corrupt else 0)) & 0xFF
    return frame + bytes([checksum])


@dataclass(frozen=True)
class SentFrame:
    index: int
    time_s: float
    """emulated time of the frame, STREAM_PERIOD_S * index"""
    left: int
    right: int
    corrupted: bool
    data: bytes


class Create2Device:
    """The robot on the far end of a pty; the driver opens `path`. Use as a context manager."""

    def __init__(
        self,
        wheels: Wheels = standing,
        *,
        start_counts: tuple[int, int] = (0, 0),
        speed: float = 1.0,
        corrupt_every: int = 0,
        split_seed: int | None = None,
        garbage: bytes = b"",
        stop_after: int | None = None,
        vanish: bool = False,
    ):
        """`speed`: emulated seconds per host second (frames every 15 ms / speed). `corrupt_every`: every
        Nth frame's checksum is wrong. `split_seed`: each write (noise and frame) is cut at 1-3 random
        places and the parts written spread over the frame period. `garbage`: written before every
        frame. `stop_after`: frames to send before going silent, or with `vanish`, before closing the
        pty's master side as a pulled cable does (once the driver has read what was sent)."""
        self.wheels = wheels
        self.start_counts = start_counts
        self.period_s = STREAM_PERIOD_S / speed
        self.corrupt_every = corrupt_every
        self.garbage = garbage
        self.stop_after = stop_after
        self.vanish = vanish
        self._rng = random.Random(split_seed) if split_seed is not None else None
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.path = os.ttyname(self._slave)
        self.received: list[int] = []
        """every byte the driver wrote, in order"""
        self.commands: list[tuple[int, ...]] = []
        """the commands, each as (opcode, data bytes...)"""
        self.sent: list[SentFrame] = []
        self.garbage_sent = 0
        self.overflowed = 0
        """bytes the pty had no room for (the driver not reading): lost, as on a real line"""
        self.mode = "off"
        self.stream_ids: tuple[int, ...] = ()
        self.streaming = False
        self.vanished = False
        self._changed = threading.Condition()
        self._closing = threading.Event()
        self._thread = threading.Thread(target=self._main, name="create2-device", daemon=True)
        self._thread.start()

    def __enter__(self) -> Create2Device:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def wait_for(self, predicate: Callable[[Create2Device], bool], timeout_s: float = 5.0) -> bool:
        """Wait until `predicate(self)` holds (re-checked on every change); False at the deadline."""
        with self._changed:
            return self._changed.wait_for(lambda: predicate(self), timeout_s)

    def good_frames(self) -> list[SentFrame]:
        with self._changed:
            return [f for f in self.sent if not f.corrupted]

    def close(self) -> None:
        self._closing.set()
        self._thread.join(timeout=5)
        for fd in (self._master, self._slave):
            if fd >= 0:
                os.close(fd)
        self._master = self._slave = -1

    # ------------------------------------------------------------------------- the device thread

    def _main(self) -> None:
        pending = bytearray()
        outbox: deque[tuple[float, bytes]] = deque()
        next_frame = 0.0
        while not self._closing.is_set():
            now = time.monotonic()
            while outbox and outbox[0][0] <= now:
                self._write(outbox.popleft()[1])
            done = self.stop_after is not None and len(self.sent) >= self.stop_after
            if self.streaming and not done and now >= next_frame:
                self._schedule_frame(outbox, next_frame)
                next_frame += self.period_s
            if done and not outbox and self.vanish:
                self._vanish()
                return
            waits = [IDLE_POLL_S]
            if outbox:
                waits.append(outbox[0][0] - now)
            if self.streaming and not done:
                waits.append(next_frame - now)
            ready, _, _ = select.select([self._master], [], [], max(0.0, min(waits)))
            if ready:
                try:
                    data = os.read(self._master, 1024)
                except (BlockingIOError, InterruptedError):
                    continue
                started = self.streaming
                pending += data
                self._commands(pending)
                if self.streaming and not started:
                    next_frame = time.monotonic()

    def _write(self, data: bytes) -> None:
        try:
            written = os.write(self._master, data)
        except BlockingIOError:
            written = 0
        with self._changed:
            self.overflowed += len(data) - written
            self._changed.notify_all()

    def _schedule_frame(self, outbox: deque[tuple[float, bytes]], due: float) -> None:
        index = len(self.sent)
        t = index * STREAM_PERIOD_S
        left_rad, right_rad = self.wheels(t)
        left, right = counts(left_rad, self.start_counts[0]), counts(right_rad, self.start_counts[1])
        values = {43: left, 44: right, 35: OI_MODES[self.mode], 7: 0}
        corrupt = self.corrupt_every > 0 and (index + 1) % self.corrupt_every == 0
        frame = encode_frame([(packet, values[packet]) for packet in self.stream_ids], corrupt)
        data = self.garbage + frame
        parts = [data]
        if self._rng is not None:
            cuts = sorted(self._rng.sample(range(1, len(data)), k=min(len(data) - 1, self._rng.randint(1, 3))))
            parts = [data[a:b] for a, b in zip([0, *cuts], [*cuts, len(data)], strict=True)]
        for i, part in enumerate(parts):
            outbox.append((due + i * self.period_s / len(parts), part))
        with self._changed:
            self.sent.append(SentFrame(index, t, left, right, corrupt, frame))
            self.garbage_sent += len(self.garbage)
            self._changed.notify_all()

    def _commands(self, pending: bytearray) -> None:
        """Take every complete command off `pending` and act on it."""
        while pending:
            opcode = pending[0]
            if opcode in (STREAM, QUERY_LIST):
                if len(pending) < 2 or len(pending) < 2 + pending[1]:
                    return
                size = 1 + pending[1]
            else:
                size = FIXED_DATA_BYTES.get(opcode, 0)
                if len(pending) < 1 + size:
                    return
            command = tuple(pending[: 1 + size])
            del pending[: 1 + size]
            self._act(command)

    def _act(self, command: tuple[int, ...]) -> None:
        opcode, data = command[0], command[1:]
        with self._changed:
            self.received.extend(command)
            self.commands.append(command)
            if opcode == START:
                self.mode = "passive"
            elif self.mode == "off":
                pass  # the OI ignores everything but Start while it is off
            elif opcode == SAFE:
                self.mode = "safe"
            elif opcode == FULL:
                self.mode = "full"
            elif opcode == STREAM:
                self.stream_ids = tuple(p for p in data[1:] if p in PACKET_BYTES)
                self.streaming = bool(self.stream_ids)
            elif opcode == PAUSE_RESUME:
                self.streaming = bool(data[0]) and bool(self.stream_ids)
            elif opcode == STOP:
                self.mode, self.streaming = "off", False
            self._changed.notify_all()

    def _vanish(self) -> None:
        """Close the master side, as a pulled cable: the driver's reads fail from then on. Waits first
        until the driver has read every byte sent (closing drops what is still queued)."""
        now = time.monotonic()
        deadline, empty_since, empty_looks = now + DRAIN_LIMIT_S, now, 0
        while now < deadline and not self._closing.wait(DRAIN_POLL_S):
            now = time.monotonic()
            if _queued(self._slave):
                empty_since, empty_looks = now, 0
            else:
                empty_looks += 1
            if empty_looks >= DRAIN_SETTLE_POLLS and now - empty_since >= DRAIN_SETTLE_S:
                break
        os.close(self._master)
        self._master = -1
        with self._changed:
            self.vanished = True
            self._changed.notify_all()


def _queued(fd: int) -> int:
    """Bytes waiting to be read on a terminal."""
    return struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0]
