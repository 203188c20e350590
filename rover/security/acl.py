"""Zenoh access control generated from the wiring, bound to the hosts' certificate identities.

Zenoh checks every message that crosses a link against the rules of the router on each side,
and identifies the other side by the common name of its TLS certificate. So the rules are per
link: on host X, what neighbour Y may send in (ingress) and what X sends out to Y (egress). A
flow (a key from the host that produces it to the host that reads it) may cross the link Y->X
when some path of the pipeline's link graph from producer to consumer takes it: in a star only the
hub relays (for the hosts behind it); in a mesh, any host on a path between two others may.
What a host may send is therefore its own operators' outputs that others read, its presence
tokens and status, and what it relays; what it may ask for (declare a subscriber on) is what its
operators read and what it relays. The read-only `monitor` identity may query the hosts'
status and nothing else. Anything not allowed is denied (`default_permission: deny`),
including any identity the pipeline does not name.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

from rover.pipeline.spec import MONITOR, PipelineSpec
from rover.pipeline.validation import host_links
from rover.runtime.status import status_key
from rover.transport import keys

MESSAGES_IN = ("put", "liveliness_token", "reply", "declare_queryable")
"""What travels with a flow, from its producer toward its consumer."""


@dataclass(frozen=True)
class Flow:
    """One kind of traffic from host `src` to host `dst` on key expression `key`."""

    key: str
    src: str
    dst: str
    messages: tuple[str, ...]
    """Zenoh message kinds that travel src -> dst; their subscriber declarations travel dst -> src"""


def flows(spec: PipelineSpec) -> list[Flow]:
    """Every flow of a run between two of its hosts."""
    name = spec.name
    out: list[Flow] = []
    for op in spec.operators.values():
        for wire in op.inputs.values():
            source = spec.operators.get(wire.source)
            if source is None or source.host == op.host or not (source.host and op.host):
                continue
            out.append(Flow(keys.port_key(name, wire.source, wire.source_port), source.host, op.host, ("put",)))
            out.append(Flow(keys.ack_key(name, op.name, wire.port), op.host, source.host, ("put",)))
    for host in spec.hosts:
        for other in spec.hosts:
            if other != host:
                out.append(
                    Flow(f"{keys.PREFIX}/{name}/{keys.HOSTS}/{host}/**", host, other, ("put", "liveliness_token"))
                )
                out.append(Flow(status_key(name, host), host, other, ("reply", "declare_queryable")))
    return list(dict.fromkeys(out))


def _paths(links: Mapping[str, set[str]], src: str, dst: str) -> Iterator[list[str]]:
    """Every simple path from src to dst. Their number grows quickly with the links of a mesh, but
    pipelines have a handful of hosts (a full mesh of 8 has ~2,000 paths per pair)."""
    stack = [[src]]
    while stack:
        path = stack.pop()
        if path[-1] == dst:
            yield path
            continue
        stack.extend(path + [n] for n in sorted(links.get(path[-1], ())) if n not in path)


def carried(spec: PipelineSpec) -> dict[tuple[str, str], list[Flow]]:
    """(from, to) of each link -> the flows that may cross it in that direction."""
    links = host_links(spec)
    out: dict[tuple[str, str], list[Flow]] = {(a, b): [] for a in links for b in links[a]}
    for flow in flows(spec):
        edges = {(p[i], p[i + 1]) for p in _paths(links, flow.src, flow.dst) for i in range(len(p) - 1)}
        for edge in sorted(edges):
            out[edge].append(flow)
    return out


def _rules_for_link(
    pipeline: str, mine: str, other: str, table: dict[tuple[str, str], list[Flow]]
) -> list[dict[str, Any]]:
    """The rules on host `mine` for its link with `other`."""
    incoming, outgoing = table.get((other, mine), []), table.get((mine, other), [])
    hosts_all = f"{keys.PREFIX}/{pipeline}/{keys.HOSTS}/**"
    status_all = f"{keys.PREFIX}/{pipeline}/_status/**"
    wanted: dict[tuple[str, str], list[str]] = {}

    def allow(flow: str, message: str, key: str) -> None:
        wanted.setdefault((flow, message), []).append(key)

    for direction, moving, back in (("ingress", incoming, "egress"), ("egress", outgoing, "ingress")):
        for f in moving:
            for message in f.messages:
                allow(direction, message, f.key)
            if "put" in f.messages:
                allow(back, "declare_subscriber", f.key)  # the reader asks the writer's side for it
        for message in ("declare_liveliness_subscriber", "liveliness_query"):
            allow(direction, message, hosts_all)
        allow(direction, "declare_subscriber", hosts_all)  # every host listens for the others' `bye`
        allow(direction, "query", status_all)  # a monitor's status query, relayed
    return [
        {
            "id": f"{other}-{flow}-{message}",
            "messages": [message],
            "flows": [flow],
            "permission": "allow",
            "key_exprs": sorted(set(keys_)),
        }
        for (flow, message), keys_ in sorted(wanted.items())
    ]


def access_control(
    spec: PipelineSpec, host: str, table: dict[tuple[str, str], list[Flow]] | None = None
) -> dict[str, Any]:
    """Host `host`'s Zenoh `access_control` configuration: rules for each linked host and the monitor
    (`table`: `carried(spec)`, when the caller has it already)."""
    table = carried(spec) if table is None else table
    links = host_links(spec)
    status_all = f"{keys.PREFIX}/{spec.name}/_status/**"
    subjects, rules, policies = [], [], []
    for other in sorted(links.get(host, ())):
        link_rules = _rules_for_link(spec.name, host, other, table)
        subjects.append({"id": f"host-{other}", "cert_common_names": [other], "link_protocols": ["tls"]})
        rules += link_rules
        policies.append({"id": f"link-{other}", "rules": [r["id"] for r in link_rules], "subjects": [f"host-{other}"]})
    monitor_rules = [
        {
            "id": "monitor-query",
            "messages": ["query"],
            "flows": ["ingress"],
            "permission": "allow",
            "key_exprs": [status_all],
        },
        {
            "id": "monitor-reply",
            "messages": ["reply", "declare_queryable"],
            "flows": ["egress"],
            "permission": "allow",
            "key_exprs": [status_all],
        },
    ]
    subjects.append({"id": MONITOR, "cert_common_names": [MONITOR], "link_protocols": ["tls"]})
    rules += monitor_rules
    policies.append({"id": MONITOR, "rules": [r["id"] for r in monitor_rules], "subjects": [MONITOR]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def describe(spec: PipelineSpec) -> str:
    """The generated rules, host by host, as `rover check --security` prints them."""
    prefix = f"{keys.PREFIX}/{spec.name}/"
    lines = [
        f"access control of pipeline {spec.name!r} (mutual TLS; default: deny; identities are certificate common names)"
    ]
    table = carried(spec)
    for host in spec.hosts:
        conf = access_control(spec, host, table)
        lines.append(f"host {host}:")
        by_subject = {p["subjects"][0]: p["rules"] for p in conf["policies"]}
        rules = {r["id"]: r for r in conf["rules"]}
        for subject, rule_ids in by_subject.items():
            who = subject.removeprefix("host-")
            for rid in rule_ids:
                rule = rules[rid]
                verb = "from" if rule["flows"] == ["ingress"] else "to"
                shown = ", ".join(k.removeprefix(prefix) for k in rule["key_exprs"])
                lines.append(f"  {'/'.join(rule['messages'])} {verb} {who}: {shown}")
    return "\n".join(lines)
