"""Per-chain phase calibration of the receiver from CSI whose direction is known.

The Intel 5300 adds a constant phase to each receive chain: raw CSI of antenna m = physical CSI x
exp(+j phi_m) (docs/conventions.md). With a transmitter at a known angle theta, the physical CSI
of a plane wave is a common gain times the steering vector a_m(theta) = exp(+j 2 pi f p_m.u(theta)
/ c) (rover.operators.aoa.array.steering), so after each packet's sampling-time-offset slope is
removed (JointMusic.clean) and a(theta) divided out, what is left on chain m relative to chain 1
is exp(+j (phi_m - phi_1)). Only those differences matter, so phi_1 = 0.

The chains' offsets come back shifted by multiples of a jump step after a restart or a retune
(pi at 5 GHz, pi/2 at 2.4 GHz; ../shared/data/README.md), so a calibration is known only modulo
that step: `reduced_rad` is the session's offset reduced into [-step/2, step/2), which is what
two sessions can agree on; `compare` finds the jumps between two calibrations. Pure functions: the
CLI (`rover calibrate`) reads the files.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from rover.errors import BadInput
from rover.formats.intel5300 import SUBCARRIERS, decode_bfee
from rover.formats.wifi import phase_jump_step_rad
from rover.geometry import wrap_angle
from rover.operators.aoa.array import steering
from rover.operators.aoa.music import JointMusic

OUTLIER_SIGMAS = 5.0
"""A packet this many robust standard deviations from the mean on some chain is not the calibration
signal (another transmitter, a packet taken while the antenna selection changed) and is left out.
On the LGTM captures the packets lie within 3 of them or beyond 20, so the cut is not critical."""
MAD_TO_STD = 1.4826
"""Median absolute deviation to standard deviation, for Gaussian scatter."""
OUTLIER_PASSES = 2
"""Mean, cut, mean again: a second pass uses the mean without the first pass's outliers."""
MIN_SCALE_RAD = 1e-9
"""Floor of the robust scale, for noise-free input whose deviations are rounding errors."""
MIN_PACKETS = 2
"""A spread needs at least two packets."""


def jump_step_rad(channel: int) -> float:
    """The step a chain's offset jumps by on `channel` (rover.formats.wifi.phase_jump_step_rad), or
    BadInput for a number that is no channel."""
    try:
        return phase_jump_step_rad(channel)
    except (TypeError, ValueError):
        raise BadInput(f"calibrate: {channel!r} is not a WiFi channel number") from None


def reduce_offsets(offsets_rad: np.ndarray, step_rad: float) -> np.ndarray:
    """Offsets modulo the jump step, into [-step/2, step/2): what survives a restart."""
    return np.mod(np.asarray(offsets_rad, dtype=np.float64) + step_rad / 2, step_rad) - step_rad / 2


@dataclass(frozen=True)
class Calibration:
    """Per-chain phase offsets of one channel, relative to chain 1 (index 0, always 0).

    `offsets_rad` are the capture's own offsets, wrapped into [-pi, pi]; `reduced_rad` the same
    modulo `jump_step_rad`, in [-step/2, step/2); `spread_deg` each chain's circular standard
    deviation across the packets used; `outliers` the packets left out (empty or non-finite
    CSI, or beyond OUTLIER_SIGMAS robust standard deviations on some chain)."""

    channel: int
    offsets_rad: np.ndarray
    reduced_rad: np.ndarray
    spread_deg: np.ndarray
    packets: int
    jump_step_rad: float
    outliers: int = 0


@dataclass(frozen=True)
class Jumps:
    """How calibration `a` differs from `b`: a = b + multiples x step + residual, per chain.
    `multiples` are in 0 .. 2 pi / step - 1 (at 5 GHz: 1 = shifted by pi); `residual_rad` in
    [-step/2, step/2) is the disagreement left once the jumps are removed."""

    multiples: np.ndarray
    residual_rad: np.ndarray
    step_rad: float


def chain_phasors(csi: np.ndarray, antennas_m: np.ndarray, channel: int, angle_rad: np.ndarray | float) -> np.ndarray:
    """Each packet's phase of every chain relative to chain 1 once the known direction is divided
    out, as a complex number (P, M): the amplitude-weighted sum over subcarriers of
    x_m conj(x_1), x = the STO-free CSI over the steering vector. Its angle estimates phi_m - phi_1;
    its size is 0 for an empty packet."""
    h = np.asarray(csi)
    antennas = np.asarray(antennas_m, dtype=np.float64)
    if h.ndim != 3 or h.shape[1] != SUBCARRIERS:
        raise BadInput(f"calibrate: CSI must be (packets, {SUBCARRIERS}, antennas), got shape {h.shape}")
    if antennas.ndim != 2 or antennas.shape[1] != 2 or len(antennas) < 2:
        raise BadInput(f"calibrate: antenna positions must be (antennas >= 2, 2) in metres, got shape {antennas.shape}")
    if h.shape[2] != len(antennas):
        raise BadInput(f"calibrate: CSI has {h.shape[2]} antennas, the array {len(antennas)}")
    angles = np.asarray(angle_rad, dtype=np.float64)
    if angles.shape not in ((), (h.shape[0],)):
        raise BadInput(f"calibrate: one known angle, or one per packet ({h.shape[0]}), not shape {angles.shape}")
    angles = np.broadcast_to(angles, (h.shape[0],))
    if not np.isfinite(angles).all():
        raise BadInput("calibrate: the known angles must be finite")
    jump_step_rad(channel)  # a WiFi channel, else BadInput
    music = JointMusic(antennas, channel)
    clean = music.clean(h, None)  # removes each packet's STO slope; no offsets yet
    x = clean * steering(antennas, music.center_hz, angles).conj()[:, None, :]
    return np.einsum("pfm,pf->pm", x, x[:, :, 0].conj())


def estimate_offsets(
    csi: np.ndarray, antennas_m: np.ndarray, channel: int, angle_rad: np.ndarray | float
) -> Calibration:
    """Per-chain offsets from CSI (P, 30, M), antennas permuted as the CSI Tool says, of a plane
    wave from `angle_rad` (rad, robot frame; one for all packets or one per packet) on `channel`.

    Each packet gives one phase per chain (subcarriers weighted by amplitude, `chain_phasors`);
    packets weigh alike (their gains differ with the AGC). The offsets are the circular mean over
    the packets, after OUTLIER_PASSES rounds of leaving out packets beyond OUTLIER_SIGMAS robust
    standard deviations."""
    step = jump_step_rad(channel)
    z = chain_phasors(csi, antennas_m, channel, angle_rad)
    size = np.abs(z)
    usable = np.isfinite(z).all(axis=1) & (size > 0).all(axis=1)
    u = np.where(usable[:, None], z / np.where(size > 0, size, 1.0), 0)
    keep = usable
    for _ in range(OUTLIER_PASSES):
        if keep.sum() < MIN_PACKETS:
            break
        mean = u[keep].sum(axis=0)
        direction = mean / np.where(np.abs(mean) > 0, np.abs(mean), 1.0)
        deviation = np.abs(np.angle(u * direction.conj()))[:, 1:]
        scale = np.maximum(MAD_TO_STD * np.median(deviation[keep], axis=0), MIN_SCALE_RAD)
        keep = usable & np.all(deviation <= OUTLIER_SIGMAS * scale, axis=1)
    if keep.sum() < MIN_PACKETS:
        raise BadInput(
            f"calibrate: {int(keep.sum())} usable packet(s) on channel {channel}, at least {MIN_PACKETS} needed"
        )
    resultant = u[keep].mean(axis=0)
    offsets = wrap_angle(np.angle(resultant))
    offsets[0] = 0.0
    return Calibration(
        channel=channel,
        offsets_rad=offsets,
        reduced_rad=reduce_offsets(offsets, step),
        spread_deg=circular_std_deg(resultant),
        packets=int(keep.sum()),
        jump_step_rad=step,
        outliers=int(len(u) - keep.sum()),
    )


def match_truth(
    stamps_ns: Sequence[int], channels: Sequence[int], angles: Mapping[int, Sequence[tuple[int, float]]]
) -> tuple[list[int], list[int], list[float]]:
    """The frames with exactly one true angle of the same stamp and channel (a frame of channel 0 takes
    the angle's channel): their indices, channels and angles (rad)."""
    index, channel_of, angle_of = [], [], []
    for k, (stamp, channel) in enumerate(zip(stamps_ns, channels, strict=True)):
        match = [(c, a) for c, a in angles.get(stamp, []) if channel in (0, c)]
        if len(match) == 1 and (channel or match[0][0]):
            index.append(k)
            channel_of.append(channel or match[0][0])
            angle_of.append(match[0][1])
    return index, channel_of, angle_of


def offsets_from_truth(
    stamps_ns: Sequence[int],
    channels: Sequence[int],
    bfee: Sequence[bytes],
    angles: Mapping[int, Sequence[tuple[int, float]]],
    antennas_m: np.ndarray,
) -> list[Calibration]:
    """One calibration per channel from CSI Tool records each with its true angle (`match_truth`); the
    records with as many receive chains as the array has antennas count."""
    index, channel_of, angle_of = match_truth(stamps_ns, channels, angles)
    if not index:
        raise BadInput("no CSI frame has a true angle with its stamp and channel")
    records = decode_bfee([bfee[k] for k in index])
    m = len(antennas_m)
    rows = records.offset[records.nrx == m]
    if not len(rows):
        raise BadInput(f"no CSI frame with {m} receive chains and a true angle")
    channel_arr, angle_arr = np.array(channel_of)[rows], np.array(angle_of)[rows]
    csi = records.csi[records.nrx == m, :, :m, 0]
    return [
        estimate_offsets(csi[channel_arr == c], antennas_m, int(c), angle_arr[channel_arr == c])
        for c in np.unique(channel_arr)
    ]


def circular_std_deg(resultant: np.ndarray) -> np.ndarray:
    """Circular standard deviation (deg) from the mean of unit phasors: sqrt(-2 ln |mean|)."""
    length = np.clip(np.abs(resultant), 1e-300, 1.0)
    return np.degrees(np.sqrt(np.maximum(-2 * np.log(length), 0.0))) + 0.0  # + 0.0: no -0.0


def compare(a: Calibration, b: Calibration) -> Jumps:
    """The jumps that take calibration `b` to `a` (same channel, same array), and what is left."""
    if a.channel != b.channel:
        raise BadInput(f"calibrate: cannot compare channel {a.channel} with channel {b.channel}")
    if len(a.offsets_rad) != len(b.offsets_rad):
        raise BadInput(f"calibrate: cannot compare {len(a.offsets_rad)} chains with {len(b.offsets_rad)}")
    step = a.jump_step_rad
    difference = wrap_angle(a.offsets_rad - b.offsets_rad)
    residual = reduce_offsets(difference, step)
    turns = round(2 * math.pi / step)
    multiples = np.mod(np.rint((difference - residual) / step).astype(np.int64), turns)
    return Jumps(multiples, residual, step)


def combine(calibrations: Sequence[Calibration]) -> Calibration:
    """Several calibrations of one channel as one, in the first one's session: each is shifted by
    its jumps relative to the first, then the offsets are averaged (circular mean, weighted by
    packets). `spread_deg` is then the circular standard deviation across the calibrations."""
    if not calibrations:
        raise BadInput("calibrate: no calibration to combine")
    first = calibrations[0]
    if len(calibrations) == 1:
        return first
    aligned = np.array([first.offsets_rad + compare(c, first).residual_rad for c in calibrations])
    weights = np.array([c.packets for c in calibrations], dtype=np.float64)
    resultant = (weights[:, None] * np.exp(1j * aligned)).sum(axis=0) / weights.sum()
    offsets = wrap_angle(np.angle(resultant))
    offsets[0] = 0.0
    return Calibration(
        channel=first.channel,
        offsets_rad=offsets,
        reduced_rad=reduce_offsets(offsets, first.jump_step_rad),
        spread_deg=circular_std_deg(np.exp(1j * aligned).mean(axis=0)),
        packets=int(weights.sum()),
        jump_step_rad=first.jump_step_rad,
        outliers=sum(c.outliers for c in calibrations),
    )


def setup_block(calibrations: Sequence[Calibration]) -> str:
    """The `receiver.phase_offsets_rad` block of a setup.yaml, one entry per channel (several
    calibrations of a channel combined, `combine`)."""
    by_channel: dict[int, list[Calibration]] = {}
    for c in calibrations:
        by_channel.setdefault(c.channel, []).append(c)
    entries = ", ".join(
        f"{channel}: [{', '.join(f'{v:.4f}' for v in combine(group).offsets_rad)}]"
        for channel, group in sorted(by_channel.items())
    )
    return f"receiver:\n  phase_offsets_rad: {{{entries}}}\n"


def render(rows: Sequence[tuple[str, Calibration]]) -> str:
    """A table: source, channel, offsets, reduced offsets, spread (degrees), packets used and left out;
    then each calibration's jumps and residual against the first of its channel."""

    def deg(values: np.ndarray, digits: int) -> str:
        return " ".join(f"{v:7.{digits}f}" for v in np.degrees(values))

    name_width = max([len("source"), *(len(name) for name, _ in rows)])
    m = max((len(c.offsets_rad) for _, c in rows), default=3)
    lines = [
        f"{'source':<{name_width}}  channel  {'offset (deg)':<{8 * m - 1}}  {'reduced (deg)':<{8 * m - 1}}  "
        f"{'spread (deg)':<{8 * m - 1}}  packets  outliers"
    ]
    for name, c in rows:
        spread = " ".join(f"{v:7.2f}" for v in c.spread_deg)
        lines.append(
            f"{name:<{name_width}}  {c.channel:>7}  {deg(c.offsets_rad, 1)}  {deg(c.reduced_rad, 1)}  "
            f"{spread}  {c.packets:>7}  {c.outliers:>8}"
        )
    firsts: dict[int, tuple[str, Calibration]] = {}
    for name, c in rows:
        if c.channel not in firsts:
            firsts[c.channel] = (name, c)
            continue
        ref_name, ref = firsts[c.channel]
        jumps = compare(c, ref)
        step_deg = math.degrees(jumps.step_rad)
        shifted = ", ".join(f"chain {k + 1} by {int(n) * step_deg:g} deg" for k, n in enumerate(jumps.multiples) if n)
        lines.append(
            f"{name} vs {ref_name} (channel {c.channel}, modulo {step_deg:g} deg): "
            f"{'shifted: ' + shifted if shifted else 'no jump'}; residual "
            f"{' '.join(f'{v:.2f}' for v in np.degrees(jumps.residual_rad))} deg"
        )
    return "\n".join(lines) + "\n"
