"""`rover status`: the live state of a running pipeline, from its hosts' (or worker processes') status queryables."""

from __future__ import annotations

import argparse
import math
import sys
from typing import IO, Any

from rover.cli.args import add_set, overrides
from rover.errors import BadInput, SpecError

PIPED_WIDTH = 1000
"""columns of `rover status --once` written to a pipe or file (rich would cut it to 80)"""


def show(renderable: Any, file: IO[str] | None = None) -> None:
    """Print a table to the terminal at its width, or to a pipe or file whole."""
    from rich.console import Console

    console = Console(file=file)
    if not console.is_terminal:
        console = Console(file=file, width=PIPED_WIDTH)
    console.print(renderable)


def add_parser(sub: Any, common: argparse.ArgumentParser) -> None:
    """`rover status` and its options."""
    p = sub.add_parser(
        "status",
        parents=[common],
        help="live state of a running pipeline's hosts (or worker processes): rates, queues, lag, errors",
    )
    p.add_argument("pipeline", metavar="PIPELINE", help="the pipeline file the hosts run")
    add_set(p)
    p.add_argument(
        "--connect", action="append", metavar="ENDPOINT", help="ask through this endpoint (default: the hosts' listen)"
    )
    p.add_argument("--once", action="store_true", help="print one table (rates over --interval) and exit")
    p.add_argument("--interval", type=float, default=1.0, help="seconds between refreshes (default 1)")
    p.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for a host to answer (default 5)")
    p.add_argument("--json", action="store_true", help="print JSON (a line per refresh) instead of the table")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Live state of a running multi-host pipeline, from its hosts' status queryables. The file is
    only parsed (not checked against the operator classes): a monitoring machine needs no operator code."""
    import json
    import time

    from rich.live import Live

    from rover.pipeline.spec import endpoint_problem, parse, read_document
    from rover.runtime.status import HostStatus, render, report
    from rover.runtime.workers import running_plans
    from rover.transport.monitor import StatusClient, local_endpoint

    for option, value in (("--interval", args.interval), ("--timeout", args.timeout)):
        if not 0 < value < math.inf:
            raise BadInput(f"{option}: a number of seconds above 0, got {value:g}")
    spec, problems = parse(read_document(args.pipeline), overrides(args))
    if problems:
        raise SpecError(problems)
    for endpoint in args.connect or []:
        if problem := endpoint_problem(endpoint):
            raise BadInput(f"--connect: {problem}")
    listen = [local_endpoint(ep) for host in spec.hosts.values() for ep in host.listen]
    endpoints = list(dict.fromkeys(args.connect or listen))
    expected = sorted({op.host for op in spec.operators.values() if op.host})
    local = [] if args.connect else running_plans(spec.name)
    if len(local) > 1:
        hubs = ", ".join(plan.hub for plan in local)
        raise BadInput(
            f"{len(local)} runs of pipeline {spec.name} over workers on this machine: pass --connect (one of {hubs})"
        )
    if local:  # a run of the whole pipeline over worker processes here: its workers are the hosts
        endpoints, expected = [local[0].hub], local[0].hosts
    if not endpoints:
        raise BadInput(f"{args.pipeline}: no host of pipeline {spec.name} listens on an endpoint: pass --connect")
    tls = None
    if spec.security is not None and not local:
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
                show(render(current, previous, expected, notes, client.clocks.best()))
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
