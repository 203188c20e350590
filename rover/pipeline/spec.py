"""The pipeline file: its shape, `${var}` substitution, and the dataclasses the runtime reads.

Structural problems (unknown keys, wrong value kinds, bad names, undefined variables) are
collected here; what needs the operator classes is checked in `rover.pipeline.validation`.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from difflib import get_close_matches
from pathlib import Path
from typing import Annotated, Any

from rover.errors import BadInput, Diagnostic
from rover.pipeline import params as P
from rover.pipeline.yamlpos import MAX_YAML_BYTES, Located, load, size_error

NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_-]*$")
VAR_RE = re.compile(r"\$\{([^}]*)\}")
ENDPOINT_RE = re.compile(
    r"^(?:(?:tcp|udp|tls|quic|ws)/(?:\[[0-9A-Fa-f:.]+\]|[^/:\[\]]+):\d{1,5}|unixsock-stream/.+)(?:#.*)?$"
)

PORT_RE = re.compile(r":(\d{1,5})$")
MAX_PORT = 65535

TOP_KEYS = ("version", "name", "description", "vars", "workers", "hosts", "security", "operators")
SECURITY_KEYS = ("ca", "hosts", "monitor")
IDENTITY_KEYS = ("cert", "key")
MONITOR = "monitor"
"""The read-only identity of `rover status` (a reserved host name under security:)."""
HOST_KEYS = ("listen", "connect", "host_timeout_s", "wait_timeout_s", "connect_timeout_s")
OPERATOR_KEYS = ("uses", "host", "process", "inputs", "params", "description", "inbox")
DEFAULT_INBOX = 1024
"""Data messages per operator inbox (its memory bound: about that many messages of its inputs)."""
HostTimeout = Annotated[float, P.Range(ge=1.0, le=3600.0)]
"""A lease below 1 s breaks on ordinary hiccups; above an hour a lost host is never noticed in practice."""
DEFAULT_HOST_TIMEOUT_S = 15.0
"""A host unreachable this long is lost (the run goes on without it: partial results)."""
DEFAULT_WAIT_TIMEOUT_S = 120.0
"""How long a host waits for the others to start (and retries its connections) before giving up."""
AUTO_WORKERS = "auto"
"""`workers: auto`: a worker process per available core."""


def endpoint_problem(endpoint: Any) -> str | None:
    """Why `endpoint` is not a Zenoh endpoint Rover can use, or None."""
    example = "expected PROTOCOL/ADDRESS:PORT, e.g. 'tcp/127.0.0.1:7447'"
    if not (isinstance(endpoint, str) and ENDPOINT_RE.match(endpoint)):
        return f"bad endpoint {endpoint!r}: {example}"
    port = PORT_RE.search(endpoint.split("#")[0])
    if port and not 1 <= int(port.group(1)) <= MAX_PORT:
        return f"bad endpoint {endpoint!r}: port {int(port.group(1))} is outside 1-{MAX_PORT}"
    return None


def did_you_mean(word: str, candidates: Any) -> str:
    match = get_close_matches(str(word), [str(c) for c in candidates], n=1, cutoff=0.6)
    return f"; did you mean {match[0]!r}?" if match else ""


@dataclass(frozen=True)
class Wire:
    """An input port fed by another operator's output port."""

    port: str
    source: str
    source_port: str

    @property
    def text(self) -> str:
        return f"{self.source}/{self.source_port}"


@dataclass
class HostSpec:
    name: str
    listen: list[str] = field(default_factory=list)
    connect: list[str] = field(default_factory=list)
    host_timeout_s: float = DEFAULT_HOST_TIMEOUT_S
    wait_timeout_s: float = DEFAULT_WAIT_TIMEOUT_S


@dataclass(frozen=True)
class Identity:
    """A certificate and its private key (PEM files), as the pipeline names them."""

    cert: str
    key: str


@dataclass
class SecuritySpec:
    """Mutual TLS between the hosts: the CA every certificate is checked against, and one identity
    per host (its certificate's common name is the host's name), plus the optional monitor's."""

    ca: str
    hosts: dict[str, Identity] = field(default_factory=dict)
    monitor: Identity | None = None


@dataclass
class OperatorSpec:
    name: str
    uses: str
    host: str | None = None
    process: str | None = None
    """operators with one `process:` name run in one worker process (rover.runtime.workers)"""
    inbox: int = DEFAULT_INBOX
    """data messages the operator's inbox holds before its producers wait (or a live source's oldest go)"""
    inputs: dict[str, Wire] = field(default_factory=dict)
    params: dict[str, Any] = field(default_factory=dict)
    set_params: dict[str, Any] = field(default_factory=dict)
    """params given on the command line (`--set OPERATOR.PARAM=VALUE`), already merged into `params`"""


@dataclass
class PipelineSpec:
    """A loaded pipeline file with variables substituted; `doc` keeps source positions."""

    file: str
    name: str
    vars: dict[str, Any]
    hosts: dict[str, HostSpec]
    operators: dict[str, OperatorSpec]
    doc: Located
    set_vars: dict[str, Any] = field(default_factory=dict)
    """variables given on the command line (`--set NAME=VALUE`, `--dataset`, `--output`, `--speed`)"""
    security: SecuritySpec | None = None
    workers: int | str = AUTO_WORKERS
    """worker processes of a run of the whole pipeline: a count, or `auto` (one per core)"""

    def command_line(self) -> dict[str, Any]:
        """What the command line changed: `{"vars": {...}, "params": {"OPERATOR.PARAM": value}}`, for run.json."""
        params = {f"{op.name}.{k}": v for op in self.operators.values() for k, v in op.set_params.items()}
        return {"vars": dict(self.set_vars), "params": params}

    def operators_on(self, host: str | None) -> list[OperatorSpec]:
        return [op for op in self.operators.values() if host is None or op.host == host]


class _Collector:
    def __init__(self, doc: Located):
        self.doc = doc
        self.problems: list[Diagnostic] = []

    def add(self, path: tuple[Any, ...], message: str, *, key: bool = False) -> None:
        self.problems.append(self.doc.diag(path, message, key=key))

    def mapping(self, value: Any, path: tuple[Any, ...], what: str) -> dict[Any, Any]:
        if value is None:
            return {}
        if not isinstance(value, dict):
            self.add(path, f"{what} must be a mapping")
            return {}
        return value

    def known_keys(self, value: dict[Any, Any], path: tuple[Any, ...], allowed: tuple[str, ...], what: str) -> None:
        for key in value:
            if key not in allowed:
                self.add(path + (key,), f"unknown key {key!r} in {what}{did_you_mean(key, allowed)}", key=True)

    def string(self, value: Any, path: tuple[Any, ...], what: str) -> str | None:
        if isinstance(value, str) and value:
            return value
        self.add(path, f"{what} must be a non-empty string")
        return None


def _substitute(value: Any, path: tuple[Any, ...], variables: dict[str, Any], col: _Collector) -> Any:
    if isinstance(value, dict):
        return {k: _substitute(v, path + (k,), variables, col) for k, v in value.items()}
    if isinstance(value, list):
        return [_substitute(v, path + (i,), variables, col) for i, v in enumerate(value)]
    if not isinstance(value, str) or "${" not in value:
        return value

    def lookup(name: str) -> Any:
        if name not in variables:
            col.add(
                path,
                f"undefined variable ${{{name}}}{did_you_mean(name, variables)} "
                f"(define it under vars: or pass --set {name}=...)",
            )
            return ""
        return variables[name]

    whole = VAR_RE.fullmatch(value)
    if whole:
        return lookup(whole.group(1))
    return VAR_RE.sub(lambda m: str(lookup(m.group(1))), value)


def referenced_variables(data: Any) -> set[str]:
    """The names of every `${name}` in the string values of a loaded document."""
    if isinstance(data, str):
        return set(VAR_RE.findall(data))
    if isinstance(data, dict):
        return set().union(*(referenced_variables(v) for v in data.values()))
    if isinstance(data, list):
        return set().union(*(referenced_variables(v) for v in data))
    return set()


def parse(doc: Located, overrides: dict[str, Any] | None = None) -> tuple[PipelineSpec, list[Diagnostic]]:
    """Build a PipelineSpec from a loaded document, with the structural problems found on the way.

    Entries with problems are left out of the spec, so later checks still see the rest.
    """
    col = _Collector(doc)
    top = col.mapping(doc.data, (), "the pipeline file")
    col.known_keys(top, (), TOP_KEYS, "the pipeline file")
    if top.get("version", 1) != 1:
        col.add(("version",), f"unsupported version {top.get('version')!r}; this Rover reads version 1")
    name = top.get("name", Path(doc.file).stem)
    if not (isinstance(name, str) and NAME_RE.match(name)):
        col.add(("name",), f"pipeline name {name!r} must start with a letter and use letters, digits, _ or -")
        name = "pipeline"

    variables = dict(col.mapping(top.get("vars"), ("vars",), "vars"))
    for key in variables:
        if not (isinstance(key, str) and key.isidentifier()):
            col.add(("vars", key), f"variable name {key!r} must be an identifier", key=True)
    set_vars: dict[str, Any] = {}
    set_params: dict[str, dict[str, Any]] = {}
    for key, value in (overrides or {}).items():
        if "." in key:
            op_name, _, param = key.partition(".")
            if not (op_name and param.isidentifier()):
                raise BadInput(f"--set {key}=...: expected OPERATOR.PARAM=VALUE, e.g. slam.wheel=false")
            set_params.setdefault(op_name, {})[param] = value
            continue
        if key not in variables and not key.isidentifier():
            raise BadInput(f"--set {key}=...: variable names are identifiers (OPERATOR.PARAM sets a param)")
        if key not in variables and key not in referenced_variables(top):
            declared = sorted(str(k) for k in variables)
            raise BadInput(
                f"--set {key}=...: {doc.file} has no variable {key!r}{did_you_mean(key, declared)} "
                f"(vars: {', '.join(declared) or 'none'}; OPERATOR.PARAM sets a param)"
            )
        variables[key] = value
        set_vars[key] = value

    hosts: dict[str, HostSpec] = {}
    for hname, hval in col.mapping(top.get("hosts"), ("hosts",), "hosts").items():
        path = ("hosts", hname)
        if not (isinstance(hname, str) and NAME_RE.match(hname)):
            col.add(path, f"host name {hname!r} must start with a letter and use letters, digits, _ or -", key=True)
            continue
        hval = _substitute(col.mapping(hval, path, f"host {hname!r}"), path, variables, col)
        col.known_keys(hval, path, HOST_KEYS, f"host {hname!r}")
        host = HostSpec(hname)
        for kind in ("listen", "connect"):
            endpoints = hval.get(kind, [])
            if isinstance(endpoints, str):
                endpoints = [endpoints]
            if not isinstance(endpoints, list):
                col.add(path + (kind,), f"{kind} must be a list of endpoints like 'tcp/127.0.0.1:7447'")
                continue
            for i, ep in enumerate(endpoints):
                problem = endpoint_problem(ep)
                if problem:
                    col.add(path + (kind, i), problem)
                else:
                    getattr(host, kind).append(ep)
        # connect_timeout_s is the older name of wait_timeout_s (hosts now retry connecting all that time)
        timeouts: tuple[tuple[str, str, Any], ...] = (
            ("host_timeout_s", "host_timeout_s", HostTimeout),
            ("connect_timeout_s", "wait_timeout_s", P.PositiveFloat),
            ("wait_timeout_s", "wait_timeout_s", P.PositiveFloat),
        )
        for key, attr, kind in timeouts:
            if key in hval:
                try:
                    setattr(host, attr, P.coerce(hval[key], kind))
                except P.ParamTypeError as exc:
                    col.add(path + (key,), f"{key}: {exc}")
        hosts[hname] = host

    security = _security(top, hosts, variables, col) if "security" in top else None
    workers = _workers(_substitute(top.get("workers", AUTO_WORKERS), ("workers",), variables, col), col)
    operators: dict[str, OperatorSpec] = {}
    raw_ops = col.mapping(top.get("operators"), ("operators",), "operators")
    if "operators" not in top:
        col.add((), "the pipeline has no operators: section")
    for oname, oval in raw_ops.items():
        path = ("operators", oname)
        if not (isinstance(oname, str) and NAME_RE.match(oname) and "-" not in oname):
            col.add(path, f"operator name {oname!r} must start with a letter and use letters, digits or _", key=True)
            continue
        oval = col.mapping(oval, path, f"operator {oname!r}")
        col.known_keys(oval, path, OPERATOR_KEYS, f"operator {oname!r}")
        uses = col.string(oval.get("uses"), path + ("uses",), f"operator {oname!r}: uses") if "uses" in oval else None
        if "uses" not in oval:
            col.add(path, f"operator {oname!r} has no 'uses:' (a built-in name or a dotted path to a class)", key=True)
        host_name = oval.get("host")
        if host_name is not None and not isinstance(host_name, str):
            col.add(path + ("host",), "host must be a host name")
            host_name = None
        spec = OperatorSpec(oname, uses or "", host_name)
        process = _substitute(oval.get("process"), path + ("process",), variables, col)
        if process is not None and not (isinstance(process, str) and NAME_RE.match(process)):
            col.add(
                path + ("process",), f"process must name a worker process (letters, digits, _ or -), got {process!r}"
            )
        elif process is not None:
            spec.process = process
        if "inbox" in oval:
            try:
                spec.inbox = P.coerce(_substitute(oval["inbox"], path + ("inbox",), variables, col), P.PositiveInt)
            except P.ParamTypeError as exc:
                col.add(path + ("inbox",), f"inbox: {exc}")
        for port, src in col.mapping(oval.get("inputs"), path + ("inputs",), "inputs").items():
            src = _substitute(src, path + ("inputs", port), variables, col)
            if not (isinstance(src, str) and src.count("/") == 1 and all(src.split("/"))):
                col.add(path + ("inputs", port), f"input {port!r} must name OPERATOR/PORT, got {src!r}")
                continue
            source, source_port = src.split("/")
            spec.inputs[str(port)] = Wire(str(port), source, source_port)
        spec.params = _substitute(
            col.mapping(oval.get("params"), path + ("params",), "params"), path + ("params",), variables, col
        )
        spec.set_params = set_params.pop(oname, {})
        spec.params.update(spec.set_params)
        operators[oname] = spec

    for op_name, values in set_params.items():
        for param in values:
            col.add(
                ("operators",),
                f"--set {op_name}.{param}: the pipeline has no operator {op_name!r}{did_you_mean(op_name, raw_ops)}",
                key=True,
            )
    pipeline = PipelineSpec(doc.file, name, variables, hosts, operators, doc, set_vars, security, workers)
    return pipeline, col.problems


def _workers(value: Any, col: _Collector) -> int | str:
    """The `workers:` key: `auto` or a count of at least 1."""
    if value == AUTO_WORKERS:
        return AUTO_WORKERS
    try:
        return int(P.coerce(value, P.PositiveInt))
    except P.ParamTypeError as exc:
        col.add(("workers",), f"workers: {AUTO_WORKERS} (a process per core) or a count of at least 1: {exc}")
        return AUTO_WORKERS


def _identity(value: Any, path: tuple[Any, ...], what: str, col: _Collector) -> Identity | None:
    value = col.mapping(value, path, what)
    col.known_keys(value, path, IDENTITY_KEYS, what)
    cert = col.string(value.get("cert"), path + ("cert",), f"{what}: cert") if value else None
    key = col.string(value.get("key"), path + ("key",), f"{what}: key") if value else None
    if not value:
        col.add(path, f"{what} needs cert: and key: (PEM files, e.g. from `rover certs`)")
    return Identity(cert, key) if cert and key else None


def _security(
    top: dict[Any, Any], hosts: dict[str, HostSpec], variables: dict[str, Any], col: _Collector
) -> SecuritySpec | None:
    """The security: section; with it every endpoint must be tls/ (mutual TLS, nothing in clear)."""
    path: tuple[Any, ...] = ("security",)
    raw = _substitute(col.mapping(top.get("security"), path, "security"), path, variables, col)
    col.known_keys(raw, path, SECURITY_KEYS, "security")
    if not hosts:
        col.add(path, "security: protects the links between hosts; this pipeline declares no hosts:", key=True)
        return None
    ca = col.string(raw.get("ca"), path + ("ca",), "security: ca (the CA certificate, a PEM file)")
    security = SecuritySpec(ca or "")
    entries = col.mapping(raw.get("hosts"), path + ("hosts",), "security: hosts")
    for name, value in entries.items():
        if name not in hosts:
            col.add(
                path + ("hosts", name),
                f"security: hosts: {name!r} is not a declared host{did_you_mean(name, hosts)}",
                key=True,
            )
            continue
        ident = _identity(value, path + ("hosts", name), f"security: host {name!r}", col)
        if ident:
            security.hosts[name] = ident
    for name in hosts:
        if name == MONITOR:
            col.add(
                ("hosts", name),
                f"host name {MONITOR!r} is reserved for the read-only identity under security:",
                key=True,
            )
        elif name not in entries:
            col.add(
                path + ("hosts",),
                f"security: host {name!r} has no certificate (hosts: {name}: {{cert: ..., key: ...}})",
                key=True,
            )
    if "monitor" in raw:
        security.monitor = _identity(raw["monitor"], path + ("monitor",), "security: monitor", col)
    for host in hosts.values():
        for kind in ("listen", "connect"):
            for i, ep in enumerate(getattr(host, kind)):
                if "#" in ep:
                    col.add(
                        ("hosts", host.name, kind, i),
                        f"{ep}: under security: an endpoint takes no #options (they would override the TLS settings)",
                    )
                elif ep.startswith("tls/["):
                    col.add(
                        ("hosts", host.name, kind, i),
                        f"{ep}: Zenoh's TLS takes no IPv6 literal (it reads it as a DNS name): "
                        "use a DNS name that resolves to it, or an IPv4 address",
                    )
                elif not ep.startswith("tls/"):
                    verb = "listens on" if kind == "listen" else "connects to"
                    col.add(
                        ("hosts", host.name, kind, i),
                        f"host {host.name!r} {verb} {ep}: with security: every endpoint is tls/ "
                        f"(mutual TLS), e.g. tls/{ep.partition('/')[2]}",
                    )
    return security if ca else None


def read_yaml_text(path: str | Path) -> str:
    """The text of a YAML file a user gives (pipeline, setup, scenario); a missing, unreadable or
    non-UTF-8 file is BadInput naming it. A file over MAX_YAML_BYTES is refused from its size
    (or, for a pipe, after that many characters), never read whole."""
    path = Path(path)
    try:
        with path.open(encoding="utf-8") as stream:
            size = os.fstat(stream.fileno()).st_size
            if size > MAX_YAML_BYTES:
                raise size_error(str(path), size)
            text = stream.read(MAX_YAML_BYTES + 1)
        if len(text) > MAX_YAML_BYTES:
            raise size_error(str(path), None)
    except FileNotFoundError:
        raise BadInput(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise BadInput(f"{path}: cannot read: {exc}") from None
    return text


def read_document(path: str | Path) -> Located:
    """Read and safely load a YAML file (see `read_yaml_text`)."""
    return load(read_yaml_text(path), str(path))
