"""`rover run`: a pipeline, all of it or one host's share, on a dataset or live."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from rover.cli.args import add_set, default_pipeline, overrides
from rover.cli.registry import BUILTINS
from rover.cli.summary import run_summary


def add_parser(sub: Any, common: argparse.ArgumentParser) -> None:
    """`rover run` and its options."""
    p = sub.add_parser("run", parents=[common], help="run a pipeline (all of it, or one host's share)")
    p.add_argument("pipeline", nargs="?", help="pipeline file (default: the one shipped with rover)")
    p.add_argument("--host", help="run only the operators placed on this host")
    p.add_argument("--dataset", help="same as --set dataset=PATH")
    p.add_argument("--output", help="same as --set output=DIR")
    p.add_argument("--speed", help="same as --set speed=X: replay at X times real time (max: as fast as possible)")
    p.add_argument(
        "--timing-topic",
        metavar="TOPIC",
        help="same as --set timing_topic=TOPIC: also record the wall-clock timings in results.mcap "
        "(they are always in timing.json; recorded, they make results.mcap differ between identical runs)",
    )
    p.add_argument(
        "--view",
        nargs="?",
        const=8765,
        type=int,
        metavar="PORT",
        help="also serve a live view to Foxglove on ws://127.0.0.1:PORT (default 8765; 0: any free port); "
        "--set view.host=0.0.0.0 listens on every interface",
    )
    add_set(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from rover.pipeline.validation import load_and_check
    from rover.runtime import runner

    path = args.pipeline or default_pipeline()
    if args.view is not None:
        from rover.cli.view import load_with_view

        pipeline = load_with_view(path, BUILTINS, overrides(args), args.view, args.host)
    else:
        pipeline = load_and_check(path, BUILTINS, overrides(args))
    status = runner.run(pipeline, args.host, progress=not args.quiet)
    folders = [
        Path(str(node.spec.params.get("out", "rover-out")))
        for node in pipeline.nodes.values()
        if node.spec.uses == "run_outputs" and args.host in (None, node.spec.host)
    ]
    for line in (line for out in folders for line in run_summary(out)) if not args.quiet else ():
        print(line)
    return status
