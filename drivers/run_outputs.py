"""`run_outputs`: the files of a run beside `results.mcap`: the trajectories as TUM and the tags as CSV.

`trajectory.tum` holds each epoch's final estimate (when it left the SLAM window, or at the end),
`trajectory_live.tum` the same epochs as estimated at their own time. `tags.csv` holds each tag's
final estimate with its covariance and the times it was first heard, first localized and last
heard, all on the header-stamp clock. `timing.json` summarises the wall-clock timings (kept out
of results.mcap, so the same input gives the same bytes there). When `dataset` has ground truth,
`metrics.json` and the figures follow, computed as `rover eval` does; after an interrupt only when
they fit in the time left (`rover eval OUT --figures` writes the figures later).

The run takes the folder for itself and writes into a staging folder in it; its files are renamed
into place only when the run ended with results (rover.formats.output_folder), replacing an earlier
run's and removing those of an earlier run's files this one did not write. A failed run leaves the
earlier results as they were and writes `failed-run.json` beside them. `run.json` (or
`failed-run.json`) says how the run ended:
its `status` (complete, partial, interrupted, failed), the `reason`, the hosts `lost` during a
partial run (each with its reason and the time it was noticed), what each operator received,
sent and dropped, and where each operator spent its time (`profile`: decoding, handler, encoding,
sending, waiting for input, the runtime's share, closing, and its thread's CPU time, in seconds),
with in a run across hosts or worker processes the operators of every host that reported them and
the host each ran on (`hosts`).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rover.errors import BadInput, OutputFailed
from rover.evaluation.figures import FIGURE_FILES, write_figures
from rover.evaluation.metrics import Truth, evaluate, poses_of_messages
from rover.formats.atomic_file import write_aside
from rover.formats.output_folder import OutputFolder, claim, refuse_input, release
from rover.formats.run_dir import FAILED_RUN_FILE, RUN_FILE, Bearing, Estimates, load_truth, record, tag_entry
from rover.messages import stamp_ns
from rover.operator import COMPLETE, In, Operator, RunOutcome

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
    "status",
    "reason",
)
STATES = ("heard", "ambiguous", "judging", "contradicted", "uncertain", "localized")
"""tags.csv's `status`: rover_msgs/msg/TagStatus's states by value"""


def seconds(ns: int | None) -> str:
    if ns is None:
        return ""
    return f"{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}"


def status_columns(status: Any) -> list[str]:
    """tags.csv's status and reason of a TagStatus (empty without one), the reason quoted as CSV does."""
    if status is None:
        return ["", ""]
    state = STATES[status.state] if status.state < len(STATES) else str(status.state)
    return [state, '"' + status.reason.replace('"', '""') + '"']


def tum_line(msg: Any) -> str:
    p, q = msg.pose.position, msg.pose.orientation
    return f"{seconds(stamp_ns(msg))} {p.x:.6f} {p.y:.6f} {p.z:.6f} {q.x:.9f} {q.y:.9f} {q.z:.9f} {q.w:.9f}\n"


TIMING_FILE = "timing.json"
METRICS_FILE = "metrics.json"
ESTIMATE_FILES = ("trajectory.tum", "trajectory_live.tum", "tags.csv")
RUN_FILES = (*ESTIMATE_FILES, TIMING_FILE, METRICS_FILE, *FIGURE_FILES, RUN_FILE)
"""Everything this operator may write: what a new run's results replace (an earlier run's file this
run did not write is removed with them)."""
METRICS_MIN_S = 0.3
"""After an interrupt, metrics are computed only with this much of the time budget left (they take
about 0.1 s: the truth is read before the run). Figures are never drawn after an interrupt:
matplotlib's start-up alone takes about 1 s."""


def write_atomic(path: Path, text: str) -> None:
    """Write `text` to `path`, whole or not at all."""
    write_aside(path, lambda partial: partial.write_text(text, encoding="utf-8"))


@dataclass
class _TagRecord:
    channel: int = 0
    first_heard: int | None = None
    last_heard: int | None = None
    first_localized: int | None = None
    last: Any = None
    status: Any = None


@dataclass(frozen=True)
class RunOutputsParams:
    out: str = "rover-out"
    dataset: str = ""
    """the dataset the run reads: named in run.json; when it has ground truth, metrics and figures follow"""


class RunOutputs(Operator):
    """Writes trajectory.tum, trajectory_live.tum and tags.csv (and metrics with truth) into `out`."""

    cpu_weight = 0.4
    folder_param = "out"

    inputs = {
        "trajectory": In("geometry_msgs/msg/PoseStamped", doc="final poses (slam/trajectory)"),
        "pose": In("geometry_msgs/msg/PoseStamped", doc="live poses (slam/pose)"),
        "tags": In("rover_msgs/msg/TagArray"),
        "aoa": In(
            "rover_msgs/msg/Aoa",
            required=False,
            doc="for when each tag was heard, and the AoA metrics: the SLAM's bearings (those with a chosen candidate)",
        ),
        "timing": In("rover_msgs/msg/Timing", required=False, doc="wall-clock timings, summarised in timing.json"),
        "status": In(
            "rover_msgs/msg/TagStatus",
            required=False,
            doc="each tag's latest state and why (slam/status): tags.csv's status and reason",
        ),
    }
    Params = RunOutputsParams

    def __init__(self, params: RunOutputsParams | None = None):
        super().__init__(params)
        self.final: list[Any] = []
        self.live: list[Any] = []
        self.tags: dict[int, _TagRecord] = {}
        self.history: Estimates = []
        self.aoa: list[Bearing] = []
        self.seen: list[tuple[int, int]] = []
        """(stamp, tag id) of every bearing, resolved or not"""
        self.timing: dict[str, list[float]] = {}
        self.written: list[str] = []
        """the files this run wrote, by name (staged until the run's end)"""
        self.folder: OutputFolder | None = None
        self.notes: list[str] = []
        self.out = Path(self.params.out)
        self.truth: Truth | None = None
        self.unresolved = 0

    def start(self) -> None:
        """Take the output folder for this run (refused when it holds the dataset, or another run has
        it); read the dataset's ground truth now, so that after an interrupt the metrics fit in the
        time budget."""
        if self.params.dataset:
            refuse_input(self.out, [self.params.dataset])
        self.folder = claim(self.out)
        if self.params.dataset:
            self.truth = load_truth(Path(self.params.dataset))
            if self.truth is None:
                log.info("outputs: %s has no ground truth: no metrics", self.params.dataset)

    def on_input(self, port: str, msg: Any, stamp: int):
        if port == "timing":
            self.timing.setdefault(msg.stage, []).append(msg.wall_s)
        elif port == "trajectory":
            self.final.append(msg)
        elif port == "status":
            self.tags.setdefault(msg.id, _TagRecord()).status = msg
        elif port == "pose":
            self.live.append(msg)
        elif port == "aoa":
            record = self.tags.setdefault(msg.tag_id, _TagRecord())
            record.channel = msg.channel
            s = stamp_ns(msg)
            record.first_heard = s if record.first_heard is None else min(record.first_heard, s)
            record.last_heard = s if record.last_heard is None else max(record.last_heard, s)
            self.seen.append((s, msg.tag_id))
            if msg.chosen >= 0:
                self.aoa.append((s, msg.tag_id, msg.angle_rad, msg.std_rad))
            else:
                self.unresolved += 1
        else:
            for tag in msg.tags:
                self.history.append(tag_entry(stamp_ns(msg), tag))
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
                        *status_columns(r.status),
                    ]
                )
                + "\n"
            )
        return "".join(lines)

    def close(self, outcome: RunOutcome = COMPLETE) -> None:
        """The estimates and timings; then metrics and figures, when there is truth and time."""
        if not outcome.keeps_outputs or self.folder is None:
            return
        self._write("trajectory.tum", "".join(tum_line(m) for m in sorted(self.final, key=stamp_ns)))
        self._write("trajectory_live.tum", "".join(tum_line(m) for m in sorted(self.live, key=stamp_ns)))
        self._write("tags.csv", self.tags_csv())
        self._write(TIMING_FILE, json.dumps(self.timing_summary(), indent=2) + "\n")
        if self.unresolved:
            self.notes.append(
                f"{self.unresolved} AoA(s) left the SLAM window before their tag was found: no candidate was "
                "chosen for them, and the AoA metrics leave them out"
            )
        if self.truth is not None and self.final:
            self._evaluate(self.truth, outcome)
        elif self.truth is not None:
            self._note("no metrics: no epoch left the SLAM window (no final pose)")

    def report(self, outcome: RunOutcome) -> None:
        """A run with results: its files and run.json renamed into place. A failed run (or one whose
        files cannot be put in place): its files dropped, the earlier results kept, failed-run.json
        beside them. Nothing when the folder was never taken (another run's, or not writable: the
        run failed saying so)."""
        folder, self.folder = self.folder, None
        if folder is None:
            return
        dataset = str(Path(self.params.dataset).resolve()) if self.params.dataset else ""
        failure: OutputFailed | None = None
        try:
            if outcome.keeps_outputs:
                try:
                    write_atomic(
                        folder.stage(RUN_FILE), json.dumps(self.run_description(dataset, outcome), indent=2) + "\n"
                    )
                    folder.commit([*self.written, RUN_FILE], stale=[*RUN_FILES, FAILED_RUN_FILE])
                    return
                except OutputFailed as exc:
                    failure = exc
                    outcome = dataclasses.replace(outcome, status="failed", reason=str(exc))
            folder.discard([*self.written, RUN_FILE])
            self.written = []
            write_atomic(
                folder.path / FAILED_RUN_FILE, json.dumps(self.run_description(dataset, outcome), indent=2) + "\n"
            )
            if failure is not None:
                raise failure
        finally:
            release(folder)

    def _note(self, text: str) -> None:
        """Something the user should know about this run's files: logged, and kept in run.json."""
        log.warning("outputs: %s", text)
        self.notes.append(text)

    def _write(self, name: str, text: str) -> None:
        assert self.folder is not None  # close() writes only with the folder taken
        write_atomic(self.folder.stage(name), text)
        self.written.append(name)

    def timing_summary(self) -> dict[str, dict[str, float | int]]:
        """Per timed stage: how many, and the median, 90th percentile, largest and total wall-clock seconds."""
        summary = {}
        for stage, values in sorted(self.timing.items()):
            v = np.array(values)
            summary[stage] = {
                "count": len(v),
                "median_s": float(np.median(v)),
                "p90_s": float(np.percentile(v, 90)),
                "max_s": float(v.max()),
                "total_s": float(v.sum()),
            }
        return summary

    def run_description(self, dataset: str, outcome: RunOutcome = COMPLETE) -> dict[str, Any]:
        """run.json: how the run ended and what it processed, the dataset read (so `rover eval` finds
        its truth), the pipeline and the command line's settings."""
        pipeline = str(Path(self.context.pipeline_file).resolve()) if self.context.pipeline_file else ""
        counts = {
            name: {"received": dict(c.received), "sent": dict(c.sent), "dropped": dict(c.dropped)}
            for name, c in sorted(outcome.counts.items())
        }
        return {
            "status": outcome.status,
            "reason": outcome.reason,
            "lost": [{"host": h.host, "reason": h.reason, "time": h.time} for h in outcome.lost],
            "dataset": dataset,
            "pipeline": pipeline,
            "command_line": dict(self.context.command_line),
            "files": sorted(self.written),
            "notes": self.notes,
            "received": sum(sum(c["received"].values()) for c in counts.values()),
            "dropped": sum(sum(c["dropped"].values()) for c in counts.values()),
            "operators": counts,
            "profile": {name: dataclasses.asdict(prof) for name, prof in sorted(outcome.profile.items())},
            "hosts": dict(sorted(outcome.hosts.items())),
        }

    def _evaluate(self, truth: Truth, outcome: RunOutcome) -> None:
        """metrics.json and figures, when the dataset carries ground truth and the time budget allows."""
        if outcome.time_left_s() < METRICS_MIN_S:
            self._note(f"metrics and figures skipped after the interrupt: run `rover eval {self.out} --figures`")
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
            {
                i: (r.first_heard, r.last_heard)
                for i, r in self.tags.items()
                if r.first_heard is not None and r.last_heard is not None
            },
            self.seen,
        )
        try:
            metrics = evaluate(run, truth)
        except BadInput as exc:  # the estimate stands; only the comparison with this truth is impossible
            self._note(f"no metrics: {exc}")
            return
        self._write(METRICS_FILE, json.dumps(metrics, indent=2) + "\n")
        if outcome.status == "interrupted":
            self._note(f"figures skipped after the interrupt: run `rover eval {self.out} --figures`")
            return
        assert self.folder is not None  # close() runs this only with the folder taken
        try:
            self.written += [p.name for p in write_figures(run, truth, self.folder.staging)]
        except OutputFailed:
            self.folder.discard(FIGURE_FILES)
            raise
