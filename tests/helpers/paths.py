"""Where the tests, the repository and the reference data are; a free loopback port."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parents[1]
ROOT = TESTS.parent


def reference_data() -> Path:
    """The real captures in ../shared/data (or ROVER_TEST_DATA); tests that need them skip without them."""
    path = Path(os.environ.get("ROVER_TEST_DATA", ROOT.parent / "shared" / "data"))
    if not path.is_dir():
        pytest.skip(
            f"reference data not found at {path}: it is the shared/data folder beside this repository "
            "(set ROVER_TEST_DATA to point at it)"
        )
    return path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
