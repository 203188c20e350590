"""Checking a pipeline against its operators: every problem at once, each with file:line:col.

The result of a clean check is a `Pipeline`: the spec with operator classes, typed params and
the message type of every wire resolved, which is all the runtime needs.
"""

from __future__ import annotations

import hashlib
import ipaddress
import json
from collections.abc import Collection, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rover.errors import Diagnostic, SpecError
from rover.messages import ANY
from rover.operator import In, Operator, Ports, RunContext, Source
from rover.pipeline import params as P
from rover.pipeline.resolve import UnknownOperator, resolve
from rover.pipeline.spec import OperatorSpec, PipelineSpec, Wire, did_you_mean, parse, read_document
from rover.pipeline.yamlpos import Located


@dataclass
class Node:
    """One operator of a checked pipeline."""

    spec: OperatorSpec
    cls: type[Operator]
    params: Any
    context: RunContext = RunContext()
    ports: Ports = field(default_factory=lambda: Ports({}, {}))
    """the operator's ports with these params (`Operator.declared_ports`)"""
    local: bool = False
    """added by this process's command line (`rover run --view`), not by the file: the other hosts
    do not know it, so it is left out of the digest (and reads only outputs of its own host)"""

    @property
    def name(self) -> str:
        return self.spec.name

    def input_type(self, port: str) -> str:
        spec = self.ports.input_spec(port)
        return spec.type if spec else ANY

    def output_type(self, port: str) -> str:
        return self.ports.outputs[port].type

    def build(self) -> Operator:
        op = self.cls(self.params)
        op.context = self.context
        return op


@dataclass
class Pipeline:
    """A pipeline that passed every check."""

    spec: PipelineSpec
    nodes: dict[str, Node]

    @property
    def name(self) -> str:
        return self.spec.name

    def hosts_in_use(self) -> list[str]:
        return sorted({n.spec.host for n in self.nodes.values() if n.spec.host})

    def digest(self) -> str:
        """A short hash of the run's structure (name, hosts, placement, wiring): the hosts of one run
        agree on it whatever their own variables (each has its own output folder, dataset path...)
        and whatever local nodes each added."""
        structure = [
            self.name,
            sorted(self.spec.hosts),
            [
                [
                    n.name,
                    n.spec.uses,
                    n.spec.host,
                    sorted((p, w.text) for p, w in n.spec.inputs.items()),
                    sorted((p, o.type) for p, o in n.ports.outputs.items()),  # params may name them
                ]
                for n in sorted(self.nodes.values(), key=lambda n: n.name)
                if not n.local
            ],
        ]
        return hashlib.sha256(json.dumps(structure).encode()).hexdigest()[:16]

    def consumers(self, source: str, port: str) -> list[tuple[Node, Wire]]:
        return [
            (n, w)
            for n in self.nodes.values()
            for w in n.spec.inputs.values()
            if w.source == source and w.source_port == port
        ]

    def hubs(self) -> dict[str, list[str]]:
        """Hosts whose loss cuts others apart: hub -> the hosts that would no longer reach each other."""
        links = host_links(self.spec)
        hubs = {}
        for hub in links:
            cut = {h for me in links if me != hub for h in unreachable_without(links, me, hub)}
            if cut:
                hubs[hub] = sorted(cut)
        return hubs

    def summary(self) -> str:
        wires = sum(len(n.spec.inputs) for n in self.nodes.values())
        hosts = self.hosts_in_use()
        where = f"on {len(hosts)} hosts ({', '.join(hosts)})" if hosts else "in one process"
        text = f"{self.spec.file}: ok: pipeline {self.name!r}, {len(self.nodes)} operators, {wires} wires, {where}"
        for hub, cut in sorted(self.hubs().items()):
            text += f"; hub {hub}: {' and '.join(cut)} reach each other only through it"
        return text


def _params(doc: Located, spec: OperatorSpec, cls: type[Operator], problems: list[Diagnostic]) -> Any:
    base = ("operators", spec.name, "params")
    wording = P.Wording(
        unknown=lambda key: f"operator {spec.name!r} ({spec.uses}) has no param {key!r}",
        ill_typed=lambda key: f"param {key!r} of operator {spec.name!r}",
        missing=lambda key, label: f"operator {spec.name!r} ({spec.uses}) needs param {key!r} ({label})",
        known_list=True,
    )

    def report(path: tuple[Any, ...], message: str, at_key: bool) -> None:
        if path and path[0] in spec.set_params:
            message = f"--set {spec.name}.{path[0]}={spec.set_params[path[0]]!r}: {message}"
            in_file = base + path[:1] in doc.keys
            problems.append(doc.diag(base + path[:1] if in_file else ("operators", spec.name), message, key=True))
            return
        problems.append(doc.diag(base + path if path else ("operators", spec.name), message, key=at_key))

    return P.bind(cls.Params, spec.params, wording, report)


def _ports(doc: Located, spec: OperatorSpec, cls: type[Operator], params: Any, problems: list[Diagnostic]) -> Ports:
    """The operator's ports with its params; the class's own when the params could not be bound."""
    if params is None:  # the params' own problems are reported; ports they would name are unknown
        named_by_params = any("declared_ports" in vars(c) for c in cls.__mro__ if c is not Operator)
        return Ports(cls.inputs, cls.outputs, cls.variadic, known=not named_by_params)
    where = ("operators", spec.name, "params")
    try:
        ports = cls.declared_ports(params)
    except ValueError as exc:
        problems.append(doc.diag(where, f"operator {spec.name!r} ({spec.uses}): {exc}", key=True))
        return Ports({}, {}, known=False)
    for problem in ports.problems():
        problems.append(doc.diag(where, f"operator {spec.name!r} ({spec.uses}) declares {problem}", key=True))
    return ports


def _check_ports(
    doc: Located, nodes: dict[str, Node], specs: dict[str, OperatorSpec], problems: list[Diagnostic]
) -> None:
    for node in nodes.values():
        base = ("operators", node.name, "inputs")
        cls, ports = node.cls, node.ports
        for port, wire in node.spec.inputs.items() if ports.known else ():
            spec_in: In | None = ports.input_spec(port)
            if spec_in is None:
                known = ", ".join(ports.inputs) or "none"
                problems.append(
                    doc.diag(
                        base + (port,),
                        f"operator {node.name!r} ({node.spec.uses}) has no input "
                        f"{port!r}{did_you_mean(port, ports.inputs)} (inputs: {known})",
                        key=True,
                    )
                )
                continue
            if wire.source not in specs:
                problems.append(
                    doc.diag(
                        base + (port,),
                        f"input {port!r} is wired to unknown operator "
                        f"{wire.source!r}{did_you_mean(wire.source, specs)}",
                    )
                )
                continue
            source = nodes.get(wire.source)
            if source is None or not source.ports.known:
                continue
            if wire.source_port not in source.ports.outputs:
                known = ", ".join(source.ports.outputs) or "none"
                problems.append(
                    doc.diag(
                        base + (port,),
                        f"operator {wire.source!r} ({source.spec.uses}) has no output "
                        f"{wire.source_port!r}{did_you_mean(wire.source_port, source.ports.outputs)} "
                        f"(outputs: {known})",
                    )
                )
                continue
            out_type = source.output_type(wire.source_port)
            if spec_in.type not in (ANY, out_type):
                problems.append(
                    doc.diag(
                        base + (port,),
                        f"message type mismatch: {wire.text} sends {out_type} but "
                        f"input {port!r} of {node.name!r} takes {spec_in.type}",
                    )
                )
        for port, spec_in in ports.inputs.items() if ports.known else ():
            if spec_in.required and port not in node.spec.inputs:
                problems.append(
                    doc.diag(
                        ("operators", node.name),
                        f"required input {port!r} ({spec_in.type}) of operator {node.name!r} is not wired",
                        key=True,
                    )
                )
        if issubclass(cls, Source) and node.spec.inputs:
            problems.append(
                doc.diag(base, f"operator {node.name!r} ({node.spec.uses}) is a source and takes no inputs", key=True)
            )


def _check_cycles(doc: Located, specs: dict[str, OperatorSpec], problems: list[Diagnostic]) -> None:
    """Depth-first search along inputs, with an explicit stack: a chain of thousands of operators
    listed downstream-first is as deep as it is long, too deep for recursion."""
    WHITE, GREY, BLACK = 0, 1, 2
    state = {name: WHITE for name in specs}
    for start in specs:
        if state[start] != WHITE:
            continue
        state[start] = GREY
        path = [start]
        position = {start: 0}
        pending = [iter(specs[start].inputs.values())]
        while pending:
            name = path[-1]
            wire = next(pending[-1], None)
            if wire is None:
                pending.pop()
                del position[path.pop()]
                state[name] = BLACK
                continue
            if wire.source not in specs:
                continue
            if state[wire.source] == GREY:
                loop = path[position[wire.source] :] + [wire.source]
                problems.append(
                    doc.diag(
                        ("operators", name, "inputs", wire.port),
                        f"cycle: {' <- '.join(loop)} (a pipeline must be acyclic)",
                    )
                )
            elif state[wire.source] == WHITE:
                state[wire.source] = GREY
                position[wire.source] = len(path)
                path.append(wire.source)
                pending.append(iter(specs[wire.source].inputs.values()))


def _endpoint_parts(endpoint: str) -> tuple[str, str, str]:
    proto, _, address = endpoint.partition("/")
    address = address.split("#", 1)[0]
    host, _, port = address.rpartition(":")
    return proto, host.strip("[]"), port


def _is_wildcard(host: str) -> bool:
    return host in ("0.0.0.0", "::", "")


def is_ip(host: str) -> bool:
    """Whether `host` is an IP address (else a DNS name)."""
    try:
        ipaddress.ip_address(host)
        return True
    except ValueError:
        return False


def _reaches(connect: str, listen: str) -> bool:
    """Whether a connect endpoint can be the same socket as a listen endpoint (names are not resolved)."""
    cp, ch, cport = _endpoint_parts(connect)
    lp, lh, lport = _endpoint_parts(listen)
    if cp != lp or cport != lport:
        return False
    return ch == lh or _is_wildcard(lh) or not is_ip(ch) or not is_ip(lh)


def _listeners(spec: PipelineSpec, host: str, endpoint: str) -> list[str]:
    """The other hosts that listen where `host` connects with `endpoint`."""
    return [b.name for b in spec.hosts.values() if b.name != host and any(_reaches(endpoint, lep) for lep in b.listen)]


def unreachable_without(links: Mapping[str, Collection[str]], me: str, gone: str) -> set[str]:
    """The hosts `me` can no longer reach once `gone` is gone (`gone` itself not included)."""
    seen, todo = {me, gone}, [me]
    while todo:
        for other in links.get(todo.pop(), ()):
            if other not in seen:
                seen.add(other)
                todo.append(other)
    return set(links) - seen


def served_addresses(spec: PipelineSpec, host: str) -> list[tuple[str, str]]:
    """The addresses TLS checks `host`'s certificate against, each with why: where it listens (but a
    wildcard) and where the others connect to it. A connect endpoint that several hosts may serve
    (a DNS name on a port several listen on) is left out: names are not resolved here."""
    out = []
    for ep in spec.hosts[host].listen:
        address = _endpoint_parts(ep)[1]
        if not _is_wildcard(address):
            out.append((address, f"{host} listens on {ep}"))
    for other in spec.hosts.values():
        for ep in other.connect if other.name != host else ():
            if _listeners(spec, other.name, ep) == [host]:
                out.append((_endpoint_parts(ep)[1], f"{other.name} connects to {ep}"))
    return list(dict.fromkeys(out))


def listens_on_wildcard(spec: PipelineSpec, host: str) -> bool:
    return any(_is_wildcard(_endpoint_parts(ep)[1]) for ep in spec.hosts[host].listen)


def host_links(spec: PipelineSpec) -> dict[str, set[str]]:
    """Which hosts talk to each other directly: one connects where the other listens."""
    links: dict[str, set[str]] = {h: set() for h in spec.hosts}
    for a in spec.hosts.values():
        for ep in a.connect:
            for b in _listeners(spec, a.name, ep):
                links[a.name].add(b)
                links[b].add(a.name)
    return links


def place_with_inputs(spec: PipelineSpec) -> dict[str, str]:
    """Put each operator without `host:` on the host its inputs come from, when they all come from
    one (through other such operators too): an operator added to a multi-host pipeline runs beside
    what feeds it, as written, without a host of its own. Returns the placements made."""
    placed: dict[str, str] = {}
    if not spec.hosts:
        return placed
    changed = True
    while changed:
        changed = False
        for op in spec.operators.values():
            if op.host is not None or not op.inputs:
                continue
            sources = {spec.operators[w.source].host for w in op.inputs.values() if w.source in spec.operators}
            (host,) = sources if len(sources) == 1 else (None,)
            if host is not None:
                op.host = placed[op.name] = host
                changed = True
    return placed


def _check_hosts(doc: Located, spec: PipelineSpec, problems: list[Diagnostic]) -> None:
    hosts = spec.hosts
    place_with_inputs(spec)
    for op in spec.operators.values():
        path = ("operators", op.name, "host")
        if op.host is None:
            if hosts:
                sources = sorted(
                    {str(spec.operators[w.source].host) for w in op.inputs.values() if w.source in spec.operators}
                )
                why = f"; its inputs come from several ({', '.join(sources)})" if len(sources) > 1 else ""
                problems.append(
                    doc.diag(
                        ("operators", op.name),
                        f"operator {op.name!r} has no host: (hosts: {', '.join(hosts)}){why}",
                        key=True,
                    )
                )
        elif op.host not in hosts:
            declared = f" (hosts: {', '.join(hosts)})" if hosts else " (the file declares no hosts:)"
            problems.append(
                doc.diag(
                    path,
                    f"operator {op.name!r} is placed on undeclared host "
                    f"{op.host!r}{did_you_mean(op.host, hosts)}{declared}",
                )
            )
    if spec.security is None and not (isinstance(doc.data, dict) and "security" in doc.data):
        for host in hosts.values():  # without certificates Zenoh cannot open tls/ or quic/ links
            for kind in ("listen", "connect"):
                for i, ep in enumerate(getattr(host, kind)):
                    if ep.startswith(("tls/", "quic/")):
                        problems.append(
                            doc.diag(
                                ("hosts", host.name, kind, i),
                                f"{ep}: {ep.partition('/')[0]}/ needs certificates: add a security: section "
                                "(rover certs makes them) and use tls/ endpoints",
                            )
                        )
    if len(hosts) < 2:
        return
    for a in hosts.values():
        raw = (doc.data.get("hosts") or {}).get(a.name) or {}
        if not a.listen and not a.connect and not ({"listen", "connect"} & set(raw)):
            problems.append(
                doc.diag(
                    ("hosts", a.name),
                    f"host {a.name!r} has neither listen nor connect endpoints, so no other host can reach it",
                    key=True,
                )
            )
        for i, ep in enumerate(a.connect):
            reached = _listeners(spec, a.name, ep)
            if not reached:
                problems.append(
                    doc.diag(
                        ("hosts", a.name, "connect", i),
                        f"host {a.name!r} connects to {ep}, where no declared host listens",
                    )
                )
            elif len(reached) > 1 and spec.security is not None:
                problems.append(
                    doc.diag(
                        ("hosts", a.name, "connect", i),
                        f"host {a.name!r} connects to {ep}, which could be {' or '.join(reached)} (names are not "
                        "resolved, a wildcard listens everywhere): under security: the access rules follow the "
                        "links, so connect to the exact address one host listens on, or give each host its own port",
                    )
                )
    links = host_links(spec)
    seen, todo = set(), [next(iter(hosts))]
    while todo:
        h = todo.pop()
        if h not in seen:
            seen.add(h)
            todo.extend(links[h] - seen)
    for h in hosts:
        if h not in seen and (hosts[h].listen or hosts[h].connect):
            problems.append(
                doc.diag(
                    ("hosts", h),
                    f"host {h!r} has no connect path to host {next(iter(hosts))!r} "
                    "(connect to an endpoint another host listens on)",
                    key=True,
                )
            )


def check(
    spec: PipelineSpec,
    builtins: Mapping[str, str],
    problems: list[Diagnostic] | None = None,
    local: Collection[str] = (),
) -> Pipeline:
    """Resolve operators (short names through `builtins`), params and wires; raise SpecError with every problem.
    `local` names the operators this process added to the file's (`Node.local`)."""
    problems = list(problems or [])
    doc = spec.doc
    nodes: dict[str, Node] = {}
    context = RunContext(spec.file, spec.name, spec.command_line())
    for op in spec.operators.values():
        try:
            cls = resolve(op.uses, builtins)
        except UnknownOperator as exc:
            hint = did_you_mean(op.uses, builtins) if "." not in op.uses else ""
            problems.append(doc.diag(("operators", op.name, "uses"), f"{exc}{hint}"))
            continue
        params = _params(doc, op, cls, problems)
        nodes[op.name] = Node(op, cls, params, context, _ports(doc, op, cls, params, problems), op.name in local)
    _check_ports(doc, nodes, spec.operators, problems)
    _check_cycles(doc, spec.operators, problems)
    _check_hosts(doc, spec, problems)
    _check_local(spec, local, problems)
    if problems:
        raise SpecError(problems)
    return Pipeline(spec, nodes)


def _check_local(spec: PipelineSpec, local: Collection[str], problems: list[Diagnostic]) -> None:
    """A local node reads only outputs of its own host: no traffic between hosts, so neither the
    digest nor the access rules (`rover.security.acl.flows`, which come from such traffic) change."""
    for op in (spec.operators[name] for name in local if name in spec.operators):
        for wire in op.inputs.values():
            source = spec.operators.get(wire.source)
            if source is not None and source.host and op.host and source.host != op.host:
                problems.append(
                    spec.doc.diag(
                        ("operators",),
                        f"operator {op.name!r} (added on host {op.host} by the command line) cannot read "
                        f"{wire.text}: it is produced on host {source.host}",
                        key=True,
                    )
                )


def load_and_check(path: str | Path, builtins: Mapping[str, str], overrides: dict[str, Any] | None = None) -> Pipeline:
    """Read, parse and check a pipeline file in one go (what `rover check` and `rover run` do)."""
    spec, problems = parse(read_document(path), overrides)
    return check(spec, builtins, problems)
