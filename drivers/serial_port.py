"""Opening the serial port of a device driver (pyserial), with one clear line when it cannot be."""

from __future__ import annotations

import termios
from typing import Protocol

import serial  # type: ignore[import-untyped]

from rover.errors import BadInput

POLL_S = 0.05
"""How long a read waits for a first byte: the longest a driver leaves `stop` unnoticed."""
WRITE_TIMEOUT_S = 0.5
"""A write that cannot finish this fast means the device is gone (a pulled USB cable)."""


class SerialPort(Protocol):
    """What the drivers use of a pyserial `Serial` (tests may pass another)."""

    @property
    def in_waiting(self) -> int: ...

    def read(self, size: int = 1) -> bytes: ...

    def write(self, data: bytes) -> int | None: ...

    def flush(self) -> None: ...

    def reset_input_buffer(self) -> None: ...

    def close(self) -> None: ...


def explain(exc: BaseException) -> str:
    """The operating system's words for why a port could not be opened or used: pyserial wraps
    the OSError it got (strerror "could not open port ...: [Errno 2] ...") around the cause."""
    cause: BaseException | None = exc
    while cause is not None:
        if isinstance(cause, OSError) and not isinstance(cause, serial.SerialException) and cause.strerror:
            return str(cause.strerror)
        if isinstance(cause, termios.error) and len(cause.args) == 2:
            return f"not a serial port ({cause.args[1]})"
        cause = cause.__cause__ or cause.__context__
    return str(exc)


def open_serial(driver: str, port: str, baud: int) -> SerialPort:
    """`port` at `baud`, 8N1, reads timing out after POLL_S, locked against a second user;
    BadInput naming the driver, the port and the reason when it cannot be opened."""
    try:
        opened: SerialPort = serial.Serial(port, baud, timeout=POLL_S, write_timeout=WRITE_TIMEOUT_S, exclusive=True)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise BadInput(f"{driver}: cannot open serial port {port}: {explain(exc)}") from None
    return opened
