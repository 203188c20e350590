"""The `rover` command. Library errors become one line on stderr and an exit status:
2 for bad input, 1 for a failed run, 130/143 after an interrupt."""

from __future__ import annotations

import argparse
import logging
import math
import signal
import sys
import threading
from importlib import resources
from pathlib import Path
from types import FrameType
from typing import Any

from rover import __version__
from rover.cli.registry import BUILTINS
from rover.errors import BadInput, Interrupted, RoverError, SpecError
from rover.pipeline.yamlpos import parse_scalar

EXIT_BAD_INPUT = 2
EXIT_FAILED = 1


def default_pipeline() -> Path:
    """The pipeline shipped inside the package (identical to the repository's pipeline.yaml)."""
    return Path(str(resources.files("rover").joinpath("pipeline.yaml")))


def _overrides(args: argparse.Namespace) -> dict[str, Any]:
    values: dict[str, Any] = {}
    for item in args.set or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise BadInput(f"--set {item!r}: expected NAME=VALUE")
        values[key.strip()] = parse_scalar(value, f"--set {key.strip()}")
    if getattr(args, "dataset", None) is not None:
        values["dataset"] = args.dataset
    if getattr(args, "output", None) is not None:
        values["output"] = args.output
    if getattr(args, "speed", None) is not None:
        values["speed"] = parse_scalar(args.speed, "--speed")
    if getattr(args, "timing_topic", None) is not None:
        values["timing_topic"] = args.timing_topic
    return values


def _check_one(file: str, overrides: dict[str, Any]) -> tuple[str, list[str]]:
    """Summary line and warnings of one pipeline or setup file; raises on problems."""
    from rover.formats.rig import parse_rig
    from rover.operators.channel_sweep.channel_plan import best_excitation, conflicts, max_tags
    from rover.pipeline.spec import parse, read_document
    from rover.pipeline.validation import check

    doc = read_document(file)
    if (
        isinstance(doc.data, dict)
        and "operators" not in doc.data
        and ({"receiver", "tags", "excitation"} & set(doc.data))
    ):
        rig = parse_rig(doc)
        warnings = [f"{d} (warning)" for d in rig.warnings]
        warnings += [
            f"{file}: warning: channel plan: {c.message}"
            for c in conflicts(rig.excitation_channel, {t.id: t.channel for t in rig.tags})
        ]
        tags = ", ".join(f"{t.id}@{t.channel}" for t in rig.tags)
        best = best_excitation()
        here = len(max_tags(rig.excitation_channel))
        advice = "" if here >= best.max_tags else f"; channel {best.channel} would allow {best.max_tags}"
        return (
            f"{file}: ok: rig with {len(rig.antenna_positions_m)} antennas, excitation channel "
            f"{rig.excitation_channel} (at most {here} tags at once{advice}), {len(rig.tags)} tags ({tags})"
        ), warnings
    spec, problems = parse(doc, overrides)
    return check(spec, BUILTINS, problems).summary(), []


def cmd_check(args: argparse.Namespace) -> int:
    problems: list[str] = []
    for file in args.files:
        try:
            summary, warnings = _check_one(file, _overrides(args))
            print(summary)
            for line in warnings:
                print(line, file=sys.stderr)
        except SpecError as exc:
            problems += [str(d) for d in exc.diagnostics]
        except BadInput as exc:
            problems.append(str(exc))
    for line in problems:
        print(line, file=sys.stderr)
    if problems:
        print(f"{len(problems)} problem{'s' if len(problems) > 1 else ''} found", file=sys.stderr)
        return EXIT_BAD_INPUT
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    from rover.pipeline.validation import load_and_check
    from rover.runtime.runner import run

    pipeline = load_and_check(args.pipeline or default_pipeline(), BUILTINS, _overrides(args))
    return run(pipeline, args.host)


def cmd_graph(args: argparse.Namespace) -> int:
    from rover.pipeline import graph
    from rover.pipeline.validation import load_and_check

    pipeline = load_and_check(args.pipeline or default_pipeline(), BUILTINS, _overrides(args))
    sys.stdout.write(graph.dot(pipeline) if args.format == "dot" else graph.mermaid(pipeline))
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    import json

    from rover.datasets.info import dataset_info, render

    info = dataset_info(args.path)
    sys.stdout.write(json.dumps(info.as_json(), indent=2) + "\n" if args.json else render(info))
    return 0


def cmd_convert(args: argparse.Namespace) -> int:
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
        )
    finally:
        done()
    for line in report.lines():
        print(line)
    print(f"wrote {report.output}")
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    import shlex

    from rover.datasets.scenario import load_scenario
    from rover.datasets.simulate import simulate
    from rover.formats.bag import check_output

    overrides = {}
    for item in args.set or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise BadInput(f"--set {item!r}: expected SECTION.KEY=VALUE")
        overrides[key] = value
    check_output(args.output, force=args.force)  # before the scenario is read or anything simulated
    if Path(args.scenario).exists() and Path(args.scenario).resolve() == Path(args.output).resolve():
        raise BadInput(f"{args.output}: is also the scenario file; simulating onto it would destroy it")
    scenario = load_scenario(args.scenario, overrides)
    report = simulate(scenario, args.seed, args.output, shlex.join(["rover", *sys.argv[1:]]), force=args.force)
    per_tag = ", ".join(f"tag {t}: {n:,}" for t, n in report.packets_per_tag.items())
    print(f"simulated {report.duration_s:.1f} s, {report.path_length_m:.2f} m of path; CSI packets {per_tag}")
    print(f"wrote {report.output}")
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    import json

    from rover.evaluation.metrics import evaluate, render
    from rover.formats.run_dir import load_run, load_truth, read_run_description

    description = read_run_description(args.run)
    if description is not None and description.status == "failed":
        raise BadInput(f"{args.run}: the run failed, nothing to evaluate: {description.reason}")
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
    sys.stdout.write(json.dumps(metrics, indent=2) + "\n" if args.json else render(metrics))
    if args.figures:
        from rover.evaluation.figures import write_figures

        written = write_figures(run, truth, Path(args.run))
        print(f"wrote {', '.join(p.name for p in written)} in {args.run}", file=sys.stderr)
    return 0


def _add_set(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--set",
        action="append",
        metavar="NAME=VALUE",
        help="set a ${NAME} variable of the pipeline, or OPERATOR.PARAM (e.g. slam.wheel=false) "
        "typed and checked like the file's own params",
    )


def _seconds(text: str) -> float:
    """--start/--end: a number of seconds from 0 to 2**31 (a ROS 2 stamp's range)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0 <= value < 2**31:
        raise argparse.ArgumentTypeError(f"seconds from 0 to 2**31, got {text!r}")
    return value


def _seed(text: str) -> int:
    """--seed: a whole number from 0."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"a whole number from 0, got {text!r}")
    return value


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="rover", description="Localize a robot and WiFi backscatter tags with AoA-IMU SLAM, as a Zenoh dataflow."
    )
    ap.add_argument("--version", action="version", version=f"rover {__version__}")
    ap.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv: debug)")
    ap.add_argument("-q", "--quiet", action="store_true", help="only errors")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("-v", "--verbose", action="count", default=argparse.SUPPRESS, help="more log output")
    common.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS, help="only errors")
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def command(name: str, help: str) -> argparse.ArgumentParser:
        return sub.add_parser(name, help=help, parents=[common])  # -v/-q work after the command too

    p = command("run", help="run a pipeline (all of it, or one host's share)")
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
    _add_set(p)
    p.set_defaults(func=cmd_run)

    p = command("check", help="validate pipeline and setup files; report every problem as FILE:LINE:COL")
    p.add_argument("files", nargs="+", metavar="FILE")
    _add_set(p)
    p.set_defaults(func=cmd_check)

    p = command("graph", help="print the pipeline as Mermaid (default) or DOT")
    p.add_argument("pipeline", nargs="?", help="pipeline file (default: the one shipped with rover)")
    p.add_argument("--format", choices=("mermaid", "dot"), default="mermaid")
    _add_set(p)
    p.set_defaults(func=cmd_graph)

    p = command("convert", help="ROS 1/ROS 2 bags or a recording folder to a dataset")
    p.add_argument("sources", nargs="+", metavar="SRC", help=".bag, ROS 2 bag folder, .db3, .mcap, recording folder")
    p.add_argument("-o", "--output", required=True, help="the dataset to write (.mcap)")
    p.add_argument("--setup", help="setup.yaml (default: the recording folder's)")
    p.add_argument("--topic", action="append", metavar="ROLE=/NAME", help="source topic of csi, imu or odom")
    p.add_argument("--start", type=_seconds, help="seconds from the start (or absolute seconds)")
    p.add_argument("--end", type=_seconds, help="seconds from the start (or absolute seconds)")
    p.add_argument("--truth", help="ground-truth trajectory: a TUM file, or a dataset with /groundtruth/pose")
    p.add_argument("--tags", help="ground-truth tags (CSV: id,channel,x,y,z,nlos)")
    p.add_argument("--force", action="store_true", help="replace an existing output")
    p.set_defaults(func=cmd_convert)

    p = command("simulate", help="a dataset with ground truth from a scenario")
    p.add_argument("--scenario", default="paper", help="a built-in scenario name or a scenario .yaml file")
    p.add_argument("--seed", type=_seed, default=0, help="a whole number from 0 (the same seed gives the same bytes)")
    p.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE", help="override a scenario value")
    p.add_argument("-o", "--output", required=True, help="the dataset to write (.mcap)")
    p.add_argument("--force", action="store_true", help="replace an existing output")
    p.set_defaults(func=cmd_simulate)

    p = command("eval", help="errors of a run against ground truth (robot, tags, AoA), as evo computes them")
    p.add_argument("run", help="the --output directory of a `rover run`")
    p.add_argument("--truth", help="dataset or TUM file with the true trajectory (default: the run's dataset)")
    p.add_argument("--tags", help="true tag positions (CSV: id,channel,x,y,z,nlos)")
    p.add_argument("--t-max-diff", type=float, default=0.01, help="largest stamp gap when pairing poses (s)")
    p.add_argument("--json", action="store_true", help="print metrics.json instead of the table")
    p.add_argument("--figures", action="store_true", help="also draw the figures into the run's folder")
    p.set_defaults(func=cmd_eval)

    p = command("info", help="what a dataset holds, like `ros2 bag info`")
    p.add_argument("path")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.set_defaults(func=cmd_info)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    level = logging.ERROR if args.quiet else (logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)]
    logging.basicConfig(level=level, format="rover: %(levelname)s: %(message)s")
    previous = (
        {sig: signal.signal(sig, _interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
        if threading.current_thread() is threading.main_thread()
        else {}
    )
    try:
        return args.func(args)
    except Interrupted as exc:
        return 128 + exc.signum
    except SpecError as exc:
        for d in exc.diagnostics:
            print(d, file=sys.stderr)
        return EXIT_BAD_INPUT
    except BadInput as exc:
        print(f"rover: error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except RoverError as exc:
        print(f"rover: error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_FAILED
    except KeyboardInterrupt:
        return 128 + signal.SIGINT
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _one_line(exc: Exception) -> str:
    """An error's message on one line, whatever a library put in it (a reason quoting a file's text)."""
    return " ".join(str(exc).split())


def _interrupt(signum: int, _frame: FrameType | None) -> None:
    """SIGINT and SIGTERM stop a command where it is; its outputs clean up on the way out
    (`rover run` has its own handlers, which let the operators drain and finish)."""
    raise Interrupted(signum)


if __name__ == "__main__":
    sys.exit(main())
