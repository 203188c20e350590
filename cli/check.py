"""`rover check`: pipeline and setup files validated; every problem as FILE:LINE:COL."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from rover.cli.args import EXIT_BAD_INPUT, add_set, overrides
from rover.cli.registry import BUILTINS
from rover.errors import BadInput, SpecError


def add_parser(sub: Any, common: argparse.ArgumentParser) -> None:
    """`rover check` and its options."""
    p = sub.add_parser(
        "check", parents=[common], help="validate pipeline and setup files; report every problem as FILE:LINE:COL"
    )
    p.add_argument("files", nargs="+", metavar="FILE")
    p.add_argument(
        "--host", help="under security:, check only this host's (or the monitor's) certificate and key, and the CA"
    )
    p.add_argument("--security", action="store_true", help="also print the access rules generated from the wiring")
    add_set(p)
    p.set_defaults(func=run)


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


def run(args: argparse.Namespace) -> int:
    problems: list[str] = []
    for file in args.files:
        try:
            summary, warnings = _check_one(file, overrides(args), args.host, args.security)
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
