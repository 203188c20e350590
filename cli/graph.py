"""`rover graph`: a pipeline as Mermaid or DOT."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from rover.cli.args import add_set, default_pipeline, overrides
from rover.cli.registry import BUILTINS


def add_parser(sub: Any, common: argparse.ArgumentParser) -> None:
    """`rover graph` and its options."""
    p = sub.add_parser("graph", parents=[common], help="print the pipeline as Mermaid (default) or DOT")
    p.add_argument("pipeline", nargs="?", help="pipeline file (default: the one shipped with rover)")
    p.add_argument("--format", choices=("mermaid", "dot"), default="mermaid")
    add_set(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from rover.pipeline import graph
    from rover.pipeline.validation import load_and_check

    pipeline = load_and_check(args.pipeline or default_pipeline(), BUILTINS, overrides(args))
    sys.stdout.write(graph.dot(pipeline) if args.format == "dot" else graph.mermaid(pipeline))
    return 0
