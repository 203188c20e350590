"""`rover aoa`: angles of arrival from a bare CSI Tool log or another tool's capture, every candidate per burst."""

from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path
from typing import Any

from rover.cli.args import burst
from rover.errors import BadInput


def add_parser(sub: Any, common: argparse.ArgumentParser) -> None:
    """`rover aoa` and its options."""
    p = sub.add_parser(
        "aoa",
        parents=[common],
        help="angles of arrival from a bare CSI Tool log or capture (no robot): every candidate per burst",
    )
    p.add_argument(
        "log",
        metavar="LOG.dat",
        help="a CSI Tool log (log_to_file output), an Atheros, Nexmon or PicoScenes capture, or a WiROS bag",
    )
    p.add_argument("--setup", required=True, help="rig file: the receiver's antennas (and channel, calibration)")
    p.add_argument("--calibration", help="a `rover calibrate --out` file: its phase offsets replace the setup's")
    p.add_argument("--channel", type=int, help="the channel the log was recorded on (default: receiver.channel)")
    p.add_argument("--burst", type=burst, default=50, help="packets per burst (default 50, at least 3)")
    p.add_argument(
        "--format",
        choices=("atheros", "nexmon", "picoscenes", "wiros"),
        help="a capture's format (default: from its contents)",
    )
    p.add_argument("--chip", help="a Nexmon capture's chip: 4339, 43455c0, 4358 or 4366c0")
    p.add_argument("--topic", help="a WiROS bag's rf_msgs/msg/Wifi topic (default: its one, or /csi)")
    p.add_argument("--compensation", help="WiROS's static calibration: an RX_ID-CHAN.npy file, or a folder of them")
    p.add_argument("--csv", help="also write the rows to this CSV file")
    p.add_argument("--force", action="store_true", help="replace an existing --csv file")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Angles of arrival from a bare CSI Tool log or capture: one row per burst, every candidate with its power."""
    from rover.formats.bag import check_output
    from rover.formats.rig import load_rig
    from rover.formats.text import read_text
    from rover.formats.wifi import channel_freq_hz
    from rover.operators.aoa.bare_log import with_calibration

    out = check_output(args.csv, force=args.force) if args.csv else None  # before any work
    rig = load_rig(args.setup)
    if args.calibration:
        rig = with_calibration(rig, read_text(Path(args.calibration)), args.calibration)
    channel = args.channel if args.channel is not None else rig.receiver_channel
    if channel is not None:
        try:
            channel_freq_hz(channel)
        except ValueError:
            raise BadInput(f"--channel: {channel} is not a WiFi channel number") from None
    source = Path(args.log)
    if not source.exists():
        raise BadInput(f"{source}: no such file or folder")
    fmt = args.format or _capture_format(source)
    if fmt is not None:
        bursts, summary = _capture_bursts(source, fmt, args, rig, channel)
    elif source.is_dir():
        raise BadInput(f"{source}: is a folder, and no ROS 2 bag of WiROS's rf_msgs/msg/Wifi")
    else:
        bursts, summary = _log_bursts(source, args, rig, channel)
    _report(bursts, summary, out)
    return 0


def _capture_format(source: Path) -> str | None:
    """The capture format of the file, or None for anything else (a CSI Tool log, then)."""
    from rover.formats.csi_sources import detect_format

    try:
        return detect_format(source)
    except BadInput:
        return None


def _capture_bursts(source: Path, fmt: str, args: argparse.Namespace, rig: Any, channel: int | None):
    """The bursts of another tool's capture, and the line that describes them."""
    from rover.formats.csi_sources import read_capture
    from rover.operators.aoa.capture import capture_bursts, capture_channel

    frames = read_capture(source, fmt, args.chip, topic=args.topic, compensation=args.compensation)
    for why, n in frames.dropped.items():
        logging.getLogger("rover.aoa").warning("%s: %d %s (left out)", source, n, why)
    try:
        channel, centre_hz = capture_channel(frames, channel)
        bursts = capture_bursts(frames, rig, channel, centre_hz, args.burst)
    except BadInput as exc:
        raise BadInput(f"{source}: {exc}") from None
    summary = (
        f"{source.name}: {frames.source}, {len(frames)} packets, {len(bursts)} bursts of {args.burst} packets, "
        f"channel {channel}"
    )
    return bursts, summary


def _log_bursts(source: Path, args: argparse.Namespace, rig: Any, channel: int | None):
    """The bursts of a CSI Tool log, and the line that describes them."""
    from rover.formats.intel5300 import decode_bfee, split_records
    from rover.operators.aoa.bare_log import log_bursts

    if channel is None:
        raise BadInput(f"{args.setup}: give --channel N, the channel the log was recorded on (or receiver.channel)")
    try:
        raw, counts = split_records(source.read_bytes())
    except OSError as exc:
        raise BadInput(f"{source}: cannot read: {exc.strerror or exc}") from None
    records = decode_bfee(raw)
    if counts.n_corrupt or counts.n_garbage_bytes:
        logging.getLogger("rover.aoa").warning(
            "%s: %d record(s) cut short or corrupt and %d byte(s) of garbage skipped "
            "(a log cut while being written ends with a cut record)",
            source,
            counts.n_corrupt,
            counts.n_garbage_bytes,
        )
    try:
        bursts = log_bursts(records, rig, channel, args.burst)
    except BadInput as exc:
        raise BadInput(f"{source}: {exc}") from None
    return (
        bursts,
        f"{source.name}: {len(records.nrx)} records, {len(bursts)} bursts of {args.burst} packets, channel {channel}",
    )


def _report(bursts: list[Any], summary: str, out: Path | None) -> None:
    """Print the bursts, one row each, and write them to `out` as CSV when given."""
    from rover.formats.atomic_file import write_aside

    lines = ["time_s,packets,angle_deg,std_deg,quality,candidates_deg,candidate_powers"]
    print(summary)
    print(f"{'time s':>8} {'packets':>7} {'angle deg':>9} {'std deg':>7}  candidates deg (power)")
    for b in bursts:
        t = (b.header.stamp.sec * 1_000_000_000 + b.header.stamp.nanosec) / 1e9
        angles = [math.degrees(a) for a in b.candidate_angles_rad]
        powers = list(b.candidate_powers)
        shown = "  ".join(f"{a:6.1f} ({p:.2f})" for a, p in zip(angles, powers, strict=True))
        print(f"{t:8.3f} {b.packets:7d} {math.degrees(b.angle_rad):9.1f} {math.degrees(b.std_rad):7.1f}  {shown}")
        lines.append(
            f"{t:.6f},{b.packets},{math.degrees(b.angle_rad):.2f},{math.degrees(b.std_rad):.2f},{b.quality},"
            f"{';'.join(f'{a:.2f}' for a in angles)},{';'.join(f'{p:.3f}' for p in powers)}"
        )
    if out is not None:
        write_aside(out, lambda partial: partial.write_text("\n".join(lines) + "\n"))
        print(f"wrote {out}")
