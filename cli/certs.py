"""`rover certs`: a CA and one certificate per host for a pipeline's security: section."""

from __future__ import annotations

import argparse
from typing import Any

from rover.cli.args import add_set, overrides
from rover.errors import BadInput, SpecError


def add_parser(sub: Any, common: argparse.ArgumentParser) -> None:
    """`rover certs` and its options."""
    p = sub.add_parser(
        "certs", parents=[common], help="a CA and per-host certificates for a pipeline's security: section"
    )
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
    add_set(p)
    p.set_defaults(func=run)


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


def run(args: argparse.Namespace) -> int:
    """Issue a CA and one certificate per host (and the monitor) into a folder; print the
    security: section that uses them."""
    from rover.pipeline.spec import MONITOR, NAME_RE, did_you_mean, parse, read_document
    from rover.pipeline.validation import listens_on_wildcard, served_addresses
    from rover.security.certs import issue

    spec = None
    if args.pipeline:
        values = overrides(args, flags=())  # its -o is the certificates' folder, not ${output}
        spec, problems = parse(read_document(args.pipeline), values)
        if problems:
            raise SpecError(problems)
    hosts = [h.strip() for h in args.hosts.split(",") if h.strip()] if args.hosts else list(spec.hosts if spec else [])
    if not hosts:
        raise BadInput("rover certs: name the hosts (--hosts nuc,base,laptop) or give a pipeline with hosts:")
    for host in hosts:
        if not NAME_RE.match(host) or host == MONITOR:
            raise BadInput(f"--hosts: {host!r} is not a host name (letters, digits, _ or -; {MONITOR!r} is reserved)")
        if spec is not None and host not in spec.hosts:
            raise BadInput(
                f"--hosts: {args.pipeline} declares no host {host!r}{did_you_mean(host, spec.hosts)} "
                f"(hosts: {', '.join(spec.hosts) or 'none'}): a certificate for it would serve no host of the pipeline"
            )
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
