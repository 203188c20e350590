"""Drawing a pipeline: Mermaid (renders on GitHub) or Graphviz DOT, hosts as subgraphs, types on edges."""

from __future__ import annotations

from collections.abc import Iterator

from rover.pipeline.validation import Pipeline


def _short(typename: str) -> str:
    return typename.replace("/msg/", "/")


def _groups(pipeline: Pipeline) -> dict[str | None, list[str]]:
    groups: dict[str | None, list[str]] = {}
    for node in pipeline.nodes.values():
        groups.setdefault(node.spec.host, []).append(node.name)
    return groups


def _edges(pipeline: Pipeline) -> Iterator[tuple[str, str, str, str]]:
    for node in pipeline.nodes.values():
        for port, wire in node.spec.inputs.items():
            source = pipeline.nodes[wire.source]
            yield wire.source, node.name, f"{wire.source_port} → {port}", _short(source.output_type(wire.source_port))


def mermaid(pipeline: Pipeline) -> str:
    lines = ["flowchart LR"]
    for host, names in _groups(pipeline).items():
        indent = "    "
        if host is not None:
            lines.append(f"    subgraph {host}[host {host}]")
            indent = "        "
        for name in names:
            lines.append(f'{indent}{name}["{name}<br/><small>{pipeline.nodes[name].spec.uses}</small>"]')
        if host is not None:
            lines.append("    end")
    for src, dst, ports, typename in _edges(pipeline):
        lines.append(f'    {src} -- "{ports}<br/>{typename}" --> {dst}')
    return "\n".join(lines) + "\n"


def dot(pipeline: Pipeline) -> str:
    lines = [f'digraph "{pipeline.name}" {{', "    rankdir=LR;", "    node [shape=box, fontname=Helvetica];"]
    for host, names in _groups(pipeline).items():
        indent = "    "
        if host is not None:
            lines += [f'    subgraph "cluster_{host}" {{', f'        label="host {host}";']
            indent = "        "
        for name in names:
            lines.append(f'{indent}"{name}" [label="{name}\\n({pipeline.nodes[name].spec.uses})"];')
        if host is not None:
            lines.append("    }")
    for src, dst, ports, typename in _edges(pipeline):
        lines.append(f'    "{src}" -> "{dst}" [label="{ports}\\n{typename}"];')
    lines.append("}")
    return "\n".join(lines) + "\n"
