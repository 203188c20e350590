"""What several commands share: exit statuses, the default pipeline, `--set` and the argument types."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from importlib import resources
from pathlib import Path
from typing import Any

from rover.errors import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_PARTIAL, BadInput
from rover.pipeline.yamlpos import parse_scalar

__all__ = ["EXIT_BAD_INPUT", "EXIT_FAILED", "EXIT_PARTIAL"]  # re-exported for the commands


def default_pipeline() -> Path:
    """The pipeline shipped inside the package (identical to the repository's pipeline.yaml)."""
    return Path(str(resources.files("rover").joinpath("pipeline.yaml")))


PIPELINE_FLAGS = ("dataset", "output", "speed", "timing_topic")
"""options that stand for a pipeline variable (`--output DIR` is `--set output=DIR`)"""


def overrides(args: argparse.Namespace, flags: tuple[str, ...] = PIPELINE_FLAGS) -> dict[str, Any]:
    """The pipeline's `${var}` and `OPERATOR.PARAM` values given by `--set` and by the options `flags`
    that stand for one (a command whose option of that name means something else leaves it out)."""
    values: dict[str, Any] = {}
    for item in args.set or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise BadInput(f"--set {item!r}: expected NAME=VALUE")
        values[key.strip()] = parse_scalar(value, f"--set {key.strip()}")
    for flag in flags:
        if getattr(args, flag, None) is not None:
            value = getattr(args, flag)
            values[flag] = parse_scalar(value, f"--{flag}") if flag == "speed" else value
    return values


def add_set(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--set",
        action="append",
        metavar="NAME=VALUE",
        help="set a ${NAME} variable of the pipeline, or OPERATOR.PARAM (e.g. slam.wheel=false) "
        "typed and checked like the file's own params",
    )


def _number(text: str, ok: Callable[[float], bool], wanted: str) -> float:
    """An argument that is a number `ok` accepts; argparse's error naming `wanted` otherwise."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not ok(value):
        raise argparse.ArgumentTypeError(f"{wanted}, got {text!r}")
    return value


def degrees(text: str) -> float:
    """--angle-deg: a finite number of degrees."""
    return _number(text, math.isfinite, "a number of degrees")


def seconds(text: str) -> float:
    """--start/--end: a number of seconds from 0 to 2**31 (a ROS 2 stamp's range)."""
    return _number(text, lambda v: 0 <= v < 2**31, "seconds from 0 to 2**31")


def burst(text: str) -> int:
    """--burst: a whole number of packets, at least the aoa operator's `min_packets`."""
    from rover.operators.aoa.operator import AoaParams

    least = AoaParams().min_packets
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < least:
        raise argparse.ArgumentTypeError(f"a whole number of packets from {least}, got {text!r}")
    return value


def seed(text: str) -> int:
    """--seed: a whole number from 0."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"a whole number from 0, got {text!r}")
    return value
