"""A run of the whole pipeline over worker processes (rover/runtime/workers.py, supervisor.py):
how operators are grouped, the `workers:` and `process:` keys, and real runs of the default
pipeline in two workers: the same bytes as one process, a killed worker, Ctrl-C."""

from __future__ import annotations

import itertools
import json
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import popen_rover, run_rover, wait_for_line, wait_until
from helpers.processes import children

from rover.cli.registry import BUILTINS
from rover.errors import BadInput
from rover.pipeline.validation import load_and_check
from rover.runtime import workers
from rover.runtime.workers import WorkerPlan

HUB = "unixsock-stream//tmp/rover-test/hub.sock"
COMPARED = ("results.mcap", "trajectory.tum", "trajectory_live.tum", "tags.csv", "metrics.json")
DEFAULT = Path(__file__).parents[1] / "pipeline.yaml"
UNDER_WAY = "rover: INFO: preintegration: gyro bias"
"""What worker 0 logs (-v) once the IMU's still start is over: every worker is running, the lap has begun"""
PACE = ("--speed", "8")
"""one lap (90 s) in about 11 s: time to act mid-run"""


def pipeline_text(tmp_path: Path, body: str, name: str = "p.yaml") -> Path:
    path = tmp_path / name
    path.write_text(body)
    return path


def toy(tmp_path: Path, count: int, extra: str = "", top: str = "") -> Path:
    """A chain of `count` toy operators after a dataset replay (tests/toyops.py)."""
    lines = [f"name: toy\n{top}operators:", "  src: {uses: dataset_replay, params: {path: d.mcap}}"]
    prev = "src/imu"
    for i in range(count):
        lines.append(f"  op{i}: {{uses: toyops.Passthrough, inputs: {{imu: {prev}}}{extra}}}")
        prev = f"op{i}/imu"
    return pipeline_text(tmp_path, "\n".join(lines) + "\n")


def load_toy(path: Path):
    return load_and_check(path, BUILTINS)


def best_makespan(costs: list[float], count: int) -> float:
    """The least load of the busiest worker over every assignment, by enumeration with numpy."""
    choices = np.array(list(itertools.product(range(count), repeat=len(costs))))
    loads = np.stack([((choices == k) * np.array(costs)).sum(axis=1) for k in range(count)], axis=1)
    return float(loads.max(axis=1).min())


# -- grouping


@pytest.mark.parametrize("seed", range(5))
def test_the_busiest_worker_has_the_least_possible_load(tmp_path, seed):
    pipeline = load_toy(toy(tmp_path, 6))
    rng = np.random.default_rng(seed)
    cost = {name: float(c) for name, c in zip(pipeline.nodes, rng.uniform(0.1, 10.0, len(pipeline.nodes)), strict=True)}
    plan = workers.plan(pipeline, 3, HUB, cost)
    placed = [name for group in plan.groups for name in group]
    assert sorted(placed) == sorted(pipeline.nodes), "every operator runs in exactly one worker"
    makespan = max(sum(cost[n] for n in group) for group in plan.groups)
    assert makespan == pytest.approx(best_makespan(list(cost.values()), 3))
    assert "src" in plan.groups[0], "the worker with the source comes first: it shows the progress"


def test_equal_loads_are_split_where_fewer_wires_cross(tmp_path):
    """src -> op0 -> op1 -> op2, all of one cost, in two workers: cut once (2 + 2), not three times."""
    pipeline = load_toy(toy(tmp_path, 3))
    plan = workers.plan(pipeline, 2, HUB, dict.fromkeys(pipeline.nodes, 1.0))
    assert plan.groups == (("src", "op0"), ("op1", "op2"))


def test_operators_writing_one_folder_share_a_worker(tmp_path):
    pipeline = load_and_check(DEFAULT, BUILTINS, {"dataset": "d.mcap"})
    cost = dict.fromkeys(pipeline.nodes, 1.0) | {"outputs": 50.0, "record": 50.0}
    plan = workers.plan(pipeline, 2, HUB, cost)
    holding = [group for group in plan.groups if "outputs" in group]
    assert "record" in holding[0], plan.groups


def test_named_processes_are_kept_apart_and_together(tmp_path):
    path = toy(tmp_path, 3)
    text = path.read_text().replace("op0: {", "op0: {process: a, ").replace("op2: {", "op2: {process: a, ")
    text = text.replace("op1: {", "op1: {process: b, ")
    pipeline = load_toy(pipeline_text(tmp_path, text))
    plan = workers.plan(pipeline, 2, HUB, dict.fromkeys(pipeline.nodes, 1.0))
    where = {name: k for k, group in enumerate(plan.groups) for name in group}
    assert where["op0"] == where["op2"] != where["op1"]
    with pytest.raises(BadInput, match=r"2 named processes \(a, b\) need as many workers; got 1"):
        workers.plan(pipeline, 1, HUB, dict.fromkeys(pipeline.nodes, 1.0))


def test_worker_count_is_capped_by_the_units_to_place(tmp_path, monkeypatch):
    pipeline = load_toy(toy(tmp_path, 1))  # two operators
    assert workers.worker_count(8, pipeline) == 2
    monkeypatch.setattr(workers, "available_cores", lambda: 1)
    assert workers.worker_count("auto", pipeline) == 1
    assert workers.worker_count(None, pipeline) == 1  # the file says nothing: auto
    with pytest.raises(BadInput, match="at least 1"):
        workers.worker_count(0, pipeline)


def test_the_workers_are_the_hosts_of_a_distributed_run(tmp_path):
    pipeline = load_toy(toy(tmp_path, 2))
    plan = WorkerPlan("toy", (("src", "op0"), ("op1",)), HUB)
    split = workers.as_workers(pipeline, plan)
    assert split.spec.hosts["worker0"].listen == [HUB] and split.spec.hosts["worker1"].connect == [HUB]
    assert {n.name: n.spec.host for n in split.nodes.values()} == {"src": "worker0", "op0": "worker0", "op1": "worker1"}
    assert WorkerPlan.from_json(plan.to_json(), "plan.json") == plan
    with pytest.raises(BadInput, match=r"plan.json: not a worker plan"):
        WorkerPlan.from_json('{"groups": 3}', "plan.json")


# -- the pipeline's keys, as `rover check` sees them


@pytest.mark.parametrize(
    ("top", "extra", "message"),
    [
        ("workers: 0\n", "", "workers: auto (a process per core) or a count of at least 1"),
        ("workers: many\n", "", "workers: auto (a process per core) or a count of at least 1"),
        ("", ", process: 3", "process must name a worker process"),
    ],
)
def test_rover_check_refuses_bad_workers_keys_naming_the_line(tmp_path, top, extra, message):
    path = toy(tmp_path, 1, extra, top)
    proc = run_rover("check", str(path))
    assert proc.returncode == 2, proc.stderr
    assert message in proc.stderr and f"{path}:" in proc.stderr, proc.stderr


def test_rover_check_takes_good_workers_keys(tmp_path):
    assert run_rover("check", str(toy(tmp_path, 1, ", process: heavy", "workers: 2\n"))).returncode == 0


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--workers", "0"], "--workers '0': at least 1"),
        (["--workers", "two"], "--workers 'two': a count of worker processes, or auto"),
        (["--workers", "2", "--host", "nuc"], "--workers 2: --host: a host of a multi-host run runs in one process"),
    ],
)
def test_rover_run_refuses_a_bad_worker_count_in_one_line(tmp_path, args, message):
    proc = run_rover("run", "--dataset", str(tmp_path / "d.mcap"), "--output", str(tmp_path / "out"), *args)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and lines[0].startswith(f"rover: error: {message}"), proc.stderr
    assert not (tmp_path / "out").exists()


def test_a_worker_failing_before_the_run_begins_stops_them_all(tmp_path):
    """A missing dataset is found by the worker that replays it: exit 2, its one error line, the
    other worker stopped (not waiting for it), nothing written."""
    out = tmp_path / "out"
    proc = run_rover("run", "--dataset", str(tmp_path / "nope.mcap"), "--output", str(out), "--workers", "2")
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip() == f"rover: error: {tmp_path / 'nope.mcap'}: no such dataset file", proc.stderr
    assert not out.exists()


# -- real runs of the default pipeline in two workers


@pytest.mark.slow
def test_two_workers_write_the_bytes_of_one_process(lap_runs, tmp_path):
    one = lap_runs["with"]
    assert one.status == 0, one.stderr
    out = tmp_path / "out"
    proc = run_rover("-v", "run", "--dataset", str(one.dataset), "--output", str(out), *one.args, "--workers", "2",
                     timeout=300)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "worker0 runs replay" in proc.stderr and "worker1 runs slam" in proc.stderr, proc.stderr
    lines = proc.stderr.splitlines()
    assert any(line.startswith("rover: INFO: slam: in ") for line in lines), "worker 1's log did not reach stderr"
    for name in COMPARED:
        assert (out / name).read_bytes() == (one.output / name).read_bytes(), f"{name} differs from one process's"
    run, alone = (json.loads((folder / "run.json").read_text()) for folder in (out, one.output))
    assert run["operators"] == alone["operators"], "run.json counts every worker's operators, as one process's"
    assert sorted(run["profile"]) == sorted(alone["profile"])
    assert set(run["hosts"].values()) == {"worker0", "worker1"} and sorted(run["hosts"]) == sorted(alone["profile"])
    assert alone["hosts"] == {}
    assert "run complete" in proc.stdout, proc.stdout


def worker_pids(parent: int) -> dict[int, int]:
    """worker index -> pid, of the workers `parent` started."""
    found = {}
    for pid, cmd in children(parent).items():
        words = cmd.split()
        if "--worker-index" in words:
            found[int(words[words.index("--worker-index") + 1])] = pid
    return found


@pytest.mark.slow
def test_a_killed_worker_leaves_partial_results_and_exit_3(simulated, tmp_path):
    """kill -9 of the worker running the SLAM once the run is under way: the run ends with exit 3, the
    other worker's outputs are kept (run.json partial, naming the lost worker), no traceback."""
    dataset = simulated("paper", 2, "trajectory.laps=1")
    out = tmp_path / "out"
    proc = popen_rover("-v", "run", "--dataset", str(dataset), "--output", str(out), "--workers", "2", *PACE)
    wait_until(lambda: len(worker_pids(proc.pid)) == 2, "two workers", procs=[proc])
    head = wait_for_line(proc, UNDER_WAY)
    slam_worker = 1  # the default pipeline's weights put the SLAM alone in worker 1
    os.kill(worker_pids(proc.pid)[slam_worker], signal.SIGKILL)
    _stdout, err = proc.communicate(timeout=120)
    err = head + err
    assert proc.returncode == 3, err
    run = json.loads((out / "run.json").read_text())
    assert run["status"] == "partial" and [lost["host"] for lost in run["lost"]] == ["worker1"], run
    assert "worker1 (slam) was killed by SIGKILL" in err, err
    assert "Traceback" not in err, err


@pytest.mark.slow
def test_status_shows_the_workers_and_sigint_stops_them_all(simulated, tmp_path):
    """`rover status` of the pipeline finds the run's workers on this machine, both answering; SIGINT
    to `rover run` alone (not its process group) is passed on: every worker stops, exit 130, the
    outputs kept as an interrupted run's. The pipeline has a name of its own: other tests' runs of
    the default one may be under way on this machine."""
    dataset = simulated("paper", 2, "trajectory.laps=1")
    out = tmp_path / "out"
    pipeline = tmp_path / "watched.yaml"
    pipeline.write_text(DEFAULT.read_text().replace("\nname: rover\n", "\nname: watched\n", 1))
    run = ["-v", "run", str(pipeline), "--dataset", str(dataset), "--output", str(out), "--workers", "2", *PACE]
    proc = popen_rover(*run)
    try:
        wait_until(lambda: len(worker_pids(proc.pid)) == 2, "two workers", procs=[proc])
        pids = worker_pids(proc.pid)
        head = wait_for_line(proc, UNDER_WAY)
        status = run_rover("status", str(pipeline), "--once", "--json", "--interval", "0.2")
        assert status.returncode == 0, status.stderr
        hosts = {h["host"]: h for h in json.loads(status.stdout)["hosts"]}
        assert sorted(hosts) == ["worker0", "worker1"] and all(h["answering"] for h in hosts.values()), hosts
    except BaseException:
        proc.terminate()  # passed on to the workers: none is left behind
        proc.communicate(timeout=60)
        raise
    sent = time.monotonic()
    proc.send_signal(signal.SIGINT)
    _stdout, err = proc.communicate(timeout=60)
    err = head + err
    took_s = time.monotonic() - sent
    assert proc.returncode == 130, err
    assert not children(proc.pid) and all(not Path(f"/proc/{pid}").exists() for pid in pids.values())
    assert json.loads((out / "run.json").read_text())["status"] == "interrupted"
    assert "Traceback" not in err, err
    print(f"every worker stopped {took_s:.2f} s after SIGINT")


def test_operators_writing_one_folder_cannot_be_named_into_two_processes():
    pipeline = load_and_check(DEFAULT, BUILTINS, {"dataset": "d.mcap"})
    pipeline.nodes["outputs"].spec.process = "a"
    pipeline.nodes["record"].spec.process = "b"
    with pytest.raises(BadInput, match=r"operators outputs, record write one folder, so they run in one process"):
        workers.plan(pipeline, 2, HUB, dict.fromkeys(pipeline.nodes, 1.0))
