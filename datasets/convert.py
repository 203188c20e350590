"""`rover convert`: ROS 1 / ROS 2 bags (and recording folders) to a Rover dataset.

A dataset is one MCAP file that is also a ROS 2 bag: `/csi`, `/imu/data`, optional `/odom`,
optional ground truth (`/groundtruth/pose`, `/groundtruth/tags`), and the rig description and
provenance as MCAP metadata. Messages are decoded with the source bag's own definitions, so
custom definitions are honoured, and logged at their header stamp (event time).
"""

from __future__ import annotations

import logging
import math
import struct
import sys
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from rosbags.highlevel import AnyReader, AnyReaderError

from rover.datasets.capture_csi import capture_messages
from rover.errors import BadInput, SpecError
from rover.formats import dataset
from rover.formats.bag import BagReader, BagWriter, check_output
from rover.formats.csi_sources import wiros
from rover.formats.rig import Rig, load_rig
from rover.formats.truth import read_tags_csv, read_tum
from rover.messages import Raw, cdr_stamp_ns, header, make, serialize

log = logging.getLogger("rover.convert")
T = TypeVar("T")

ROLES = dataset.TYPES
OUTPUT_TOPICS = dataset.TOPICS
TRUTH_POSE, TRUTH_TAGS = "/groundtruth/pose", "/groundtruth/tags"
STANDARD_GRAVITY_M_S2 = 9.80665
G_UNITS_BAND = (0.8, 1.2)
"""Median |a| over the first second in this band (in the file's units) means the IMU reports g."""
RECORDING_FILES = {"setup": "setup.yaml", "truth": "truth_robot.tum", "tags": "truth_tags.csv"}


@dataclass
class Report:
    """What a conversion wrote and what it had to fix or drop."""

    output: Path
    topics: dict[str, str] = field(default_factory=dict)
    """role -> source topic"""
    written: Counter = field(default_factory=Counter)
    dropped: Counter = field(default_factory=Counter)
    resorted: Counter = field(default_factory=Counter)
    imu_in_g: bool = False
    capture: bool = False
    """the CSI is WiROS's rf_msgs/msg/Wifi, written decoded on dataset.CAPTURE_TOPIC"""

    def lines(self) -> list[str]:
        written = {**OUTPUT_TOPICS, "csi": dataset.CAPTURE_TOPIC} if self.capture else OUTPUT_TOPICS
        out = [f"{role}: {topic} -> {written.get(role, topic)}" for role, topic in self.topics.items()]
        out += [f"wrote {n:,} messages on {topic}" for topic, n in sorted(self.written.items())]
        return out


@dataclass(frozen=True)
class Sources:
    bags: list[Path]
    setup: Path | None
    truth: Path | None
    tags: Path | None


def resolve_sources(paths: Sequence[str | Path]) -> Sources:
    """Expand recording folders (a `bag/` folder with setup.yaml and truth files beside it)."""
    bags: list[Path] = []
    found: dict[str, Path] = {}
    for raw in paths:
        path = Path(raw)
        if not path.exists():
            raise BadInput(f"{path}: no such file or folder")
        if path.is_dir() and (path / "bag").is_dir() and not (path / "metadata.yaml").exists():
            bags.append(path / "bag")
            for key, name in RECORDING_FILES.items():
                if (path / name).is_file():
                    found.setdefault(key, path / name)
        elif path.is_file() and path.suffix == ".db3":
            if not (path.parent / "metadata.yaml").is_file():
                raise BadInput(f"{path}: a .db3 file needs the metadata.yaml of its bag folder beside it")
            bags.append(path.parent)
        else:
            bags.append(path)
    return Sources(bags, found.get("setup"), found.get("truth"), found.get("tags"))


def _choose_topics(reader: AnyReader, rig: Rig, overrides: dict[str, str]) -> dict[str, str | None]:
    """role -> source topic: --topic, else the setup's topics:, else the one topic of the role's type."""
    by_topic = {c.topic: c.msgtype for c in reader.connections}
    listing = ", ".join(f"{t} ({m})" for t, m in sorted(by_topic.items())) or "none"
    chosen: dict[str, str | None] = {}
    for role, msgtype in ROLES.items():
        topic: str | None
        if role in overrides:
            topic = overrides[role]
        elif role in rig.topics and (rig.topics[role] is None or rig.topics[role] in by_topic):
            topic = rig.topics[role]
        else:
            candidates = [t for t, m in by_topic.items() if m == msgtype]
            topic = candidates[0] if len(candidates) == 1 else None
            if len(candidates) > 1:
                raise BadInput(
                    f"several {msgtype} topics ({', '.join(candidates)}): choose one with --topic {role}=NAME"
                )
        if topic is not None and topic not in by_topic:
            raise BadInput(f"topic {topic} for {role} is not in the bag; topics there: {listing}")
        chosen[role] = topic
    if chosen["imu"] is None:
        raise BadInput(f"no IMU topic (sensor_msgs/msg/Imu) found; topics there: {listing}")
    wifi = [t for t, m in by_topic.items() if m == wiros.WIFI_TYPE]
    if chosen["csi"] is None and rig.topics.get("csi", "/csi") is not None and wifi:
        if len(wifi) > 1:
            raise BadInput(f"several {wiros.WIFI_TYPE} topics ({', '.join(wifi)}): choose one with --topic csi=NAME")
        chosen["csi"] = wifi[0]
    if chosen["csi"] is None and rig.topics.get("csi", "/csi") is not None:
        raise BadInput(
            f"no CSI topic (rover_msgs/msg/CsiFrame, or WiROS's {wiros.WIFI_TYPE}) found; topics there: {listing}. "
            "For an IMU/odometry-only "
            "dataset say so in the setup: topics: {csi: null}"
        )
    return chosen


def _read_guarded(records: Iterator[T], bags: list[Path]) -> Iterator[T]:
    """The records of a bag reader; whatever the reader raises on a truncated or corrupt file
    (rosbags' ReaderError, a zstd or lz4 error, struct.error, ...) is BadInput naming the bags.
    Only the reader's own `next()` is guarded: errors of the code consuming the records are not."""
    while True:
        try:
            record = next(records)
        except StopIteration:
            return
        except Exception as exc:  # noqa: BLE001 - any failure of the library on untrusted bytes
            names = ", ".join(map(str, bags))
            raise BadInput(f"{names}: cannot read as a ROS bag: {type(exc).__name__}: {exc}") from None
        yield record


def _stamp_of(payload: bytes | None) -> int | None:
    """The header stamp of a CDR payload; None when there is none or it is too short to hold one."""
    try:
        return cdr_stamp_ns(payload) if payload is not None else None
    except (ValueError, struct.error):
        return None


def _stamp(msg: Any, fallback_ns: int) -> int:
    stamp = getattr(getattr(msg, "header", None), "stamp", None)
    return stamp.sec * 1_000_000_000 + stamp.nanosec if stamp is not None else fallback_ns


def _time_bound(value: float | None, start_ns: int) -> int | None:
    """--start/--end: seconds from the start of the bag, or absolute seconds (anything past 1e9)."""
    if value is None:
        return None
    return int(round(value * 1e9)) if value > 1e9 else start_ns + int(round(value * 1e9))


def _finite(values: Sequence[float]) -> bool:
    return all(math.isfinite(v) for v in values)


_F64x3 = struct.Struct("<3d")


def _imu_vectors_at(payload: bytes) -> tuple[int, int]:
    """Byte offsets of angular_velocity and linear_acceleration in a little-endian CDR Imu."""
    (length,) = struct.unpack_from("<I", payload, 4 + 8)
    orientation = (12 + length + 7) & ~7
    return 4 + orientation + 104, 4 + orientation + 200


class _Imu:
    """IMU checks on CDR bytes: NaN and duplicate samples dropped, g units detected on the first second."""

    def __init__(self, report: Report):
        self.report = report
        self.last_stamp: int | None = None
        self.scale: float | None = None
        self.pending: list[tuple[int, bytes, tuple[float, ...]]] = []

    def convert(self, stamp: int, payload: bytes) -> list[tuple[int, Raw]]:
        gyro_at, accel_at = _imu_vectors_at(payload)
        accel = _F64x3.unpack_from(payload, accel_at)
        if not _finite(accel + _F64x3.unpack_from(payload, gyro_at)):
            self.report.dropped["imu: NaN or infinite sample"] += 1
            return []
        if stamp == self.last_stamp:
            self.report.dropped["imu: duplicate stamp"] += 1
            return []
        self.last_stamp = stamp
        if self.scale is None:
            self.pending.append((stamp, payload, accel))
            if stamp - self.pending[0][0] < 1_000_000_000:
                return []
            return self.flush()
        return [(stamp, self._scaled(payload, accel))]

    def _decide(self) -> None:
        norms = [math.sqrt(sum(v * v for v in accel)) for _, _, accel in self.pending]
        in_g = bool(norms) and G_UNITS_BAND[0] < float(np.median(norms)) < G_UNITS_BAND[1]
        self.scale = STANDARD_GRAVITY_M_S2 if in_g else 1.0
        if in_g:
            self.report.imu_in_g = True
            log.warning("the IMU reports acceleration in g (|a| = %.2f at rest): converted to m/s^2", np.median(norms))

    def _scaled(self, payload: bytes, accel: tuple[float, ...]) -> Raw:
        scale = self.scale
        assert scale is not None, "decided before any sample leaves"
        if scale != 1.0:
            data = bytearray(payload)
            _F64x3.pack_into(data, _imu_vectors_at(payload)[1], *(v * scale for v in accel))
            payload = bytes(data)
        return Raw(ROLES["imu"], payload)

    def flush(self) -> list[tuple[int, Raw]]:
        if self.scale is None and self.pending:
            self._decide()
        ready, self.pending = self.pending, []
        return [(stamp, self._scaled(payload, accel)) for stamp, payload, accel in ready]


def _imu(msg: Any, stamp: int) -> Any:
    a, w = msg.linear_acceleration, msg.angular_velocity
    return make(
        "sensor_msgs/msg/Imu",
        header=header(stamp, msg.header.frame_id),
        orientation=make(
            "geometry_msgs/msg/Quaternion",
            x=msg.orientation.x,
            y=msg.orientation.y,
            z=msg.orientation.z,
            w=msg.orientation.w,
        ),
        orientation_covariance=np.asarray(msg.orientation_covariance, dtype=np.float64),
        angular_velocity=make("geometry_msgs/msg/Vector3", x=w.x, y=w.y, z=w.z),
        angular_velocity_covariance=np.asarray(msg.angular_velocity_covariance, dtype=np.float64),
        linear_acceleration=make("geometry_msgs/msg/Vector3", x=a.x, y=a.y, z=a.z),
        linear_acceleration_covariance=np.asarray(msg.linear_acceleration_covariance, dtype=np.float64),
    )


def _csi(msg: Any, stamp: int) -> Any:
    return make(
        "rover_msgs/msg/CsiFrame",
        header=header(stamp, msg.header.frame_id),
        channel=int(msg.channel),
        bfee=np.asarray(msg.bfee, dtype=np.uint8),
    )


def _odom(msg: Any, stamp: int) -> Any:
    out = make("nav_msgs/msg/Odometry", header=header(stamp, msg.header.frame_id), child_frame_id=msg.child_frame_id)
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    out.pose.pose.position.x, out.pose.pose.position.y, out.pose.pose.position.z = p.x, p.y, p.z
    o = out.pose.pose.orientation
    o.x, o.y, o.z, o.w = q.x, q.y, q.z, q.w
    out.pose.covariance = np.asarray(msg.pose.covariance, dtype=np.float64)
    t_in, t_out = msg.twist.twist, out.twist.twist
    t_out.linear.x, t_out.linear.y, t_out.linear.z = t_in.linear.x, t_in.linear.y, t_in.linear.z
    t_out.angular.x, t_out.angular.y, t_out.angular.z = t_in.angular.x, t_in.angular.y, t_in.angular.z
    out.twist.covariance = np.asarray(msg.twist.covariance, dtype=np.float64)
    return out


_TO_ROVER = {"csi": _csi, "imu": _imu, "odom": _odom}


def _as_rover_cdr(reader: AnyReader, conn: Any, raw: bytes, role: str, same_layout: dict[int, bool]) -> bytes | None:
    """The message as little-endian CDR of Rover's type. A ROS 2 connection whose first message
    re-serializes to the same bytes is passed through as is; anything else is decoded with the
    bag's own definitions and re-encoded."""
    try:
        if same_layout.get(conn.id):
            return raw
        msg = reader.deserialize(raw, conn.msgtype)
        ours = serialize(_TO_ROVER[role](msg, _stamp(msg, 0)))
    except Exception:  # noqa: BLE001 - a message its own definition cannot decode is dropped and counted
        return None
    if conn.id not in same_layout:
        same_layout[conn.id] = bool(reader.is2) and ours == bytes(raw) and bytes(raw[:2]) == b"\x00\x01"
    return ours


def _check_some_csi(
    where: str, report: Report, topic: str | None, types: list[str], rows: list[tuple[int, int, str, Any]]
) -> None:
    """Refuse a conversion that dropped every CSI message of its CSI topic: a dataset without CSI
    is not what was asked for (a setup that wants none says `topics: {csi: null}`)."""
    dropped = {why: n for why, n in report.dropped.items() if why.startswith("csi:")}
    if topic is None or not dropped or any(r[2] == OUTPUT_TOPICS["csi"] for r in rows):
        return
    reasons = ", ".join(f"{n:,} {why.removeprefix('csi: ')}" for why, n in sorted(dropped.items()))
    raise BadInput(
        f"{where}: topic {topic} ({', '.join(sorted(set(types)))}): every CSI message was dropped ({reasons}); Rover "
        f"reads {ROLES['csi']} (the CSI Tool's records): nothing written"
    )


def _mcap_files(bags: Sequence[Path]) -> list[Path]:
    """The MCAP files of the bags: each `.mcap` bag, and those in ROS 2 bag folders."""
    found = [b for b in bags if b.suffix == ".mcap" and b.is_file()]
    return found + [f for b in bags if b.is_dir() for f in sorted(b.glob("*.mcap"))]


def _resolved(path: Path) -> Path:
    try:
        return path.resolve()
    except (OSError, RuntimeError) as exc:  # RuntimeError: a symbolic link loop (Python 3.11)
        raise BadInput(f"{path}: cannot resolve the path: {exc}") from None


def _check_not_an_input(output: Path, inputs: Sequence[Path]) -> None:
    """Reject an output that is one of the inputs or inside a bag folder read: --force would destroy it."""
    target = _resolved(output)
    for source in inputs:
        resolved = _resolved(source)
        if target == resolved or (output.exists() and source.exists() and output.samefile(source)):
            raise BadInput(f"{output}: is also an input ({source}); converting onto it would destroy it")
        if source.is_dir() and resolved in target.parents:
            raise BadInput(f"{output}: is inside the bag folder {source} being converted; write it elsewhere")


def convert(
    paths: Sequence[str | Path],
    output: str | Path,
    *,
    setup: str | Path | None = None,
    topics: dict[str, str] | None = None,
    start: float | None = None,
    end: float | None = None,
    truth: str | Path | None = None,
    tags: str | Path | None = None,
    force: bool = False,
    command_line: str = "",
    progress: Callable[[int, int], None] | None = None,
    compensation: str | Path | None = None,
) -> Report:
    """Convert bags to a dataset. The output is checked before any work (not a directory, not one
    of the inputs) and appears only when complete."""
    output = Path(output)
    sources = resolve_sources(paths)
    setup_path = Path(setup) if setup else sources.setup
    if setup_path is None:
        raise BadInput("no rig description: pass --setup setup.yaml (or convert a recording folder that has one)")
    try:
        rig = load_rig(setup_path)
    except SpecError as exc:
        raise BadInput("; ".join(str(d) for d in exc.diagnostics)) from None
    truth = truth or sources.truth
    tags = tags or sources.tags
    inputs = [*sources.bags, setup_path, *[Path(x) for x in (truth, tags) if x]]
    _check_not_an_input(output, inputs)
    check_output(output, force=force)
    report = Report(output)
    origin = dataset.provenance(command_line, inputs)
    for mcap in _mcap_files(sources.bags):  # a cut file says so, and where, before rosbags' own words
        with BagReader(mcap, "cannot read as a ROS bag"):
            pass
    try:
        reader = AnyReader(sources.bags)
        reader.open()
    except AnyReaderError as exc:
        raise BadInput(f"{', '.join(map(str, sources.bags))}: cannot read as a ROS bag: {exc}") from None
    except Exception as exc:  # noqa: BLE001 - any failure of the library on untrusted bytes, as in _read_guarded
        names = ", ".join(map(str, sources.bags))
        raise BadInput(f"{names}: cannot read as a ROS bag: {type(exc).__name__}: {exc}") from None
    try:
        try:
            chosen = _choose_topics(reader, rig, topics or {})
        except BadInput as exc:
            raise BadInput(f"{', '.join(map(str, sources.bags))}: {exc}") from None
        report.topics = {role: topic for role, topic in chosen.items() if topic is not None}
        types = {c.topic: c.msgtype for c in reader.connections}
        report.capture = chosen["csi"] is not None and types[chosen["csi"]] == wiros.WIFI_TYPE
        if compensation is not None and not report.capture:
            raise BadInput(f"--compensation {compensation}: it is WiROS's, and the CSI is no {wiros.WIFI_TYPE}")
        for line in (f"{role}: {topic}" for role, topic in report.topics.items()):
            log.info("topic %s", line)
        if chosen["csi"] is None:
            log.warning("the setup says topics: {csi: null}: writing an IMU/odometry-only dataset")
        lo, hi = _time_bound(start, reader.start_time), _time_bound(end, reader.start_time)
        if lo is not None and hi is not None and lo >= hi:
            raise BadInput(f"--start {start:g} is not before --end {end:g}: the window holds nothing")
        role_of = {topic: role for role, topic in report.topics.items() if not (report.capture and role == "csi")}
        connections = [c for c in reader.connections if c.topic in role_of]
        total = sum(c.msgcount for c in connections)
        imu = _Imu(report)
        rows: list[tuple[int, int, str, Any]] = []
        last: dict[str, int] = {}
        same_layout: dict[int, bool] = {}
        messages = _read_guarded(reader.messages(connections=connections), sources.bags)
        for n, (conn, _log_ns, raw) in enumerate(messages):
            if progress is not None and n % 2000 == 0:
                progress(n, total)
            role = role_of[conn.topic]
            payload = _as_rover_cdr(reader, conn, raw, role, same_layout)
            stamp = _stamp_of(payload)
            if payload is None or stamp is None:
                report.dropped[f"{role}: undecodable"] += 1
                continue
            if stamp < 0:  # a header's sec is signed: before 1970, which no MCAP log time can hold
                report.dropped[f"{role}: stamp before 1970"] += 1
                continue
            if (lo is not None and stamp < lo) or (hi is not None and stamp > hi):
                continue
            if stamp < last.get(role, stamp):
                report.resorted[role] += 1
            last[role] = max(stamp, last.get(role, stamp))
            try:
                converted = imu.convert(stamp, payload) if role == "imu" else [(stamp, Raw(ROLES[role], payload))]
            except struct.error:  # a passed-through message shorter than its type's layout
                report.dropped[f"{role}: undecodable"] += 1
                continue
            rows += [(s, len(rows) + k, OUTPUT_TOPICS[role], m) for k, (s, m) in enumerate(converted)]
        rows += [(s, len(rows) + k, OUTPUT_TOPICS["imu"], m) for k, (s, m) in enumerate(imu.flush())]
        if report.capture:
            assert chosen["csi"] is not None
            captured = capture_messages(sources.bags, chosen["csi"], compensation, (lo, hi), report.dropped)
            rows += [(s, len(rows) + k, dataset.CAPTURE_TOPIC, m) for k, (s, m) in enumerate(captured)]
        csi_types = [c.msgtype for c in connections if role_of[c.topic] == "csi"]
        _check_some_csi(", ".join(map(str, sources.bags)), report, chosen["csi"], csi_types, rows)
        if not rows and total and (lo is not None or hi is not None):
            span = (reader.end_time - reader.start_time) / 1e9
            raise BadInput(
                f"{', '.join(map(str, sources.bags))}: --start/--end hold none of its {total:,} sensor messages "
                f"(it spans {span:.1f} s from its start, {reader.start_time / 1e9:.3f} s absolute)"
            )
    finally:
        reader.close()
    for role, n in report.resorted.items():
        log.warning("%d %s messages were out of stamp order: sorted", n, role)
    for why, n in sorted(report.dropped.items()):
        log.warning("dropped %d messages: %s", n, why)
    rows.sort(key=lambda r: (r[0], r[1]))
    first = rows[0][0] if rows else 0
    truth_rows = [
        (stamp, TRUTH_POSE if msg.__msgtype__ == "geometry_msgs/msg/PoseStamped" else TRUTH_TAGS, msg)
        for stamp, msg in _truth_messages(truth, tags, first)
    ]
    # the truth is clipped to the --start/--end window too (the tags have no time)
    rows += [
        (stamp, len(rows) + k, topic, msg)
        for k, (stamp, topic, msg) in enumerate(truth_rows)
        if topic == TRUTH_TAGS or ((lo is None or stamp >= lo) and (hi is None or stamp <= hi))
    ]
    rows.sort(key=lambda r: (r[0], r[1]))
    metadata = {dataset.SETUP_METADATA: {"yaml": dataset.setup_yaml(rig)}, dataset.PROVENANCE_METADATA: origin}
    if tags:
        metadata["rover.truth"] = {"tags_csv": Path(tags).read_text(encoding="utf-8")}
    with BagWriter(output, metadata=metadata) as bag:
        for stamp, _order, topic, msg in rows:
            bag.write(topic, msg, stamp)
            report.written[topic] += 1
    return report


def _truth_messages(truth: str | Path | None, tags: str | Path | None, first_ns: int):
    if truth and Path(truth).suffix == ".mcap":
        yield from _truth_from_dataset(Path(truth), with_tags=not tags)
        truth = None
    if tags:
        array = make(
            "rover_msgs/msg/TagArray",
            header=header(first_ns, "world"),
            tags=[
                make(
                    "rover_msgs/msg/Tag",
                    id=t.id,
                    channel=t.channel,
                    observable=True,
                    position=make("geometry_msgs/msg/Point", x=t.xyz[0], y=t.xyz[1], z=t.xyz[2]),
                )
                for t in read_tags_csv(tags)
            ],
        )
        yield first_ns, array
    if truth:
        trajectory = read_tum(truth)
        for stamp, xyz, q in zip(trajectory.stamp_ns.tolist(), trajectory.xyz, trajectory.quat_xyzw, strict=True):
            pose = make("geometry_msgs/msg/PoseStamped", header=header(stamp, "world"))
            p, o = pose.pose.position, pose.pose.orientation
            p.x, p.y, p.z = (float(v) for v in xyz)
            o.x, o.y, o.z, o.w = (float(v) for v in q)
            yield stamp, pose


def _truth_from_dataset(path: Path, with_tags: bool):
    """The ground truth of another dataset (e.g. the simulated run a recording was made from)."""
    topics = {TRUTH_POSE: "geometry_msgs/msg/PoseStamped"}
    if with_tags:
        topics[TRUTH_TAGS] = "rover_msgs/msg/TagArray"
    with BagReader(path, "not a readable dataset") as bag:
        found = [(m.log_time_ns, bag.decode(m, topics[m.topic])) for m in bag.messages(topics)]
    if not found:
        raise BadInput(f"{path}: has no {TRUTH_POSE} to use as ground truth")
    yield from found


def terminal_progress() -> tuple[Callable[[int, int], None] | None, Callable[[], None]]:
    """A progress callback drawing a bar on stderr when it is a terminal, and its closer."""
    if not sys.stderr.isatty():
        return None, lambda: None
    from rich.progress import Progress

    bar = Progress(transient=True)
    task = bar.add_task("converting")
    bar.start()

    def update(done: int, total: int) -> None:
        bar.update(task, completed=done, total=total)

    return update, bar.stop
