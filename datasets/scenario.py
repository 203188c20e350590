"""Simulation scenarios as data: a YAML file per scenario (room, access point, tags, receiver,
trajectory, IMU, odometry) that users copy and edit; `--set section.key=value` overrides."""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Annotated, Any

from rover.errors import BadInput, Diagnostic, SpecError
from rover.pipeline import params as P
from rover.pipeline.params import Fraction, NonNegativeFloat, PositiveFloat, PositiveInt, Range
from rover.pipeline.spec import did_you_mean, read_yaml_text
from rover.pipeline.yamlpos import Located, load, parse_scalar

Decibels = Annotated[float, Range(ge=-40, le=80)]
"""a signal-to-noise ratio within what a receiver meets (beyond it the CSI is all noise, or exact)"""
Loss = Annotated[float, Range(ge=0, le=60)]
"""a loss in dB (beyond 60 dB a path is gone: leave it out instead)"""
MAX_SCATTERERS = 1000
"""the simulation holds a path per scatterer for every packet"""


@dataclass(frozen=True)
class Room:
    size_m: tuple[PositiveFloat, PositiveFloat] = (9.0, 5.0)
    wall_reflection: Fraction = 0.5
    scatterers: Annotated[int, Range(ge=0, le=MAX_SCATTERERS)] = 0
    """point scatterers (furniture, people, shelves) placed at random in the room, each a path
    tag -> scatterer -> robot (rover.datasets.clutter)"""
    scatterer_reflectivity_m: tuple[Annotated[float, Range(gt=0, le=10)], Annotated[float, Range(ge=0, le=20)]] = (
        0.15,
        6.0,
    )
    """their amplitude reflectivity: median (m) and log-normal spread (dB of power)"""
    shadowing_db: Loss = 0.0
    """std of each tag's direct path's shadow fading along the robot's path (0: none)"""
    shadowing_distance_m: PositiveFloat = 1.5
    """distance along the path over which the shadowing decorrelates (to 1/e)"""


@dataclass(frozen=True)
class AccessPoint:
    position_m: tuple[float, float] = (4.5, 4.6)
    channel: int = 165


@dataclass(frozen=True)
class SimTag:
    id: int
    channel: int
    position_m: tuple[float, float]
    nlos: bool = False


@dataclass(frozen=True)
class Receiver:
    card: typing.Literal["intel5300", "nexmon"] = "intel5300"
    """what records the CSI: the Intel 5300 (CSI Tool records on /csi: 2 or 3 chains, 30 subcarriers,
    int8 after its AGC), or a Broadcom chip patched by nexmon_csi, such as the 4x4 BCM4366c0 of
    WiROS's router (2-8 antennas, the 20 MHz channel's 50 data subcarriers as WiROS keeps them, as
    floats, decoded on /csi/capture as `rover convert` writes a WiROS bag). Its chains' phase states
    are not modelled: the Intel 5300's jump models are refused with it"""
    array: typing.Literal["triangle", "linear", "positions"] = "triangle"
    spacing_wavelengths: PositiveFloat = 0.5
    antenna_positions_m: list[tuple[float, float]] = field(default_factory=list)
    range_m: PositiveFloat = 5.0
    packet_rate_hz: PositiveFloat = 150.0
    dwell_s: PositiveFloat = 0.05
    hop_gap_s: NonNegativeFloat = 0.005
    latency_ms: tuple[float, float] = (0.3, 0.5)
    snr_db: tuple[Decibels, Decibels] = (20.0, 30.0)
    phase_offsets_rad: list[float] = field(default_factory=lambda: [0.0, 0.9, -1.7])
    calibration_error_deg: NonNegativeFloat = 3.0
    sampling_offset_ns: tuple[float, float] = (0.0, 100.0)
    nlos_attenuation_db: tuple[Loss, Loss] = (10.0, 15.0)
    agc_peak: tuple[float, float] = (40.0, 90.0)
    jumps_per_run: bool = False
    """each chain's phase comes back shifted by a random multiple of the jump step (pi at 5 GHz,
    pi/2 at 2.4 GHz) from the calibration, drawn once per channel for the run: a card restarted
    since it was calibrated (CSI Tool issues #113 and #446; the LGTM repeats in the test data)"""
    jumps_per_retune: Fraction = 0.0
    """chance that a retune draws each chain's multiple afresh (not settled by the evidence)"""
    jumps_per_packet: Fraction = 0.0
    """chance that a packet's chains jump by a random multiple for that packet only (2.4 GHz, CSI
    Tool issue #6)"""
    steps_per_minute: NonNegativeFloat = 0.0
    """persistent jumps at random moments: at this rate (a Poisson process in time) one chain, drawn
    at random, steps by one jump step (pi at 5 GHz; up or down) on every channel and stays so until
    its next step ("the phase difference changes suddenly": CSI Tool issues #23, #295 and #113)"""


@dataclass(frozen=True)
class Trajectory:
    start_m: tuple[float, float] = (1.0, 0.755)
    heading_deg: float = 0.0
    waypoints_m: list[tuple[float, float]] = field(default_factory=list)
    laps: PositiveInt = 1
    speed_m_s: PositiveFloat = 0.3
    ramp_s: NonNegativeFloat = 1.0
    turn_rate_deg_s: PositiveFloat = 45.0
    stationary_s: NonNegativeFloat = 3.0
    pause_s: NonNegativeFloat = 0.0
    """standing still at every waypoint before turning (a robot that stops at its goals)"""


@dataclass(frozen=True)
class Imu:
    rate_hz: PositiveFloat = 200.0
    gyro_noise_deg_s_rthz: NonNegativeFloat = 0.005
    gyro_bias_deg_s: NonNegativeFloat = 0.02
    gyro_bias_walk_deg_s_rts: NonNegativeFloat = 0.0005
    gyro_bias_drift_deg_s: NonNegativeFloat = 0.0
    """how far each axis's bias moves after power-up as the IMU warms (random sign per axis), which
    the still start cannot see: a consumer MEMS gyro moves 0.1-0.5 deg/s"""
    gyro_bias_drift_tau_s: PositiveFloat = 300.0
    """time constant of that warm-up (exponential approach)"""
    vibration_deg_s: NonNegativeFloat = 0.0
    """gyro shake (std per sample, white) while the robot drives or turns: 1-2 deg/s on a Jackal"""
    vibration_mg: NonNegativeFloat = 0.0
    """accelerometer shake (std per sample, white) while the robot drives or turns"""
    accel_noise_ug_rthz: NonNegativeFloat = 100.0
    accel_bias_mg: NonNegativeFloat = 2.0
    accel_bias_walk_mg_rts: NonNegativeFloat = 0.004


@dataclass(frozen=True)
class Odometry:
    enabled: bool = True
    rate_hz: PositiveFloat = 20.0
    scale_error: NonNegativeFloat = 0.02
    heading_drift_deg_s: NonNegativeFloat = 0.1
    speed_noise_m_s: NonNegativeFloat = 0.005


@dataclass(frozen=True)
class Scenario:
    name: str
    text: str
    room: Room
    access_point: AccessPoint
    tags: list[SimTag]
    receiver: Receiver
    trajectory: Trajectory
    imu: Imu
    odometry: Odometry


SECTIONS = {
    "room": Room,
    "access_point": AccessPoint,
    "receiver": Receiver,
    "trajectory": Trajectory,
    "imu": Imu,
    "odometry": Odometry,
}


def builtin_scenarios() -> list[str]:
    folder = resources.files("rover.datasets").joinpath("scenarios")
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".yaml"))


def _section(doc: Located, data: Any, path: tuple, cls: type, problems: list[Diagnostic]) -> Any:
    where = ".".join(map(str, path))
    if data is None:
        data = {}
    if not isinstance(data, dict):
        problems.append(doc.diag(path, f"{where} must be a mapping"))
        return None
    wording = P.Wording(
        unknown=lambda key: f"unknown key {key!r} in {where}",
        ill_typed=lambda key: f"{where}.{key}",
        missing=lambda key, _label: f"{where} needs {key}",
    )

    def report(sub: tuple, message: str, at_key: bool) -> None:
        problems.append(doc.diag(path + sub, message, key=at_key and bool(sub)))

    return P.bind(cls, data, wording, report)


def _check_override(key: str) -> None:
    """BadInput naming the `--set` when its section, or its key in a section, is none the scenario
    has (with a did-you-mean), before the scenario file's own checks would point at the file."""
    parts = key.split(".")
    section = parts[0]
    if section == "tags":
        return
    if section not in SECTIONS:
        names = [*SECTIONS, "tags"]
        raise BadInput(f"--set {key}: no section {section!r} in a scenario{did_you_mean(section, names)}")
    known = [f.name for f in dataclasses.fields(SECTIONS[section])]
    if len(parts) >= 2 and parts[1] not in known:
        raise BadInput(f"--set {key}: no key {parts[1]!r} in section {section!r}{did_you_mean(parts[1], known)}")


def _override(data: dict, key: str, value: Any) -> None:
    _check_override(key)
    parts = key.split(".")
    node = data
    for part in parts[:-1]:
        if part.isdigit() and isinstance(node, list) and int(part) < len(node):
            node = node[int(part)]
        elif isinstance(node, dict):
            node = node.setdefault(part, {})
        else:
            raise BadInput(f"--set {key}: {part!r} is not a section of the scenario")
    last = parts[-1]
    if isinstance(node, list) and last.isdigit() and int(last) < len(node):
        node[int(last)] = value
    elif isinstance(node, dict):
        node[last] = value
    else:
        raise BadInput(f"--set {key}: cannot set {last!r} there")


def load_scenario(name_or_path: str, overrides: dict[str, str] | None = None) -> Scenario:
    """A built-in scenario by name, or a scenario file; raise SpecError/BadInput on problems."""
    path = Path(name_or_path)
    if path.suffix in (".yaml", ".yml") or path.exists():
        text = read_yaml_text(path)
        file = str(path)
    else:
        names = builtin_scenarios()
        if name_or_path not in names:
            raise BadInput(
                f"unknown scenario {name_or_path!r}{did_you_mean(name_or_path, names)} "
                f"(built in: {', '.join(names)}; or give a .yaml file)"
            )
        file = f"{name_or_path}.yaml"
        text = resources.files("rover.datasets").joinpath("scenarios", file).read_text(encoding="utf-8")
    doc = load(text, file)
    if not isinstance(doc.data, dict):
        raise SpecError([doc.diag((), "a scenario is a mapping of sections")])
    for key, value in (overrides or {}).items():
        _override(doc.data, key, parse_scalar(value, f"--set {key}"))
    problems: list[Diagnostic] = []
    for key in doc.data:
        if key not in (*SECTIONS, "tags"):
            problems.append(
                doc.diag((key,), f"unknown section {key!r}{did_you_mean(key, [*SECTIONS, 'tags'])}", key=True)
            )
    sections = {name: _section(doc, doc.data.get(name), (name,), cls, problems) for name, cls in SECTIONS.items()}
    tags = []
    raw_tags = doc.data.get("tags") or []
    if not isinstance(raw_tags, list) or not raw_tags:
        problems.append(doc.diag(("tags",), "tags must be a non-empty list of {id, channel, position_m}"))
        raw_tags = []
    for i, raw in enumerate(raw_tags):
        tag = _section(doc, raw, ("tags", i), SimTag, problems)
        if tag is not None:
            tags.append(tag)
    if sections["trajectory"] is not None and not sections["trajectory"].waypoints_m:
        problems.append(doc.diag(("trajectory",), "trajectory needs waypoints_m"))
    if problems:
        raise SpecError(problems)
    return Scenario(Path(file).stem, text, tags=tags, **sections)
