"""The rig description (`setup.yaml`, MCAP metadata `rover.setup`, `RigSetup` messages).

Antenna positions in the robot frame (x forward, y left), per-chain phase calibration, the
channel and field of view of the receiver, and for a backscatter set-up the excitation channel
and the tags with their channels; topic names and the IMU mounting. A bare receiver (antennas,
channel, calibration; no excitation, no tags) is a valid rig.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from rover.errors import BadInput, Diagnostic, SpecError
from rover.formats.wifi import INTEL5300_CHANNELS_5GHZ, channel_freq_hz, freq_channel
from rover.pipeline import params as P
from rover.pipeline.spec import did_you_mean, read_yaml_text
from rover.pipeline.yamlpos import Located, load

TOP_KEYS = ("receiver", "excitation", "tags", "topics", "imu", "sweep")
RECEIVER_KEYS = ("antenna_positions_m", "phase_offsets_rad", "interface", "channel", "field_of_view_deg")
TAG_KEYS = ("id", "channel", "shift_hz", "name")
DEFAULT_TOPICS = {"csi": "/csi", "imu": "/imu/data", "odom": "/odom"}
UNNAMED_CHANNEL_FREQ_HZ = 5.9e9
"""the top of the 5 GHz band: where a rig that names no channel has its array checked (the worst case)"""
FULL_CIRCLE_DEG = 360.0
MIN_FIELD_OF_VIEW_DEG = 1.0
"""a field of view must hold at least one whole degree, the angle grid of the aoa operator"""


@dataclass(frozen=True)
class TagSpec:
    """A tag: its id and the channel it backscatters into (given, or derived from its shift)."""

    id: int
    channel: int
    shift_hz: float | None
    """None when the setup has no excitation channel to measure the shift from"""


@dataclass(frozen=True)
class ImuMount(P.Checked):
    """The `imu:` section: how the IMU sits on the robot (rotation as roll, pitch, yaw in degrees)."""

    frame_id: str = "imu_link"
    rate_hz: P.PositiveFloat | None = None
    rotation_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    position_m: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Sweep(P.Checked):
    """The `sweep:` section: the dwell per channel the receiver used, when the setup knows it."""

    dwell_s: P.PositiveFloat | None = None


@dataclass(frozen=True)
class Rig:
    """A checked rig description. `text` is the YAML it came from, passed along verbatim."""

    antenna_positions_m: np.ndarray
    excitation_channel: int | None
    """None for a bare receiver (no `excitation:`); see `require_excitation`"""
    tags: tuple[TagSpec, ...]
    phase_offsets_rad: dict[int | None, np.ndarray] = field(default_factory=dict)
    interface: str = "wlan0"
    topics: dict[str, str | None] = field(default_factory=lambda: dict(DEFAULT_TOPICS))
    imu: ImuMount = ImuMount()
    dwell_s: float | None = None
    text: str = ""
    warnings: tuple[Diagnostic, ...] = ()
    receiver_channel: int | None = None
    """`receiver.channel`: the channel a bare receiver listens on"""
    field_of_view_deg: tuple[float, float] | None = None
    """`receiver.field_of_view_deg` as given: [from, to] counter-clockwise (None: the array's default)"""

    @property
    def max_freq_hz(self) -> float:
        """The highest frequency the receiver listens on (its tags' channels and receiver.channel): the
        array's geometry is checked there, where aliasing is worst; the top of the 5 GHz band when the
        rig names no channel."""
        channels = [t.channel for t in self.tags]
        if self.receiver_channel is not None:
            channels.append(self.receiver_channel)
        return max((channel_freq_hz(c) for c in channels), default=UNNAMED_CHANNEL_FREQ_HZ)

    def require_excitation(self, what: str) -> int:
        """The excitation channel, for `what`, which needs a backscatter set-up; BadInput without one."""
        if self.excitation_channel is None:
            raise BadInput(f"{what}: the setup has no excitation channel: add excitation: {{channel: N}} to it")
        return self.excitation_channel

    def phase_offsets(self, channel: int) -> np.ndarray:
        """Per-antenna phase offsets for a channel (zeros when the rig has no calibration for it)."""
        offsets = self.phase_offsets_rad.get(channel, self.phase_offsets_rad.get(None))
        return offsets if offsets is not None else np.zeros(len(self.antenna_positions_m))

    def tag_on(self, channel: int) -> TagSpec | None:
        return next((t for t in self.tags if t.channel == channel), None)


class _Reader:
    def __init__(self, doc: Located):
        self.doc = doc
        self.errors: list[Diagnostic] = []
        self.warnings: list[Diagnostic] = []

    def error(self, path: tuple[Any, ...], message: str, key: bool = False) -> None:
        self.errors.append(self.doc.diag(path, message, key=key))

    def section(self, data: Any, path: tuple[Any, ...], allowed: tuple[str, ...], what: str) -> dict[Any, Any]:
        if data is None:
            return {}
        if not isinstance(data, dict):
            self.error(path, f"{what} must be a mapping")
            return {}
        for key in data:
            if key not in allowed:
                self.warnings.append(
                    self.doc.diag(
                        path + (key,), f"unknown key {key!r} in {what} is ignored{did_you_mean(key, allowed)}", key=True
                    )
                )
        return data

    def numbers(self, value: Any, path: tuple[Any, ...], what: str, length: int | None = None) -> list[float] | None:
        try:
            row = P.coerce(value, list[float])
        except P.ParamTypeError:
            row = None
        if row is None or (length is not None and len(row) != length):
            size = f"{length} " if length is not None else ""
            self.error(path, f"{what} must be a list of {size}finite numbers, got {value!r}")
            return None
        return list(row)

    def bind(self, data: Any, path: tuple[Any, ...], cls: type) -> Any:
        """A section bound to its dataclass (unknown keys warned about and left out), or None after reporting."""
        what = ".".join(map(str, path))
        known = tuple(P.fields(cls))
        values = {k: v for k, v in self.section(data, path, known, what).items() if k in known}
        wording = P.Wording(
            unknown=lambda key: f"unknown key {key!r} in {what}",
            ill_typed=lambda key: f"{what}.{key}",
            missing=lambda key, _label: f"{what} needs {key}",
        )

        def report(sub: tuple[Any, ...], message: str, at_key: bool) -> None:
            self.error(path + sub, message, key=at_key and bool(sub))

        return P.bind(cls, values, wording, report)

    def positive(self, value: Any, path: tuple[Any, ...], what: str) -> float | None:
        """A positive finite number, or None after reporting it."""
        try:
            return float(P.coerce(value, P.PositiveFloat))
        except P.ParamTypeError as exc:
            self.error(path, f"{what}: {exc}")
            return None

    def channel(self, value: Any, path: tuple[Any, ...], what: str) -> int | None:
        try:
            channel_freq_hz(value)
            if isinstance(value, int) and not isinstance(value, bool):
                return value
        except (TypeError, ValueError):
            pass
        self.error(path, f"{what}: {value!r} is not a WiFi channel number")
        return None


def parse_rig(doc: Located) -> Rig:
    """Check a loaded setup document; raise SpecError with every problem found."""
    r = _Reader(doc)
    top = r.section(doc.data, (), TOP_KEYS, "the setup")
    receiver = r.section(top.get("receiver"), ("receiver",), RECEIVER_KEYS, "receiver")

    positions = receiver.get("antenna_positions_m")
    antennas = np.zeros((0, 2))
    if not isinstance(positions, list) or len(positions) < 2:
        r.error(
            ("receiver", "antenna_positions_m") if positions is not None else ("receiver",),
            "receiver.antenna_positions_m must list at least two antenna positions [x, y] in metres",
        )
    else:
        rows = [
            r.numbers(p, ("receiver", "antenna_positions_m", i), f"antenna {i} position")
            for i, p in enumerate(positions)
        ]
        if all(row is not None and len(row) in (2, 3) for row in rows):
            antennas = np.array([row[:2] for row in rows if row is not None])
            if np.ptp(antennas, axis=0).max() == 0:
                r.error(("receiver", "antenna_positions_m"), "the antennas are all at one position")
        elif all(row is not None for row in rows):
            r.error(("receiver", "antenna_positions_m"), "antenna positions are [x, y] (or [x, y, z]) in metres")

    offsets: dict[int | None, np.ndarray] = {}
    raw_offsets = receiver.get("phase_offsets_rad")
    items = (
        raw_offsets.items()
        if isinstance(raw_offsets, dict)
        else [(None, raw_offsets)]
        if raw_offsets is not None
        else []
    )
    for ch, values in items:
        path = ("receiver", "phase_offsets_rad") + ((ch,) if ch is not None else ())
        if ch is not None and r.channel(ch, path, "phase_offsets_rad key") is None:
            continue
        row = r.numbers(values, path, "phase offsets", len(antennas) or None)
        if row is not None:
            offsets[ch] = np.array(row)

    rx_channel = (
        r.channel(receiver["channel"], ("receiver", "channel"), "receiver.channel") if "channel" in receiver else None
    )
    field_of_view = _field_of_view(r, receiver.get("field_of_view_deg"))

    excitation = r.section(top.get("excitation"), ("excitation",), ("channel",), "excitation")
    exc_channel = (
        r.channel(excitation.get("channel"), ("excitation", "channel"), "excitation.channel")
        if "channel" in excitation
        else None
    )
    if "excitation" in top and "channel" not in excitation:
        r.error(("excitation",), "excitation needs its channel: excitation: {channel: N}")

    tags: list[TagSpec] = []
    raw_tags = top.get("tags", [])
    if not isinstance(raw_tags, list):
        r.error(("tags",), "tags must be a list of {id, channel} or {id, shift_hz}")
        raw_tags = []
    for i, raw in enumerate(raw_tags):
        tag = r.section(raw, ("tags", i), TAG_KEYS, f"tag {i}")
        tag_id = tag.get("id")
        if not isinstance(tag_id, int) or isinstance(tag_id, bool) or tag_id < 0:
            r.error(("tags", i), f"tag {i} needs a non-negative integer id")
            continue
        if any(t.id == tag_id for t in tags):
            r.error(("tags", i, "id"), f"tag id {tag_id} appears twice")
        spec = _tag(r, ("tags", i), tag_id, tag, exc_channel, "excitation" in top)
        if spec is not None:
            tags.append(spec)

    topics: dict[str, str | None] = dict(DEFAULT_TOPICS)
    for key, value in r.section(top.get("topics"), ("topics",), tuple(DEFAULT_TOPICS), "topics").items():
        if value is not None and not (isinstance(value, str) and value.startswith("/")):
            r.error(("topics", key), f"topic {key} must be a name starting with '/' or null, got {value!r}")
        else:
            topics[key] = value

    imu = r.bind(top.get("imu"), ("imu",), ImuMount) or ImuMount()
    sweep = r.bind(top.get("sweep"), ("sweep",), Sweep) or Sweep()

    if r.errors:
        raise SpecError(r.errors + r.warnings)
    interface = receiver.get("interface", "wlan0")
    return Rig(
        antennas,
        exc_channel,
        tuple(tags),
        offsets,
        str(interface),
        topics,
        imu,
        sweep.dwell_s,
        "",
        tuple(r.warnings),
        rx_channel,
        field_of_view,
    )


def field_of_view_span_deg(field_of_view_deg: tuple[float, float]) -> float:
    """Degrees a field of view [from, to] covers going counter-clockwise from `from` to `to`, in (0, 360]:
    [-90, 90] and [270, 90] are the front half, [90, -90] the back half, [0, 360] the whole circle."""
    start, stop = field_of_view_deg
    span = (stop - start) % FULL_CIRCLE_DEG
    return FULL_CIRCLE_DEG if span == 0 and stop != start else span


def _field_of_view(r: _Reader, value: Any) -> tuple[float, float] | None:
    """receiver.field_of_view_deg as [from, to] in degrees, or None (absent, or reported)."""
    if value is None:
        return None
    path = ("receiver", "field_of_view_deg")
    row = r.numbers(value, path, "receiver.field_of_view_deg [from, to] (degrees)", 2)
    if row is None:
        return None
    field_of_view = (row[0], row[1])
    if row[0] == row[1] or field_of_view_span_deg(field_of_view) < MIN_FIELD_OF_VIEW_DEG:
        r.error(
            path,
            f"receiver.field_of_view_deg {row} covers less than {MIN_FIELD_OF_VIEW_DEG:g} degree "
            "(it runs counter-clockwise from the first angle to the second; [0, 360] is the whole circle)",
        )
        return None
    return field_of_view


def _tag(
    r: _Reader,
    path: tuple[Any, ...],
    tag_id: int,
    tag: dict[Any, Any],
    exc_channel: int | None,
    excitation_given: bool,
) -> TagSpec | None:
    """A tag's spec; without an excitation channel (none given, or a bad one reported already) a tag
    needs its channel, and its shift stays unknown."""
    channel = r.channel(tag["channel"], path + ("channel",), f"tag {tag_id} channel") if "channel" in tag else None
    shift = tag.get("shift_hz")
    if "channel" in tag and channel is None:
        return None
    if exc_channel is None:
        if shift is not None and not excitation_given:
            r.error(
                path + ("shift_hz",),
                f"tag {tag_id}: shift_hz needs the excitation channel: add excitation: {{channel: N}} "
                "or give the tag's channel",
            )
        elif shift is None and channel is None:
            r.error(path, f"tag {tag_id} needs a channel or a shift_hz")
        return TagSpec(tag_id, channel, None) if channel is not None and shift is None else None
    f_c = channel_freq_hz(exc_channel)
    if shift is not None:
        if r.positive(shift, path + ("shift_hz",), f"tag {tag_id} shift_hz (Hz)") is None:
            return None
        sides = [c for c in (freq_channel(f_c - shift), freq_channel(f_c + shift)) if c in INTEL5300_CHANNELS_5GHZ]
        if channel is None:
            if len(sides) != 1:
                r.error(
                    path + ("shift_hz",),
                    f"tag {tag_id}: a shift of {shift / 1e6:g} MHz from channel "
                    f"{exc_channel} lands on {'no channel' if not sides else 'channels ' + str(sides)}; "
                    "give its channel too",
                )
                return None
            channel = sides[0]
        elif channel not in sides:
            r.error(path, f"tag {tag_id}: channel {channel} is not {shift / 1e6:g} MHz from channel {exc_channel}")
            return None
        return TagSpec(tag_id, channel, float(shift))
    if channel is None:
        r.error(path, f"tag {tag_id} needs a channel or a shift_hz")
        return None
    return TagSpec(tag_id, channel, abs(channel_freq_hz(channel) - f_c))


def rig_from_text(text: str, file: str = "setup.yaml") -> Rig:
    """Parse and check a rig description given as YAML text (a RigSetup message, MCAP metadata)."""
    return replace(parse_rig(load(text, file)), text=text)


def rig_from_message(msg: Any) -> Rig:
    """The rig of a RigSetup message; a description that does not check is BadInput with its first problem."""
    try:
        return rig_from_text(msg.setup_yaml, "RigSetup")
    except SpecError as exc:
        raise BadInput(f"rig description on the setup input: {exc.diagnostics[0]}") from None


class RigInput:
    """An operator's `setup` input: the rig of the latest RigSetup message, parsed again only when
    its text changes (a replay or a live driver may repeat the same description)."""

    def __init__(self) -> None:
        self.rig: Rig | None = None

    def update(self, msg: Any) -> Rig:
        """The rig `msg` describes (BadInput when it does not check; the previous rig is then kept)."""
        if self.rig is None or msg.setup_yaml != self.rig.text:
            self.rig = rig_from_message(msg)
        return self.rig


def load_rig(path: str | Path) -> Rig:
    """Read and check a setup.yaml file."""
    return rig_from_text(read_yaml_text(path), str(path))
