"""The pipeline file: its shape, `${var}` substitution, and the dataclasses the runtime reads.

Structural problems (unknown keys, wrong value kinds, bad names, undefined variables) are
collected here; what needs the operator classes is checked in `rover.pipeline.validation`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from difflib import get_close_matches
from pathlib import Path
from typing import Any

from rover.errors import BadInput, Diagnostic
from rover.pipeline.yamlpos import Located, load

NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_-]*$")
VAR_RE = re.compile(r"\$\{([^}]*)\}")
ENDPOINT_RE = re.compile(
    r"^(?:(?:tcp|udp|tls|quic|ws)/(?:\[[0-9A-Fa-f:.]+\]|[^/:\[\]]+):\d{1,5}|unixsock-stream/.+)(?:#.*)?$"
)

TOP_KEYS = ("version", "name", "description", "vars", "hosts", "operators")
HOST_KEYS = ("listen", "connect", "connect_timeout_s")
OPERATOR_KEYS = ("uses", "host", "inputs", "params", "description")
DEFAULT_CONNECT_TIMEOUT_S = 10.0


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
    connect_timeout_s: float = DEFAULT_CONNECT_TIMEOUT_S


@dataclass
class OperatorSpec:
    name: str
    uses: str
    host: str | None = None
    inputs: dict[str, Wire] = field(default_factory=dict)
    params: dict[str, Any] = field(default_factory=dict)


@dataclass
class PipelineSpec:
    """A loaded pipeline file with variables substituted; `doc` keeps source positions."""

    file: str
    name: str
    vars: dict[str, Any]
    hosts: dict[str, HostSpec]
    operators: dict[str, OperatorSpec]
    doc: Located

    def operators_on(self, host: str | None) -> list[OperatorSpec]:
        return [op for op in self.operators.values() if host is None or op.host == host]


class _Collector:
    def __init__(self, doc: Located):
        self.doc = doc
        self.problems: list[Diagnostic] = []

    def add(self, path: tuple, message: str, *, key: bool = False) -> None:
        self.problems.append(self.doc.diag(path, message, key=key))

    def mapping(self, value: Any, path: tuple, what: str) -> dict:
        if value is None:
            return {}
        if not isinstance(value, dict):
            self.add(path, f"{what} must be a mapping")
            return {}
        return value

    def known_keys(self, value: dict, path: tuple, allowed: tuple[str, ...], what: str) -> None:
        for key in value:
            if key not in allowed:
                self.add(path + (key,), f"unknown key {key!r} in {what}{did_you_mean(key, allowed)}", key=True)

    def string(self, value: Any, path: tuple, what: str) -> str | None:
        if isinstance(value, str) and value:
            return value
        self.add(path, f"{what} must be a non-empty string")
        return None


def _substitute(value: Any, path: tuple, variables: dict[str, Any], col: _Collector) -> Any:
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
    for key, value in (overrides or {}).items():
        if key not in variables and not key.isidentifier():
            raise BadInput(f"--set {key}=...: variable names are identifiers")
        variables[key] = value

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
                if not (isinstance(ep, str) and ENDPOINT_RE.match(ep)):
                    col.add(
                        path + (kind, i), f"bad endpoint {ep!r}: expected PROTOCOL/ADDRESS, e.g. 'tcp/127.0.0.1:7447'"
                    )
                else:
                    getattr(host, kind).append(ep)
        timeout = hval.get("connect_timeout_s", DEFAULT_CONNECT_TIMEOUT_S)
        if isinstance(timeout, (int, float)) and not isinstance(timeout, bool) and timeout > 0:
            host.connect_timeout_s = float(timeout)
        else:
            col.add(path + ("connect_timeout_s",), f"connect_timeout_s must be a positive number, got {timeout!r}")
        hosts[hname] = host

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
        host = oval.get("host")
        if host is not None and not isinstance(host, str):
            col.add(path + ("host",), "host must be a host name")
            host = None
        spec = OperatorSpec(oname, uses or "", host)
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
        operators[oname] = spec

    return PipelineSpec(doc.file, name, variables, hosts, operators, doc), col.problems


def read_document(path: str | Path) -> Located:
    """Read and safely load a YAML file; a missing or unreadable file is BadInput naming it."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise BadInput(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise BadInput(f"{path}: cannot read: {exc}") from None
    return load(text, str(path))
