"""A run of the whole pipeline spread over worker processes on one machine, as dora-rs runs each
node in its own process: one interpreter per worker, so every core works.

The workers are the hosts of an ordinary distributed run (`worker0`, `worker1`, ...): worker 0
listens on a Unix socket in a private folder and the others connect to it. Everything a
distributed run promises holds for them: sources start once every worker has subscribed, the
outputs are byte-identical to one process's, and a worker that dies is a lost host (exit 3,
partial results kept).

Which operator runs where comes from their cost (the CPU seconds each took in the last run into
the same output folder, else each class's `cpu_weight`): of every grouping, the one whose busiest
worker has the least to do, then the one with the fewest wires between workers. The pipeline's
`workers:` key and an operator's `process:` key override it; operators that write one folder
always share a process (its lock is per process: rover.formats.output_folder).
"""

from __future__ import annotations

import itertools
import json
import os
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from rover.errors import BadInput
from rover.operator import Source
from rover.pipeline.spec import HostSpec
from rover.pipeline.validation import Pipeline

WORKER = "worker"
"""Worker k is the host `worker{k}`."""
MAX_GROUPINGS = 100_000
"""Groupings tried one by one up to this many; beyond, the costliest unit goes to the least busy worker."""
CUT_COST = 1e-6
"""What a wire between two workers adds to a grouping's cost: it only breaks ties between equal loads."""


@dataclass(frozen=True)
class WorkerPlan:
    """Which operators each worker runs, and where worker 0 listens for the others."""

    pipeline: str
    """the pipeline's name (`rover status` finds a run's workers by it)"""
    groups: tuple[tuple[str, ...], ...]
    hub: str
    """worker 0's endpoint (`unixsock-stream/PATH`)"""

    @staticmethod
    def host(k: int) -> str:
        return f"{WORKER}{k}"

    @property
    def hosts(self) -> list[str]:
        return [self.host(k) for k in range(len(self.groups))]

    def to_json(self) -> str:
        return json.dumps({"pipeline": self.pipeline, "groups": [list(g) for g in self.groups], "hub": self.hub})

    @classmethod
    def from_json(cls, text: str, where: str) -> WorkerPlan:
        """The plan `to_json` wrote; BadInput naming `where` for anything else."""
        try:
            doc = json.loads(text)
            groups = tuple(tuple(str(name) for name in group) for group in doc["groups"])
            return cls(str(doc["pipeline"]), groups, str(doc["hub"]))
        except (ValueError, KeyError, TypeError) as exc:
            raise BadInput(f"{where}: not a worker plan ({type(exc).__name__}: {exc})") from None


PLAN_FILE = "plan.json"
FOLDER_PREFIX = "rover-workers-"
"""A run's private folder (`runs_folder`): its plan and worker 0's socket."""
SOCKET_PATH_MAX = 60
"""The longest folder for runs: a Unix socket's path must fit in 108 bytes (sun_path)."""


def runs_folder() -> str:
    """Where a run over workers makes its private folder: the temporary directory, or /tmp when its
    path leaves no room for a socket's."""
    folder = tempfile.gettempdir()
    return folder if len(folder) <= SOCKET_PATH_MAX else "/tmp"


def running_plans(pipeline: str, folder: str | None = None) -> list[WorkerPlan]:
    """The plans of this user's runs of `pipeline` over workers on this machine, still listening."""
    plans = []
    for path in sorted(Path(folder or runs_folder()).glob(f"{FOLDER_PREFIX}*/{PLAN_FILE}")):
        try:
            if path.stat().st_uid != os.getuid():
                continue
            found = WorkerPlan.from_json(path.read_text(), str(path))
        except (OSError, BadInput):
            continue  # a run ending as we look, or not one of ours
        socket = found.hub.removeprefix("unixsock-stream/")
        if found.pipeline == pipeline and Path(socket).exists():
            plans.append(found)
    return plans


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity, as a container or `taskset` sets it)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def worker_count(requested: int | str | None, pipeline: Pipeline) -> int:
    """How many workers to start: `requested` (the command line's, else the file's `workers:`), or
    with `auto` one per available core, never more than there are operators to place apart."""
    wanted = pipeline.spec.workers if requested is None else requested
    units = len(_units(pipeline))
    if wanted == "auto":
        return max(1, min(available_cores(), units))
    count = int(wanted)
    if count < 1:
        raise BadInput(f"--workers {count}: at least 1 (1 runs everything in this process)")
    return max(1, min(count, units))


def costs(pipeline: Pipeline, measured: Mapping[str, float]) -> dict[str, float]:
    """Each operator's cost: its `measured` CPU seconds where given for all of them (a run of this
    pipeline), else its class's `cpu_weight`."""
    names = list(pipeline.nodes)
    if names and all(measured.get(name, 0.0) > 0.0 for name in names):
        return {name: float(measured[name]) for name in names}
    return {name: float(node.cls.cpu_weight) for name, node in pipeline.nodes.items()}


def plan(pipeline: Pipeline, count: int, hub: str, cost: Mapping[str, float]) -> WorkerPlan:
    """Group the operators into `count` workers (fewer when there are fewer units to place)."""
    units = _units(pipeline)
    count = min(count, len(units))
    process = [_process_of(pipeline, unit) for unit in units]
    pinned = sorted({p for p in process if p is not None})
    if len(pinned) > count:
        raise BadInput(
            f"{pipeline.spec.file}: {len(pinned)} named processes ({', '.join(pinned)}) need as many workers; "
            f"got {count} (--workers, or the file's workers:)"
        )
    unit_cost = [sum(cost[name] for name in unit) for unit in units]
    fixed = {i: pinned.index(p) for i, p in enumerate(process) if p is not None}
    wires = _unit_wires(pipeline, units)
    assignment = _assign(unit_cost, count, fixed, wires)
    groups = [[name for i, unit in enumerate(units) if assignment[i] == k for name in unit] for k in range(count)]
    groups = [g for g in groups if g]
    # the worker with the sources first: it shows the progress; then by their first operator's place in the file
    order = list(pipeline.nodes)
    sources = {name for name, node in pipeline.nodes.items() if issubclass(node.cls, Source)}
    groups.sort(key=lambda g: (not sources & set(g), min(order.index(name) for name in g)))
    return WorkerPlan(pipeline.name, tuple(tuple(sorted(g, key=order.index)) for g in groups), hub)


def as_workers(pipeline: Pipeline, worker_plan: WorkerPlan) -> Pipeline:
    """The same pipeline as a distributed run whose hosts are the workers (no TLS: the socket is
    in a folder only this user can enter)."""
    host_of = {name: WorkerPlan.host(k) for k, group in enumerate(worker_plan.groups) for name in group}
    if set(host_of) != set(pipeline.nodes):
        raise BadInput(f"the worker plan places {sorted(host_of)}, the pipeline has {sorted(pipeline.nodes)}")
    hosts = {WorkerPlan.host(0): HostSpec(WorkerPlan.host(0), listen=[worker_plan.hub])}
    for k in range(1, len(worker_plan.groups)):
        hosts[WorkerPlan.host(k)] = HostSpec(WorkerPlan.host(k), connect=[worker_plan.hub])
    nodes = {name: replace(node, spec=replace(node.spec, host=host_of[name])) for name, node in pipeline.nodes.items()}
    operators = {name: node.spec for name, node in nodes.items()}
    spec = replace(pipeline.spec, hosts=hosts, operators=operators, security=None)
    return Pipeline(spec, nodes)


def _units(pipeline: Pipeline) -> list[list[str]]:
    """Operators that must share a process, in file order: one `process:` name, or one output folder."""
    parent = {name: name for name in pipeline.nodes}

    def find(name: str) -> str:
        while parent[name] != name:
            name = parent[name]
        return name

    by_key: dict[tuple[str, str], str] = {}
    for name, node in pipeline.nodes.items():
        keys = []
        if node.spec.process is not None:
            keys.append(("process", node.spec.process))
        if node.cls.folder_param is not None:
            folder = getattr(node.params, node.cls.folder_param, None)
            if folder is not None:
                keys.append(("folder", os.path.realpath(str(folder))))
        for key in keys:
            if key in by_key:
                parent[find(name)] = find(by_key[key])
            else:
                by_key[key] = name
    units: dict[str, list[str]] = {}
    for name in pipeline.nodes:
        units.setdefault(find(name), []).append(name)
    return list(units.values())


def _process_of(pipeline: Pipeline, unit: Sequence[str]) -> str | None:
    """The `process:` name of operators that must share a process; BadInput when they name two."""
    names = sorted({p for name in unit if (p := pipeline.nodes[name].spec.process) is not None})
    if len(names) > 1:
        raise BadInput(
            f"{pipeline.spec.file}: operators {', '.join(unit)} write one folder, so they run in one process; "
            f"their process: keys name {', '.join(names)}"
        )
    return names[0] if names else None


def _unit_wires(pipeline: Pipeline, units: Sequence[Sequence[str]]) -> list[tuple[int, int]]:
    unit_of = {name: i for i, unit in enumerate(units) for name in unit}
    return [
        (unit_of[wire.source], unit_of[name])
        for name, node in pipeline.nodes.items()
        for wire in node.spec.inputs.values()
        if wire.source in unit_of and unit_of[wire.source] != unit_of[name]
    ]


def _assign(cost: Sequence[float], count: int, fixed: Mapping[int, int], wires: Sequence[tuple[int, int]]) -> list[int]:
    """A worker per unit: the busiest worker least busy, then the fewest wires between workers."""
    free = [i for i in range(len(cost)) if i not in fixed]

    def score(assignment: Sequence[int]) -> float:
        loads = [0.0] * count
        for i, k in enumerate(assignment):
            loads[k] += cost[i]
        return max(loads) + CUT_COST * sum(assignment[a] != assignment[b] for a, b in wires)

    if count ** len(free) <= MAX_GROUPINGS:
        best: list[int] | None = None
        best_score = float("inf")
        for choice in itertools.product(range(count), repeat=len(free)):
            assignment = [fixed.get(i, 0) for i in range(len(cost))]
            for i, k in zip(free, choice, strict=True):
                assignment[i] = k
            s = score(assignment)
            if s < best_score - 1e-12:
                best, best_score = assignment, s
        assert best is not None
        return best
    assignment = [fixed.get(i, 0) for i in range(len(cost))]
    loads = [0.0] * count
    for i, k in fixed.items():
        loads[k] += cost[i]
    for i in sorted(free, key=lambda i: -cost[i]):
        k = min(range(count), key=lambda k: loads[k])
        assignment[i] = k
        loads[k] += cost[i]
    return assignment
