"""`rover simulate`: a dataset with ground truth from a scenario: real CSI Tool records from the
two-hop multipath channel, a swept receiver that hears tags only in range, a noisy IMU and wheel
odometry, all deterministic for a seed."""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from rover.datasets.clutter import place_scatterers, shadowing_db
from rover.datasets.imu_model import imu_samples, odometry_samples
from rover.datasets.motion import Motion
from rover.datasets.radio import Impairments, backscatter_csi, impair, subcarrier_offsets_hz, true_aoa
from rover.datasets.scenario import Receiver, Scenario
from rover.datasets.scenario_size import TRUTH_RATE_HZ, check_size
from rover.errors import BadInput
from rover.formats import dataset
from rover.formats.bag import BagWriter, check_output
from rover.formats.csi_sources.wiros import KEPT_SUBCARRIERS
from rover.formats.intel5300 import RecordHeader, encode_record
from rover.formats.wifi import SPEED_OF_LIGHT_M_S, SUBCARRIER_SPACING_HZ, channel_freq_hz, phase_jump_step_rad
from rover.geometry import quaternion_from_yaw, wrap_angle
from rover.messages import header, make

T0_NS = 1_700_000_000_000_000_000
"""Simulated clock origin (2023-11-14), so stamps look like a real recording's."""
NOISE_HEADER_DB = -127
NOISE_FLOOR_DB = -92
RATE_N_FLAGS = 0x4101
PERMUTATIONS = (0b100100, 0b011000, 0b001001, 0b010010, 0b000110, 0b100001)
"""antenna_sel values of the six permutations; the NIC usually reports the identity."""
JUMP_STREAM = 14
"""the phase jumps draw from their own random stream, so turning them on changes nothing else"""
STEP_STREAM = 15
"""the persistent steps draw from a stream of their own too"""
PATH_STEP_S = 0.25
"""the robot's path, as the scatterers keep clear of it: a point every this many seconds"""
CLUTTER_STREAM = 16
"""the clutter (scatterers and shadowing) draws from a stream of its own"""
IMU_STREAM = 17
"""the gyro's warm-up drift and the base's shake draw from a stream of their own"""
NEXMON_ANTENNAS = (2, 8)
"""the antennas a Nexmon-patched chip's rig may have (the BCM4366c0 has four receive chains)"""
NEXMON_SUBCARRIERS = KEPT_SUBCARRIERS[20e6]
"""the 20 MHz channel's data subcarriers, as WiROS keeps them"""
JUMP_DRAWS = 4
"""jumps are drawn as 0..3 steps: at 5 GHz (step pi) that is 0 or pi, each equally likely"""


@dataclass
class SimReport:
    output: Path
    duration_s: float
    path_length_m: float
    counts: Counter = field(default_factory=Counter)
    packets_per_tag: dict[int, int] = field(default_factory=dict)
    direct_to_multipath_db: dict[int, float] = field(default_factory=dict)


def antenna_positions(scenario: Scenario) -> np.ndarray:
    rx = scenario.receiver
    if rx.array == "positions":
        if len(rx.antenna_positions_m) < 2:
            raise BadInput("receiver.array: positions needs receiver.antenna_positions_m")
        return np.array(rx.antenna_positions_m, dtype=np.float64)
    wavelength = SPEED_OF_LIGHT_M_S / max(channel_freq_hz(t.channel) for t in scenario.tags)
    d = rx.spacing_wavelengths * wavelength
    if rx.array == "linear":
        return np.array([[0.0, 0.0], [d, 0.0], [2 * d, 0.0]])
    return np.array([[0.0, 0.0], [d, 0.0], [d / 2, -d * math.sqrt(3) / 2]])


def _windows(scenario: Scenario, duration_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Receiving windows of the sweep: (start, end, tag index), visiting the tags' channels in turn."""
    rx = scenario.receiver
    order = sorted(range(len(scenario.tags)), key=lambda i: scenario.tags[i].channel)
    count = int(duration_s / rx.dwell_s) + 1
    starts = np.arange(count) * rx.dwell_s
    tags = np.array(order)[np.arange(count) % len(order)]
    return starts + rx.hop_gap_s, starts + rx.dwell_s, tags


def _setup_yaml(scenario: Scenario, antennas: np.ndarray, offsets: np.ndarray) -> str:
    receiver: dict[str, Any] = {
        "antenna_positions_m": [[round(float(v), 10) for v in p] for p in antennas],
        "phase_offsets_rad": [round(float(v), 6) for v in offsets],
        "interface": "wlan0",
    }
    if np.linalg.matrix_rank(antennas - antennas[0], tol=1e-9) < 2:  # collinear, tags all around it: each
        receiver["field_of_view_deg"] = [-180.0, 180.0]  # angle and its mirror image are candidates
    data = {
        "receiver": receiver,
        "excitation": {"channel": scenario.access_point.channel},
        "tags": [{"id": t.id, "channel": t.channel} for t in scenario.tags],
        "topics": {"csi": "/csi", "imu": "/imu/data", "odom": "/odom" if scenario.odometry.enabled else None},
        "imu": {"frame_id": "imu_link", "rate_hz": scenario.imu.rate_hz},
        "sweep": {"dwell_s": scenario.receiver.dwell_s},
    }
    return "# Rig description written by rover simulate (calibration includes its simulated error)\n" + yaml.safe_dump(
        data, sort_keys=False
    )


@dataclass(frozen=True)
class ChainJumps:
    """The simulated chains' phase jumps: per packet, the phase (N, M) added to the calibrated
    offsets; per channel, the multiples of its jump step drawn for the run; how many retunes drew afresh."""

    phase_rad: np.ndarray
    run_steps: dict[int, list[int]]
    retunes_redrawn: int
    steps: list[tuple[float, int, int]] = field(default_factory=list)
    """the persistent steps: (time s from the start, chain, +1 or -1 jump step)"""


def persistent_steps(
    rate_per_min: float, seed: int, duration_s: float, chains: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The steps of a Poisson process at `rate_per_min` over the run: their times (s, ascending),
    the chain each moves and its direction (+1 or -1 jump step)."""
    rng = np.random.default_rng([seed, STEP_STREAM])
    count = rng.poisson(rate_per_min * duration_s / 60.0) if rate_per_min > 0 else 0
    times = np.sort(rng.uniform(0.0, duration_s, count))
    return times, rng.integers(0, chains, count), rng.choice([-1, 1], count)


def step_state(times: np.ndarray, chain: np.ndarray, sign: np.ndarray, at_s: np.ndarray, chains: int) -> np.ndarray:
    """Each chain's accumulated steps (multiples of the jump step) at the times `at_s`: (len(at_s), chains)."""
    moves = np.zeros((len(times) + 1, chains), dtype=int)
    moves[np.arange(1, len(times) + 1), chain] = sign
    return np.cumsum(moves, axis=0)[np.searchsorted(times, at_s, side="right")]


def chain_jumps(
    rx: Receiver,
    seed: int,
    window: np.ndarray,
    window_channel: np.ndarray,
    chains: int,
    packet_t: np.ndarray | None = None,
    duration_s: float = 0.0,
) -> ChainJumps:
    """Phase jumps of each packet (window: its sweep window; window_channel: each window's channel;
    packet_t: its time in s from the start, for the persistent steps over `duration_s`)."""
    rng = np.random.default_rng([seed, JUMP_STREAM])
    channels = sorted({int(c) for c in window_channel})
    run = {c: rng.integers(0, JUMP_DRAWS, chains) * rx.jumps_per_run for c in channels}
    redraw = rng.uniform(size=len(window_channel)) < rx.jumps_per_retune
    fresh = rng.integers(0, JUMP_DRAWS, (len(window_channel), chains))
    per_packet = rng.uniform(size=len(window)) < rx.jumps_per_packet
    extra = rng.integers(0, JUMP_DRAWS, (len(window), chains)) * per_packet[:, None]
    state = np.array([run[int(c)] for c in window_channel]).reshape(len(window_channel), chains)
    state = np.where(redraw[:, None], fresh, state)
    steps = np.array([phase_jump_step_rad(int(c)) for c in channels])
    step = steps[np.searchsorted(channels, window_channel[window])] if len(window) else np.zeros(0)
    levels = {c: round(2 * math.pi / s) for c, s in zip(channels, steps, strict=True)}
    multiples = state[window] + extra
    times, chain, sign = persistent_steps(rx.steps_per_minute, seed, duration_s, chains)
    if len(times) and packet_t is not None:
        multiples = multiples + step_state(times, chain, sign, packet_t, chains)
    return ChainJumps(
        multiples * step[:, None],
        {c: [int(v) % levels[c] for v in run[c]] for c in channels},
        int(redraw.sum()),
        [(round(float(t), 6), int(c), int(s)) for t, c, s in zip(times, chain, sign, strict=True)],
    )


class _World:
    """The room frame to the world frame: origin at the robot's first pose, x along its heading."""

    def __init__(self, start: tuple[float, float], heading_rad: float):
        self.start = np.array(start, dtype=np.float64)
        self.heading = heading_rad
        c, s = math.cos(heading_rad), math.sin(heading_rad)
        self.rotation = np.array([[c, s], [-s, c]])

    def point(self, xy: np.ndarray) -> np.ndarray:
        return (np.asarray(xy) - self.start) @ self.rotation.T

    def yaw(self, yaw: np.ndarray) -> np.ndarray:
        return wrap_angle(yaw - self.heading)


def _check_nexmon(rx: Receiver, antennas: int) -> None:
    """BadInput for a Nexmon rig the simulator does not model: its antenna count, the Intel 5300's jumps."""
    low, high = NEXMON_ANTENNAS
    if not low <= antennas <= high:
        raise BadInput(f"receiver: {antennas} antennas: a Nexmon rig here has {low} to {high}")
    intel = {
        "jumps_per_run": rx.jumps_per_run,
        "jumps_per_retune": rx.jumps_per_retune,
        "jumps_per_packet": rx.jumps_per_packet,
        "steps_per_minute": rx.steps_per_minute,
    }
    on = [key for key, value in intel.items() if value]
    if on:
        raise BadInput(
            f"receiver.card nexmon: receiver.{', receiver.'.join(on)} model the Intel 5300's chains, not a Nexmon "
            "chip's: set them to 0 (false)"
        )


def _nexmon_csi(stamp: int, tag: int, channel: int, sequence: int, csi: np.ndarray) -> Any:
    """A Nexmon rig's packet as `rover convert` writes a WiROS one: decoded CSI (K, M) of one stream."""
    return make(
        "rover_msgs/msg/Csi",
        header=header(stamp, "base_link"),
        tag_id=tag,
        channel=channel,
        bfee_count=sequence % 2**32,
        nrx=csi.shape[1],
        ntx=1,
        noise=NOISE_HEADER_DB,
        csi_real=np.ascontiguousarray(csi.real, dtype=np.float32).ravel(),
        csi_imag=np.ascontiguousarray(csi.imag, dtype=np.float32).ravel(),
        subcarriers=NEXMON_SUBCARRIERS.astype(np.int16),
        centre_freq_hz=channel_freq_hz(channel),
    )


def simulate(
    scenario: Scenario, seed: int, output: str | Path, command_line: str = "", force: bool = False
) -> SimReport:
    """Simulate `scenario` with `seed` into the dataset `output`, which is checked before any
    work and appears only when complete."""
    check_size(scenario, f"scenario {scenario.name}")  # before the output is touched or anything allocated
    output = check_output(output, force=force)
    rng = np.random.default_rng(seed)
    rx = scenario.receiver
    motion = Motion(scenario.trajectory)
    duration = motion.duration_s
    world = _World(scenario.trajectory.start_m, math.radians(scenario.trajectory.heading_deg))
    antennas = antenna_positions(scenario)
    nexmon = rx.card == "nexmon"
    if nexmon:
        _check_nexmon(rx, len(antennas))
    elif len(antennas) not in (2, 3):
        raise BadInput(
            f"receiver: {len(antennas)} antennas: the Intel 5300 has three receive chains, so 2 or 3 antennas "
            "(records of 2 or 3 chains)"
        )
    if len(rx.phase_offsets_rad) != len(antennas):
        raise BadInput(
            f"receiver.phase_offsets_rad has {len(rx.phase_offsets_rad)} values for {len(antennas)} antennas"
        )
    true_offsets = np.array(rx.phase_offsets_rad, dtype=np.float64)
    calibration = true_offsets + np.radians(rng.normal(0, rx.calibration_error_deg, len(antennas))) * (
        np.arange(len(antennas)) > 0
    )
    report = SimReport(output, duration, motion.path_length_m)
    rows: list[tuple[int, int, str, object]] = []

    def add(stamp: int, topic: str, msg: object) -> None:
        rows.append((stamp, len(rows), topic, msg))
        report.counts[topic] += 1

    starts, ends, window_tags = _windows(scenario, duration)
    n_packets = rng.poisson(rx.packet_rate_hz * (ends - starts))
    owner = np.repeat(window_tags, n_packets)
    true_t = np.repeat(starts, n_packets) + rng.uniform(0, 1, n_packets.sum()) * np.repeat(ends - starts, n_packets)
    order = np.argsort(true_t, kind="stable")
    true_t, owner = true_t[order], owner[order]
    window = np.repeat(np.arange(len(starts)), n_packets)[order]
    state = motion.state(true_t)
    ap = np.array(scenario.access_point.position_m, dtype=np.float64)
    room = (scenario.room.size_m[0], scenario.room.size_m[1])
    heard = np.zeros(len(true_t), dtype=bool)
    offsets_hz = NEXMON_SUBCARRIERS * SUBCARRIER_SPACING_HZ if nexmon else subcarrier_offsets_hz()
    csi = np.zeros((len(true_t), len(offsets_hz), len(antennas)), dtype=np.complex128)
    clutter_rng = np.random.default_rng([seed, CLUTTER_STREAM])
    path = motion.state(np.arange(0.0, duration, PATH_STEP_S)).xy
    scatterers = place_scatterers(
        room, scenario.room.scatterers, *scenario.room.scatterer_reflectivity_m, clutter_rng, path
    )
    for i, tag in enumerate(scenario.tags):
        mine = owner == i
        position = np.array(tag.position_m, dtype=np.float64)
        in_range = mine & (np.linalg.norm(state.xy - position, axis=1) <= rx.range_m)
        heard |= in_range
        if not in_range.any():
            report.packets_per_tag[tag.id] = 0
            continue
        attenuation = rng.uniform(*rx.nlos_attenuation_db) if tag.nlos else 0.0
        shadow = shadowing_db(
            state.along_m[in_range], scenario.room.shadowing_db, scenario.room.shadowing_distance_m, clutter_rng
        )
        clean, ratio = backscatter_csi(
            ap,
            position,
            state.xy[in_range],
            state.yaw[in_range],
            antennas,
            scenario.access_point.channel,
            tag.channel,
            room,
            scenario.room.wall_reflection,
            attenuation + shadow,
            scatterers,
            offsets_hz,
        )
        csi[in_range] = clean
        report.packets_per_tag[tag.id] = int(in_range.sum())
        report.direct_to_multipath_db[tag.id] = round(float(np.median(ratio)), 2)
    keep = np.flatnonzero(heard)
    n = len(keep)
    window_channel = np.array([scenario.tags[i].channel for i in window_tags])
    jumps = chain_jumps(rx, seed, window[keep], window_channel, len(antennas), true_t[keep], duration)
    imp = Impairments(
        rng.uniform(*rx.sampling_offset_ns, n) * 1e-9,
        rng.uniform(0, 2 * np.pi, n),
        rng.uniform(*rx.snr_db, n),
        rng.uniform(*rx.agc_peak, n),
        true_offsets[None, :] + jumps.phase_rad,
    )
    quantized = impair(csi[keep], imp, rng, offsets_hz, int8=not nexmon)
    latency_s = (rx.latency_ms[0] + rng.exponential(rx.latency_ms[1], n)) * 1e-3
    stamps = T0_NS + np.round((true_t[keep] + latency_s) * 1e9).astype(np.int64)
    agc = rng.integers(30, 46, n)
    rss_dbm = NOISE_FLOOR_DB + imp.snr_db - 10 * math.log10(len(antennas))
    rssi = np.clip(np.rint(rss_dbm + 44 + agc), 1, 255).astype(int)
    selection = np.where(rng.uniform(size=n) < 0.8, PERMUTATIONS[0], rng.choice(PERMUTATIONS, n))
    clock_offset_us = int(rng.integers(0, 2**32))
    for k, index in enumerate(keep):
        tag = scenario.tags[owner[index]]
        stamp = int(stamps[k])
        if nexmon:
            add(stamp, dataset.CAPTURE_TOPIC, _nexmon_csi(stamp, tag.id, tag.channel, k, quantized[k]))
        else:
            head = RecordHeader(
                (clock_offset_us + int(true_t[index] * 1e6)) % 2**32,
                k % 2**16,
                (int(rssi[k]),) * 3,
                NOISE_HEADER_DB,
                int(agc[k]),
                int(selection[k]),
                RATE_N_FLAGS,
            )
            bfee = encode_record(head, quantized[k][:, :, None])
            add(
                stamp,
                "/csi",
                make(
                    "rover_msgs/msg/CsiFrame",
                    header=header(stamp, "base_link"),
                    channel=tag.channel,
                    bfee=np.frombuffer(bfee, dtype=np.uint8),
                ),
            )
        angle = true_aoa(np.array(tag.position_m), state.xy[index : index + 1], state.yaw[index : index + 1])[0]
        add(
            stamp,
            "/groundtruth/aoa",
            make(
                "rover_msgs/msg/Aoa",
                header=header(stamp, "base_link"),
                tag_id=tag.id,
                channel=tag.channel,
                angle_rad=float(angle),
                packets=1,
            ),
        )

    imu_t = np.arange(0.0, duration, 1.0 / scenario.imu.rate_hz)
    imu_state = motion.state(imu_t)
    imu = imu_samples(imu_state, scenario.imu, rng, np.random.default_rng([seed, IMU_STREAM]))

    def vec(v: np.ndarray) -> Any:
        return make("geometry_msgs/msg/Vector3", x=float(v[0]), y=float(v[1]), z=float(v[2]))

    no_orientation = np.zeros(9)
    no_orientation[0] = -1.0
    for k, t in enumerate(imu_t):
        stamp = T0_NS + int(round(t * 1e9))
        add(
            stamp,
            "/imu/data",
            make(
                "sensor_msgs/msg/Imu",
                header=header(stamp, "imu_link"),
                orientation_covariance=no_orientation,
                angular_velocity=vec(imu.gyro[k]),
                linear_acceleration=vec(imu.accel[k]),
            ),
        )
    if scenario.odometry.enabled:
        odom_t = np.arange(0.0, duration, 1.0 / scenario.odometry.rate_hz)
        odom_state = motion.state(odom_t)
        odom = odometry_samples(odom_state, odom_t, scenario.odometry, rng)
        _, _, odom_qz, odom_qw = quaternion_from_yaw(odom.yaw)
        for k, t in enumerate(odom_t):
            stamp = T0_NS + int(round(t * 1e9))
            msg = make("nav_msgs/msg/Odometry", header=header(stamp, "odom"), child_frame_id="base_link")
            msg.pose.pose.position.x, msg.pose.pose.position.y = float(odom.xy[k, 0]), float(odom.xy[k, 1])
            msg.pose.pose.orientation.z, msg.pose.pose.orientation.w = float(odom_qz[k]), float(odom_qw[k])
            msg.twist.twist.linear.x = float(odom.speed[k])
            msg.twist.twist.angular.z = float(odom.yaw_rate[k])
            add(stamp, "/odom", msg)

    truth_t = np.arange(0.0, duration, 1.0 / TRUTH_RATE_HZ)
    truth_state = motion.state(truth_t)
    xy, yaw = world.point(truth_state.xy), world.yaw(truth_state.yaw)
    _, _, qz, qw = quaternion_from_yaw(yaw)
    for k, t in enumerate(truth_t):
        stamp = T0_NS + int(round(t * 1e9))
        pose = make("geometry_msgs/msg/PoseStamped", header=header(stamp, "world"))
        pose.pose.position.x, pose.pose.position.y = float(xy[k, 0]), float(xy[k, 1])
        pose.pose.orientation.z, pose.pose.orientation.w = float(qz[k]), float(qw[k])
        add(stamp, "/groundtruth/pose", pose)
    tag_world = {t.id: world.point(np.array(t.position_m)) for t in scenario.tags}
    add(
        T0_NS,
        "/groundtruth/tags",
        make(
            "rover_msgs/msg/TagArray",
            header=header(T0_NS, "world"),
            tags=[
                make(
                    "rover_msgs/msg/Tag",
                    id=t.id,
                    channel=t.channel,
                    observable=True,
                    position=make("geometry_msgs/msg/Point", x=float(tag_world[t.id][0]), y=float(tag_world[t.id][1])),
                )
                for t in scenario.tags
            ],
        ),
    )

    rows.sort(key=lambda r: (r[0], r[1]))
    tags_csv = "id,channel,x,y,z,nlos\n" + "".join(
        f"{t.id},{t.channel},{tag_world[t.id][0]:.4f},{tag_world[t.id][1]:.4f},0.0000,{int(t.nlos)}\n"
        for t in scenario.tags
    )
    simulation = {
        "scenario": scenario.name,
        "seed": seed,
        "duration_s": round(duration, 3),
        "path_length_m": round(motion.path_length_m, 3),
        "direct_to_multipath_db": report.direct_to_multipath_db,
        "nlos": {t.id: t.nlos for t in scenario.tags},
        "true_phase_offsets_rad": [float(v) for v in true_offsets],
        "phase_jumps": {
            "per_run": rx.jumps_per_run,
            "per_retune": rx.jumps_per_retune,
            "per_packet": rx.jumps_per_packet,
            "run_steps": jumps.run_steps,
            "retunes_redrawn": jumps.retunes_redrawn,
            **(
                {
                    "steps_per_minute": rx.steps_per_minute,
                    "steps": [{"time_s": t, "chain": c, "step": s} for t, c, s in jumps.steps],
                }
                if rx.steps_per_minute
                else {}
            ),
        },
    }
    metadata = {
        dataset.SETUP_METADATA: {"yaml": _setup_yaml(scenario, antennas, calibration)},
        dataset.PROVENANCE_METADATA: dataset.provenance(command_line, f"scenario {scenario.name}, seed {seed}"),
        "rover.simulation": {"yaml": yaml.safe_dump(simulation, sort_keys=False), "scenario": scenario.text},
        "rover.truth": {"tags_csv": tags_csv},
    }
    with BagWriter(output, metadata=metadata) as bag:
        for stamp, _order, topic, msg in rows:
            bag.write(topic, msg, stamp)
    return report
