"""`rover info`: what a dataset holds, like `ros2 bag info`."""

from __future__ import annotations

import argparse
import sys
from typing import Any


def add_parser(sub: Any, common: argparse.ArgumentParser) -> None:
    """`rover info` and its options."""
    p = sub.add_parser("info", parents=[common], help="what a dataset holds, like `ros2 bag info`")
    p.add_argument("path")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import json

    from rover.datasets.info import dataset_info, render

    info = dataset_info(args.path)
    sys.stdout.write(json.dumps(info.as_json(), indent=2) + "\n" if args.json else render(info))
    return 0
