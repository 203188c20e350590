"""Which tool wrote a CSI capture, from its first bytes; and reading it as `CsiFrames`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rover.errors import BadInput
from rover.formats.csi_sources import atheros, nexmon, picoscenes, wiros
from rover.formats.csi_sources.frames import CsiFrames

FORMATS = ("atheros", "nexmon", "picoscenes", "wiros")
HEAD_BYTES = 256
"""bytes read to tell the format (a pcap's first Nexmon frame header is within 84)"""
LOOKS = {"atheros": atheros.looks_like, "nexmon": nexmon.looks_like, "picoscenes": picoscenes.looks_like}


def detect_format(path: Path) -> str:
    """The format of the file (or ROS 2 bag folder), from its contents; BadInput naming what was
    tried when none fits."""
    if wiros.holds_wifi(path):
        return "wiros"
    try:
        with path.open("rb") as f:
            head = f.read(HEAD_BYTES)
    except OSError as exc:
        raise BadInput(f"{path}: cannot read: {exc.strerror or exc}") from None
    found = [name for name, looks in LOOKS.items() if looks(head)]
    if not found:
        raise BadInput(
            f"{path}: neither an MCAP dataset nor a CSI capture Rover reads (tried: Atheros CSI Tool log, "
            f"Nexmon pcap, PicoScenes .csi, a ROS bag of WiROS's {wiros.WIFI_TYPE}; the Intel 5300's CSI Tool logs "
            "go to `rover aoa` and `rover calibrate`)"
        )
    return found[0]


def read_capture(
    path: str | Path,
    fmt: str | None = None,
    chip: str | None = None,
    *,
    topic: str | None = None,
    compensation: str | Path | None = None,
) -> CsiFrames:
    """The capture's CSI: its format from its contents unless `fmt` says (a Nexmon capture needs
    its `chip`; a WiROS bag may name its `topic` and `compensation`)."""
    path = Path(path)
    if fmt is not None and fmt not in FORMATS:
        raise BadInput(f"--format {fmt}: not one of {', '.join(FORMATS)}")
    fmt = fmt or detect_format(path)
    try:
        if fmt == "nexmon":
            frames = nexmon.read(path, chip or "")
        elif fmt == "wiros":
            frames = wiros.read(path, topic, compensation)
        else:
            frames = atheros.read(path) if fmt == "atheros" else picoscenes.read(path)
    except OSError as exc:
        raise BadInput(f"{path}: cannot read: {exc.strerror or exc}") from None
    if len(frames) == 0:
        why = "; ".join(f"{n:,} {reason}" for reason, n in frames.dropped.items()) or "it holds none"
        raise BadInput(f"{path}: no packet Rover can use ({why})")
    freq = frames.centre_freq_hz
    same = np.flatnonzero((freq == freq[0]) | (np.isnan(freq) & np.isnan(freq[0])))
    return frames.take(same, "packets on another channel than the first's (a capture is read one channel at a time)")
