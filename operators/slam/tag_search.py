"""Where a tag not yet localized is, from its bearings' candidates over the robot's path.

The Intel 5300's chain phase jumps give each burst several candidate angles (one per jump
combination, rover.operators.aoa.jumps) that a single burst cannot tell apart: the wrong ones are
clean plane waves too. Geometry can: only the true candidates of a tag's bearings, seen from the
robot's successive positions, cross at one point. So the search triangulates pairs of bearings
(every pair of candidates, from well-separated positions) into hypotheses, scores each against all
the tag's bearings with each bearing's best candidate (a max-mixture, capped: a bearing no
candidate of which fits costs the same anywhere), refines the best by Gauss-Newton on its inliers,
and accepts it only when no hypothesis elsewhere comes close: a tag stays unlocalized rather than
be guessed. This works whether the jumps happen once per run or at every retune, since each
bearing picks its own candidate.
"""

from __future__ import annotations

import math
from collections.abc import Generator
from dataclasses import dataclass, replace
from typing import TypeVar

import numpy as np

from rover.geometry import wrap_angle


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
    min_inliers: float = 0.9
    """share of the bearings the position must explain"""
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
    """the jump combination all its bearings share (-1: each bearing its own)"""

    def clear(self, s: SearchSettings) -> bool:
        """Whether the evidence settles the position: no rival elsewhere, most bearings agreeing, parallax."""
        return self.margin >= s.min_margin and self.inliers >= s.min_inliers and self.parallax_deg >= s.min_parallax_deg


RAY_POINTS = 8
"""hypotheses along each candidate ray of the pair bearings, from min_range_m to max_range_m"""
FREE_MARGIN_FACTOR = 2.0
"""a position where each bearing picks its own candidate needs this many times the margin: with a
free choice per bearing, a wrong place finds more ways to fit"""
SCORE_CHUNK = 65_536
"""residuals (hypotheses x bearings x candidates) scored at once: half a megabyte, in cache"""
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


def _scores(q: np.ndarray, robot: np.ndarray, angles: np.ndarray, stds: np.ndarray, cap: float) -> np.ndarray:
    """Per hypothesis q (H, 2): the sum over bearings of the best candidate's capped squared
    residual (all at once; `_score_steps` a chunk per step)."""
    return finish(_score_steps(q, robot, angles, stds, cap))


def _score_steps(
    q: np.ndarray, robot: np.ndarray, angles: np.ndarray, stds: np.ndarray, cap: float
) -> Generator[None, None, np.ndarray]:
    """_scores, the hot loop of the search (hypotheses x bearings x candidates), one cache-sized
    chunk of hypotheses per step.

    Each hypothesis's direction from each robot position is one atan2; with the candidates wrapped
    once, a residual's size is the smaller of |difference| and a turn less it (no trigonometry
    per candidate); a padding candidate (NaN) is never the best. Candidates lead the layout: the
    reductions then run over contiguous rows."""
    out = np.empty(len(q))
    if len(q) == 0:
        return out
    turn = 2 * math.pi
    candidate = wrap_angle(angles).T[:, None, :]  # (K, 1, n)
    inverse = (1.0 / stds).T[:, None, :]
    per = max(1, SCORE_CHUNK // max(angles.size, 1))
    for i in range(0, len(q), per):
        if i:
            yield
        h = q[i : i + per]
        predicted = np.arctan2(h[:, 1, None] - robot[None, :, 1], h[:, 0, None] - robot[None, :, 0])
        r = np.abs(predicted[None] - candidate)  # (K, h, n), within two turns
        np.minimum(r, turn - r, out=r)
        r *= inverse
        r *= r
        out[i : i + per] = np.fmin(np.fmin.reduce(r, axis=0), cap**2).sum(axis=1)
    return out


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


def by_combination(angles: np.ndarray, stds: np.ndarray, jumps: np.ndarray, combination: int):
    """Each bearing's candidate for one jump combination as a one-candidate set (n, 1); a bearing
    whose candidate for it was merged into another's keeps all its candidates (it fits either way)."""
    has = jumps == combination
    own = has.any(axis=1)
    index = np.argmax(has, axis=1)
    rows = np.arange(len(angles))
    pick_a = np.where(own[:, None], np.nan, angles)
    pick_s = np.where(own[:, None], 1.0, stds)
    pick_a[own, 0], pick_s[own, 0] = angles[rows[own], index[own]], stds[rows[own], index[own]]
    source = np.where(own[:, None], index[:, None], np.arange(angles.shape[1])[None, :])
    return pick_a, pick_s, source


def search(
    robot_xy: np.ndarray, angles: np.ndarray, stds: np.ndarray, s: SearchSettings, jumps: np.ndarray | None = None
) -> Found | None:
    """The likeliest position of the tag from its bearings: robot positions (n, 2), world-frame
    candidate angles and their stds (n, K), NaN where a bearing has fewer candidates; None without
    enough bearings or rays that cross. `Found.clear` says whether the evidence settles it.

    With the candidates' jump combinations (n, K), a combination held by the tag's channel all run
    long is tried first, one hypothesis family per combination (far fewer ways for a wrong place
    to fit); failing that, each bearing picks its own candidate (a jump at any retune)."""
    return finish(search_steps(robot_xy, angles, stds, s, jumps))


def search_steps(
    robot_xy: np.ndarray, angles: np.ndarray, stds: np.ndarray, s: SearchSettings, jumps: np.ndarray | None = None
) -> Generator[None, None, Found | None]:
    """`search` a step at a time: each step scores one chunk of hypotheses (SCORE_CHUNK residuals)
    or refines one, so that a caller can spread a search over its idle time (the same result as
    `search`, whatever the steps taken at once)."""
    n = len(robot_xy)
    if n < s.min_bearings:
        return None
    if jumps is None:
        jumps = np.full(angles.shape, -1)
    if n > s.score_bearings:
        keep = spread_along(robot_xy, s.score_bearings)
        if len(keep) < n:
            found = yield from search_steps(robot_xy[keep], angles[keep], stds[keep], s, jumps[keep])
            if found is None:
                return None
            yield
            return _on_all(found, robot_xy, angles, stds, jumps, s)
    held: list[Found] = []
    for combination in np.unique(jumps[jumps >= 0]):
        picked_a, picked_s, source = by_combination(angles, stds, jumps, int(combination))
        one = yield from _search_steps(robot_xy, picked_a, picked_s, s)
        if one is not None:
            choice = np.where(one.choice >= 0, source[np.arange(n), np.maximum(one.choice, 0)], -1)
            held.append(replace(one, choice=choice, combination=int(combination)))
    if held:
        best = min(held, key=lambda f: f.score)
        reach = _reach(robot_xy, best.position, s)
        rivals = [f.score - best.score for f in held if np.linalg.norm(f.position - best.position) > reach]
        best = replace(best, margin=min([best.margin, *rivals]))
        if best.clear(s):
            return best
    free = yield from _search_steps(robot_xy, angles, stds, s)
    if free is not None:
        reach = _reach(robot_xy, free.position, s)
        elsewhere = np.array([f.position for f in held if np.linalg.norm(f.position - free.position) > reach])
        cost = _scores(elsewhere.reshape(-1, 2), robot_xy, angles, stds, s.cap_sigma)
        margin = min([free.margin, *(cost - free.score)])  # a place another search found
        free = replace(free, margin=margin / FREE_MARGIN_FACTOR)
    return free if not held or (free is not None and free.clear(s)) else best


def _on_all(
    found: Found, robot_xy: np.ndarray, angles: np.ndarray, stds: np.ndarray, jumps: np.ndarray, s: SearchSettings
) -> Found:
    """A position found on part of the bearings, refined on all of them (with the same jump
    combination, if it has one): its choices, information, inliers and parallax are all the
    bearings'; its margin stays the scoring bearings' (the rivals were scored on those)."""
    if found.combination >= 0:
        angles, stds, source = by_combination(angles, stds, jumps, found.combination)
    position, choice, info, score = _refine(found.position, robot_xy, angles, stds, s.cap_sigma)
    if found.combination >= 0:
        choice = np.where(choice >= 0, source[np.arange(len(choice)), np.maximum(choice, 0)], -1)
    inlier = choice >= 0
    return replace(
        found,
        position=position,
        choice=choice,
        info=info,
        inliers=float(np.mean(inlier)),
        parallax_deg=_parallax_deg(position, robot_xy[inlier]),
        score=score,
    )


def _parallax_deg(position: np.ndarray, seen_from: np.ndarray) -> float:
    """Spread of the directions from which a position was seen (deg)."""
    seen = position[None, :] - seen_from
    return math.degrees(_spread(np.arctan2(seen[:, 1], seen[:, 0]))) if len(seen) else 0.0


def _search_steps(
    robot_xy: np.ndarray, angles: np.ndarray, stds: np.ndarray, s: SearchSettings
) -> Generator[None, None, Found | None]:
    """One family of hypotheses (the candidates given), scored, its best refined, its margin."""
    q = _hypotheses(robot_xy, angles, s)
    if len(q) == 0:
        return None
    yield
    score = yield from _score_steps(q, robot_xy, angles, stds, s.cap_sigma)
    yield
    position, choice, info, best = _refine(q[np.argmin(score)], robot_xy, angles, stds, s.cap_sigma)
    elsewhere = score[np.linalg.norm(q - position, axis=1) > _reach(robot_xy, position, s)]
    margin = float(elsewhere.min() - best) if len(elsewhere) else math.inf
    if (choice >= 0).any():  # the range must be settled too: half as far again out, or a third in
        centre = robot_xy[choice >= 0].mean(axis=0)
        moved = centre + np.outer(RANGE_CHECK, position - centre)
        margin = min(margin, float(_scores(moved, robot_xy, angles, stds, s.cap_sigma).min() - best))
    inliers = float(np.mean(choice >= 0))
    return Found(position, choice, info, margin, inliers, _parallax_deg(position, robot_xy[choice >= 0]), best)


def _reach(robot_xy: np.ndarray, position: np.ndarray, s: SearchSettings) -> float:
    """How far from a position another hypothesis must be to be a different place."""
    return max(s.separation_m, 0.2 * float(np.median(np.linalg.norm(robot_xy - position, axis=1))))


def _spread(angles: np.ndarray) -> float:
    """Smallest arc (rad) that holds all the angles."""
    a = np.sort(np.mod(angles, 2 * math.pi))
    gaps = np.diff(np.concatenate([a, [a[0] + 2 * math.pi]]))
    return float(2 * math.pi - gaps.max())
