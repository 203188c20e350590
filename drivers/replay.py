"""`dataset_replay`: plays a dataset (an MCAP file that is a ROS 2 bag) into the pipeline.

Messages leave as their recorded CDR bytes, in log-time order, as fast as possible or paced
at `speed` times real time. The rig description (MCAP metadata `rover.setup`) is sent once
on `setup`, stamped at the first message.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from rover.errors import BadInput, SpecError
from rover.formats.bag import BagReader, shown
from rover.formats.bearings_csv import Bearings, read_bearings
from rover.formats.csi_sources.wiros import looks_like_bag
from rover.formats.dataset import CAPTURE_TOPIC, CAPTURE_TYPE, SETUP_METADATA
from rover.formats.dataset import TOPICS as DEFAULT_TOPICS
from rover.formats.rig import load_rig
from rover.formats.wiros_bearings import read_wiros_bearings
from rover.messages import Raw, cdr_stamp_ns, header, make, message_class
from rover.operator import Emit, Out, Source, Watermark
from rover.pipeline.params import Checked, PositiveFloat

log = logging.getLogger("rover.dataset_replay")

READ_FAILURE = "not a readable MCAP dataset"


@dataclass(frozen=True)
class ReplayParams(Checked):
    path: str = ""
    speed: Literal["max"] | PositiveFloat = "max"
    topics: dict[str, str] = field(default_factory=lambda: {**DEFAULT_TOPICS, "capture": CAPTURE_TOPIC})
    setup: str = ""
    """A setup.yaml to send instead of the dataset's own rig description (or when it has none)."""
    bearings: str = ""
    """Bearings from another AoA front end, sent on `aoa` in time order among the dataset's
    messages: the SLAM then runs from them, no CSI needed. A CSV (rover.formats.bearings_csv), or a
    ROS bag of WiROS's `rf_msgs/msg/Bearing` (rover.formats.wiros_bearings)."""
    bearings_topic: str = ""
    """the bag's topic of rf_msgs/msg/Bearing (empty: its one, or /bearing among several)"""
    bearing_std_deg: PositiveFloat = 10.0
    """the std of a bag's bearings, which carry none (a real building's: a median error of 6-12 deg)"""
    radio_yaw_deg: float = 0.0
    """where the radio that measured a bag's bearings faces on the robot (deg, counterclockwise from
    its x axis): their angles are in the radio's frame"""


class DatasetReplay(Source):
    """Replays `/csi` (or `/csi/capture`), `/imu/data` and `/odom` of a dataset, and its rig description."""

    cpu_weight = 1.2

    outputs = {
        "csi": Out("rover_msgs/msg/CsiFrame", "raw CSI Tool records"),
        "capture": Out(CAPTURE_TYPE, "another tool's CSI, decoded, a transmitter per tag_id (a converted WiROS bag)"),
        "imu": Out("sensor_msgs/msg/Imu", "IMU samples"),
        "odom": Out("nav_msgs/msg/Odometry", "wheel odometry, when recorded"),
        "setup": Out("rover_msgs/msg/RigSetup", "the rig description, once at the start"),
        "aoa": Out("rover_msgs/msg/Aoa", "the `bearings` file's bearings, one candidate each (none without it)"),
    }
    Params = ReplayParams

    def __init__(self, params: ReplayParams | None = None):
        super().__init__(params)
        p = self.params
        if not p.path:
            raise BadInput("dataset_replay: no dataset given (pass --dataset PATH or set params.path)")
        self.path = Path(p.path)
        if self.path.is_dir():
            raise BadInput(
                f"{self.path}: is a folder, not a dataset: a ROS 2 bag or a recording folder becomes one with "
                f"`rover convert {self.path} -o DATASET.mcap`"
            )
        if not self.path.is_file():
            raise BadInput(f"{self.path}: no such dataset file")
        for port in p.topics:
            if port not in self.outputs or port in ("setup", "aoa"):
                raise BadInput(f"dataset_replay: topics maps unknown port {port!r} (ports: csi, capture, imu, odom)")
        self._port_of = {topic: port for port, topic in p.topics.items()}
        self._setup_yaml, self._channels, self._span = self._inspect()
        self._bearings = self._read_bearings() if p.bearings else None
        self._sent = 0
        """bearings of the file sent so far"""
        self._done = 0
        if p.setup:
            try:
                rig = load_rig(p.setup)
            except SpecError as exc:
                raise BadInput("; ".join(str(d) for d in exc.diagnostics)) from None
            if self._setup_yaml is not None:
                log.warning("dataset_replay: %s replaces the rig description stored in %s", p.setup, self.path)
            self._setup_yaml = rig.text

    def _read_bearings(self) -> Bearings:
        """The `bearings` file's: a CSV, or a bag of rf_msgs/msg/Bearing (what it drops counted)."""
        p = self.params
        if not looks_like_bag(Path(p.bearings)):
            return read_bearings(p.bearings)
        std, yaw = math.radians(p.bearing_std_deg), math.radians(p.radio_yaw_deg)
        bearings, dropped = read_wiros_bearings(p.bearings, std, yaw, p.bearings_topic or None)
        for reason, count in dropped.items():
            self.drop(reason, count)
        return bearings

    def _inspect(self) -> tuple[str | None, dict[str, str], tuple[int, int] | None]:
        """Read the summary: which wanted topics exist with the right types, the rig description,
        and the span of log time the file covers (None when it holds none of the wanted topics)."""
        with BagReader(self.path, READ_FAILURE) as bag:
            summary = bag.summary()
            metadata = bag.metadata()
        if summary is None:
            raise BadInput(f"{self.path}: MCAP file has no summary section (was it closed properly?)")
        found: dict[str, str] = {}
        for channel in summary.channels:
            port = self._port_of.get(channel.topic)
            if port is None:
                continue
            wanted = self.outputs[port].type
            if channel.schema != wanted or channel.encoding != "cdr":
                got = f"{shown(channel.schema) if channel.schema else 'no schema'} ({shown(channel.encoding)})"
                raise BadInput(f"{self.path}: topic {channel.topic} is {got}, expected {wanted} (cdr)")
            found[channel.topic] = port
        setup = metadata.get(SETUP_METADATA, {}).get("yaml")
        stats = summary.statistics
        span = None
        if found and stats is not None and stats.message_count:
            span = (stats.start_ns, stats.end_ns)
        return setup, found, span

    def span_ns(self) -> tuple[int, int] | None:
        return self._span

    def _skip_bearings_before(self, start_ns: int) -> None:
        """Drop (and count) the bearings before the dataset's first message: the run's stamps start
        there, and a source's stamps never go back."""
        if self._bearings is not None:
            early = int(np.searchsorted(self._bearings.stamp_ns, start_ns, side="left"))
            if early:
                self.drop("bearings before the dataset's first message", early)
            self._sent = max(self._sent, early)

    def _bearings_until(self, until_ns: int | None) -> list[Emit]:
        """The `bearings` file's bearings up to `until_ns` (None: all the rest) not sent yet, as Aoa
        messages of one candidate."""
        b = self._bearings
        if b is None:
            return []
        end = len(b) if until_ns is None else int(np.searchsorted(b.stamp_ns, until_ns, side="right"))
        start, self._sent = self._sent, max(self._sent, end)
        return [
            Emit(
                "aoa",
                make(
                    "rover_msgs/msg/Aoa",
                    header=header(int(b.stamp_ns[k]), "base_link"),
                    tag_id=int(b.tag[k]),
                    angle_rad=float(b.angle_rad[k]),
                    std_rad=float(b.std_rad[k]),
                    candidate_angles_rad=b.angle_rad[k : k + 1],
                    candidate_stds_rad=b.std_rad[k : k + 1],
                    candidate_powers=np.ones(1),
                    candidate_jumps=np.zeros(1, np.uint16),
                    chosen=-1,
                ),
                int(b.stamp_ns[k]),
            )  # fmt: skip
            for k in range(start, end)
        ]

    def run(self, stop: threading.Event) -> Iterator[Emit | Watermark]:
        speed = self.params.speed
        RigSetup = message_class("rover_msgs/msg/RigSetup")
        self._sent = 0
        started_wall = started_log = None
        with BagReader(self.path, READ_FAILURE) as bag:
            for message in bag.messages(self._channels, log_time_order=True):
                if stop.is_set():
                    return
                if started_log is None:
                    started_log, started_wall = message.log_time_ns, time.monotonic()
                    self._skip_bearings_before(started_log)
                    if self._setup_yaml is not None:
                        yield Emit(
                            "setup",
                            RigSetup(header=header(message.log_time_ns, "base_link"), setup_yaml=self._setup_yaml),
                            message.log_time_ns,
                        )
                elif speed != "max":
                    due = started_wall + (message.log_time_ns - started_log) / 1e9 / speed
                    while (wait := due - time.monotonic()) > 0:
                        if stop.wait(min(wait, 0.1)):
                            return
                port = self._channels[message.topic]
                self._done += 1
                try:
                    stamp = cdr_stamp_ns(message.data)
                except ValueError:
                    self.drop(f"messages on {message.topic} too short to carry a header")
                    continue
                yield from self._bearings_until(stamp)
                yield Emit(port, Raw(self.outputs[port].type, message.data), stamp)
        yield from self._bearings_until(None)
        if not self._done:
            wanted = ", ".join(self.params.topics.values())
            log.warning("%s: no messages on %s: the run's outputs are empty", self.path, wanted)
