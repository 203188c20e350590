"""`rover calibrate`: per-chain phase offsets from CSI at a known angle, as a setup.yaml block."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rover.cli.args import degrees
from rover.errors import BadInput, SpecError

if TYPE_CHECKING:
    from rover.formats.rig import Rig
    from rover.operators.aoa.calibration import Calibration


def add_parser(sub: Any, common: argparse.ArgumentParser) -> None:
    """`rover calibrate` and its options."""
    p = sub.add_parser(
        "calibrate", parents=[common], help="per-chain phase offsets from CSI at a known angle, as a setup.yaml block"
    )
    p.add_argument(
        "sources", nargs="+", metavar="INPUT", help="CSI Tool logs (.dat) or datasets with ground truth (.mcap)"
    )
    p.add_argument("--setup", help="rig file with the antenna positions (default for a dataset: its own)")
    p.add_argument(
        "--angle-deg", type=degrees, action="append", help="a log's transmitter angle, robot frame (once, or per log)"
    )
    p.add_argument("--channel", type=int, action="append", help="the channel a log was recorded on (once, or per log)")
    p.add_argument("--out", help="also write the receiver.phase_offsets_rad block to this YAML file")
    p.add_argument("--force", action="store_true", help="replace an existing --out file")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Per-chain phase offsets from CSI logs at a known angle or datasets with ground truth."""
    import shlex

    from rover.formats.atomic_file import write_aside
    from rover.formats.bag import MAGIC, check_output
    from rover.operators.aoa.calibration import render, setup_block

    out = check_output(args.out, force=args.force) if args.out else None  # before any work
    kinds = []
    for source in map(Path, args.sources):
        if not source.is_file():
            raise BadInput(f"{source}: {'is a directory' if source.is_dir() else 'no such file'}")
        if out is not None and source.resolve() == out.resolve():
            raise BadInput(f"{out}: is also an input; writing the calibration onto it would destroy it")
        with source.open("rb") as f:
            kinds.append("dataset" if f.read(len(MAGIC)) == MAGIC else "log")
    logs = [s for s, kind in zip(args.sources, kinds, strict=True) if kind == "log"]
    datasets = [s for s, kind in zip(args.sources, kinds, strict=True) if kind == "dataset"]
    angles = _per_log(args.angle_deg, logs, "--angle-deg", datasets)
    channels = _per_log(args.channel, logs, "--channel", datasets)
    rig = None
    if args.setup:
        from rover.formats.rig import load_rig

        rig = load_rig(args.setup)
    rows, k = [], 0
    for source, kind in zip(args.sources, kinds, strict=True):
        if kind == "dataset":
            rows += _calibrate_dataset(Path(source), rig)
        else:
            rows.append(
                _calibrate_log(Path(source), rig, angles[k] if angles else None, channels[k] if channels else None)
            )
            k += 1
    sys.stdout.write(render(rows))
    block = setup_block([c for _, c in rows])
    print()
    sys.stdout.write(block)
    if out is not None:
        write_aside(
            out, lambda partial: partial.write_text(f"# {shlex.join(['rover', 'calibrate', *args.sources])}\n{block}")
        )
        print(f"wrote {out}")
    return 0


def _per_log(values: list[Any] | None, logs: list[str], option: str, datasets: list[str]) -> list[Any]:
    """One value of an option per CSI log: given once for all of them, or once per log in order."""
    if not values:
        return []
    if not logs:
        raise BadInput(
            f"{option} is for CSI logs, and {', '.join(datasets)} is a dataset (MCAP): its angles and channels "
            "come from its frames and ground truth"
        )
    if len(values) not in (1, len(logs)):
        raise BadInput(f"{option} given {len(values)} times for {len(logs)} CSI logs: give it once, or once per log")
    return list(values) * len(logs) if len(values) == 1 else list(values)


def _calibrate_log(
    path: Path, rig: Rig | None, angle_deg: float | None, channel: int | None
) -> tuple[str, Calibration]:
    """One CSI Tool log of a transmitter at a known angle."""
    from rover.formats.intel5300 import read_dat
    from rover.operators.aoa.calibration import estimate_offsets

    if rig is None:
        raise BadInput(f"{path}: a CSI log needs --setup RIG.yaml (the antenna positions)")
    if angle_deg is None:
        raise BadInput(f"{path}: a CSI log needs --angle-deg A, the transmitter's angle in the robot frame")
    channel = channel if channel is not None else rig.receiver_channel
    if channel is None:
        raise BadInput(f"{path}: give --channel N, the channel the log was recorded on (or receiver.channel)")
    try:
        records = read_dat(path)
    except OSError as exc:
        raise BadInput(f"{path}: cannot read: {exc.strerror or exc}") from None
    m = len(rig.antenna_positions_m)
    usable = records.nrx == m
    if not usable.any():
        raise BadInput(f"{path}: no beamforming record with {m} receive chains ({len(records)} records)")
    try:
        calibration = estimate_offsets(
            records.csi[usable, :, :m, 0], rig.antenna_positions_m, channel, math.radians(angle_deg)
        )
    except BadInput as exc:
        raise BadInput(f"{path}: {exc}") from None
    return path.name, calibration


def _calibrate_dataset(path: Path, rig: Rig | None) -> list[tuple[str, Calibration]]:
    """A dataset's /csi frames with the true angle of each (/groundtruth/aoa, matched by stamp), per channel."""
    from rover.datasets.aoa_truth import read_aoa_truth
    from rover.formats.rig import rig_from_text
    from rover.operators.aoa.calibration import offsets_from_truth

    found = read_aoa_truth(path)
    if rig is None:
        if found.setup_yaml is None:
            raise BadInput(f"{path}: no rig description (rover.setup metadata): pass --setup RIG.yaml")
        try:
            rig = rig_from_text(found.setup_yaml, f"{path} (rover.setup)")
        except SpecError as exc:
            raise BadInput(str(exc.diagnostics[0])) from None
    try:
        calibrations = offsets_from_truth(
            found.stamps_ns, found.channels, found.bfee, found.angles, rig.antenna_positions_m
        )
    except BadInput as exc:
        raise BadInput(f"{path}: {exc}") from None
    return [(path.name, c) for c in calibrations]
