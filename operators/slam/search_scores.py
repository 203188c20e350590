"""How well a tag's bearings fit a place, their jump combination a hidden sequence in time: the
objective of the tag search (`tag_search`), for thousands of places at once.

The chains hold a combination and step to another at some moment (CSI Tool issues #23, #295,
#113). So a place's cost is, over the best sequence of combinations through the bearings (in time
order), each bearing's candidate of its combination as a squared residual in stds, capped at
cap^2 (a bearing no candidate of which fits costs the same anywhere), plus twice the -log odds of
each transition: the chains redraw their combination (uniformly, the same one included) at a rate
per second, so between two bearings a gap apart one of the C - 1 others follows with chance
p / C, p = 1 - exp(-rate gap), the same with 1 - p (C - 1) / C (a robot that stood still a minute
between two bearings may well have seen a step). The rate is not known before the tag is found, so
the cost is the least over REDRAWS_PER_S and FREE, the model in which each bearing draws its
combination afresh (a jump at every retune: each bearing takes its best candidate, each transition costs
log C). A bearing without a candidate of its own for a
combination (merged into another of the same direction) takes its best; one with two (a collinear
array's direction and its mirror image) the better of them. A step within the history
then costs a few units where one combination held throughout fails, and a wrong place cannot take
every bearing's best candidate for free.
"""

from __future__ import annotations

import math
from collections.abc import Generator
from dataclasses import dataclass

import numpy as np

from rover.geometry import wrap_angle

REDRAWS_PER_S = np.array([0.1, 1.0, 10.0]) / 60
"""redraws a second of the sequence models besides FREE: one every ten minutes, every minute, every
six seconds"""
FREE = math.inf
"""the redraw rate of the model in which every bearing draws its combination afresh"""
SCORE_CHUNK = 65_536
"""candidate residuals (bearings x candidates x places) scored per step: half a megabyte, in cache"""


@dataclass(frozen=True)
class Bearings:
    """A tag's bearings in time order: when (s), the robot's position (n, 2), each one's candidate
    angles in the world and their stds (n, K; NaN-padded), the combination of each (-1: none)."""

    times_s: np.ndarray
    robot: np.ndarray
    angles: np.ndarray
    stds: np.ndarray
    jumps: np.ndarray

    def __len__(self) -> int:
        return len(self.robot)

    def take(self, rows: np.ndarray) -> Bearings:
        """Some of the bearings, in time order."""
        return Bearings(self.times_s[rows], self.robot[rows], self.angles[rows], self.stds[rows], self.jumps[rows])


def combinations(jumps: np.ndarray) -> int:
    """How many jump combinations the candidates (n, K; -1 none) are numbered over (1: no jumps)."""
    return max(int(jumps.max(initial=-1)) + 1, 1)


def model_rates(combos: int) -> np.ndarray:
    """The redraw rates of the models scored for `combos` combinations, FREE last."""
    return np.append(REDRAWS_PER_S, FREE) if combos > 1 else np.array([FREE])


def _candidate_index(jumps: np.ndarray, combos: int) -> np.ndarray:
    """(n, C, M) each bearing's candidates of each combination, -1 where it has fewer: one, or a
    direction and its mirror image for a collinear array (rover.operators.aoa)."""
    row, k = np.nonzero(jumps >= 0)
    combo = jumps[row, k]
    slot = row * combos + combo
    order = np.argsort(slot, kind="stable")
    slot, k = slot[order], k[order]
    first = np.searchsorted(slot, slot)
    rank = np.arange(len(slot)) - first
    index = np.full((len(jumps) * combos, max(int(rank.max(initial=0)) + 1, 1)), -1)
    index[slot, rank] = k
    return index.reshape(len(jumps), combos, -1)


def _candidate_costs(q: np.ndarray, robot: np.ndarray, angles: np.ndarray, stds: np.ndarray, cap: float) -> np.ndarray:
    """(n, K, H) capped squared residuals in stds of places q (H, 2) against the candidates (n, K),
    a padding candidate (NaN) at the cap. With the candidates wrapped once, a residual's size is the
    smaller of |difference| and a turn less it: one atan2 per place and bearing."""
    predicted = np.arctan2(q[None, :, 1] - robot[:, 1, None], q[None, :, 0] - robot[:, 0, None])  # (n, H)
    r = np.abs(predicted[:, None, :] - wrap_angle(angles)[:, :, None])
    np.minimum(r, 2 * math.pi - r, out=r)
    r /= stds[:, :, None]
    r *= r
    return np.fmin(r, cap**2, out=r)


def _per_combination(r: np.ndarray, index: np.ndarray) -> np.ndarray:
    """(n, C, H) each combination's cost from the candidates' (n, K, H): its best candidate's (index
    (n, C, M) as `_candidate_index`), or the bearing's best where it has none of its own."""
    per = np.take_along_axis(r, np.maximum(index[:, :, 0], 0)[:, :, None], axis=1)
    for m in range(1, index.shape[2]):  # a mirror image: the better of the two
        other = np.take_along_axis(r, np.maximum(index[:, :, m], 0)[:, :, None], axis=1)
        per = np.where((index[:, :, m] >= 0)[:, :, None], np.minimum(per, other), per)
    return np.where((index[:, :, 0] >= 0)[:, :, None], per, r.min(axis=1, keepdims=True))


MIN_REDRAW_CHANCE = 1e-9
"""the least chance of a redraw between two bearings (two of one instant)"""


def _transitions(rates: np.ndarray, gaps_s: np.ndarray, combos: int) -> tuple[np.ndarray, np.ndarray]:
    """(R, n - 1) costs of staying and of switching between consecutive bearings `gaps_s` apart
    under each redraw rate."""
    p = np.maximum(-np.expm1(-np.outer(rates, np.maximum(gaps_s, 0.0))), MIN_REDRAW_CHANCE)
    return -2 * np.log1p(-p * (combos - 1) / combos), -2 * np.log(p / combos)


def _model_costs(r: np.ndarray, index: np.ndarray, gaps_s: np.ndarray, combos: int) -> np.ndarray:
    """(M, H) each model's least cost (model_rates order) from the candidates' costs (n, K, H)."""
    n = len(r)
    free = r.min(axis=1).sum(axis=0) + (n - 1) * 2 * math.log(combos)
    if combos == 1:
        return free[None]
    per = _per_combination(r, index)
    stay, switch = (c.T[:, :, None, None] for c in _transitions(REDRAWS_PER_S, gaps_s, combos))  # (n - 1, R, 1, 1)
    best = np.repeat(per[0][None], len(REDRAWS_PER_S), axis=0)  # (R, C, H)
    for k, row in enumerate(per[1:]):
        best = np.minimum(best + stay[k], best.min(axis=1, keepdims=True) + switch[k])
        best += row
    return np.concatenate([best.min(axis=1), free[None]])


def score_steps(q: np.ndarray, b: Bearings, cap: float) -> Generator[None, None, np.ndarray]:
    """The cost of each place q (H, 2) (the least over the models), one chunk of SCORE_CHUNK
    residuals per step: the hot loop of the search."""
    out = np.empty(len(q))
    combos = combinations(b.jumps)
    index = _candidate_index(b.jumps, combos)
    gaps_s = np.diff(b.times_s)
    angles = b.angles
    per = max(1, SCORE_CHUNK // max(angles.size, 1))
    for i in range(0, len(q), per):
        if i:
            yield
        r = _candidate_costs(q[i : i + per], b.robot, angles, b.stds, cap)
        out[i : i + per] = _model_costs(r, index, gaps_s, combos).min(axis=0)
    return out


def model_costs(q: np.ndarray, b: Bearings, cap: float) -> np.ndarray:
    """(M, H) each model's cost of a few places (model_rates order)."""
    combos = combinations(b.jumps)
    r = _candidate_costs(q, b.robot, b.angles, b.stds, cap)
    return _model_costs(r, _candidate_index(b.jumps, combos), np.diff(b.times_s), combos)


def decode(q: np.ndarray, b: Bearings, rate: float, cap: float) -> np.ndarray:
    """Each bearing's combination (n,) on the least-cost sequence at place q (2,) under the model of
    redraw rate `rate`; -1 throughout for FREE (each bearing takes its best candidate)."""
    combos = combinations(b.jumps)
    n = len(b)
    if rate == FREE or combos == 1:
        return np.full(n, -1)
    r = _candidate_costs(q[None], b.robot, b.angles, b.stds, cap)
    per = _per_combination(r, _candidate_index(b.jumps, combos))[..., 0]
    stay, switch = (c[0] for c in _transitions(np.array([rate]), np.diff(b.times_s), combos))
    best = per[0].copy()
    back = np.zeros((n, combos), dtype=int)
    everyone = np.arange(combos)
    for k in range(1, n):
        leader = int(np.argmin(best))
        kept, moved = best + stay[k - 1], best[leader] + switch[k - 1]
        back[k] = np.where(kept <= moved, everyone, leader)
        best = np.minimum(kept, moved) + per[k]
    path = np.empty(n, dtype=int)
    path[-1] = int(np.argmin(best))
    for k in range(n - 1, 0, -1):
        path[k - 1] = back[k, path[k]]
    return path
