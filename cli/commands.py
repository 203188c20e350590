"""The `rover` command. Library errors become one line on stderr and an exit status:
2 for bad input, 1 for a failed run, 130/143 after an interrupt."""

from __future__ import annotations

import argparse
import logging
import math
import os
import signal
import sys
import threading
from importlib import resources
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any

from rover import __version__
from rover.cli.registry import BUILTINS
from rover.errors import BadInput, Interrupted, PeerLost, RoverError, SpecError
from rover.pipeline.yamlpos import parse_scalar

if TYPE_CHECKING:
    from rover.formats.rig import Rig
    from rover.operators.aoa.calibration import Calibration

EXIT_PARTIAL = 3
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


def _check_one(
    file: str, overrides: dict[str, Any], host: str | None = None, security: bool = False
) -> tuple[str, list[str]]:
    """Summary line and warnings of one pipeline or setup file; raises on problems. Under
    `security:` the certificates are checked too: every host's, or only `host`'s (on a deployed
    machine, which holds its own key only); `security` adds the generated access rules."""
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
        from rover.operators.aoa.array import check_rig_geometry

        rig = parse_rig(doc)
        warnings = [f"{d} (warning)" for d in rig.warnings]
        geometry = check_rig_geometry(rig)  # BadInput for an ambiguous planar array, as aoa raises at run time
        if geometry:
            warnings.append(f"{file}: warning: {geometry}")
        head = f"{file}: ok: rig with {len(rig.antenna_positions_m)} antennas"
        tags = ", ".join(f"{t.id}@{t.channel}" for t in rig.tags)
        if rig.excitation_channel is None:
            listens = f" on channel {rig.receiver_channel}" if rig.receiver_channel is not None else ""
            listed = f", {len(rig.tags)} tags ({tags})" if rig.tags else ""
            return f"{head}{listens}, no excitation channel (a bare receiver){listed}", warnings
        warnings += [
            f"{file}: warning: channel plan: {c.message}"
            for c in conflicts(rig.excitation_channel, {t.id: t.channel for t in rig.tags})
        ]
        best = best_excitation()
        here = len(max_tags(rig.excitation_channel))
        advice = "" if here >= best.max_tags else f"; channel {best.channel} would allow {best.max_tags}"
        return (
            f"{head}, excitation channel {rig.excitation_channel} "
            f"(at most {here} tags at once{advice}), {len(rig.tags)} tags ({tags})"
        ), warnings
    from rover.pipeline.spec import MONITOR

    spec, problems = parse(doc, overrides)
    summary = check(spec, BUILTINS, problems).summary()
    secured = spec.security is not None
    if host is not None and host not in spec.hosts and not (secured and host == MONITOR):
        also = f" (or {MONITOR}, under security:)" if secured else ""
        raise BadInput(f"{file}: --host {host!r} is not declared under hosts: ({', '.join(spec.hosts)}){also}")
    if spec.security is None:
        if security:
            summary += "\n(no security: section: every host accepts any connection; see docs/security.md)"
        return summary, []
    from rover.security.acl import describe
    from rover.security.check import check_security

    hosts = None if host is None else [h for h in [host] if h != MONITOR]
    monitor = host == MONITOR or (host is None and spec.security.monitor is not None)
    found, warnings = check_security(spec, hosts, monitor=monitor)
    if found:
        raise SpecError(found)
    summary += f"; mutual TLS, certificates of {host or 'every host'} valid"
    return (summary + "\n" + describe(spec) if security else summary), warnings


def cmd_check(args: argparse.Namespace) -> int:
    problems: list[str] = []
    for file in args.files:
        try:
            summary, warnings = _check_one(file, _overrides(args), args.host, args.security)
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

    path = args.pipeline or default_pipeline()
    if args.view is not None:
        from rover.cli.view import load_with_view

        return run(load_with_view(path, BUILTINS, _overrides(args), args.view, args.host), args.host)
    pipeline = load_and_check(path, BUILTINS, _overrides(args))
    return run(pipeline, args.host)


def cmd_record(args: argparse.Namespace) -> int:
    """`rover run` with the pipeline's `dataset_recorder` writing the session to `-o` (that operator's
    `path` and `command` params, set here so every host still runs the same pipeline)."""
    import shlex

    from rover.formats.bag import check_output
    from rover.pipeline.validation import load_and_check
    from rover.runtime.runner import run

    file = args.pipeline
    overrides = _overrides(args)
    pipeline = load_and_check(file, BUILTINS, overrides)
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
    overrides[f"{name}.path"] = args.record_to
    overrides[f"{name}.command"] = shlex.join(["rover", *sys.argv[1:]])
    return run(load_and_check(file, BUILTINS, overrides), args.host)


def cmd_graph(args: argparse.Namespace) -> int:
    from rover.pipeline import graph
    from rover.pipeline.validation import load_and_check

    pipeline = load_and_check(args.pipeline or default_pipeline(), BUILTINS, _overrides(args))
    sys.stdout.write(graph.dot(pipeline) if args.format == "dot" else graph.mermaid(pipeline))
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    """Live state of a running multi-host pipeline, from its hosts' status queryables. The file is
    only parsed (not checked against the operator classes): a monitoring machine needs no operator code."""
    import json
    import time

    from rich.console import Console
    from rich.live import Live

    from rover.pipeline.spec import endpoint_problem, parse, read_document
    from rover.runtime.status import HostStatus, render, report
    from rover.transport.monitor import StatusClient, local_endpoint

    for option, value in (("--interval", args.interval), ("--timeout", args.timeout)):
        if not 0 < value < math.inf:
            raise BadInput(f"{option}: a number of seconds above 0, got {value:g}")
    spec, problems = parse(read_document(args.pipeline), _overrides(args))
    if problems:
        raise SpecError(problems)
    for endpoint in args.connect or []:
        if problem := endpoint_problem(endpoint):
            raise BadInput(f"--connect: {problem}")
    listen = [local_endpoint(ep) for host in spec.hosts.values() for ep in host.listen]
    endpoints = list(dict.fromkeys(args.connect or listen))
    if not endpoints:
        raise BadInput(f"{args.pipeline}: no host of pipeline {spec.name} listens on an endpoint: pass --connect")
    expected = sorted({op.host for op in spec.operators.values() if op.host})
    tls = None
    if spec.security is not None:
        from rover.security.check import check_security
        from rover.transport.session import TlsFiles

        found, warnings = check_security(spec, [], monitor=True)
        if found:
            raise SpecError(found)
        for line in warnings:
            print(line, file=sys.stderr)
        assert spec.security.monitor is not None  # check_security(monitor=True) made sure
        tls = TlsFiles(spec.security.ca, spec.security.monitor.cert, spec.security.monitor.key)
    with StatusClient(spec.name, endpoints, args.timeout, tls) as client:

        def snapshot(first: bool = False) -> tuple[dict[str, HostStatus], list[str]]:
            # also measures each host's clock offset: client.clocks; the first waits for an answer
            statuses, notes = client.first_poll() if first else client.poll()
            return statuses, notes + ([f"{client.errors} error replies"] if client.errors else [])

        def as_json(current: dict[str, HostStatus], previous: dict[str, HostStatus], notes: list[str]) -> str:
            return json.dumps(report(current, previous, expected, notes, client.clocks.best()), allow_nan=False)

        current, notes = snapshot(first=True)
        previous: dict[str, HostStatus] = {}
        if args.once:  # rates from two snapshots --interval apart
            time.sleep(args.interval)
            later, notes = snapshot()
            previous, current = current, {**current, **later}
            if args.json:
                print(as_json(current, previous, notes))
            else:
                Console().print(render(current, previous, expected, notes, client.clocks.best()))
            return 0
        if args.json:  # one line per refresh
            print(as_json(current, previous, notes), flush=True)
            while True:  # until Ctrl-C: main() turns Interrupted into status 130
                time.sleep(args.interval)
                later, notes = snapshot()
                previous, current = {**previous, **current}, later
                print(as_json(current, previous, notes), flush=True)
        with Live(render(current, previous, expected, notes, client.clocks.best()), auto_refresh=False) as live:
            while True:  # until Ctrl-C: main() turns Interrupted into status 130
                time.sleep(args.interval)
                later, notes = snapshot()
                previous, current = {**previous, **current}, later
                live.update(render(current, previous, expected, notes, client.clocks.best()), refresh=True)


def _names(args: argparse.Namespace, hosts: list[str]) -> dict[str, list[str]]:
    given: dict[str, list[str]] = {}
    for item in args.names or []:
        for pair in item.split(","):
            host, sep, name = pair.partition("=")
            if not (sep and host and name):
                raise BadInput(f"--names {item!r}: expected HOST=DNS_OR_IP,..., e.g. nuc=10.0.0.5,nuc=nuc.lab")
            if host not in hosts:
                raise BadInput(f"--names {item!r}: {host!r} is not one of the hosts ({', '.join(hosts)})")
            given.setdefault(host, []).append(name)
    return given


def cmd_certs(args: argparse.Namespace) -> int:
    """Issue a CA and one certificate per host (and the monitor) into a folder; print the
    security: section that uses them."""
    from rover.pipeline.spec import MONITOR, NAME_RE, parse, read_document
    from rover.pipeline.validation import listens_on_wildcard, served_addresses
    from rover.security.certs import issue

    spec = None
    if args.pipeline:
        spec, problems = parse(read_document(args.pipeline), _overrides(args))
        if problems:
            raise SpecError(problems)
    hosts = [h.strip() for h in args.hosts.split(",") if h.strip()] if args.hosts else list(spec.hosts if spec else [])
    if not hosts:
        raise BadInput("rover certs: name the hosts (--hosts nuc,base,laptop) or give a pipeline with hosts:")
    for host in hosts:
        if not NAME_RE.match(host) or host == MONITOR:
            raise BadInput(f"--hosts: {host!r} is not a host name (letters, digits, _ or -; {MONITOR!r} is reserved)")
    hosts = list(dict.fromkeys(hosts))
    given = _names(args, hosts)
    names: dict[str, list[str]] = {}
    for host in hosts:
        derived: list[str] = []
        if spec is not None and host in spec.hosts:
            derived = list(dict.fromkeys(address for address, _why in served_addresses(spec, host)))
            if listens_on_wildcard(spec, host):
                derived += ["localhost", "127.0.0.1"]  # where `rover status` on that machine connects
        names[host] = given.get(host, derived)
    label = f"rover pipeline {spec.name}" if spec else "rover"
    issued = issue(args.output, names, monitor=args.monitor, label=label, days=args.days, force=args.force)
    print(f"{issued.ca}: CA certificate ({label} CA; its private key was not kept: a new host means a new set)")
    for ident, (cert, key) in issued.identities.items():
        shown = ", ".join(dict.fromkeys([ident] + names.get(ident, [])))
        print(f"{cert}, {key}: {ident} (names: {shown})")
    out = args.output
    print("\nsecurity:  # give each host only the CA, its own certificate and its own key")
    print(f"  ca: {out}/ca.pem\n  hosts:")
    for host in hosts:
        print(f"    {host}: {{cert: {out}/{host}.pem, key: {out}/{host}.key}}")
    if args.monitor:
        print(f"  monitor: {{cert: {out}/{MONITOR}.pem, key: {out}/{MONITOR}.key}}")
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


def cmd_calibrate(args: argparse.Namespace) -> int:
    """Per-chain phase offsets from CSI logs at a known angle or datasets with ground truth."""
    import shlex

    from rover.formats.atomic_file import write_aside
    from rover.formats.bag import MAGIC, check_output
    from rover.operators.aoa.calibration import render, setup_block

    out = check_output(args.out, force=args.force) if args.out else None  # before any work
    kinds = []
    for source in map(Path, args.sources):
        if not source.is_file():
            raise BadInput(f"{source}: {'is a directory' if source.is_dir() else 'no such file'}")
        if out is not None and source.resolve() == out.resolve():
            raise BadInput(f"{out}: is also an input; writing the calibration onto it would destroy it")
        with source.open("rb") as f:
            kinds.append("dataset" if f.read(len(MAGIC)) == MAGIC else "log")
    logs = [s for s, kind in zip(args.sources, kinds, strict=True) if kind == "log"]
    datasets = [s for s, kind in zip(args.sources, kinds, strict=True) if kind == "dataset"]
    angles = _per_log(args.angle_deg, logs, "--angle-deg", datasets)
    channels = _per_log(args.channel, logs, "--channel", datasets)
    rig = None
    if args.setup:
        from rover.formats.rig import load_rig

        rig = load_rig(args.setup)
    rows, k = [], 0
    for source, kind in zip(args.sources, kinds, strict=True):
        if kind == "dataset":
            rows += _calibrate_dataset(Path(source), rig)
        else:
            rows.append(
                _calibrate_log(Path(source), rig, angles[k] if angles else None, channels[k] if channels else None)
            )
            k += 1
    sys.stdout.write(render(rows))
    block = setup_block([c for _, c in rows])
    print()
    sys.stdout.write(block)
    if out is not None:
        write_aside(
            out, lambda partial: partial.write_text(f"# {shlex.join(['rover', 'calibrate', *args.sources])}\n{block}")
        )
        print(f"wrote {out}")
    return 0


def cmd_aoa(args: argparse.Namespace) -> int:
    """Angles of arrival from a bare CSI Tool log: one row per burst, every candidate with its power."""
    from rover.formats.atomic_file import write_aside
    from rover.formats.bag import check_output
    from rover.formats.intel5300 import read_dat
    from rover.formats.rig import load_rig
    from rover.formats.text import read_text
    from rover.formats.wifi import channel_freq_hz
    from rover.operators.aoa.bare_log import log_bursts, with_calibration

    out = check_output(args.csv, force=args.force) if args.csv else None  # before any work
    rig = load_rig(args.setup)
    if args.calibration:
        rig = with_calibration(rig, read_text(Path(args.calibration)), args.calibration)
    channel = args.channel if args.channel is not None else rig.receiver_channel
    if channel is None:
        raise BadInput(f"{args.setup}: give --channel N, the channel the log was recorded on (or receiver.channel)")
    try:
        channel_freq_hz(channel)
    except ValueError:
        raise BadInput(f"--channel: {channel} is not a WiFi channel number") from None
    source = Path(args.log)
    if not source.is_file():
        raise BadInput(f"{source}: {'is a directory' if source.is_dir() else 'no such file'}")
    try:
        records = read_dat(source)
    except OSError as exc:
        raise BadInput(f"{source}: cannot read: {exc.strerror or exc}") from None
    try:
        bursts = log_bursts(records, rig, channel, args.burst)
    except BadInput as exc:
        raise BadInput(f"{source}: {exc}") from None
    lines = ["time_s,packets,angle_deg,std_deg,quality,candidates_deg,candidate_powers"]
    print(f"{source.name}: {len(records.nrx)} records, {len(bursts)} bursts of {args.burst} packets, channel {channel}")
    print(f"{'time s':>8} {'packets':>7} {'angle deg':>9} {'std deg':>7}  candidates deg (power)")
    for b in bursts:
        t = (b.header.stamp.sec * 1_000_000_000 + b.header.stamp.nanosec) / 1e9
        angles = [math.degrees(a) for a in b.candidate_angles_rad]
        powers = list(b.candidate_powers)
        shown = "  ".join(f"{a:6.1f} ({p:.2f})" for a, p in zip(angles, powers, strict=True))
        print(f"{t:8.3f} {b.packets:7d} {math.degrees(b.angle_rad):9.1f} {math.degrees(b.std_rad):7.1f}  {shown}")
        lines.append(
            f"{t:.6f},{b.packets},{math.degrees(b.angle_rad):.2f},{math.degrees(b.std_rad):.2f},{b.quality},"
            f"{';'.join(f'{a:.2f}' for a in angles)},{';'.join(f'{p:.3f}' for p in powers)}"
        )
    if out is not None:
        write_aside(out, lambda partial: partial.write_text("\n".join(lines) + "\n"))
        print(f"wrote {out}")
    return 0


def _per_log(values: list[Any] | None, logs: list[str], option: str, datasets: list[str]) -> list[Any]:
    """One value of an option per CSI log: given once for all of them, or once per log in order."""
    if not values:
        return []
    if not logs:
        raise BadInput(
            f"{option} is for CSI logs, and {', '.join(datasets)} is a dataset (MCAP): its angles and channels "
            "come from its frames and ground truth"
        )
    if len(values) not in (1, len(logs)):
        raise BadInput(f"{option} given {len(values)} times for {len(logs)} CSI logs: give it once, or once per log")
    return list(values) * len(logs) if len(values) == 1 else list(values)


def _calibrate_log(
    path: Path, rig: Rig | None, angle_deg: float | None, channel: int | None
) -> tuple[str, Calibration]:
    """One CSI Tool log of a transmitter at a known angle."""
    from rover.formats.intel5300 import read_dat
    from rover.operators.aoa.calibration import estimate_offsets

    if rig is None:
        raise BadInput(f"{path}: a CSI log needs --setup RIG.yaml (the antenna positions)")
    if angle_deg is None:
        raise BadInput(f"{path}: a CSI log needs --angle-deg A, the transmitter's angle in the robot frame")
    channel = channel if channel is not None else rig.receiver_channel
    if channel is None:
        raise BadInput(f"{path}: give --channel N, the channel the log was recorded on (or receiver.channel)")
    try:
        records = read_dat(path)
    except OSError as exc:
        raise BadInput(f"{path}: cannot read: {exc.strerror or exc}") from None
    m = len(rig.antenna_positions_m)
    usable = records.nrx == m
    if not usable.any():
        raise BadInput(f"{path}: no beamforming record with {m} receive chains ({len(records)} records)")
    try:
        calibration = estimate_offsets(
            records.csi[usable, :, :m, 0], rig.antenna_positions_m, channel, math.radians(angle_deg)
        )
    except BadInput as exc:
        raise BadInput(f"{path}: {exc}") from None
    return path.name, calibration


def _calibrate_dataset(path: Path, rig: Rig | None) -> list[tuple[str, Calibration]]:
    """A dataset's /csi frames with the true angle of each (/groundtruth/aoa, matched by stamp), per channel."""
    import numpy as np

    from rover.errors import SpecError
    from rover.formats.bag import BagReader
    from rover.formats.intel5300 import decode_bfee
    from rover.formats.rig import rig_from_text
    from rover.messages import stamp_ns
    from rover.operators.aoa.calibration import estimate_offsets

    frames: list[tuple[int, int, bytes]] = []
    truth: dict[int, list[tuple[int, float]]] = {}
    with BagReader(path, "not a readable MCAP dataset") as bag:
        setup = bag.metadata().get("rover.setup", {}).get("yaml")
        for message in bag.messages(["/csi", "/groundtruth/aoa"]):
            if message.topic == "/csi":
                frame = bag.decode(message, "rover_msgs/msg/CsiFrame")
                frames.append((stamp_ns(frame), int(frame.channel), bytes(frame.bfee)))
            else:
                aoa = bag.decode(message, "rover_msgs/msg/Aoa")
                truth.setdefault(stamp_ns(aoa), []).append((int(aoa.channel), float(aoa.angle_rad)))
    if not truth:
        raise BadInput(f"{path}: no ground-truth angles (/groundtruth/aoa); a CSI log with --angle-deg instead?")
    if not frames:
        raise BadInput(f"{path}: no CSI frames (/csi)")
    if rig is None:
        if setup is None:
            raise BadInput(f"{path}: no rig description (rover.setup metadata): pass --setup RIG.yaml")
        try:
            rig = rig_from_text(setup, f"{path} (rover.setup)")
        except SpecError as exc:
            raise BadInput(str(exc.diagnostics[0])) from None
    index, channel_of, angle_of = [], [], []
    for k, (stamp, channel, _) in enumerate(frames):
        match = [(c, a) for c, a in truth.get(stamp, []) if channel in (0, c)]
        if len(match) == 1 and (channel or match[0][0]):
            index.append(k)
            channel_of.append(channel or match[0][0])
            angle_of.append(match[0][1])
    if not index:
        raise BadInput(f"{path}: no /csi frame has a /groundtruth/aoa angle with its stamp and channel")
    records = decode_bfee([frames[k][2] for k in index])
    m = len(rig.antenna_positions_m)
    rows = records.offset[records.nrx == m]
    channels, angles = np.array(channel_of)[rows], np.array(angle_of)[rows]
    csi = records.csi[records.nrx == m, :, :m, 0]
    if not len(rows):
        raise BadInput(f"{path}: no CSI frame with {m} receive chains and a ground-truth angle")
    out = []
    for channel in np.unique(channels):
        mine = channels == channel
        try:
            calibration = estimate_offsets(csi[mine], rig.antenna_positions_m, int(channel), angles[mine])
        except BadInput as exc:
            raise BadInput(f"{path}: {exc}") from None
        out.append((path.name, calibration))
    return out


def _degrees(text: str) -> float:
    """--angle-deg: a finite number of degrees."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"a number of degrees, got {text!r}")
    return value


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


def _burst(text: str) -> int:
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
    p.add_argument(
        "--view",
        nargs="?",
        const=8765,
        type=int,
        metavar="PORT",
        help="also serve a live view to Foxglove on ws://127.0.0.1:PORT (default 8765; 0: any free port); "
        "--set view.host=0.0.0.0 listens on every interface",
    )
    _add_set(p)
    p.set_defaults(func=cmd_run)

    p = command("record", help="run a live pipeline (or one host's share) and write the session as a dataset")
    p.add_argument("pipeline", metavar="PIPELINE", help="a pipeline with a dataset_recorder operator")
    p.add_argument("--host", help="run only this host's operators (the dataset_recorder's host)")
    p.add_argument("-o", dest="record_to", metavar="DATASET.mcap", required=True, help="the dataset to write")
    p.add_argument("--force", action="store_true", help="replace an existing dataset")
    p.add_argument("--output", help="same as --set output=DIR (the run's own results)")
    _add_set(p)
    p.set_defaults(func=cmd_record)

    p = command("check", help="validate pipeline and setup files; report every problem as FILE:LINE:COL")
    p.add_argument("files", nargs="+", metavar="FILE")
    p.add_argument(
        "--host", help="under security:, check only this host's (or the monitor's) certificate and key, and the CA"
    )
    p.add_argument("--security", action="store_true", help="also print the access rules generated from the wiring")
    _add_set(p)
    p.set_defaults(func=cmd_check)

    p = command("certs", help="a CA and per-host certificates for a pipeline's security: section")
    p.add_argument("pipeline", nargs="?", help="take host names and addresses from this pipeline's endpoints")
    p.add_argument("--hosts", help="comma-separated host names (default: the pipeline's hosts)")
    p.add_argument("--monitor", action="store_true", help="also a read-only identity for rover status")
    p.add_argument(
        "--names",
        action="append",
        metavar="HOST=DNS_OR_IP,...",
        help="the names a host is reached at (replace those taken from the pipeline); repeat HOST= for several",
    )
    p.add_argument(
        "--days", type=int, default=365, help="lifetime of the host certificates (default 365, at most 1825)"
    )
    p.add_argument("-o", "--output", required=True, help="the folder to write into")
    p.add_argument("--force", action="store_true", help="replace existing certificates in the folder")
    _add_set(p)
    p.set_defaults(func=cmd_certs)

    p = command("graph", help="print the pipeline as Mermaid (default) or DOT")
    p.add_argument("pipeline", nargs="?", help="pipeline file (default: the one shipped with rover)")
    p.add_argument("--format", choices=("mermaid", "dot"), default="mermaid")
    _add_set(p)
    p.set_defaults(func=cmd_graph)

    p = command("status", help="live state of a running multi-host pipeline: hosts, rates, queues, lag, errors")
    p.add_argument("pipeline", metavar="PIPELINE", help="the pipeline file the hosts run")
    _add_set(p)
    p.add_argument(
        "--connect", action="append", metavar="ENDPOINT", help="ask through this endpoint (default: the hosts' listen)"
    )
    p.add_argument("--once", action="store_true", help="print one table (rates over --interval) and exit")
    p.add_argument("--interval", type=float, default=1.0, help="seconds between refreshes (default 1)")
    p.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for a host to answer (default 5)")
    p.add_argument("--json", action="store_true", help="print JSON (a line per refresh) instead of the table")
    p.set_defaults(func=cmd_status)

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

    p = command("calibrate", help="per-chain phase offsets from CSI at a known angle, as a setup.yaml block")
    p.add_argument(
        "sources", nargs="+", metavar="INPUT", help="CSI Tool logs (.dat) or datasets with ground truth (.mcap)"
    )
    p.add_argument("--setup", help="rig file with the antenna positions (default for a dataset: its own)")
    p.add_argument(
        "--angle-deg", type=_degrees, action="append", help="a log's transmitter angle, robot frame (once, or per log)"
    )
    p.add_argument("--channel", type=int, action="append", help="the channel a log was recorded on (once, or per log)")
    p.add_argument("--out", help="also write the receiver.phase_offsets_rad block to this YAML file")
    p.add_argument("--force", action="store_true", help="replace an existing --out file")
    p.set_defaults(func=cmd_calibrate)

    p = command("aoa", help="angles of arrival from a bare CSI Tool log (no robot): every candidate per burst")
    p.add_argument("log", metavar="LOG.dat", help="a CSI Tool log (log_to_file output)")
    p.add_argument("--setup", required=True, help="rig file: the receiver's antennas (and channel, calibration)")
    p.add_argument("--calibration", help="a `rover calibrate --out` file: its phase offsets replace the setup's")
    p.add_argument("--channel", type=int, help="the channel the log was recorded on (default: receiver.channel)")
    p.add_argument("--burst", type=_burst, default=50, help="packets per burst (default 50, at least 3)")
    p.add_argument("--csv", help="also write the rows to this CSV file")
    p.add_argument("--force", action="store_true", help="replace an existing --csv file")
    p.set_defaults(func=cmd_aoa)

    p = command("info", help="what a dataset holds, like `ros2 bag info`")
    p.add_argument("path")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.set_defaults(func=cmd_info)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    level = logging.ERROR if args.quiet else (logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)]
    logging.basicConfig(level=level, format="rover: %(levelname)s: %(message)s")
    if os.environ.get("RUST_LOG"):  # Zenoh's own log, e.g. its access-control decisions (docs/security.md)
        import zenoh

        zenoh.init_log_from_env_or("error")
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
    except PeerLost as exc:
        print(f"rover: error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_PARTIAL
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
