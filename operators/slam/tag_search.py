"""Where a tag not yet localized is, from its bearings' candidates over the robot's path.

The Intel 5300's chain phase jumps give each burst several candidate angles (one per jump
combination, rover.operators.aoa.jumps) that a single burst cannot tell apart: the wrong ones are
clean plane waves too. Geometry can: only the true candidates of a tag's bearings, seen from the
robot's successive positions, cross at one point. So the search triangulates pairs of bearings
(every pair of candidates, from well-separated positions) into hypotheses, scores each against all
the tag's bearings with their combination a hidden sequence in time (`search_scores`: held all
run, stepping now and then, or drawn afresh at every retune), refines the best by Gauss-Newton on
the candidates of its best sequence, and accepts it only when no hypothesis elsewhere comes close:
a tag stays unlocalized rather than be guessed.
"""

from __future__ import annotations

import math
from collections.abc import Generator
from dataclasses import dataclass, replace
from typing import TypeVar

import numpy as np

from rover.geometry import parallax_deg, wrap_angle
from rover.operators.slam.search_scores import (
    FREE,
    Bearings,
    combinations,
    decode,
    model_costs,
    model_rates,
    score_steps,
)


@dataclass(frozen=True)
class SearchSettings:
    min_bearings: int = 12
    """bearings a tag needs before it is searched for"""
    pair_bearings: int = 16
    """bearings, spread over the history, whose candidate pairs are triangulated into hypotheses"""
    score_bearings: int = 96
    """bearings, spread over the history, that score the hypotheses (more only refine the winner):
    bounds a search's work however long a tag waits"""
    cap_sigma: float = 3.0
    """a bearing whose best candidate is further off than this many stds costs cap_sigma^2 (an outlier)"""
    min_margin: float = 25.0
    """how much more (in squared stds) the best hypothesis elsewhere must cost: the evidence needed"""
    min_inliers: float = 0.8
    """share of the bearings the position must explain: real bearings have heavy tails (a building's
    arrays: a 90th percentile of 14-48 deg against a median of 6-12), and an NLOS tag's bursts follow
    its reflection for a while, so one in five may be beyond cap_sigma (at 0.9, `paper` seed 1 with
    a jump at every retune never found its NLOS tag, the right place explaining 81-82% of its
    bearings with the margin there: 29)"""
    min_parallax_deg: float = 10.0
    """spread of the inliers' directions seen from the tag: the robot must have moved around it"""
    min_range_m: float = 0.3
    max_range_m: float = 10.0
    separation_m: float = 0.5
    """hypotheses closer than this (or a fifth of the range) to the best are the same place"""
    min_crossing_deg: float = 3.0
    """two rays more parallel than this do not triangulate"""


@dataclass(frozen=True)
class Found:
    """A tag's position, the candidate each bearing uses (-1: outlier), and the evidence."""

    position: np.ndarray
    choice: np.ndarray
    info: np.ndarray
    """2x2 information of the position from the inlier bearings (robot positions taken as known)"""
    margin: float
    inliers: float
    parallax_deg: float
    score: float = math.inf
    combination: int = -1
    """the jump combination all its inlier bearings share (-1: they step or pick their own)"""
    redraw_rate: float = FREE
    """redraws a second of the jump model that fits best (FREE: a combination per bearing)"""

    def clear(self, s: SearchSettings) -> bool:
        """Whether the evidence settles the position: no rival elsewhere, most bearings agreeing, parallax."""
        return self.margin >= s.min_margin and self.inliers >= s.min_inliers and self.parallax_deg >= s.min_parallax_deg


RAY_POINTS = 8
"""hypotheses along each candidate ray of the pair bearings, from min_range_m to max_range_m"""
RANGE_CHECK = np.array([1.5, 2 / 3])
"""a found position's distance from the robot path scaled by these must cost the margin too: a
place the bearings would fit as well farther out (a ghost at the edge of the search) is no place"""
STEP_LIMIT_M = 5.0
"""a Gauss-Newton step longer than this is an unconstrained range, not a refinement"""


def _residuals(q: np.ndarray, robot: np.ndarray, angles: np.ndarray, stds: np.ndarray) -> np.ndarray:
    """(H, n, K) angle residuals in stds of positions q (H, 2) against the candidates (n, K); NaN-padded -> inf."""
    d = q[:, None, :] - robot[None, :, :]
    predicted = np.arctan2(d[..., 1], d[..., 0])
    r = wrap_angle(predicted[:, :, None] - angles[None]) / stds[None]
    return np.where(np.isfinite(r), r, np.inf)


T = TypeVar("T")


def finish(steps: Generator[None, None, T]) -> T:
    """Run a search's steps (see `search_steps`) to the end; its result."""
    while True:
        try:
            next(steps)
        except StopIteration as done:
            return done.value


def spread_along(robot: np.ndarray, count: int) -> np.ndarray:
    """Indices of at most `count` robot positions spread evenly over the path (not the time: a
    robot standing still adds no view)."""
    n = len(robot)
    along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(robot, axis=0), axis=1))])
    spots = np.linspace(0.0, along[-1], min(n, count))
    return np.unique(np.minimum(np.searchsorted(along, spots), n - 1))


def _hypotheses(robot: np.ndarray, angles: np.ndarray, s: SearchSettings) -> np.ndarray:
    """Intersections (H, 2) of candidate rays from pairs of bearings spread over the history."""
    k = angles.shape[1]
    pick = spread_along(robot, s.pair_bearings)
    i, j = np.triu_indices(len(pick), 1)
    i, j = pick[i], pick[j]
    a_i = np.repeat(angles[i], k, axis=1)  # (pairs, K*K): candidate a of i with every b of j
    a_j = np.tile(angles[j], (1, k))
    u = np.stack([np.cos(a_i), np.sin(a_i)], axis=-1)
    v = np.stack([np.cos(a_j), np.sin(a_j)], axis=-1)
    base = (robot[j] - robot[i])[:, None, :]
    cross = u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]
    ok = np.abs(cross) >= math.sin(math.radians(s.min_crossing_deg))
    cross = np.where(ok, cross, 1.0)
    along_i = (base[..., 0] * v[..., 1] - base[..., 1] * v[..., 0]) / cross
    along_j = (base[..., 0] * u[..., 1] - base[..., 1] * u[..., 0]) / cross
    ok &= (along_i >= s.min_range_m) & (along_j >= s.min_range_m)
    ok &= (along_i <= s.max_range_m) & (along_j <= s.max_range_m) & np.isfinite(along_i + along_j)
    q = robot[i][:, None, :] + along_i[..., None] * u
    # and points along each ray: where the rays are too parallel to cross (a tag ahead on a straight
    # path), these are the places that explain them, and they compete with any crossing elsewhere
    ranges = np.geomspace(s.min_range_m, s.max_range_m, RAY_POINTS)
    a = angles[pick]
    ray = robot[pick][:, None, None, :] + ranges[None, None, :, None] * np.stack([np.cos(a), np.sin(a)], -1)[:, :, None]
    ray = ray.reshape(-1, 2)
    return np.concatenate([q[ok], ray[np.isfinite(ray).all(axis=1)]])


def _linearized(q: np.ndarray, robot: np.ndarray, angles: np.ndarray, stds: np.ndarray, cap: float):
    """At q: the capped score, each bearing's best candidate (-1 outlier), and the inliers'
    residuals and Jacobians."""
    r = _residuals(q[None], robot, angles, stds)[0]
    best = np.argmin(r**2, axis=1)
    rb = r[np.arange(len(r)), best]
    inlier = np.abs(rb) < cap
    d = q[None, :] - robot
    range2 = np.maximum(np.sum(d**2, axis=1), 1e-6)
    sb = stds[np.arange(len(r)), best]
    jac = np.stack([-d[:, 1], d[:, 0]], axis=1) / (range2 * sb)[:, None]
    score = float(np.minimum(rb**2, cap**2).sum())
    return score, np.where(inlier, best, -1), jac[inlier], rb[inlier]


def _refine(q: np.ndarray, robot: np.ndarray, angles: np.ndarray, stds: np.ndarray, cap: float, steps: int = 5):
    """Gauss-Newton on the inliers' best candidates from q, a step kept only when it lowers the
    capped score (where the rays are nearly parallel a step can slide along them to a worse
    place); returns q, choice (-1 outlier), info, and the capped score there."""
    score, choice, jac, rb = _linearized(q, robot, angles, stds, cap)
    for _ in range(steps):
        info = jac.T @ jac
        if len(rb) < 2 or np.linalg.cond(info) > 1e12:
            break
        step = np.linalg.solve(info, jac.T @ rb)
        if not np.all(np.isfinite(step)) or np.linalg.norm(step) > STEP_LIMIT_M:
            break  # rays too parallel to pin the range: the hypothesis stays as triangulated
        trial = _linearized(q - step, robot, angles, stds, cap)
        if trial[0] > score:
            break
        q = q - step
        score, choice, jac, rb = trial
    return q, choice, jac.T @ jac, score


def by_combination(angles: np.ndarray, stds: np.ndarray, jumps: np.ndarray, combination: int | np.ndarray):
    """Each bearing's candidates for a jump combination (one for all, or one per bearing; -1: none)
    as a candidate set (n, K; NaN-padded): its own of that combination (one, or a direction and its
    mirror image for a collinear array); a bearing without one of its own for it (merged into
    another's, or -1) keeps all its candidates (it fits either way). Also (n, K) the index of each
    kept candidate among the bearing's own."""
    has = (jumps == np.broadcast_to(np.asarray(combination), len(angles))[:, None]) & (jumps >= 0)
    own = has.any(axis=1)
    keep = np.where(own[:, None], has, True)
    # the kept candidates first, in their order, then the others as padding
    source = np.argsort(~keep, axis=1, kind="stable")
    kept = np.take_along_axis(keep, source, axis=1)
    pick_a = np.where(kept, np.take_along_axis(angles, source, axis=1), np.nan)
    pick_s = np.where(kept, np.take_along_axis(stds, source, axis=1), 1.0)
    return pick_a, pick_s, source


def search(b: Bearings, s: SearchSettings) -> Found | None:
    """The likeliest position of the tag from its bearings (candidates' combinations -1: unknown,
    each bearing takes its best); None without enough bearings or rays that cross. `Found.clear`
    says whether the evidence settles it."""
    return finish(search_steps(b, s))


def search_steps(b: Bearings, s: SearchSettings) -> Generator[None, None, Found | None]:
    """`search` a step at a time: each step scores one chunk of hypotheses (SCORE_CHUNK residuals)
    or refines one, so that a caller can spread a search over its idle time (the same result as
    `search`, whatever the steps taken at once)."""
    if len(b) < s.min_bearings:
        return None
    if len(b) > s.score_bearings:
        keep = spread_along(b.robot, s.score_bearings)
        if len(keep) < len(b):
            found = yield from search_steps(b.take(keep), s)
            if found is None:
                return None
            yield
            return _on_all(found, b, s)
    return (yield from _search_steps(b, s))


def _fit(q: np.ndarray, b: Bearings, rate: float, s: SearchSettings):
    """Gauss-Newton from place q on the candidates of the best sequence there under the model of
    `rate`; returns the place, each bearing's candidate (-1 outlier) and the information."""
    picked_a, picked_s, source = by_combination(b.angles, b.stds, b.jumps, decode(q, b, rate, s.cap_sigma))
    position, choice, info, _ = _refine(q, b.robot, picked_a, picked_s, s.cap_sigma)
    return position, np.where(choice >= 0, source[np.arange(len(choice)), np.maximum(choice, 0)], -1), info


def _held(choice: np.ndarray, jumps: np.ndarray, rate: float) -> int:
    """The one combination all inlier bearings use, if they do under a sequence model (-1: not)."""
    used = np.unique(jumps[np.flatnonzero(choice >= 0), choice[choice >= 0]])
    return int(used[0]) if rate != FREE and len(used) == 1 and used[0] >= 0 else -1


def _on_all(found: Found, b: Bearings, s: SearchSettings) -> Found:
    """A position found on part of the bearings, refined on all of them under the same model: its
    choices, information, inliers and parallax are all the bearings'; its margin stays the scoring
    bearings' (the rivals were scored on those)."""
    position, choice, info = _fit(found.position, b, found.redraw_rate, s)
    inlier = choice >= 0
    return replace(
        found,
        position=position,
        choice=choice,
        info=info,
        inliers=float(np.mean(inlier)),
        parallax_deg=parallax_deg(position, b.robot[inlier]),
        score=float(model_costs(position[None], b, s.cap_sigma).min()),
        combination=_held(choice, b.jumps, found.redraw_rate),
    )


def _search_steps(b: Bearings, s: SearchSettings) -> Generator[None, None, Found | None]:
    """The hypotheses, scored, the best refined under its best model, its margin over the best
    elsewhere and over the same direction half as far again out or a third in (the range must be
    settled too)."""
    q = _hypotheses(b.robot, b.angles, s)
    if len(q) == 0:
        return None
    yield
    score = yield from score_steps(q, b, s.cap_sigma)
    yield
    start = q[np.argmin(score)]
    rate = float(model_rates(combinations(b.jumps))[np.argmin(model_costs(start[None], b, s.cap_sigma)[:, 0])])
    position, choice, info = _fit(start, b, rate, s)
    best = float(model_costs(position[None], b, s.cap_sigma).min())
    elsewhere = score[np.linalg.norm(q - position, axis=1) > _reach(b.robot, position, s)]
    margin = float(elsewhere.min() - best) if len(elsewhere) else math.inf
    inlier = choice >= 0
    if inlier.any():
        centre = b.robot[inlier].mean(axis=0)
        moved = centre + np.outer(RANGE_CHECK, position - centre)
        margin = min(margin, float(model_costs(moved, b, s.cap_sigma).min() - best))
    parallax = parallax_deg(position, b.robot[inlier])
    held = _held(choice, b.jumps, rate)
    return Found(position, choice, info, margin, float(np.mean(inlier)), parallax, best, held, rate)


def _reach(robot_xy: np.ndarray, position: np.ndarray, s: SearchSettings) -> float:
    """How far from a position another hypothesis must be to be a different place."""
    return max(s.separation_m, 0.2 * float(np.median(np.linalg.norm(robot_xy - position, axis=1))))


def elsewhere(robot_xy: np.ndarray, position: np.ndarray, other: np.ndarray, s: SearchSettings) -> bool:
    """Whether `other` is a different place from `position`, seen from robot positions (n, 2)."""
    return float(np.linalg.norm(other - position)) > _reach(robot_xy, position, s)
