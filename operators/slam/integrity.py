"""Whether a localized tag's covariance covers its error: a block jackknife over the places its
bearings were taken from.

A tag's bearings do not err independently. Clutter near the robot or the tag bends them alike for
as long as the geometry holds (seconds at walking speed), and again each time the robot passes the
same place (rover.datasets.clutter; a real building's arrays: errors persisting for seconds). The
window weighs them as independent (their burst stds scaled by `aoa_std_scale`), so where the
clutter is heavy its covariance can be several times too small: `paper` seed 2 in a cluttered room
(scatterers then allowed on the robot's path) published a tag 40 cm off at 6 sigma of a 7 cm std.

So the bearings of a localized tag that left the window are grouped by the cell the robot
took them from, the tag is re-estimated leaving out each cell in turn (robust least squares on the
bearings, the robot positions as final), and the spread of those estimates is the jackknife
covariance J = (B - 1) / B sum_b (x_-b - mean)(x_-b - mean)^T: how much the estimate depends on
where it was seen from, whatever the errors' correlation within a cell. The published covariance
is the window's C scaled by the least k >= 1 with k C >= c J (the largest eigenvalue of C^-1 c J),
where c makes up for the jackknife's own uncertainty with B cells: J is then an estimate on B - 1
degrees of freedom, so an error measured in it follows Hotelling's T^2, not chi^2, and
c = 2 (B - 1) / (B - 2) F^-1(p; 2, B - 2) / chi2^-1(p; 2) at p = 98.9% (3 sigma in two dimensions)
keeps errors beyond 3 sigma of the published covariance at a 2-D Gaussian's 1.1% (1.4 at 20 cells,
2.7 at 8). How far the errors' correlation reaches depends on the room, so this is done with cells
of each size in CELLS_M and the largest k is kept: a bend shared over 2 m of path leaves 15% of
the estimates beyond 3 sigma of the 1 m jackknife's scaling, none of both's
(tests/test_integrity.py); a 30-scatterer room (`paper` seed 2, shadowing 8 dB) 45% of the LOS
estimates -> 23%, and `clutter` seed 2's NLOS tag 99% -> 53%. It cannot see a bias every view
shares (a scatterer beside the tag shifts it alike from everywhere).

A covariance too small by k means the window weighs the tag's bearings k times more than they are
worth, and not only for the tag: every robot pose they were taken from is pulled by errors it
takes as independent (a cluttered room's bearings made the robot 1.4-1.8 times worse than its
odometry alone). So the jackknife's own estimate (without c) also sets the tag's `weight`, what
the window multiplies its bearings' variance by, moved at each jackknife toward the value at which
the window's covariance covers it (at most WEIGHT_STEP at a time, between 1 and MAX_WEIGHT), and
the tag's part of the prior, which its earlier bearings built at the old weight, is scaled by the
same step, either way (only relaxed, a jackknife's passing overestimate would take information
from the tag for good: a tag published 109 s into a 127 s run no longer was). A tag whose place
does not explain its bearings keeps its weight: there the estimate is wrong, not its covariance,
and its bearings must stay strong enough to move it.

Nor can it see bearings that scatter more than their bursts say all over (an NLOS tag: the wall's
image blends into every burst): so the published covariance is also at least the window's times
the variance factor, the square of the robust spread of the residuals in the bursts' own stds,
when that is above 1 (`paper` seed 2: the NLOS tag 3% of its estimates beyond 3 sigma -> 0%).

Nor can it see a bias every view shares, and a tag on a wall has one: its image in the wall, a
few tens of centimetres behind it, blends into every burst. Two paths a small angle apart read as one
between them, by how much depending on their phase difference, which the robot sweeps when it moves
toward the wall and hardly at all when it drives along it (`paper` seed 6 in clutter: a tag 0.25 m
from a wall, passed along the wall at 0.7 m on both laps, read 2-5 deg toward the wall from either
side, both laps alike; published 20 cm off with a 6 cm std). So the published covariance adds
`WindowSettings.source_std_m` in every direction.

Nor can it see a tag's own bearings pulling the robot: it holds the robot positions fixed, and
bearings that pull the robot pull those positions with the tag, so every leave-one-out estimate
agrees. So a tag's weight is not lowered while its estimate is on its way (moved since the last
jackknife by more than one std of what the jackknives allow: `_reweigh`).

And a tag is published as localized only once it has a verdict (`TagIntegrity.verdict`): no
check search over all its candidates contradicts its place (`doubt`, tag_finder.contradiction),
MIN_VERDICT_BEARINGS of its bearings left the window and were judged, they span MIN_PARALLAX_DEG
seen from the estimate, the estimate explains them (at most half beyond 3 of their stds:
MAX_VARIANCE_FACTOR), and they were taken from MIN_CELLS places, so that the jackknife has checked
its covariance, and, where that first jackknife inflated it more than CONFIRM_INFLATION, a second
has confirmed it. Before that its covariance is the window's alone, and a window fed
bearings with persistent errors from a short stretch of path converges to a crossing near the
robot, where a small covariance is easy (a real building's bearings replayed: declared localized
7-16 s after first heard, 6-11 m off, stds of 0.05-0.2 m, the bearings' median residual 60 deg
there against 6 at the true place; our cluttered room with one bearing per burst: 2-3.4 m off at
5-13 s, up to 9 sigma).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2, f

from rover.geometry import parallax_deg, wrap_angle
from rover.operators.slam.factors import huber_weight

CELL_M = 1.0
"""side of the smallest square cells of robot positions that group a tag's bearings"""
CELLS_M = (CELL_M, 2.0)
"""the cell sizes of the jackknives whose largest scaling is kept"""
MIN_CELLS = 5
"""cells a tag's bearings must span before the jackknife speaks (fewer: the window's covariance)"""
CONFIRM_INFLATION = 2.0
"""a tag whose published covariance would rest on its first jackknife (inflating the window's more
than this) is not published until a second one, EVERY_BEARINGS on, has looked: a jackknife from a
few places is itself uncertain, more than Hotelling's factor allows where neighbouring places err
alike (`paper` seed 2's lap from bearings: a first jackknife at 5 cells inflated 4.1-fold and let a
tag out 0.88 m off at 3.5 sigma of a 0.35 m std; the next scaled it 27-fold). A tag whose window
covariance already covers its first jackknife (most, at `aoa_std_scale` 4) is published at once"""
EVERY_BEARINGS = 20
"""new bearings of a tag between two jackknife estimates"""
ITERATIONS = 4
"""Gauss-Newton steps of each leave-one-cell-out estimate, from the tag's estimate"""
THREE_SIGMA = 3.0
MAD_TO_STD = 1.4826
"""a Gaussian's std over its median absolute deviation"""
MIN_VERDICT_BEARINGS = 12
"""bearings of a tag that left the window before its first verdict (the search's `min_bearings`)"""
MAX_VARIANCE_FACTOR = (MAD_TO_STD * THREE_SIGMA) ** 2
"""a variance factor above this (about 20) means half the tag's bearings are beyond 3 of their
stds from its estimate: the place does not explain them, however small its covariance"""
MIN_PARALLAX_DEG = 10.0
"""spread of the directions of a tag's judged bearings seen from its estimate that a verdict needs
(the search's `min_parallax_deg`)"""
HISTORY_BEARINGS = 4000
"""bearings kept per tag (the latest)"""
MAX_WEIGHT = 100.0
"""the most a tag's bearings' variance in the window is multiplied by (`TagIntegrity.weight`): ten
times their std, bearings that err alike a hundred at a time"""
WEIGHT_STEP = 4.0
"""the most one jackknife multiplies or divides a tag's weight by: a jackknife of an estimate on
its way to the right place is itself far off, and a tag weighed down at once has nothing left to
get there with"""


def residuals_rad(position: np.ndarray, robot: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Each bearing's angle residual (rad) at `position`: the direction from its robot position
    less its world angle."""
    d = position[None, :] - robot
    return wrap_angle(np.arctan2(d[:, 1], d[:, 0]) - angles)


def jackknife_covariance(
    position: np.ndarray,
    robot: np.ndarray,
    angles: np.ndarray,
    stds: np.ndarray,
    huber_sigma: float,
    cell_m: float = CELL_M,
) -> np.ndarray | None:
    """The block jackknife covariance (2, 2) of a tag at `position` from its bearings grouped by
    square cells of side `cell_m` (`jackknife_spread`), scaled by small_sample_factor so that 3
    sigma of it covers; None while they span fewer than MIN_CELLS cells."""
    return covering(jackknife_spread(position, robot, angles, stds, huber_sigma, cell_m))


def covering(spread: tuple[np.ndarray, int] | None) -> np.ndarray | None:
    """A jackknife's spread and cell count (`jackknife_spread`) as the covariance 3 sigma of which
    covers: the spread times small_sample_factor."""
    return None if spread is None else spread[0] * small_sample_factor(spread[1])


def jackknife_spread(
    position: np.ndarray,
    robot: np.ndarray,
    angles: np.ndarray,
    stds: np.ndarray,
    huber_sigma: float,
    cell_m: float = CELL_M,
) -> tuple[np.ndarray, int] | None:
    """The block jackknife's estimate of the covariance (2, 2) of a tag at `position`, and the
    number of cells it left out in turn: robot positions (n, 2), world angles (n,) and stds (n,),
    grouped by square cells of side `cell_m`; None while they span fewer than MIN_CELLS cells.
    Each bearing keeps the Huber weight it has at `position`."""
    cells = np.floor(robot / cell_m).astype(np.int64)
    _, block = np.unique(cells, axis=0, return_inverse=True)
    block = block.ravel()
    count = int(block.max()) + 1 if len(block) else 0
    if count < MIN_CELLS:
        return None
    weight = huber_weight(residuals_rad(position, robot, angles) / stds, huber_sigma) / stds**2
    keep = weight[None, :] * (block[None, :] != np.arange(count)[:, None])  # (B, n)
    q = np.repeat(position[None, :], count, axis=0)
    for _ in range(ITERATIONS):
        # each bearing's row is (-dy, dx) / range^2: the 2x2 information and gradient per block,
        # summed component by component (B x n arrays, no (B, n, 2) stacks)
        dx, dy = q[:, 0, None] - robot[None, :, 0], q[:, 1, None] - robot[None, :, 1]
        range2 = np.maximum(dx * dx + dy * dy, 1e-6)
        res = wrap_angle(np.arctan2(dy, dx) - angles[None])
        per_info, per_grad = keep / (range2 * range2), keep * res / range2
        ixx, ixy, iyy = np.sum(per_info * dy * dy, 1), -np.sum(per_info * dx * dy, 1), np.sum(per_info * dx * dx, 1)
        gx, gy = -np.sum(per_grad * dy, 1), np.sum(per_grad * dx, 1)
        det = ixx * iyy - ixy * ixy
        if not np.all(det != 0.0):
            return np.full((2, 2), np.inf), count  # leaving a cell out leaves the tag unconstrained
        q = q - np.stack([iyy * gx - ixy * gy, ixx * gy - ixy * gx], axis=1) / det[:, None]
    dev = q - q.mean(axis=0)
    return (count - 1) / count * dev.T @ dev, count


def variance_factor(
    position: np.ndarray, robot: np.ndarray, angles: np.ndarray, stds: np.ndarray, aoa_std_scale: float
) -> float:
    """How much larger the bearings' scatter about `position` is than their bursts say: the square of
    the robust spread (1.4826 times the median absolute residual) of the residuals in the bursts'
    own stds (the window's `stds` over `aoa_std_scale`); about 1 when the stds are right, 0 without
    bearings."""
    if len(robot) == 0:
        return 0.0
    r = residuals_rad(position, robot, angles) / (stds / aoa_std_scale)
    return float((MAD_TO_STD * np.median(np.abs(r))) ** 2)


def small_sample_factor(cells: int) -> float:
    """c: how much a jackknife covariance from `cells` cells is scaled so that 3 sigma of it holds
    a 2-D Gaussian's share (Hotelling's T^2 on cells - 1 degrees of freedom)."""
    p = chi2.cdf(THREE_SIGMA**2, 2)
    return float(2 * (cells - 1) / (cells - 2) * f.ppf(p, 2, cells - 2) / chi2.ppf(p, 2))


def disagreeing(
    counts: dict[int, int], tags: np.ndarray, active: np.ndarray, localized: np.ndarray, updates: int
) -> list[int]:
    """The localized tags to re-examine: `counts` per tag slot the consecutive updates in which
    most of its window bearings (their slots `tags`) were Huber-active (`active`), at least 3 of
    them; those reaching `updates` (0: never) start again from nought."""
    again = []
    for t in range(len(localized)):
        mine = tags == t
        if localized[t] and mine.sum() >= 3 and active[mine].mean() > 0.5:
            counts[t] = counts.get(t, 0) + 1
        elif mine.any():
            counts[t] = 0
        if updates and counts.get(t, 0) >= updates:
            counts[t] = 0
            again.append(t)
    return again


def _moved_beyond(moved: np.ndarray, covering: np.ndarray | None) -> bool:
    """Whether a step `moved` (2,) is beyond one std of a covering jackknife covariance (a singular
    one: across its flat direction, any step is)."""
    if covering is None or not np.all(np.isfinite(covering)) or not np.any(moved):
        return False
    inverse = np.linalg.pinv(covering)
    return float(moved @ inverse @ moved) > 1.0 or not np.allclose(covering @ inverse @ moved, moved)


def cover_ratio(covariance: np.ndarray, jackknife: np.ndarray | None) -> float:
    """The least k with k covariance >= jackknife, below 1 when the covariance already covers it
    (1 without a jackknife or with a singular covariance, infinite when the jackknife is): the
    largest root of det(jackknife - k covariance) = 0, in closed form for 2x2 (LAPACK's call costs
    ten times more, on every tag at every update)."""
    if jackknife is None:
        return 1.0
    if not np.all(np.isfinite(jackknife)):
        return float("inf")
    (c11, c12), (c21, c22) = covariance.tolist()
    (j11, j12), (j21, j22) = jackknife.tolist()
    a = c11 * c22 - c12 * c21
    if not a > 0.0:
        return 1.0
    b = c11 * j22 + c22 * j11 - c12 * j21 - c21 * j12
    disc = b * b - 4.0 * a * (j11 * j22 - j12 * j21)
    return (b + math.sqrt(max(disc, 0.0))) / (2.0 * a)


def inflation(covariance: np.ndarray, jackknife: np.ndarray | None) -> float:
    """The least k >= 1 with k covariance >= jackknife (infinite when the jackknife is)."""
    return max(1.0, cover_ratio(covariance, jackknife))


@dataclass
class TagIntegrity:
    """Per tag slot: the bearings that left the window (robot position, world angle, the window's
    std) since it was localized, its latest jackknife covariances, variance factor and parallax, and
    the scale they set."""

    seen: dict[int, list[tuple[float, float, float, float]]] = field(default_factory=dict)
    jackknife: dict[int, list[np.ndarray | None]] = field(default_factory=dict)
    """per slot: its latest jackknife covariance at each size of CELLS_M"""
    checks: dict[int, int] = field(default_factory=dict)
    """per slot: the jackknives it has had from MIN_CELLS places or more"""
    inflated: dict[int, float] = field(default_factory=dict)
    """per slot: how much its latest jackknives inflate the window's covariance (`inflation`)"""
    due: dict[int, int] = field(default_factory=dict)
    """per slot: bearings to come before its next jackknife"""
    factor: dict[int, float] = field(default_factory=dict)
    """per slot: its bearings' latest variance factor"""
    judged_xy: dict[int, np.ndarray] = field(default_factory=dict)
    """per slot: the robot positions (n, 2) of the bearings its latest verdict judged"""
    parallax: dict[int, float] = field(default_factory=dict)
    """per slot: the spread (deg) of its judged bearings' directions seen from its estimate"""
    scale: dict[int, float] = field(default_factory=dict)
    """per slot: the factor its window covariance is published with (`judge`)"""
    judged_at: dict[int, np.ndarray] = field(default_factory=dict)
    """per slot: its estimate at its latest jackknife"""
    weight: dict[int, float] = field(default_factory=dict)
    """per slot: how much the window multiplies its bearings' variance, so that its covariance is
    the jackknives' (`judge`): bearings that err alike carry that much less information, and the
    robot's poses as well as the tag's place must weigh them so"""
    doubts: dict[int, str] = field(default_factory=dict)
    """per slot: why the latest check search over its bearings contradicts its place (`doubt`)"""

    def doubt(self, tag_slot: int, reason: str | None) -> None:
        """What the latest check search over the tag's bearings says of its place (tag_finder's
        `contradiction`; None: nothing against it). A contradicted tag is not published localized."""
        if reason is None:
            self.doubts.pop(tag_slot, None)
        else:
            self.doubts[tag_slot] = reason

    def start(self, tag_slot: int, robot: np.ndarray, angles: np.ndarray, stds: np.ndarray) -> None:
        """A tag found by the search: its bearings that already left the window, as the search chose
        their candidates; the jackknife is due at once, with nothing earlier to say how far it moved."""
        rows = np.column_stack([robot, angles, stds]) if len(robot) else np.zeros((0, 4))
        self.seen[tag_slot] = [tuple(r) for r in rows[-HISTORY_BEARINGS:].tolist()]
        self.due[tag_slot] = 0
        self.judged_at.pop(tag_slot, None)

    def add(self, tag_slot: int, robot_xy: np.ndarray, angle: float, std: float) -> None:
        """A bearing of a localized tag left the window with this robot position and candidate."""
        kept = self.seen.setdefault(tag_slot, [])
        kept.append((float(robot_xy[0]), float(robot_xy[1]), float(angle), float(std)))
        del kept[:-HISTORY_BEARINGS]
        self.due[tag_slot] = self.due.get(tag_slot, MIN_VERDICT_BEARINGS) - 1

    def judge(
        self,
        tag_slot: int,
        position: np.ndarray,
        covariance: np.ndarray,
        window_xy: np.ndarray,
        huber_sigma: float,
        aoa_std_scale: float,
    ) -> float:
        """Set `scale[tag_slot]`, how much the tag's window covariance is scaled up to be published:
        enough to cover the jackknives, and the variance factor of its bearings when above 1 (both
        re-estimated every EVERY_BEARINGS bearings, with the window's Huber threshold and scale,
        once MIN_VERDICT_BEARINGS left the window); and the parallax of its bearings, those that
        left and those still in the window (taken from `window_xy`, (m, 2)). Returns what its
        `weight` was multiplied by (1: unchanged)."""
        weight = self.weight.get(tag_slot, 1.0)
        if self.due.get(tag_slot, 1) <= 0:
            rows = np.array(self.seen.get(tag_slot, [])).reshape(-1, 4)
            if len(rows) < MIN_VERDICT_BEARINGS:
                self.due[tag_slot] = MIN_VERDICT_BEARINGS - len(rows)
            else:
                robot, angles, stds = rows[:, :2], rows[:, 2], rows[:, 3]
                spreads = [jackknife_spread(position, robot, angles, stds, huber_sigma, cell_m) for cell_m in CELLS_M]
                self.jackknife[tag_slot] = [covering(j) for j in spreads]
                self.checks[tag_slot] = self.checks.get(tag_slot, 0) + (spreads[0] is not None)
                self.factor[tag_slot] = variance_factor(position, robot, angles, stds, aoa_std_scale)
                moved = position - self.judged_at.get(tag_slot, position)
                self._reweigh(tag_slot, covariance, [None if j is None else j[0] for j in spreads], moved)
                self.judged_at[tag_slot] = position.copy()
                self.judged_xy[tag_slot] = robot
                self.due[tag_slot] = EVERY_BEARINGS
        if tag_slot in self.judged_xy:
            self.parallax[tag_slot] = parallax_deg(position, np.concatenate([self.judged_xy[tag_slot], window_xy]))
        k = max((inflation(covariance, j) for j in self.jackknife.get(tag_slot, [])), default=1.0)
        self.inflated[tag_slot] = k
        self.scale[tag_slot] = max(k, self.factor.get(tag_slot, 0.0))
        return self.weight.get(tag_slot, 1.0) / weight

    def _reweigh(
        self, tag_slot: int, covariance: np.ndarray, spreads: list[np.ndarray | None], moved: np.ndarray
    ) -> None:
        """Move the tag's `weight` toward what makes the window's covariance cover the jackknives'
        estimates (`spreads`, not scaled to cover; a size too few cells span counts as covered),
        by at most WEIGHT_STEP; not while its place does not explain its bearings (then the
        estimate is wrong, not its covariance) or a jackknife is unbounded. Nor is it lowered while
        the estimate is on its way: `moved` since the last jackknife by more than one std of what
        the jackknives say it is uncertain by (the robot positions they hold fixed move with it)."""
        if self.factor[tag_slot] > MAX_VARIANCE_FACTOR:
            return
        ratio = max((cover_ratio(covariance, j) for j in spreads), default=1.0)
        if not math.isfinite(ratio):
            return
        if ratio < 1.0 and any(_moved_beyond(moved, c) for c in self.jackknife[tag_slot]):
            return
        step = min(max(ratio, 1 / WEIGHT_STEP), WEIGHT_STEP)
        self.weight[tag_slot] = min(max(self.weight.get(tag_slot, 1.0) * step, 1.0), MAX_WEIGHT)

    def contradicted(self, tag_slot: int) -> str | None:
        """How its judged bearings scatter about its estimate beyond what their stds allow (None:
        they do not, or were not judged yet)."""
        factor = self.factor.get(tag_slot, 0.0)
        if factor <= MAX_VARIANCE_FACTOR:
            return None
        spread = math.sqrt(factor)
        return f"its bearings scatter about it {spread:.1f} times their stds: its place does not explain them"

    def verdict(self, tag_slot: int) -> str | None:
        """Why the tag may not be published as localized whatever its covariance (None: it may)."""
        if (doubt := self.doubts.get(tag_slot)) is not None:
            return doubt
        if tag_slot not in self.parallax:
            left = len(self.seen.get(tag_slot, []))
            return f"{left} of its bearings left the window, {MIN_VERDICT_BEARINGS} needed to judge it"
        if self.parallax[tag_slot] < MIN_PARALLAX_DEG:
            return f"its bearings span {self.parallax[tag_slot]:.0f} deg seen from it ({MIN_PARALLAX_DEG:.0f} needed)"
        if (scatter := self.contradicted(tag_slot)) is not None:
            return scatter
        if self.jackknife[tag_slot][0] is None:
            return f"its judged bearings were taken from fewer than {MIN_CELLS} places ({CELL_M:g} m cells)"
        first_look = self.checks.get(tag_slot, 0) < 2
        if first_look and (k := self.inflated.get(tag_slot, 1.0)) > CONFIRM_INFLATION:
            return f"its first jackknife inflated its covariance {k:.1f}-fold: a second must confirm it"
        return None

    def std_factor(self, tag_slots: np.ndarray) -> np.ndarray:
        """What the window multiplies the std of bearings of these tag slots by: the square root of
        their `weight`."""
        slots = np.asarray(tag_slots, dtype=int)
        per_slot = np.ones(int(slots.max(initial=-1)) + 1)
        for t, w in self.weight.items():
            if t < len(per_slot):
                per_slot[t] = w
        return np.sqrt(per_slot[slots])

    def scaled(self, covariances: np.ndarray, source_std_m: float) -> np.ndarray:
        """The tags' covariances (tags, 2, 2) as published: each scaled by its `scale`, plus
        `source_std_m` squared in every direction (where its signal appears to come from, which no
        number of bearings tells from where it is: `WindowSettings.source_std_m`)."""
        out = covariances.copy()
        for t, k in self.scale.items():
            if t < len(out):
                out[t] = out[t] * k if np.isfinite(k) else np.inf
        return out + source_std_m**2 * np.eye(2)
