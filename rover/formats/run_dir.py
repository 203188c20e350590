"""Reading what `rover eval` compares: a run's output files and the ground truth, into plain arrays."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, get_args

import numpy as np

from rover.errors import BadInput
from rover.evaluation.metrics import Poses2D, RunRecord, Truth
from rover.formats.text import csv_float, read_text, tag_rows
from rover.formats.truth import Trajectory, TruthTag, read_dataset_truth, read_tags_csv, read_tum
from rover.geometry import yaw_from_quaternion
from rover.operator import RunStatus

RUN_FILE = "run.json"
FAILED_RUN_FILE = "failed-run.json"
"""how the last run into the folder ended when it failed (the folder keeps the results of the one before)"""
"""names the dataset a run read, so `rover eval` finds its truth"""


def poses_of(trajectory: Trajectory) -> Poses2D:
    return Poses2D(trajectory.stamp_ns, trajectory.xyz[:, :2], yaw_from_quaternion(*trajectory.quat_xyzw.T))


RUN_TAG_COLUMNS = ("id", "x", "y", "var_x", "cov_xy", "var_y")
RESULT_TYPES = {
    "/rover/tags": "rover_msgs/msg/TagArray",
    "/rover/aoa": "rover_msgs/msg/Aoa",
    "/rover/bearings": "rover_msgs/msg/Aoa",
}


def _read_tags(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A run's tags.csv: ids, final positions and covariances, nan where a cell is empty (a tag never
    localized); BadInput names the file and line of a missing column, a bad number or a repeated id."""
    ids: list[int] = []
    xy: list[list[float]] = []
    cov: list[list[list[float]]] = []
    for where, tag_id, row in tag_rows(read_text(path), str(path), RUN_TAG_COLUMNS):
        x, y, var_x, cov_xy, var_y = (_optional_float(row, c, where) for c in RUN_TAG_COLUMNS[1:])
        if math.isnan(x) != math.isnan(y):
            raise BadInput(f"{where}: x and y are both numbers, or both empty for a tag never localized")
        if not math.isnan(x) and any(math.isnan(v) for v in (var_x, cov_xy, var_y)):
            raise BadInput(f"{where}: a localized tag has var_x, cov_xy and var_y")
        ids.append(tag_id)
        xy.append([x, y])
        cov.append([[var_x, cov_xy], [cov_xy, var_y]])
    return np.array(ids, dtype=int), np.array(xy).reshape(-1, 2), np.array(cov).reshape(-1, 2, 2)


def _read_heard(path: Path) -> dict[int, tuple[int, int]]:
    """tag id -> (first, last) heard, ns, from a run's tags.csv (tags without both left out)."""
    heard = {}
    for where, tag_id, row in tag_rows(read_text(path), str(path), RUN_TAG_COLUMNS):
        first, last = (_optional_float(row, c, where) for c in ("first_heard_s", "last_heard_s"))
        if math.isfinite(first) and math.isfinite(last):
            heard[tag_id] = (round(first * 1e9), round(last * 1e9))
    return heard


def _optional_float(row: dict[str, str], column: str, where: str) -> float:
    """A finite number, or nan for an empty cell (a value the run never had)."""
    return csv_float(row, column, where) if row.get(column, "").strip() else math.nan


Estimate = tuple[int, int, float, float, bool, float, float, float, float]
"""one published tag estimate: stamp (ns), tag id, x, y (m), localized, covariance (2x2 row-major)"""
Bearing = tuple[int, int, float, float]
"""one AoA: stamp (ns), tag id, angle and std (rad)"""
Estimates = list[Estimate]


def _read_results(path: Path) -> tuple[Estimates, list[Bearing], list[tuple[int, int]]]:
    """Tag estimates over time, the AoAs, and (stamp, tag id) of every AoA from results.mcap (empty
    when the file is absent): the AoAs as the SLAM used them (`/rover/bearings`, those it resolved)
    when the run recorded them."""
    from rover.formats.bag import BagReader

    history: Estimates = []
    aoa: dict[str, list[Bearing]] = {"/rover/aoa": [], "/rover/bearings": []}
    seen: list[tuple[int, int]] = []
    resolved_recorded = False
    if not path.exists():
        return history, [], seen
    with BagReader(path, "cannot read") as bag:
        for m in bag.messages(RESULT_TYPES):
            msg = bag.decode(m, RESULT_TYPES[m.topic])
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            if m.topic == "/rover/tags":
                history += [tag_entry(stamp, t) for t in msg.tags]
            elif m.topic == "/rover/bearings":
                resolved_recorded = True
                seen.append((stamp, msg.tag_id))
                if msg.chosen >= 0:
                    aoa[m.topic].append((stamp, msg.tag_id, msg.angle_rad, msg.std_rad))
            else:
                aoa[m.topic].append((stamp, msg.tag_id, msg.angle_rad, msg.std_rad))
    if resolved_recorded:
        return history, aoa["/rover/bearings"], seen
    return history, aoa["/rover/aoa"], [(a[0], a[1]) for a in aoa["/rover/aoa"]]


def tag_entry(stamp: int, tag: Any) -> Estimate:
    """One published tag estimate (a rover_msgs/msg/Tag) as a row of RunRecord.tag_history."""
    c00, c01, c10, c11 = (float(v) for v in tag.covariance_xy)
    return (stamp, int(tag.id), float(tag.position.x), float(tag.position.y), bool(tag.observable), c00, c01, c10, c11)


def record(
    final: Poses2D,
    live: Poses2D,
    tags: tuple[np.ndarray, np.ndarray, np.ndarray],
    history: Estimates,
    aoa: list[Bearing],
    heard: dict[int, tuple[int, int]] | None = None,
    seen: list[tuple[int, int]] | None = None,
) -> RunRecord:
    h = np.array(history, dtype=object).reshape(-1, 9)
    a = np.array(aoa, dtype=object).reshape(-1, 4)
    return RunRecord(
        final,
        live,
        *tags,
        tag_history=(
            h[:, 0].astype(np.int64),
            h[:, 1].astype(int),
            h[:, 2:4].astype(float).reshape(-1, 2),
            h[:, 4].astype(bool),
            h[:, 5:9].astype(float).reshape(-1, 2, 2),
        ),
        aoa=(a[:, 0].astype(np.int64), a[:, 1].astype(int), a[:, 2].astype(float), a[:, 3].astype(float)),
        heard=dict(heard or {}),
        seen=(
            np.array([v[0] for v in seen or []], dtype=np.int64),
            np.array([v[1] for v in seen or []], dtype=int),
        ),
    )


def load_run(run_dir: str | Path) -> RunRecord:
    run_dir = Path(run_dir)
    if not (run_dir / "trajectory.tum").exists():
        raise BadInput(f"{run_dir}: no trajectory.tum (is it the --output directory of a `rover run`?)")
    final = poses_of(read_tum(run_dir / "trajectory.tum"))
    live_path = run_dir / "trajectory_live.tum"
    live = (
        poses_of(read_tum(live_path))
        if live_path.exists()
        else Poses2D(np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0))
    )
    tags = (
        _read_tags(run_dir / "tags.csv")
        if (run_dir / "tags.csv").exists()
        else (np.zeros(0, int), np.zeros((0, 2)), np.zeros((0, 2, 2)))
    )
    history, aoa, seen = _read_results(run_dir / "results.mcap")
    heard = _read_heard(run_dir / "tags.csv") if (run_dir / "tags.csv").exists() else {}
    return record(final, live, tags, history, aoa, heard, seen)


RUN_STATUSES = ("", *get_args(RunStatus))
"""The `status` values of run.json ("" for one written before runs had a status)."""


@dataclass(frozen=True)
class RunDescription:
    """What `rover eval` needs of a run's run.json."""

    dataset: Path | None
    status: str
    """complete, partial, interrupted or failed ("" in a run.json written before runs had a status)"""
    reason: str


def read_run_description(run_dir: str | Path, name: str = RUN_FILE) -> RunDescription | None:
    """The run.json (or failed-run.json) of a run folder; None when there is none."""
    path = Path(run_dir) / name
    if not path.exists():
        return None
    try:
        description = json.loads(read_text(path))
    except (ValueError, RecursionError) as exc:
        raise BadInput(f"{path}: not a run description: not JSON ({exc})") from None
    if not isinstance(description, dict):
        raise BadInput(f"{path}: not a run description: a JSON object, got {_json_type(description)}")
    for name in ("status", "reason"):
        if not isinstance(description.get(name, ""), str):
            raise BadInput(f"{path}: field {name}: a string, got {_json_type(description[name])}")
    if description.get("status", "") not in RUN_STATUSES:
        raise BadInput(f"{path}: field status: one of {', '.join(RUN_STATUSES[1:])}, got {description['status']!r}")
    dataset = description.get("dataset")
    if dataset is not None and not isinstance(dataset, str):
        raise BadInput(f"{path}: field dataset: a file path (a string), got {_json_type(dataset)}")
    if dataset is not None and "\x00" in dataset:
        raise BadInput(f"{path}: field dataset: not a file path (it holds a NUL character)")
    reason = " ".join(description.get("reason", "").split())  # one line, whatever the file holds
    return RunDescription(Path(dataset) if dataset else None, description.get("status", ""), reason)


def read_run_files(run_dir: str | Path) -> set[str]:
    """The names of the files the folder's run.json says its run wrote (none without a readable one)."""
    path = Path(run_dir) / RUN_FILE
    try:
        files = json.loads(read_text(path)).get("files", [])
    except (OSError, BadInput, ValueError, RecursionError, AttributeError):
        return set()
    return {f for f in files if isinstance(f, str)} if isinstance(files, list) else set()


def _json_type(value: object) -> str:
    """The JSON name of a decoded value's type, for messages."""
    names = {
        dict: "an object",
        list: "an array",
        str: "a string",
        bool: "a boolean",
        int: "a number",
        float: "a number",
    }
    return names.get(type(value), "null")


def load_truth(source: str | Path, tags_csv: str | Path | None = None) -> Truth | None:
    """Ground truth from a dataset (MCAP file or bag directory) or a TUM file (with a tags CSV)."""
    source = Path(source)
    trajectory: Trajectory | None
    tags: list[TruthTag]
    if source.suffix in (".tum", ".txt"):
        trajectory, tags = _in_time_order(read_tum(source)), []
    elif source.suffix == ".csv":
        raise BadInput(
            f"{source}: a CSV is not a trajectory: the truth is a dataset (.mcap, or a bag folder) or a TUM file "
            "(.tum, .txt); tag positions go to --tags"
        )
    else:
        if source.is_dir():
            candidates = sorted(source.glob("*.mcap"))
            if not candidates:
                raise BadInput(f"{source}: no .mcap dataset in this directory")
            source = candidates[0]
        trajectory, tags = read_dataset_truth(source)
        if trajectory is None:
            return None
    if tags_csv is not None:
        tags = read_tags_csv(tags_csv)
    return Truth(poses_of(trajectory), {t.id: (np.array(t.xyz[:2]), t.nlos) for t in tags})


def _in_time_order(trajectory: Trajectory) -> Trajectory:
    """The poses sorted by stamp (a TUM file need not be; evo accepts it unsorted too)."""
    order = np.argsort(trajectory.stamp_ns, kind="stable")
    return Trajectory(trajectory.stamp_ns[order], trajectory.xyz[order], trajectory.quat_xyzw[order])
