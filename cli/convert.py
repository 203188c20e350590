"""`rover convert`: ROS 1 / ROS 2 bags or a recording folder to a dataset."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from rover.cli.args import seconds
from rover.errors import BadInput


def add_parser(sub: Any, common: argparse.ArgumentParser) -> None:
    """`rover convert` and its options."""
    p = sub.add_parser("convert", parents=[common], help="ROS 1/ROS 2 bags or a recording folder to a dataset")
    p.add_argument(
        "sources",
        nargs="+",
        metavar="SRC",
        help=".bag, ROS 2 bag folder, .db3, .mcap, recording folder (CSI Tool or WiROS CSI)",
    )
    p.add_argument("-o", "--output", required=True, help="the dataset to write (.mcap)")
    p.add_argument("--setup", help="setup.yaml (default: the recording folder's)")
    p.add_argument("--topic", action="append", metavar="ROLE=/NAME", help="source topic of csi, imu or odom")
    p.add_argument("--start", type=seconds, help="seconds from the start (or absolute seconds)")
    p.add_argument("--end", type=seconds, help="seconds from the start (or absolute seconds)")
    p.add_argument("--truth", help="ground-truth trajectory: a TUM file, or a dataset with /groundtruth/pose")
    p.add_argument("--tags", help="ground-truth tags (CSV: id,channel,x,y,z,nlos)")
    p.add_argument(
        "--compensation", help="WiROS's static calibration for its CSI: an RX_ID-CHAN.npy file, or a folder of them"
    )
    p.add_argument("--force", action="store_true", help="replace an existing output")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import shlex

    from rover.datasets.convert import convert, terminal_progress

    roles = {}
    for item in args.topic or []:
        role, sep, name = item.partition("=")
        if not sep or role not in ("csi", "imu", "odom"):
            raise BadInput(f"--topic {item!r}: expected ROLE=/name with ROLE one of csi, imu, odom")
        roles[role] = name
    progress, done = terminal_progress()
    try:
        report = convert(
            args.sources,
            args.output,
            setup=args.setup,
            topics=roles,
            start=args.start,
            end=args.end,
            truth=args.truth,
            tags=args.tags,
            force=args.force,
            command_line=shlex.join(["rover", *sys.argv[1:]]),
            progress=progress,
            compensation=args.compensation,
        )
    finally:
        done()
    for line in report.lines():
        print(line)
    print(f"wrote {report.output}")
    return 0
