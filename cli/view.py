"""`rover run --view [PORT]`: a `foxglove_view` operator named `view` added to the pipeline being run.

It is added to the spec before the check, so it is validated like the file's own operators, and
wired by type to the operator that sends the robot's pose (the SLAM: its pose, path, tags,
bearings and diagnostics). `--set view.PARAM=VALUE` sets its params (`host`, `ray_m`, ...). The
node is local to this process: with `--host H` it runs on H and reads only what H produces, and
it changes neither the pipeline's digest (the hosts compare it) nor the access rules.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from rover.errors import BadInput
from rover.operator import In
from rover.pipeline.resolve import UnknownOperator, resolve
from rover.pipeline.spec import OperatorSpec, PipelineSpec, Wire, parse, read_document
from rover.pipeline.validation import Pipeline, check

VIEW = "view"
"""the added operator's name (`--set view.PARAM=VALUE`)"""
VIEW_USES = "foxglove_view"
MAX_PORT = 65535


def view_inputs() -> Mapping[str, In]:
    from rover.drivers.foxglove_view import FoxgloveView

    return FoxgloveView.inputs


def _wires(outputs: Mapping[str, str], inputs: Mapping[str, In]) -> dict[str, str]:
    """View input -> the output feeding it: the output of the same name and type, else the only one of that type."""
    wires = {}
    for port, spec in inputs.items():
        if outputs.get(port) == spec.type:
            wires[port] = port
            continue
        same = [name for name, kind in outputs.items() if kind == spec.type]
        if len(same) == 1:
            wires[port] = same[0]
    return wires


def add_view(
    spec: PipelineSpec, builtins: Mapping[str, str], port: int, host: str | None, params: Mapping[str, Any]
) -> OperatorSpec:
    """Add the `view` operator to `spec`, wired to the operator that sends the most of its inputs (the
    robot's pose among them); on `host` when given. BadInput says why it cannot be."""
    if not 0 <= port <= MAX_PORT:
        raise BadInput(f"--view {port}: a port from 0 (any free one) to {MAX_PORT}")
    if VIEW in spec.operators:
        raise BadInput(f"{spec.file}: --view adds an operator named {VIEW!r}: the pipeline already has one")
    inputs = view_inputs()
    found: dict[str, dict[str, str]] = {}
    for op in spec.operators.values():
        try:
            cls = resolve(op.uses, builtins)
        except UnknownOperator:
            continue  # the check reports it
        wires = _wires({name: out.type for name, out in cls.outputs.items()}, inputs)
        if "pose" in wires:
            found[op.name] = wires
    pose_type = inputs["pose"].type
    if not found:
        raise BadInput(f"{spec.file}: --view needs an operator that sends the robot's pose ({pose_type}, as slam/pose)")
    distributed = host is not None and bool(spec.hosts)
    here = {name: w for name, w in found.items() if not distributed or spec.operators[name].host == host}
    if not here:
        elsewhere = ", ".join(f"{name} on {spec.operators[name].host}" for name in sorted(found))
        raise BadInput(
            f"{spec.file}: --view on host {host}: the robot's pose is sent by {elsewhere}: "
            "give --view to `rover run --host` on that host"
        )
    best = max(len(w) for w in here.values())
    tied = sorted(name for name, w in here.items() if len(w) == best)
    if len(tied) > 1:
        raise BadInput(f"{spec.file}: --view: several operators send the robot's pose ({', '.join(tied)}): ambiguous")
    source = tied[0]
    view = OperatorSpec(
        VIEW,
        VIEW_USES,
        host if distributed else spec.operators[source].host,
        inputs={p: Wire(p, source, out) for p, out in here[source].items()},
        params={"port": port, **params},
        set_params=dict(params),
    )
    spec.operators[VIEW] = view
    return view


def load_with_view(
    path: str | Path, builtins: Mapping[str, str], overrides: dict[str, Any], port: int, host: str | None
) -> Pipeline:
    """`load_and_check` with the view added; `--set view.PARAM=VALUE` goes to the view. Its
    "listening on" line is shown unless the command is quiet."""
    mine = {k.partition(".")[2]: v for k, v in overrides.items() if k.startswith(f"{VIEW}.")}
    rest = {k: v for k, v in overrides.items() if not k.startswith(f"{VIEW}.")}
    spec, problems = parse(read_document(path), rest)
    try:
        add_view(spec, builtins, port, host, mine)
    except BadInput:
        check(spec, builtins, problems)  # the file's own problems first: they may be why
        raise
    if logging.getLogger().getEffectiveLevel() < logging.ERROR:
        logging.getLogger("rover.view").setLevel(logging.INFO)
    return check(spec, builtins, problems, local=[VIEW])
