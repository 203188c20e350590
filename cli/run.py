"""`rover run`: a pipeline, all of it or one host's share, on a dataset or live."""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import tempfile
from pathlib import Path
from typing import Any

from rover.cli.args import add_set, default_pipeline, overrides
from rover.cli.registry import BUILTINS
from rover.cli.summary import run_summary
from rover.errors import BadInput
from rover.pipeline.validation import Pipeline

log = logging.getLogger("rover")

WORKERS_ENV = "ROVER_WORKERS"
"""The default of --workers when the command line gives none (the tests run in one process)."""


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
    p.add_argument(
        "--workers",
        metavar="N",
        help="worker processes for a run of the whole pipeline: a count, or auto (a process per core; "
        f"the default, or the file's workers:, or ${WORKERS_ENV}); 1 runs everything in this process",
    )
    p.add_argument("--worker-plan", help=argparse.SUPPRESS)
    p.add_argument("--worker-index", type=int, default=0, help=argparse.SUPPRESS)
    p.add_argument("--worker-ready-fd", type=int, help=argparse.SUPPRESS)
    add_set(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from rover.pipeline.validation import load_and_check
    from rover.runtime import runner, workers

    path = args.pipeline or default_pipeline()
    if args.worker_plan:
        return _run_worker(args, load_and_check(path, BUILTINS, overrides(args)))
    if args.view is not None:
        from rover.cli.view import load_with_view

        pipeline = load_with_view(path, BUILTINS, overrides(args), args.view, args.host)
    else:
        pipeline = load_and_check(path, BUILTINS, overrides(args))
    requested = _requested_workers(args)
    if args.host is not None or args.view is not None:
        if requested not in (None, "auto", 1):
            why = "--host: a host of a multi-host run" if args.host is not None else "--view: a run with a live view"
            raise BadInput(f"--workers {requested}: {why} runs in one process")
        count = 1
    else:
        count = workers.worker_count(requested, pipeline)
    if count > 1:
        status = _run_in_workers(args, pipeline, count)
    else:
        status = runner.run(pipeline, args.host, progress=not args.quiet)
    folders = [
        Path(str(node.spec.params.get("out", "rover-out")))
        for node in pipeline.nodes.values()
        if node.spec.uses == "run_outputs" and args.host in (None, node.spec.host)
    ]
    for line in (line for out in folders for line in run_summary(out)) if not args.quiet else ():
        print(line)
    return status


def _requested_workers(args: argparse.Namespace) -> int | str | None:
    """--workers, else $ROVER_WORKERS, else None (the file's `workers:`)."""
    value = args.workers if args.workers is not None else os.environ.get(WORKERS_ENV)
    where = "--workers" if args.workers is not None else f"${WORKERS_ENV}"
    if value is None or value == "auto":
        return value
    try:
        count = int(value)
    except ValueError:
        raise BadInput(f"{where} {value!r}: a count of worker processes, or auto") from None
    if count < 1:
        raise BadInput(f"{where} {value!r}: at least 1 (1 runs everything in this process)")
    return count


def _measured_cpu(pipeline: Pipeline) -> dict[str, float]:
    """The CPU seconds each operator took in the last complete run into the same output folder
    (its run.json's profile), where one is there."""
    from rover.formats.run_dir import RUN_FILE

    for node in pipeline.nodes.values():
        if node.cls.folder_param is None:
            continue
        try:
            doc = json.loads((Path(str(getattr(node.params, node.cls.folder_param))) / RUN_FILE).read_text())
            if doc.get("status") == "complete":
                return {name: float(p["cpu_s"]) for name, p in doc["profile"].items()}
        except (OSError, ValueError, TypeError, KeyError, AttributeError):
            continue  # no earlier run, or one of another kind: the classes' weights place them
    return {}


def _run_in_workers(args: argparse.Namespace, pipeline: Pipeline, count: int) -> int:
    """The run spread over `count` worker processes (rover.runtime.workers), each a `rover run` of
    its share with this command line."""
    from rover.runtime import supervisor, workers

    with tempfile.TemporaryDirectory(prefix=workers.FOLDER_PREFIX, dir=workers.runs_folder()) as folder:
        hub = f"unixsock-stream/{folder}/hub.sock"
        plan = workers.plan(pipeline, count, hub, workers.costs(pipeline, _measured_cpu(pipeline)))
        for k, group in enumerate(plan.groups):
            log.info("%s runs %s", workers.WorkerPlan.host(k), ", ".join(group))
        plan_file = Path(folder) / workers.PLAN_FILE
        plan_file.write_text(plan.to_json())
        same = _same_command_line(args)

        def command(k: int, ready_fd: int) -> list[str]:
            quiet = ["-q"] if args.quiet else []
            return [
                sys.executable,
                "-m",
                "rover.cli",
                *quiet,
                *["-v"] * args.verbose,
                "run",
                *same,
                "--worker-plan",
                str(plan_file),
                "--worker-index",
                str(k),
                "--worker-ready-fd",
                str(ready_fd),
            ]

        return supervisor.supervise(plan, command)


def _same_command_line(args: argparse.Namespace) -> list[str]:
    """This command line's pipeline and settings, for a worker to load the same pipeline."""
    argv = [str(Path(args.pipeline).resolve())] if args.pipeline else []
    for flag in ("dataset", "output", "speed", "timing_topic"):
        if getattr(args, flag) is not None:
            argv += [f"--{flag.replace('_', '-')}", str(getattr(args, flag))]
    for item in args.set or []:
        argv += ["--set", item]
    return argv


def _run_worker(args: argparse.Namespace, pipeline: Pipeline) -> int:
    """One worker's share of a run that `rover run` spread over worker processes."""
    from rover.runtime import runner, supervisor, workers

    plan_file = Path(args.worker_plan)
    try:
        text = plan_file.read_text()
    except OSError as exc:
        raise BadInput(f"{plan_file}: cannot read the worker plan: {exc.strerror}") from None
    plan = workers.WorkerPlan.from_json(text, str(plan_file))
    fd = args.worker_ready_fd

    def running() -> None:
        if fd is not None:
            os.write(fd, supervisor.RUNNING)

    host = workers.WorkerPlan.host(args.worker_index)
    progress = not args.quiet and args.worker_index == 0  # worker 0 has the sources: it shows the progress
    return runner.run(workers.as_workers(pipeline, plan), host, progress=progress, on_running=running)
