"""`run_outputs`: the files of a run beside `results.mcap`: the trajectories as TUM and the tags as CSV.

`trajectory.tum` holds each epoch's final estimate (when it left the SLAM window, or at the end),
`trajectory_live.tum` the same epochs as estimated at their own time. `tags.csv` holds each tag's
final estimate with its covariance and the times it was first heard, first localized and last
heard, all on the header-stamp clock. Files appear only once complete (written aside, renamed).
When `truth` names a dataset (or TUM file) with ground truth, `metrics.json` and the figures
follow, computed as `rover eval` does.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rover.evaluation.figures import write_figures
from rover.evaluation.metrics import evaluate, poses_of_messages
from rover.formats.run_dir import RUN_FILE, load_truth, record
from rover.messages import stamp_ns
from rover.operator import In, Operator

log = logging.getLogger("rover.outputs")

TAG_COLUMNS = (
    "id",
    "channel",
    "x",
    "y",
    "z",
    "var_x",
    "cov_xy",
    "var_y",
    "observable",
    "first_heard_s",
    "first_localized_s",
    "last_heard_s",
)


def seconds(ns: int | None) -> str:
    if ns is None:
        return ""
    return f"{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}"


def tum_line(msg: Any) -> str:
    p, q = msg.pose.position, msg.pose.orientation
    return f"{seconds(stamp_ns(msg))} {p.x:.6f} {p.y:.6f} {p.z:.6f} {q.x:.9f} {q.y:.9f} {q.z:.9f} {q.w:.9f}\n"


def write_atomic(path: Path, text: str) -> None:
    partial = path.with_name(f".{path.name}.partial")
    partial.write_text(text, encoding="utf-8")
    partial.replace(path)


@dataclass
class _TagRecord:
    channel: int = 0
    first_heard: int | None = None
    last_heard: int | None = None
    first_localized: int | None = None
    last: Any = None


@dataclass(frozen=True)
class RunOutputsParams:
    out: str = "rover-out"
    dataset: str = ""
    """the dataset the run reads: named in run.json; when it has ground truth, metrics and figures follow"""


class RunOutputs(Operator):
    """Writes trajectory.tum, trajectory_live.tum and tags.csv (and metrics with truth) into `out`."""

    inputs = {
        "trajectory": In("geometry_msgs/msg/PoseStamped", doc="final poses (slam/trajectory)"),
        "pose": In("geometry_msgs/msg/PoseStamped", doc="live poses (slam/pose)"),
        "tags": In("rover_msgs/msg/TagArray"),
        "aoa": In("rover_msgs/msg/Aoa", required=False, doc="for when each tag was heard"),
    }
    Params = RunOutputsParams

    def __init__(self, params: RunOutputsParams | None = None):
        super().__init__(params)
        self.final: list[Any] = []
        self.live: list[Any] = []
        self.tags: dict[int, _TagRecord] = {}
        self.history: list[tuple[int, int, float, float, bool]] = []
        self.aoa: list[tuple[int, int, float, float]] = []

    def on_input(self, port: str, msg: Any, stamp: int):
        if port == "trajectory":
            self.final.append(msg)
        elif port == "pose":
            self.live.append(msg)
        elif port == "aoa":
            record = self.tags.setdefault(msg.tag_id, _TagRecord())
            record.channel = msg.channel
            s = stamp_ns(msg)
            record.first_heard = s if record.first_heard is None else min(record.first_heard, s)
            record.last_heard = s if record.last_heard is None else max(record.last_heard, s)
            self.aoa.append((s, msg.tag_id, msg.angle_rad, msg.std_rad))
        else:
            for tag in msg.tags:
                self.history.append((stamp_ns(msg), tag.id, tag.position.x, tag.position.y, tag.observable))
                record = self.tags.setdefault(tag.id, _TagRecord())
                record.channel = record.channel or tag.channel
                record.last = tag
                if tag.observable and record.first_localized is None:
                    record.first_localized = stamp_ns(msg)
        return ()

    def tags_csv(self) -> str:
        lines = [",".join(TAG_COLUMNS) + "\n"]
        for tag_id in sorted(self.tags):
            r = self.tags[tag_id]
            t = r.last
            known = t is not None and r.first_localized is not None
            cov = list(t.covariance_xy) if t is not None else [math.nan] * 4
            position = [f"{t.position.x:.6f}", f"{t.position.y:.6f}", f"{t.position.z:.6f}"] if known else ["", "", ""]
            variances = [f"{cov[0]:.9g}", f"{cov[1]:.9g}", f"{cov[3]:.9g}"] if t is not None else ["", "", ""]
            lines.append(
                ",".join(
                    [
                        str(tag_id),
                        str(r.channel),
                        *position,
                        *variances,
                        "1" if t is not None and t.observable else "0",
                        seconds(r.first_heard),
                        seconds(r.first_localized),
                        seconds(r.last_heard),
                    ]
                )
                + "\n"
            )
        return "".join(lines)

    def close(self, complete: bool = True) -> None:
        if not complete:
            return
        out = Path(self.params.out)
        out.mkdir(parents=True, exist_ok=True)
        write_atomic(out / "trajectory.tum", "".join(tum_line(m) for m in sorted(self.final, key=stamp_ns)))
        write_atomic(out / "trajectory_live.tum", "".join(tum_line(m) for m in sorted(self.live, key=stamp_ns)))
        write_atomic(out / "tags.csv", self.tags_csv())
        dataset = str(Path(self.params.dataset).resolve()) if self.params.dataset else ""
        write_atomic(out / RUN_FILE, json.dumps(self.run_description(dataset), indent=2) + "\n")
        if dataset and self.final:
            self._evaluate(out, Path(dataset))

    def run_description(self, dataset: str) -> dict[str, Any]:
        """run.json: the dataset read (so `rover eval` finds its truth), the pipeline and the command
        line's settings."""
        pipeline = str(Path(self.context.pipeline_file).resolve()) if self.context.pipeline_file else ""
        return {"dataset": dataset, "pipeline": pipeline, "command_line": dict(self.context.command_line)}

    def _evaluate(self, out: Path, dataset: Path) -> None:
        """metrics.json and figures, when the dataset carries ground truth."""
        truth = load_truth(dataset)
        if truth is None:
            log.info("outputs: %s has no ground truth: no metrics", dataset)
            return
        ids = np.array(sorted(self.tags), dtype=int)
        last = [self.tags[i].last for i in ids]
        localized = [self.tags[i].first_localized is not None and t is not None for i, t in zip(ids, last, strict=True)]
        xy = np.array(
            [
                [t.position.x, t.position.y] if ok else [math.nan, math.nan]
                for t, ok in zip(last, localized, strict=True)
            ]
        )
        cov = np.array(
            [np.reshape(t.covariance_xy, (2, 2)) if t is not None else np.full((2, 2), math.nan) for t in last]
        )
        run = record(
            poses_of_messages(sorted(self.final, key=stamp_ns)),
            poses_of_messages(sorted(self.live, key=stamp_ns)),
            (ids, xy.reshape(-1, 2), cov.reshape(-1, 2, 2)),
            self.history,
            self.aoa,
        )
        metrics = evaluate(run, truth)
        write_atomic(out / "metrics.json", json.dumps(metrics, indent=2) + "\n")
        write_figures(run, truth, out)
