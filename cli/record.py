"""`rover record`: a live pipeline whose dataset_recorder writes the session as a dataset."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from rover.cli.args import add_set, overrides
from rover.cli.registry import BUILTINS
from rover.errors import BadInput


def add_parser(sub: Any, common: argparse.ArgumentParser) -> None:
    """`rover record` and its options."""
    p = sub.add_parser(
        "record", parents=[common], help="run a live pipeline (or one host's share) and write the session as a dataset"
    )
    p.add_argument("pipeline", metavar="PIPELINE", help="a pipeline with a dataset_recorder operator")
    p.add_argument("--host", help="run only this host's operators (the dataset_recorder's host)")
    p.add_argument("-o", dest="record_to", metavar="DATASET.mcap", required=True, help="the dataset to write")
    p.add_argument("--force", action="store_true", help="replace an existing dataset")
    p.add_argument("--output", help="same as --set output=DIR (the run's own results)")
    add_set(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """`rover run` with the pipeline's `dataset_recorder` writing the session to `-o` (that operator's
    `path` and `command` params, set here so every host still runs the same pipeline)."""
    import shlex

    from rover.formats.bag import check_output
    from rover.pipeline.validation import load_and_check
    from rover.runtime import runner

    file = args.pipeline
    values = overrides(args)
    pipeline = load_and_check(file, BUILTINS, values)
    recorders = [n for n in pipeline.nodes.values() if n.spec.uses == "dataset_recorder"]
    here = [n for n in recorders if args.host is None or n.spec.host == args.host]
    if not here:
        placed = "; ".join(f"{n.name!r} runs on host {n.spec.host}" for n in recorders)
        raise BadInput(
            f"{file}: no dataset_recorder operator{f' on host {args.host}' if args.host else ''}"
            + (
                f" ({placed}: record there)"
                if placed
                else ": add one wired to the CSI, IMU, odometry and rig sources, as pipelines/live.yaml does"
            )
        )
    if len(here) > 1:
        names = ", ".join(repr(n.name) for n in here)
        raise BadInput(
            f"{file}: several dataset_recorder operators ({names}): set their paths with --set NAME.path=FILE"
        )
    check_output(args.record_to, force=args.force)
    name = here[0].name
    values[f"{name}.path"] = args.record_to
    values[f"{name}.command"] = shlex.join(["rover", *sys.argv[1:]])
    return runner.run(load_and_check(file, BUILTINS, values), args.host)
