"""Reading what `rover eval` compares: a run's output files and the ground truth, into plain arrays."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

from rover.errors import BadInput
from rover.evaluation.metrics import Poses2D, RunRecord, Truth
from rover.formats.truth import Trajectory, TruthTag, read_dataset_truth, read_tags_csv, read_tum
from rover.geometry import yaw_from_quaternion

RUN_FILE = "run.json"
"""names the dataset a run read, so `rover eval` finds its truth"""


def poses_of(trajectory: Trajectory) -> Poses2D:
    return Poses2D(trajectory.stamp_ns, trajectory.xyz[:, :2], yaw_from_quaternion(*trajectory.quat_xyzw.T))


def _read_tags(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ids, xy, cov = [], [], []
    try:
        with path.open(newline="", encoding="utf-8") as f:
            for number, row in enumerate(csv.DictReader(f), 2):
                try:
                    ids.append(int(row["id"]))
                    xy.append([float(row["x"]) if row["x"] else math.nan, float(row["y"]) if row["y"] else math.nan])
                    cov.append(
                        [
                            [float(row["var_x"] or "nan"), float(row["cov_xy"] or "nan")],
                            [float(row["cov_xy"] or "nan"), float(row["var_y"] or "nan")],
                        ]
                    )
                except (KeyError, TypeError, ValueError):
                    raise BadInput(f"{path}:{number}: not a tags.csv row: {row}") from None
    except OSError as exc:
        raise BadInput(f"{path}: cannot read: {exc.strerror or exc}") from None
    return np.array(ids, dtype=int), np.array(xy).reshape(-1, 2), np.array(cov).reshape(-1, 2, 2)


def _read_results(path: Path) -> tuple[list[tuple[int, int, float, float, bool]], list[tuple[int, int, float, float]]]:
    """Tag estimates over time and the AoAs from results.mcap (empty when the file is absent)."""
    from rover.formats.bag import iter_messages
    from rover.messages import deserialize

    history: list[tuple[int, int, float, float, bool]] = []
    aoa: list[tuple[int, int, float, float]] = []
    if path.exists():
        for m in iter_messages(path, ["/rover/tags", "/rover/aoa"], failure="cannot read"):
            msg = deserialize(m.data, m.schema)
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            if m.topic == "/rover/aoa":
                aoa.append((stamp, msg.tag_id, msg.angle_rad, msg.std_rad))
            else:
                history += [(stamp, t.id, t.position.x, t.position.y, t.observable) for t in msg.tags]
    return history, aoa


def record(
    final: Poses2D,
    live: Poses2D,
    tags: tuple[np.ndarray, np.ndarray, np.ndarray],
    history: list[tuple[int, int, float, float, bool]],
    aoa: list[tuple[int, int, float, float]],
) -> RunRecord:
    h = np.array(history, dtype=object).reshape(-1, 5)
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
        ),
        aoa=(a[:, 0].astype(np.int64), a[:, 1].astype(int), a[:, 2].astype(float), a[:, 3].astype(float)),
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
    history, aoa = _read_results(run_dir / "results.mcap")
    return record(final, live, tags, history, aoa)


def run_dataset(run_dir: str | Path) -> Path | None:
    """The dataset a run read, as its run.json names it."""
    path = Path(run_dir) / RUN_FILE
    if not path.exists():
        return None
    try:
        dataset = json.loads(path.read_text(encoding="utf-8")).get("dataset")
    except (OSError, ValueError) as exc:
        raise BadInput(f"{path}: not a run description: {exc}") from None
    return Path(dataset) if dataset else None


def load_truth(source: str | Path, tags_csv: str | Path | None = None) -> Truth | None:
    """Ground truth from a dataset (MCAP file or bag directory) or a TUM file (with a tags CSV)."""
    source = Path(source)
    trajectory: Trajectory | None
    tags: list[TruthTag]
    if source.suffix in (".tum", ".txt"):
        trajectory, tags = read_tum(source), []
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
