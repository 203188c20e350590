"""`aoa`: the direct-path angle of arrival of each tag, from the CSI of one burst (one dwell of the sweep).

Each packet is cleaned and smoothed (rover.operators.aoa.music); the burst's covariances are averaged (the
packets see the same paths, their random common phases cancel in the covariance), and joint
angle-delay MUSIC on that average gives the paths. The strongest peak is the direct path unless
a weaker one clearly arrives earlier (SpotFi's insight: reflections travel farther). Measured on
simulated bursts, this beats clustering per-packet peaks, whose spurious small-delay peaks win
too often. The choice is checked against the power each direction explains, and the reported
standard deviation comes from what a single plane wave from the reported angle leaves
unexplained and from the strongest rival direction (see `burst_std`).

This module is the operator (bursts in, Aoa messages out); the signal processing lives in
rover.operators.aoa.music (MUSIC, the direct-path choice and its std) and rover.operators.aoa.array
(the array model: steering vectors, ambiguity, main lobes).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from rover.formats.rig import Rig, RigInput
from rover.formats.wifi import RATE_HT40, SUBCARRIERS_20MHZ, SUBCARRIERS_40MHZ, phase_jump_step_rad
from rover.geometry import wrap_angle
from rover.messages import header, make
from rover.operator import Emit, In, Operator, Out
from rover.operators.aoa.array import ArrayResponse, array_axis, check_rig_geometry, field_mask, mirror_into_field
from rover.operators.aoa.interleaved import InterleavedBursts, Packet
from rover.operators.aoa.jumps import jump_phases
from rover.operators.aoa.music import MAX_STD_RAD, JointMusic, Peaks, burst_std, check_energy, choose_direct
from rover.pipeline.params import Checked, Fraction, NonNegativeFloat, NonNegativeInt, PositiveFloat, PositiveInt

log = logging.getLogger("rover.aoa")

QUALITY_GOOD = 0
QUALITY_RIVAL = 1
"""A direction outside the reported one's main lobe explains nearly as much power (more than RIVAL_SHARE of it)."""
QUALITY_AMBIGUOUS = 2
"""The estimate lies where the array can hardly tell it from another direction."""
QUALITY_SWITCHED = 3
"""The MUSIC choice held clearly less power than a direction outside its main lobe: that one is reported."""
RIVAL_SHARE = 0.9
NEAR_AMBIGUOUS_CORRELATION = 0.9


@dataclass(frozen=True)
class AoaParams(Checked):
    grid_deg: PositiveFloat = 4.0
    """coarse angle grid; peaks are refined on a grid 8 times finer"""
    window: PositiveInt = 8
    """subcarriers per smoothing window"""
    max_paths: PositiveInt = 4
    min_packets: PositiveInt = 3
    max_burst_s: PositiveFloat = 0.5
    support: Fraction = 0.01
    """pseudo-spectrum height, relative to the highest peak, a peak needs to be a direct-path candidate"""
    delay_margin_ns: NonNegativeFloat = 5.0
    """a weaker candidate replaces a stronger one only when it arrives more than this much earlier"""
    energy_ratio: PositiveFloat = 1.2
    """report the strongest direction instead when it holds this many times the chosen one's power"""
    resolved_ns: NonNegativeFloat = 25.0
    """...unless MUSIC sees a path there arriving this much later than its choice"""
    std_floor_deg: PositiveFloat = 2.0
    """what no burst shows: calibration error, noise"""
    multipath_std_deg: NonNegativeFloat = 30.0
    """std per unit of sqrt(unexplained / explained power) at the reported angle (coherent multipath)"""
    doubt_sharpness: PositiveFloat = 60.0
    """how fast a rival direction's chance grows with its power relative to the reported one"""
    calibrate: bool = True
    """remove the rig's per-chain phase offsets (off only to show what calibration is worth)"""
    remove_sto: bool = True
    """remove each packet's sampling-time-offset phase slope (off only to show what it is worth)"""
    jumps: bool = True
    """give a candidate per combination of the chains' phase jumps (off: trust the calibration as is)"""
    merge_deg: PositiveFloat = 2.0
    """candidates of different jump combinations closer than this are one (the one listed first is kept)"""
    align_packets: bool = False
    """align each packet's chains to the burst's before averaging (always at 2.4 GHz, whose chains
    jump from packet to packet, CSI Tool issue #6)"""
    burst_packets: NonNegativeInt = 0
    """end a burst after this many packets (0: bursts end with the tag's dwell, by time only)"""


@dataclass(frozen=True)
class Candidate:
    """The burst's direct path if the chains carry jump combination `jumps`."""

    angle_rad: float
    std_rad: float
    power: float
    jumps: int
    tof_s: float
    quality: int


def distinguishable(candidates: list[Candidate], merge_rad: float) -> list[Candidate]:
    """The candidates, the calibration's own (no jump) first and the others most power first,
    without those within `merge_rad` of one before them."""
    kept: list[Candidate] = []
    for c in sorted(candidates, key=lambda c: (c.jumps != 0, -c.power, c.jumps)):
        if all(abs(float(wrap_angle(c.angle_rad - k.angle_rad))) >= merge_rad for k in kept):
            kept.append(c)
    return kept


def align_packets(clean: np.ndarray, undo: np.ndarray, passes: int = 2) -> np.ndarray:
    """Each packet (P, F, M) with the jump combination undone (rows of `undo`, (C, M)) that best
    matches the burst's spatial covariance, the burst's own first: the packets then share one
    combination, which the candidates resolve like any burst's."""
    spatial = np.einsum("pfm,pfn->pmn", clean, clean.conj())  # (P, M, M)
    turn = undo[:, None, :, None] * undo[:, None, None, :].conj()  # (C, 1, M, M)
    reference = spatial[0]
    best = np.zeros(len(clean), int)
    for _ in range(passes):
        fit = np.einsum("mn,cpmn->cp", reference.conj(), turn * spatial[None]).real
        best = np.argmax(fit, axis=0)
        reference = np.einsum("pm,pmn,pn->mn", undo[best], spatial, undo[best].conj())
    return clean * undo[best][:, None, :]


INTEL_SUBCARRIERS = len(SUBCARRIERS_20MHZ)
"""columns of a CSI Tool record (30 at either bandwidth)"""
Plan = tuple[bool, bytes, float]
"""a record's subcarrier plan: the CSI Tool's 40 MHz flag, or another source's subcarrier indices
(as int16 bytes: a cheap key) and centre frequency"""
PLAN_DTYPE = np.int16


def plan_of(msg: Any) -> Plan:
    """The subcarrier plan of a Csi record."""
    if len(msg.subcarriers):
        return False, np.asarray(msg.subcarriers, PLAN_DTYPE).tobytes(), float(msg.centre_freq_hz)
    return bool(msg.rate & RATE_HT40), b"", 0.0


def plan_subcarriers(plan: Plan) -> tuple[np.ndarray, float | None]:
    """The subcarrier indices and centre frequency (None: the channel's) of a plan."""
    wide, given, center_hz = plan
    if given:
        return np.frombuffer(given, PLAN_DTYPE).astype(np.int64), center_hz or None
    return (SUBCARRIERS_40MHZ if wide else SUBCARRIERS_20MHZ), None


class Aoa(Operator):
    """One Aoa message per burst of a tag's packets."""

    cpu_weight = 3.7

    inputs = {
        "csi": In("rover_msgs/msg/Csi", doc="a sweep's CSI: one tag per dwell, a burst each"),
        "capture": In(
            "rover_msgs/msg/Csi",
            required=False,
            doc="another tool's CSI (a converted WiROS bag): transmitters interleaved, a burst per transmitter",
        ),
        "setup": In("rover_msgs/msg/RigSetup"),
    }
    outputs = {"aoa": Out("rover_msgs/msg/Aoa")}
    Params = AoaParams

    def __init__(self, params: AoaParams | None = None):
        super().__init__(params)
        self.setup = RigInput()
        self.rig: Rig | None = None
        self.estimators: dict[tuple[int, Plan], JointMusic] = {}
        self.waiting: list[tuple[str, Any, int]] = []
        self.burst: list[Packet] = []
        self.captured = InterleavedBursts(round(self.params.max_burst_s * 1e9), self.params.burst_packets)
        self.collinear = False
        self.axis_rad: float | None = None
        """a collinear array's axis direction (robot frame)"""
        self._responses: dict[float, ArrayResponse] = {}
        self.field = np.ones(360, dtype=bool)

    def on_input(self, port: str, msg: Any, stamp_ns: int):
        if port == "setup":
            self._configure(msg)
            pending, self.waiting = self.waiting, []
            for was, csi, stamp in pending:
                yield from self._add(csi, stamp) if was == "csi" else self._capture(csi, stamp)
        elif self.rig is None:
            self.waiting.append((port, msg, stamp_ns))
        elif port == "csi":
            yield from self._add(msg, stamp_ns)
        else:
            yield from self._capture(msg, stamp_ns)

    def _configure(self, msg: Any) -> None:
        self.rig = self.setup.update(msg)
        antennas = self.rig.antenna_positions_m
        warning = check_rig_geometry(self.rig)
        self.estimators, self._responses = {}, {}
        axis = array_axis(antennas)
        self.collinear = axis is not None
        self.axis_rad = math.atan2(axis[1], axis[0]) if axis is not None else None
        self.field = field_mask(antennas, self.rig.field_of_view_deg)
        if warning:
            log.warning("%s", warning)

    @property
    def _rig(self) -> Rig:
        """The rig description, there once the setup arrived (CSI waits for it until then)."""
        if self.rig is None:
            raise RuntimeError("aoa: no rig description yet")
        return self.rig

    def _estimator(self, channel: int, plan: Plan) -> JointMusic:
        """The estimator of a channel and subcarrier plan (the CSI Tool's 40 MHz records report other
        subcarriers than its 20 MHz ones; another source says its own)."""
        if (channel, plan) not in self.estimators:
            p = self.params
            subcarriers, center_hz = plan_subcarriers(plan)
            self.estimators[channel, plan] = JointMusic(
                self._rig.antenna_positions_m,
                channel,
                window=p.window,
                angle_step_deg=p.grid_deg,
                max_paths=p.max_paths,
                subcarriers=subcarriers,
                center_hz=center_hz,
            )
        return self.estimators[channel, plan]

    def held_since_ns(self) -> float:
        """The first stamp of the CSI held (waiting for the rig, the burst under way, a capture's open
        bursts and the AoAs queued behind them): an AoA is stamped at its burst's median packet, so
        none comes before it."""
        held = [self.waiting[0][2]] if self.waiting else []
        held += [self.burst[0][1]] if self.burst else []
        return min([*held, self.captured.held_since_ns()])

    def _add(self, msg: Any, stamp_ns: int):
        if self.burst:
            first, last = self.burst[0], self.burst[-1]
            if (
                msg.tag_id != first[0].tag_id
                or stamp_ns - first[1] > self.params.max_burst_s * 1e9
                or stamp_ns - last[1] > self.params.max_burst_s * 1e9 / 2
            ):
                yield from self._flush()
        self.burst.append((msg, stamp_ns))
        if len(self.burst) == self.params.burst_packets:
            yield from self._flush()

    def _capture(self, msg: Any, stamp_ns: int):
        """A packet of another tool's capture: the AoAs of the transmitters' bursts it closes, in stamp
        order. No candidate per jump combination: the pi jumps are the Intel 5300's, not its chains'."""
        self._queue_captured(self.captured.add(msg, stamp_ns))
        yield from self.captured.ready(stamp_ns)

    def _queue_captured(self, bursts: list[list[Packet]]) -> None:
        for burst in bursts:
            for emit in self._aoa_of(burst, jumps=False):
                self.captured.queue(emit.stamp_ns, emit)

    def _flush(self):
        burst, self.burst = self.burst, []
        yield from self._aoa_of(burst, jumps=self.params.jumps)

    def _aoa_of(self, burst: list[Packet], jumps: bool):
        """The AoA of one burst's packets (none, counted, when they are too few or carry no path)."""
        usable = [(m, s) for m, s in burst if m.nrx == len(self._rig.antenna_positions_m)]
        if len(usable) < len(burst):
            self.drop("packets with another antenna count", len(burst) - len(usable))
        first = plan_of(usable[0][0]) if usable else (False, b"", 0.0)
        same = [(m, s) for m, s in usable if plan_of(m) == first]
        if len(same) < len(usable):
            self.drop("packets of another bandwidth than their burst's first", len(usable) - len(same))
        usable = same
        if len(usable) < self.params.min_packets:
            self.drop("bursts with too few packets")
            return
        msg0 = usable[0][0]
        columns = len(msg0.subcarriers) or INTEL_SUBCARRIERS
        csi = np.stack(
            [
                (m.csi_real.astype(np.float64) + 1j * m.csi_imag.astype(np.float64)).reshape(columns, m.nrx, m.ntx)[
                    :, :, 0
                ]
                for m, _ in usable
            ]
        )
        finite = np.isfinite(csi).all(axis=(1, 2)) & (np.abs(csi).sum(axis=(1, 2)) > 0)
        if finite.sum() < self.params.min_packets:
            self.drop("bursts of empty or invalid CSI")
            return
        csi = csi[finite]
        music = self._estimator(msg0.channel, first)
        offsets = self._rig.phase_offsets(msg0.channel) if self.params.calibrate else None
        clean = music.clean(csi, offsets, sto=self.params.remove_sto)
        candidates = self._candidates(music, clean, msg0.channel, jumps)
        if not candidates:
            self.drop("bursts too noisy (no path above the noise)")
            return
        best = candidates[0]
        stamps = sorted(s for _, s in usable)
        stamp = stamps[len(stamps) // 2]
        yield Emit(
            "aoa",
            make(
                "rover_msgs/msg/Aoa",
                header=header(stamp, "base_link"),
                tag_id=msg0.tag_id,
                channel=msg0.channel,
                angle_rad=best.angle_rad,
                std_rad=best.std_rad,
                tof_s=best.tof_s,
                packets=len(csi),
                quality=best.quality,
                candidate_angles_rad=np.array([c.angle_rad for c in candidates]),
                candidate_stds_rad=np.array([c.std_rad for c in candidates]),
                candidate_powers=np.array([c.power for c in candidates]),
                candidate_jumps=np.array([c.jumps for c in candidates], dtype=np.uint16),
                chosen=-1,
            ),
            stamp,
        )

    def _candidates(self, music: JointMusic, clean: np.ndarray, channel: int, jumps: bool) -> list[Candidate]:
        """The burst's direct path under each combination of chain phase jumps (rover.operators.aoa.jumps),
        the distinguishable ones, the no-jump one first: the covariances of all combinations are one
        batch for MUSIC, since undoing a jump only rotates the chains' phases."""
        p = self.params
        phases = jump_phases(channel, clean.shape[2], jumps)
        undo = np.exp(-1j * phases)  # (C, M)
        if jumps and (p.align_packets or phase_jump_step_rad(channel) < math.pi):
            clean = align_packets(clean, undo)
        cov = music.covariance(clean).mean(axis=0)
        along = np.repeat(undo, music.window, axis=1)  # antenna-major, as the covariance's elements
        spectrum, paths = music.spectrum(along[:, :, None] * cov[None] * along[:, None, :].conj())
        peaks = music.refine(music.peaks(spectrum, k=p.max_paths))
        response = self._response(music.center_hz)
        spatial = np.einsum("pfm,pfn->mn", clean, clean.conj())
        energies = response.energy_batch(undo[:, :, None] * spatial[None] * undo[:, None, :].conj())
        found = []
        for c in np.flatnonzero(paths > 0):
            candidate = self._direction(peaks, int(c), int(paths[c]), energies[c], response)
            if candidate is not None and self.field[ArrayResponse.degree(candidate.angle_rad)]:
                found.append(candidate)  # a direction outside the rig's field of view is no candidate
        return distinguishable(found + self._mirrors(found), math.radians(p.merge_deg))

    def _mirrors(self, found: list[Candidate]) -> list[Candidate]:
        """For a collinear array (two antennas, a line), which sees a direction and its mirror image
        across its axis alike: each candidate's mirror image that is in the rig's field of view too,
        a candidate of the same jump combination (the SLAM tells the two apart by the robot's motion,
        as it does the combinations). None for a planar array, or a field on one side of the axis."""
        if self.axis_rad is None:
            return []
        mirrors = [replace(c, angle_rad=float(wrap_angle(2 * self.axis_rad - c.angle_rad))) for c in found]
        return [m for m in mirrors if self.field[ArrayResponse.degree(m.angle_rad)]]

    def _direction(
        self, peaks: Peaks, c: int, paths: int, energy: np.ndarray, response: ArrayResponse
    ) -> Candidate | None:
        """The direct path of combination `c`'s spectrum peaks, checked against the power it explains."""
        angle = mirror_into_field(peaks.angle[c], self._rig.antenna_positions_m, self.field)
        best = choose_direct(peaks.delay[c], peaks.height[c], paths, self.params)
        if best is None:
            return None
        direction = check_energy(
            angle, peaks.delay[c], peaks.height[c], best, energy, response, self.field, self.params
        )
        theta, tau = direction.angle_rad, float(peaks.delay[c, best])
        if direction.switched:
            distance = np.where(peaks.height[c] > 0, np.abs(wrap_angle(angle - theta)), np.inf)
            tau = float(peaks.delay[c, np.argmin(distance)])
        quality = QUALITY_SWITCHED if direction.switched else QUALITY_GOOD
        if direction.rival_power > direction.power * RIVAL_SHARE:
            quality = quality or QUALITY_RIVAL
        std, quality = self._ambiguity(theta, burst_std(direction, self.params), quality, response)
        return Candidate(theta, std, direction.power, c, tau, quality)

    def _ambiguity(self, theta: float, std: float, quality: int, response: ArrayResponse) -> tuple[float, int]:
        """Inflate the std where a direction outside the main lobe looks almost the same to the array."""
        if self.collinear:
            return std, quality
        worst = float(response.worst(theta))
        if worst > NEAR_AMBIGUOUS_CORRELATION:
            std = min(std * (1 + 10 * (worst - NEAR_AMBIGUOUS_CORRELATION)), MAX_STD_RAD)
            quality = quality or QUALITY_AMBIGUOUS
        return std, quality

    def _response(self, freq_hz: float) -> ArrayResponse:
        if freq_hz not in self._responses:
            self._responses[freq_hz] = ArrayResponse(self._rig.antenna_positions_m, freq_hz)
        return self._responses[freq_hz]

    def on_end(self):
        if self.burst:
            yield from self._flush()
        self._queue_captured(self.captured.rest())
        yield from self.captured.ready(math.inf)
        if self.waiting:
            self.drop("packets before any rig description", len(self.waiting))
