"""A serial port that plays back chunks, for driver tests that need exact reads rather than a pty."""

from __future__ import annotations

import serial  # type: ignore[import-untyped]


class ScriptedPort:
    """Returns the given chunks, one a read (an empty one is a read that timed out), then fails as
    an unplugged USB adapter does; writes are recorded while it is still plugged in."""

    def __init__(self, chunks: list[bytes]):
        self.chunks = list(chunks)
        self.written = bytearray()
        self.closed = False

    @property
    def in_waiting(self) -> int:
        return len(self.chunks[0]) if self.chunks else 0

    def read(self, size: int = 1) -> bytes:
        if not self.chunks:
            raise serial.SerialException("read failed: [Errno 5] Input/output error")
        return self.chunks.pop(0)

    def write(self, data: bytes) -> int:
        if self.closed or not self.chunks:
            raise OSError(5, "Input/output error")
        self.written += data
        return len(data)

    def flush(self) -> None:
        pass

    def reset_input_buffer(self) -> None:
        pass

    def close(self) -> None:
        self.closed = True
