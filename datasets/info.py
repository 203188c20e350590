"""`rover info`: what a dataset holds, read from the MCAP summary (no full scan except to count CSI per channel)."""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from rover.errors import BadInput, SpecError
from rover.formats.bag import BagReader, shown
from rover.formats.dataset import RECORD_METADATA, SETUP_METADATA
from rover.pipeline.yamlpos import safe_load_limited

CSI_TYPE = "rover_msgs/msg/CsiFrame"

log = logging.getLogger("rover.info")


def _metadata_yaml(path: str, record: str, text: str) -> dict[str, Any]:
    """The mapping a metadata record's YAML holds, loaded within the YAML limits (the file is untrusted)."""
    try:
        data = safe_load_limited(text, record)
    except SpecError as exc:
        d = exc.diagnostics[0]
        where = f", line {d.line}" if d.line else ""
        raise BadInput(f"{path}: metadata record {record!r}{where}: {d.message}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise BadInput(f"{path}: metadata record {record!r}: expected a YAML mapping, got {type(data).__name__}")
    return data


@dataclass(frozen=True)
class Simulation:
    """What `rover simulate` recorded about a dataset (metadata `rover.simulation`)."""

    scenario: str
    seed: int | None
    path_length_m: float | None
    nlos: dict[str, bool]
    direct_to_multipath_db: dict[str, float]


def _simulation(path: str, text: str) -> Simulation:
    """The simulation record, its types checked (the file is untrusted): BadInput naming the field."""
    sim = _metadata_yaml(path, "rover.simulation", text)

    def bad(name: str, expected: str) -> BadInput:
        return BadInput(f"{path}: metadata record 'rover.simulation': field {name}: {expected}")

    def number(value: Any) -> bool:
        return isinstance(value, int | float) and not isinstance(value, bool)

    seed, length = sim.get("seed"), sim.get("path_length_m")
    if seed is not None and not (isinstance(seed, int) and not isinstance(seed, bool)):
        raise bad("seed", "a whole number")
    if length is not None and not number(length):
        raise bad("path_length_m", "a number")
    nlos, ratios = sim.get("nlos") or {}, sim.get("direct_to_multipath_db") or {}
    if not isinstance(nlos, dict) or not all(isinstance(v, bool) for v in nlos.values()):
        raise bad("nlos", "a mapping of tag to true or false")
    if not isinstance(ratios, dict) or not all(number(v) for v in ratios.values()):
        raise bad("direct_to_multipath_db", "a mapping of tag to a number of dB")
    return Simulation(
        str(sim.get("scenario", "")),
        seed,
        None if length is None else float(length),
        {str(k): v for k, v in nlos.items()},
        {str(k): float(v) for k, v in ratios.items()},
    )


@dataclass
class TopicInfo:
    name: str
    type: str
    count: int
    rate_hz: float


@dataclass
class DatasetInfo:
    path: str
    start_ns: int
    end_ns: int
    duration_s: float
    message_count: int
    topics: list[TopicInfo]
    setup: str | None
    csi_packets_per_channel: dict[int, int] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)

    def as_json(self) -> dict[str, Any]:
        out = asdict(self)
        out["csi_packets_per_channel"] = {str(k): v for k, v in self.csi_packets_per_channel.items()}
        del out["metadata"]
        simulation = self.metadata.get("rover.simulation", {}).get("yaml")
        if simulation:
            out["simulation"] = asdict(_simulation(self.path, simulation))
        return out


def dataset_info(path: str | Path, csi_topic: str = "/csi") -> DatasetInfo:
    """Summarize a dataset; BadInput when it is not a readable MCAP file. A `csi_topic` of another
    type than CsiFrame is listed with a warning and no packets per channel."""
    path = Path(path)
    if path.is_dir():
        files = sorted(path.glob("*.mcap"))
        if len(files) != 1:
            raise BadInput(
                f"{path}: a bag folder for `rover info` holds one .mcap file (found {len(files)}); "
                "convert other bags with `rover convert` first"
            )
        path = files[0]
    if not path.is_file():
        raise BadInput(f"{path}: no such dataset file")
    with BagReader(path, "not a readable MCAP dataset") as bag:
        summary = bag.summary()
        if summary is None or summary.statistics is None:
            raise BadInput(f"{path}: MCAP file has no summary (was it closed properly?)")
        stats = summary.statistics
        metadata = bag.metadata()
        per_channel: Counter[int] = Counter()
        csi_types = {c.schema for c in summary.channels if c.topic == csi_topic}
        if CSI_TYPE in csi_types:
            for message in bag.messages([csi_topic], log_time_order=False):
                if message.schema == CSI_TYPE:
                    per_channel[int(bag.decode(message, CSI_TYPE).channel)] += 1
        elif csi_types:
            log.warning(
                "%s: topic %s carries %s, not %s: no CSI packets per channel",
                path,
                csi_topic,
                ", ".join(sorted(shown(t) if t else "no schema" for t in csi_types)),
                CSI_TYPE,
            )
    duration_s = (stats.end_ns - stats.start_ns) / 1e9 if stats.message_count else 0.0
    topics = []
    for channel in sorted(summary.channels, key=lambda c: c.topic):
        rate_hz = channel.count / duration_s if duration_s > 0 else 0.0
        topics.append(TopicInfo(channel.topic, channel.schema, channel.count, rate_hz))
    return DatasetInfo(
        str(path),
        stats.start_ns,
        stats.end_ns,
        duration_s,
        stats.message_count,
        topics,
        metadata.get(SETUP_METADATA, {}).get("yaml"),
        dict(sorted(per_channel.items())),
        metadata,
    )


def render(info: DatasetInfo) -> str:
    """Text like `ros2 bag info`, plus the rig and CSI packets per tag channel."""
    lines = [
        f"Files:             {info.path}",
        f"Duration:          {info.duration_s:.3f} s",
        f"Start:             {info.start_ns / 1e9:.9f}",
        f"End:               {info.end_ns / 1e9:.9f}",
        f"Messages:          {info.message_count}",
        "Topics:",
    ]
    width = max((len(t.name) for t in info.topics), default=0)
    for t in info.topics:
        lines.append(f"  {t.name:<{width}}  {t.type:<36} {t.count:>8} msgs  {t.rate_hz:8.2f} Hz")
    if info.csi_packets_per_channel:
        lines.append("CSI packets per channel:")
        tags = _tags_by_channel(info.setup)
        for ch, n in info.csi_packets_per_channel.items():
            owner = f"  (tag {tags[ch]})" if ch in tags else "  (no tag)" if tags else ""
            lines.append(f"  channel {ch:>3}: {n:>8}{owner}")
    simulation = info.metadata.get("rover.simulation", {}).get("yaml")
    if simulation:
        sim = _simulation(info.path, simulation)
        lines.append(f"Simulated: scenario {sim.scenario}, seed {sim.seed}, path {sim.path_length_m} m")
        lines.append("Direct-to-multipath power ratio of the tag-to-robot link (median over packets):")
        for tag, ratio in sim.direct_to_multipath_db.items():
            lines.append(f"  tag {tag}: {ratio:+.1f} dB{'  (NLOS)' if sim.nlos.get(tag) else ''}")
    recorded = info.metadata.get(RECORD_METADATA, {}).get("yaml")
    if recorded:
        lines.append(_recorded(info.path, recorded))
    if info.setup:
        lines.append("Rig (rover.setup):")
        lines += [f"  {line}" for line in info.setup.strip().splitlines()]
    return "\n".join(lines) + "\n"


def _recorded(path: str, text: str) -> str:
    """One line on a live recording (metadata `rover.record`): how the session ended, what came late."""
    record = _metadata_yaml(path, RECORD_METADATA, text)
    late = record.get("late") or {}
    if not isinstance(late, dict) or not all(isinstance(n, int) and not isinstance(n, bool) for n in late.values()):
        raise BadInput(f"{path}: metadata record {RECORD_METADATA!r}: field late: a mapping of topic to a count")
    counted = ", ".join(f"{topic} {n}" for topic, n in sorted(late.items())) if late else "none"
    return f"Recorded live ({record.get('session', '?')} session); late messages: {counted}"


def _tags_by_channel(setup: str | None) -> dict[int, int]:
    if not setup:
        return {}
    from rover.errors import SpecError
    from rover.formats.rig import rig_from_text

    try:
        return {t.channel: t.id for t in rig_from_text(setup, SETUP_METADATA).tags}
    except SpecError:
        return {}
