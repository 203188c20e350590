"""`rover info`: what a dataset holds, like `ros2 bag info`; or what a CSI capture of another tool
holds (Atheros, Nexmon, PicoScenes, a WiROS bag)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

MCAP_MAGIC = b"\x89MCAP"


def add_parser(sub: Any, common: argparse.ArgumentParser) -> None:
    """`rover info` and its options."""
    p = sub.add_parser("info", parents=[common], help="what a dataset or a CSI capture holds, like `ros2 bag info`")
    p.add_argument("path")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.add_argument(
        "--format",
        choices=("atheros", "nexmon", "picoscenes", "wiros"),
        help="a CSI capture's format (default: found from its contents)",
    )
    p.add_argument("--chip", help="a Nexmon capture's chip: 4339, 43455c0, 4358 or 4366c0 (the capture does not say)")
    p.add_argument("--topic", help="a WiROS bag's rf_msgs/msg/Wifi topic (default: its one, or /csi)")
    p.set_defaults(func=run)


def _is_capture(path: Path, fmt: str | None) -> bool:
    """Whether to read the path as a CSI capture: asked to, a ROS bag of WiROS's CSI, or a file
    neither named nor made as an MCAP dataset."""
    from rover.formats.csi_sources import wiros

    if fmt is not None or wiros.holds_wifi(path):
        return True
    if path.suffix == ".mcap":
        return False
    try:
        with path.open("rb") as f:
            return f.read(len(MCAP_MAGIC)) != MCAP_MAGIC
    except OSError:
        return False  # a folder, or missing: the dataset reader says which


def run(args: argparse.Namespace) -> int:
    import json

    if _is_capture(Path(args.path), args.format):
        from rover.datasets.capture_info import capture_info
        from rover.datasets.capture_info import render as render_capture

        capture = capture_info(args.path, args.format, args.chip, args.topic)
        sys.stdout.write(json.dumps(capture.as_json(), indent=2) + "\n" if args.json else render_capture(capture))
        return 0
    from rover.datasets.info import dataset_info, render

    info = dataset_info(args.path)
    sys.stdout.write(json.dumps(info.as_json(), indent=2) + "\n" if args.json else render(info))
    return 0
