"""`rover eval`: a run's errors against ground truth (robot, tags, AoA)."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any

from rover.errors import BadInput


def add_parser(sub: Any, common: argparse.ArgumentParser) -> None:
    """`rover eval` and its options."""
    p = sub.add_parser(
        "eval", parents=[common], help="errors of a run against ground truth (robot, tags, AoA), as evo computes them"
    )
    p.add_argument("run", help="the --output directory of a `rover run`")
    p.add_argument("--truth", help="dataset or TUM file with the true trajectory (default: the run's dataset)")
    p.add_argument("--tags", help="true tag positions (CSV: id,channel,x,y,z,nlos)")
    p.add_argument("--t-max-diff", type=float, default=0.01, help="largest stamp gap when pairing poses (s)")
    p.add_argument("--json", action="store_true", help="print metrics.json instead of the table")
    p.add_argument(
        "--figures",
        action="store_true",
        help="also draw the figures into the run's folder (against another truth: into its eval-TRUTH/ subfolder)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import json

    from rover.evaluation.checks import evaluation_notes
    from rover.evaluation.metrics import evaluate, render
    from rover.formats.run_dir import FAILED_RUN_FILE, load_run, load_truth, read_run_description

    description = read_run_description(args.run)
    failed = read_run_description(args.run, FAILED_RUN_FILE)
    if description is None and failed is not None:
        description = failed
    if description is not None and description.status == "failed":
        raise BadInput(f"{args.run}: the run failed, nothing to evaluate: {description.reason}")
    if failed is not None and description is not failed:  # a run with results removes failed-run.json
        logging.getLogger("rover.eval").warning(
            "%s: the last run into this folder failed (%s: %s): these are the results of the run before it",
            args.run,
            FAILED_RUN_FILE,
            failed.reason,
        )
    if description is not None and description.status in ("interrupted", "partial"):
        logging.getLogger("rover.eval").warning(
            "%s: the run is %s (%s): its results cover part of the dataset",
            args.run,
            description.status,
            description.reason,
        )
    run = load_run(args.run)
    source = args.truth or (description.dataset if description is not None else None)
    if source is None:
        raise BadInput(f"{args.run}: the run names no dataset with ground truth: pass --truth DATASET_OR_TUM")
    truth = load_truth(source, args.tags)
    if truth is None:
        raise BadInput(f"{source}: no ground truth (/groundtruth/pose) in this dataset: pass --truth")
    if not truth.tags and args.tags is None and str(source).endswith((".tum", ".txt")):
        logging.getLogger("rover.eval").warning("no tag truth: pass --tags CSV for tag errors")
    metrics = evaluate(run, truth, args.t_max_diff)
    dataset = description.dataset if description is not None else None
    own = None
    if args.truth and dataset is not None and dataset.is_file():
        own_truth = load_truth(dataset)
        own = own_truth.trajectory if own_truth is not None else None
    notes = evaluation_notes(metrics, len(run.final.stamp_ns), str(source), str(dataset), own, truth.trajectory)
    for note in notes:
        logging.getLogger("rover.eval").warning("%s: %s", args.run, note)
    if notes:
        metrics["notes"] = notes
    sys.stdout.write(json.dumps(metrics, indent=2) + "\n" if args.json else render(metrics))
    if args.figures:
        from rover.evaluation.figures import write_figures

        folder = Path(args.run)
        if args.truth and (own is None or notes):  # not (provably) the run's own truth: beside its figures
            folder = folder / f"eval-{Path(args.truth).stem}"
            try:
                folder.mkdir(exist_ok=True)
            except OSError as exc:
                raise BadInput(f"{folder}: cannot write the figures: {exc.strerror or exc}") from None
        written = write_figures(run, truth, folder)
        print(f"wrote {', '.join(p.name for p in written)} in {folder}", file=sys.stderr)
    return 0
