"""The sliding-window AoA-IMU estimator behind the `slam` operator (the paper's Section III).

The state is the robot's position and velocity (x, y, world frame) at each epoch in the window,
and the position of every tag heard so far. Rotations come from the gyro (the preintegration's
attitudes), which makes every constraint linear in the state:

- odometry: v_k+1 = v_k + dv,  p_k+1 = p_k + v_k dt + dp, weighted by the preintegration's covariance;
- AoA: the cross product u x (b - mu) = 0 of the world bearing u and the robot-to-tag vector,
  divided by d * sigma (d the current robot-tag distance, re-estimated in a few passes), under a
  Huber loss, with a cheirality hinge u . (b - mu) >= 0 carrying the row's robust weight;
- a prior on the oldest epoch and the tags: the states that left the window, marginalized by
  Schur complement (the gauge, the first pose at the origin, starts it).

The cross product is the pseudolinear bearing estimator, biased toward short ranges as the AoA
noise grows (Dogancay 2004), and reweighting by the current distance feeds that bias. Each update
therefore ends with Gauss-Newton steps on the true angle residual (atan2) from the convex solution,
or, once every tag in use is localized, from the last estimate alone (the convex passes are there
to start tags that are not: one solve an update instead of two, and the same estimates).
The distances in the weights have a floor (no tag is closer than `min_range_m` to the antennas).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Generator
from dataclasses import dataclass, field, replace
from typing import Annotated, Any

import numpy as np

from rover.operators.slam.tag_search import Found, SearchSettings, search_steps
from rover.operators.slam.window_program import (
    Program,
    Shape,
    SolverFailed,
    UpdateData,
    WindowProgram,
    edge_matrix,
    prior_indices,
    velocity_columns,
)
from rover.pipeline.params import Checked, Fraction, NonNegativeFloat, NonNegativeInt, PositiveFloat, PositiveInt, Range


@dataclass(frozen=True)
class WindowSettings(Checked):
    window: Annotated[int, Range(ge=2)] = 30
    """epochs kept in the window; older ones are marginalized into the prior"""
    huber_sigma: PositiveFloat = 1.5
    """AoA residuals beyond this many standard deviations count linearly (Huber)"""
    hinge_weight: NonNegativeFloat = 10.0
    """cost per (distance / (d * sigma)) of a tag placed behind its bearing"""
    reweight_passes: PositiveInt = 1
    """at most this many convex solves per update, each with the distances of the previous one;
    none while every tag in use is localized (the Gauss-Newton steps start from the last estimate).
    Each update starts from the last one's estimate, so reweighting goes on over the next epochs; on
    `paper` seeds 1-6, `long_hall` and the sample recording the estimates are the same as with 3 (to
    0.1 mm), the work per update bounded. Batch mode, which solves once, takes at least 3"""
    reweight_tolerance: PositiveFloat = 0.1
    """the passes stop once no distance to a tag not yet localized (inlier rows) changed by more than
    this fraction; for localized tags the distances of the last refined estimate are already right,
    and reweighting toward the convex solution would feed its short-range bias"""
    refine_iterations: NonNegativeInt = 2
    """at most this many Gauss-Newton steps on the angle residual after the convex passes (batch
    mode: at least 3)"""
    refine_tolerance_m: PositiveFloat = 2e-3
    """the steps stop once no state moved by more than this"""
    initial_range_m: PositiveFloat = 3.0
    """the distance guessed for a tag heard for the first time"""
    min_range_m: PositiveFloat = 0.3
    """floor of the distances in the AoA weights: no tag sits inside the robot"""
    tag_prior_std_m: PositiveFloat = 30.0
    """the prior on a newly heard tag, around its first bearing at `initial_range_m`"""
    gauge_std_m: PositiveFloat = 1e-3
    """the first pose is the origin of the world frame"""
    initial_velocity_std_m_s: PositiveFloat = 0.01
    """the robot starts from rest (the preintegration needs a still start for its gyro bias)"""
    wheel_speed_std_m_s: PositiveFloat = 0.01
    """wheel odometry speed noise"""
    wheel_scale_std: NonNegativeFloat = 0.03
    """wheel radius error, as a fraction of the speed: the prior std of the wheel scale state (with
    `wheel_scale`), else noise added to every speed"""
    wheel_scale: bool = True
    """estimate the wheel odometry's scale error as a state shared by the window and carried through
    the marginalization: a radius error is one number for the run, not noise per epoch, and over a
    long straight leg it is most of the robot's error (bearings say nothing of scale); the IMU makes
    it observable wherever the speed changes (starts, stops, turns in place)"""
    wheel_scale_walk_rts: NonNegativeFloat = 1e-4
    """how fast the wheel scale may wander (random walk, fraction per square-root second: tyre
    pressure, load)"""
    nonholonomic: bool = True
    """a wheeled base does not move sideways: its velocity is along its heading (linear given the gyro's)"""
    lateral_std_m_s: PositiveFloat = 0.02
    """how fast the robot may slip sideways"""
    reset_updates: NonNegativeInt = 20
    """a localized tag whose bearings in the window mostly disagree with its estimate (Huber-active)
    for this many updates in a row has its prior relaxed: the Gaussian prior of a tag first seen
    through wrong-path bearings can otherwise hold it at the wrong place for good. 0 turns it off."""
    reset_factor: Fraction = 0.01
    """how much of the tag's prior information is kept at such a reset"""
    observable_std_m: PositiveFloat = 0.5
    """a tag is reported localized once its position's largest standard deviation is below this"""
    aoa_std_scale: PositiveFloat = 4.0
    """multiplies each AoA's std in the window (not in the search for a tag, which compares bearings
    spread over the whole run): the operator's std describes one burst, but consecutive bursts of a
    tag share most of their multipath error, so each carries less information than its own std says
    (swept 1.5/2/3/4 over the eight robustness runs: 4 is best on average, 1.5 clearly worst)"""
    accel_bias: bool = True
    """estimate what the IMU integration left of the accelerometer bias, as window states carried
    through the marginalization: a bias fixed to the body (2D, turns with the robot) and one fixed to
    the world (2D: gravity leaking through a tilt, or a body bias aligned away at the start heading)"""
    accel_bias_std_m_s2: PositiveFloat = 0.03
    """prior std of each of those biases (about 3 mg: MEMS IMUs of the paper's class are within it)"""
    accel_bias_walk_m_s2_rts: NonNegativeFloat = 1e-4
    """how fast they may wander (random walk, per square-root second)"""
    turns_in_place: bool = True
    """an epoch the preintegration flags as turning in place has zero velocity (off for a platform
    that may rotate while it drifts, such as a drone)"""
    zero_velocity_std_m_s: PositiveFloat = 0.02
    """the velocity of such an epoch"""


@dataclass
class Epoch:
    stamp_ns: int
    yaw: float
    """heading from the gyro (world frame)"""
    tags: np.ndarray
    """tag slot of each bearing"""
    candidates: np.ndarray
    """world-frame angles (k, K) of each bearing's candidates (one per chain phase-jump combination), NaN-padded"""
    candidate_std: np.ndarray
    """their standard deviations (rad)"""
    candidate_jumps: np.ndarray
    """the jump combination each candidate assumes (-1: padding or unknown)"""
    choice: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    """the candidate each bearing uses now (max-mixture: the likeliest at the current estimate)"""
    messages: list[Any] = field(default_factory=list)
    """what the bearings came from, handed back with the final choice (opaque here)"""
    free_choice: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    """the candidate each bearing would take without its tag's locked combination (what the lock learns from)"""
    doubt: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """per bearing: the variance (rad^2) the other candidates' chances add to the chosen one's angle"""
    velocity_info: np.ndarray = field(default_factory=lambda: np.zeros((2, 2)))
    """wheel odometry and the velocity constraints on this epoch: 0.5 y'Wy - w'y over y = its velocity
    (and the wheel scale, when the window estimates it: window_program.velocity_columns); with the
    scale a state, its wheel reading as last linearized (SlidingWindow._linearize_wheels)"""
    velocity_linear: np.ndarray = field(default_factory=lambda: np.zeros(2))
    constraint_info: np.ndarray = field(default_factory=lambda: np.zeros((2, 2)))
    """the part of velocity_info that needs no linearization: no sideways motion, zero velocity when
    turning in place, and the wheel reading when the scale is not a state"""
    constraint_linear: np.ndarray = field(default_factory=lambda: np.zeros(2))
    speed_m_s: float = math.nan
    """the wheel odometry's forward speed read at this epoch (NaN: none)"""

    def __post_init__(self) -> None:
        if len(self.choice) != len(self.tags):
            self.choice = np.zeros(len(self.tags), int)
        if len(self.free_choice) != len(self.tags):
            self.free_choice = np.zeros(len(self.tags), int)
        if len(self.doubt) != len(self.tags):
            self.doubt = np.zeros(len(self.tags))

    @property
    def bearing(self) -> np.ndarray:
        """World-frame unit vectors (k, 2) of the chosen candidates."""
        angle = self.candidates[np.arange(len(self.tags)), self.choice]
        return np.stack([np.cos(angle), np.sin(angle)], axis=1).reshape(-1, 2)

    @property
    def std(self) -> np.ndarray:
        return self.candidate_std[np.arange(len(self.tags)), self.choice]


@dataclass
class Edge:
    """Odometry from one epoch to the next: [dv, dp] in x/y and their covariance."""

    dt: float
    delta: np.ndarray
    covariance: np.ndarray
    bias_jacobian: np.ndarray = field(default_factory=lambda: np.zeros((4, 0)))
    """(4, biases) how [dv, dp] move with the window's bias states (measured = true + J b)"""
    chol: np.ndarray = field(init=False, repr=False)
    """the covariance's Cholesky factor (the program's odometry rows are whitened by it)"""
    block: np.ndarray = field(init=False, repr=False)
    """M'WM over [p_k, v_k, p_k+1, v_k+1, biases], M = [L J]: the edge's information, for covariances"""

    def __post_init__(self) -> None:
        self.chol = np.linalg.cholesky(self.covariance)
        lmat = np.concatenate([edge_matrix(np.array([self.dt]))[0], self.bias_jacobian], axis=1)
        self.block = lmat.T @ np.linalg.solve(self.covariance, lmat)


@dataclass
class Update:
    """What one update produced."""

    iterations: int = 0
    huber_active: int = 0
    failed: str = ""


@dataclass(frozen=True)
class _Model:
    """One update's odometry, wheel and prior numbers, stacked."""

    edge_l: np.ndarray
    edge_chol: np.ndarray
    edge_whiten: np.ndarray
    edge_delta: np.ndarray
    edge_bias: np.ndarray
    pairs: np.ndarray
    velocity_info: np.ndarray
    velocity_linear: np.ndarray
    prior_index: np.ndarray


@dataclass(frozen=True)
class _Bearings:
    """The window's bearings stacked, one row each in epoch order: built once per window content
    (the epochs in it and the slots per epoch), not at every pass of every update."""

    key: tuple[int, int, int, int, int]
    epoch: np.ndarray
    tag: np.ndarray
    angles: np.ndarray
    """(rows, K) candidates, NaN-padded"""
    stds: np.ndarray
    jumps: np.ndarray
    slot: np.ndarray
    """each bearing's row in the program's slot layout (epoch * slots + its place in the epoch)"""
    starts: np.ndarray
    """the first row of each epoch, and the end"""


@dataclass
class _Search:
    """A tag search under way: the tag slot, what it searches (bearing stamps, robot positions,
    candidate stds and jumps, for putting the tag in use), and its remaining steps."""

    tag: int
    stamps: np.ndarray
    robot: np.ndarray
    stds: np.ndarray
    jumps: np.ndarray
    steps: Generator[None, None, Found | None]


@dataclass
class Prior:
    """0.5 (x - mean)' H (x - mean) + grad' (x - mean) over the oldest epoch and the tags."""

    info: np.ndarray
    mean: np.ndarray
    grad: np.ndarray


def rotation(yaw: float) -> np.ndarray:
    """The 2x2 rotation from the body's x/y to the world's at heading `yaw`."""
    return np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])


def bias_jacobian(yaw_start: float, yaw_end: float, dt: float) -> np.ndarray:
    """How an edge's [dv, dp] (x/y) move with [body-frame bias, world-frame bias] (4x4) for a robot
    turning steadily from `yaw_start` to `yaw_end` in `dt` (Simpson's rule over the turn: for
    odometry that does not say it itself)."""
    r0, rm, r1 = rotation(yaw_start), rotation(0.5 * (yaw_start + yaw_end)), rotation(yaw_end)
    body = np.concatenate([dt / 6 * (r0 + 4 * rm + r1), dt**2 / 6 * (r0 + 2 * rm)])
    world = np.concatenate([dt * np.eye(2), 0.5 * dt**2 * np.eye(2)])
    return np.concatenate([body, world], axis=1)


def wrap(angle: np.ndarray) -> np.ndarray:
    return (angle + np.pi) % (2 * np.pi) - np.pi


def huber_cost(r: np.ndarray, m: float) -> np.ndarray:
    a = np.abs(r)
    return np.where(a <= m, a**2, 2 * m * a - m**2)


def huber_weight(r: np.ndarray, m: float) -> np.ndarray:
    """The IRLS weight of the Huber loss: 1 inside the threshold, m/|r| beyond."""
    return np.minimum(1.0, m / np.maximum(np.abs(r), 1e-12))


def angle_residuals(
    delta: np.ndarray, bearing: np.ndarray, std: np.ndarray, min_range_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Bearing residuals in std units for robot-to-tag vectors `delta`, and their gradients with
    respect to the tag position (the robot's gradient is the opposite)."""
    range2 = np.maximum(np.sum(delta**2, axis=1), min_range_m**2)
    predicted = np.arctan2(delta[:, 1], delta[:, 0])
    measured = np.arctan2(bearing[:, 1], bearing[:, 0])
    residual = wrap(predicted - measured) / std
    return residual, np.stack([-delta[:, 1], delta[:, 0]], axis=1) / (range2 * std)[:, None]


SEARCH_HISTORY = 400
"""bearings kept per tag waiting for the search (the latest)"""
SEARCH_EVERY = 4
"""new bearings of a waiting tag between two searches"""
SEARCH_INFO_SCALE = 0.25
"""share of the information of a found tag's earlier bearings kept as its prior (their robot
positions are taken as known, which they are not quite)"""
SELECT_CAP_SIGMA = 3.0
"""in the max-mixture, a candidate further off than this many stds is as unlikely as any other"""
LOCK_BEARINGS = 30
LOCK_SHARE = 0.75
"""a tag locks onto a combination that is the free choice of this share of its last LOCK_BEARINGS
bearings (a jump at every retune spreads them over all, a quarter each at 5 GHz)"""
GN_HINGE_WEIGHT = 1e-6
"""the Gauss-Newton steps need no cheirality (the angle residual has it); a tiny weight keeps h unique"""
PV_FROM_VP = [2, 3, 0, 1]
"""reorders an edge's [dv, dp] (velocity first) to the state's [position, velocity]"""


def padded_rows(blocks: list[np.ndarray], width: int, pad: float) -> np.ndarray:
    """The 2-D `blocks` stacked into one (rows, width) array, each row filled out with `pad` (one
    slice assignment per block: np.pad per block cost a quarter of the SLAM's time)."""
    dtype = np.result_type(*blocks) if blocks else np.float64
    out = np.full((sum(len(b) for b in blocks), width), pad, dtype=dtype)
    row = 0
    for block in blocks:
        out[row : row + len(block), : block.shape[1]] = block
        row += len(block)
    return out


@dataclass
class SlidingWindow:
    """Sliding-window estimator: add epochs, read the estimates; the oldest epochs leave as final."""

    settings: WindowSettings = field(default_factory=WindowSettings)
    epochs: list[Epoch] = field(default_factory=list)
    edges: list[Edge] = field(default_factory=list)
    tag_ids: list[int] = field(default_factory=list)
    x: np.ndarray = field(default_factory=lambda: np.zeros(0))
    prior: Prior | None = None
    slots: int = 1
    program: Program | None = None
    program_type: Callable[[Shape], Program] = WindowProgram
    """the hand-compiled program (the hot path) or its CVXPY specification (`slam`'s batch mode)"""
    finals: list[tuple[int, float, float, float]] = field(default_factory=list)
    """(stamp, x, y, yaw) of the epochs that left the window, in order"""
    tag_covariance: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    bias_covariance: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    """of the shared states (the accelerometer biases, then the wheel scale), at the last update"""
    disagreement: dict[int, int] = field(default_factory=dict)
    """per tag slot: consecutive updates in which most of its bearings were Huber-active"""
    resets: int = 0
    search: SearchSettings = field(default_factory=SearchSettings)
    active: list[bool] = field(default_factory=list)
    """per tag slot: its bearings are used (a tag whose bearings carry several candidates waits
    until the search has found where it is)"""
    history: dict[int, list[tuple[int, np.ndarray, np.ndarray, np.ndarray]]] = field(default_factory=dict)
    """per tag slot waiting for the search: (stamp, world candidate angles, stds, jumps) of its bearings"""
    heard: dict[int, int] = field(default_factory=dict)
    """per tag slot: bearings with several candidates heard so far"""
    searched: dict[int, int] = field(default_factory=dict)
    """per tag slot: `heard` at its last search"""
    final_xy: dict[int, np.ndarray] = field(default_factory=dict)
    """robot position of each epoch that left the window, by stamp"""
    recent_jumps: dict[int, list[int]] = field(default_factory=dict)
    """per tag slot: the combinations of its last LOCK_BEARINGS free choices: the max-mixture's
    weights and the lock"""
    left: list[Epoch] = field(default_factory=list)
    """epochs that left the window since the owner last emptied this list (their choices are final)"""
    found: list[tuple[int, Found]] = field(default_factory=list)
    """(tag id, search result) of every tag the search localized, in order"""
    stacked: _Bearings | None = field(default=None, repr=False)
    modelled: tuple[tuple[int, int, int, int, int], _Model] | None = field(default=None, repr=False)
    judged: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)
    """the last observable() and the covariance it judged (the object itself: replaced, not edited)"""
    searching: _Search | None = field(default=None, repr=False)
    """the tag search under way, if any (find_tags)"""

    @property
    def _prior(self) -> Prior:
        """The prior, there from the first epoch on."""
        if self.prior is None:
            raise RuntimeError("the window has no epoch yet")
        return self.prior

    @property
    def accel_biases(self) -> int:
        """Accelerometer bias states: a body-frame and a world-frame bias, 2D each (or none)."""
        return 4 if self.settings.accel_bias else 0

    @property
    def scale(self) -> bool:
        """Whether the window estimates the wheel scale (the last shared state)."""
        return self.settings.wheel_scale and self.settings.wheel_scale_std > 0

    @property
    def biases(self) -> int:
        """States shared by the window, after the tags: the accelerometer biases, then the wheel scale."""
        return self.accel_biases + self.scale

    @property
    def shape(self) -> Shape:
        return Shape(len(self.epochs), self.slots, len(self.tag_ids), self.biases, self.scale)

    def tag_positions(self) -> np.ndarray:
        e = 4 * len(self.epochs)
        return self.x[e : e + 2 * len(self.tag_ids)].reshape(-1, 2)

    def bias(self) -> np.ndarray:
        """The accelerometer bias states' estimate: [body x, body y, world x, world y] (m/s^2), or none."""
        start = len(self.x) - self.biases
        return self.x[start : start + self.accel_biases]

    def wheel_scale(self) -> float:
        """The wheel scale state's estimate: the fraction by which the wheel odometry over-reads (it
        reads the true speed times 1 + this), 0 when not estimated."""
        return float(self.x[-1]) if self.scale else 0.0

    def _shared(self) -> np.ndarray:
        return self.x[len(self.x) - self.biases :]

    def poses(self) -> list[tuple[int, float, float, float]]:
        """(stamp, x, y, yaw) of the epochs in the window, oldest first."""
        return [(e.stamp_ns, float(self.x[4 * k]), float(self.x[4 * k + 1]), e.yaw) for k, e in enumerate(self.epochs)]

    def add_epoch(
        self,
        stamp_ns: int,
        yaw: float,
        tag_ids: list[int],
        angles_rad: np.ndarray,
        stds_rad: np.ndarray,
        edge: Edge | None,
        speed_m_s: float | None = None,
        jumps: np.ndarray | None = None,
        messages: list[Any] | None = None,
        turning_in_place: bool = False,
        levelled_std_m_s2: float = 0.0,
    ) -> None:
        """Append an epoch: the robot-frame AoAs seen there (one per tag, or (tags, K) candidates,
        NaN-padded, with the jump combination each assumes), the odometry from the previous epoch,
        when there is wheel odometry the forward speed, and whether the robot turned in place since.
        The first epoch may say what levelling the IMU on a still start left of the bias there
        (`levelled_std_m_s2`; 0: not levelled)."""
        s = self.settings
        n = len(tag_ids)
        candidates = yaw + np.asarray(angles_rad, float).reshape(n, -1 if n else 1)
        raw_std = np.asarray(stds_rad, float).reshape(n, -1 if n else 1)
        candidate_std = raw_std * s.aoa_std_scale
        jumps = np.full(candidates.shape, -1) if jumps is None else np.asarray(jumps, int).reshape(candidates.shape)
        first = candidates[:, 0]
        bearing = np.stack([np.cos(first), np.sin(first)], axis=1).reshape(-1, 2)
        if not self.epochs:
            state = np.zeros(4)
            if self.prior is None:
                info = np.diag([s.gauge_std_m**-2] * 2 + [s.initial_velocity_std_m_s**-2] * 2 + [0.0] * self.biases)
                if self.accel_biases:
                    info[4:8, 4:8] = self._bias_prior(yaw, levelled_std_m_s2)
                if self.scale:
                    info[-1, -1] = s.wheel_scale_std**-2
                self.prior = Prior(info, np.zeros(len(info)), np.zeros(len(info)))
                self.x = np.zeros(self.biases)
        else:
            if edge is None:
                raise ValueError("an epoch after the first needs its odometry edge")
            if not self.accel_biases and edge.bias_jacobian.size:
                edge = Edge(edge.dt, edge.delta, edge.covariance)
            if edge.bias_jacobian.shape != (4, self.accel_biases):
                raise ValueError(f"an edge's bias Jacobian is {edge.bias_jacobian.shape}, not (4, {self.accel_biases})")
            if self.scale:  # the odometry does not move with the wheel scale
                edge = Edge(edge.dt, edge.delta, edge.covariance, np.pad(edge.bias_jacobian, ((0, 0), (0, 1))))
            last = self.x[4 * (len(self.epochs) - 1) : 4 * len(self.epochs)]
            delta = edge.delta - edge.bias_jacobian @ self._shared()
            state = np.concatenate([last[0:2] + last[2:4] * edge.dt + delta[2:4], last[2:4] + delta[0:2]])
            self.edges.append(edge)
        tags = self.tag_positions()
        slots = []
        several = np.sum(np.isfinite(candidates), axis=1) > 1
        for j, (tag_id, u) in enumerate(zip(tag_ids, bearing, strict=True)):
            if tag_id not in self.tag_ids:
                guess = state[0:2] + s.initial_range_m * u
                self._add_tag(tag_id, guess)
                self.active.append(not several[j])
                tags = np.vstack([tags, guess])
            t = self.tag_ids.index(tag_id)
            slots.append(t)
            if several[j]:
                kept = self.history.setdefault(t, [])
                kept.append((stamp_ns, candidates[j], raw_std[j], jumps[j]))
                self.heard[t] = self.heard.get(t, 0) + 1
                del kept[:-SEARCH_HISTORY]
        self.x = np.concatenate([self.x[: 4 * len(self.epochs)], state, tags.ravel(), self._shared()])
        epoch = Epoch(
            stamp_ns, yaw, np.array(slots, dtype=int), candidates, candidate_std, jumps, messages=list(messages or [])
        )
        epoch.constraint_info, epoch.constraint_linear = self._velocity_terms(yaw, speed_m_s, turning_in_place)
        epoch.velocity_info, epoch.velocity_linear = epoch.constraint_info, epoch.constraint_linear
        epoch.speed_m_s = math.nan if speed_m_s is None else float(speed_m_s)
        if self.scale:
            self._linearize_wheels([epoch], state[2:4][None, :])
        self.epochs.append(epoch)
        if len(self.epochs) > s.window:
            self._marginalize_oldest()
        self.slots = max(len(e.tags) for e in self.epochs) or 1

    def _velocity_terms(
        self, yaw: float, speed_m_s: float | None, turning_in_place: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        """An epoch's (W, w) over its velocity (and the wheel scale s) that need no linearization: no
        sideways motion, zero velocity when turning in place, and, without the scale as a state, the
        wheel speed z (its scale error as noise). With the scale a state, the reading is
        `_linearize_wheels`'s."""
        s = self.settings
        width = 2 + self.scale
        info, linear = np.zeros((width, width)), np.zeros(width)
        forward, side = np.array([math.cos(yaw), math.sin(yaw)]), np.array([-math.sin(yaw), math.cos(yaw)])
        if s.nonholonomic:
            info[:2, :2] += np.outer(side, side) / s.lateral_std_m_s**2
        if turning_in_place and s.turns_in_place:
            info[:2, :2] += np.eye(2) / s.zero_velocity_std_m_s**2
        if speed_m_s is not None and not self.scale:
            var = s.wheel_speed_std_m_s**2 + (s.wheel_scale_std * speed_m_s) ** 2
            info[:2, :2] += np.outer(forward, forward) / var
            linear[:2] += forward * speed_m_s / var
        return info, linear

    def _linearize_wheels(self, epochs: list[Epoch], velocity: np.ndarray) -> None:
        """Each epoch's wheel reading z = u (1 + s) + noise, with u = f'v its forward speed and s the
        wheel scale, linearized at the velocities `velocity` (epochs, 2) and the window's scale s0:
        the row ((1 + s0) f'v + u0 s - z - u0 s0) / std, with u0 = f'v there.

        The reading's noise is on z, so z must not be the coefficient of the scale: written as
        f'v = z (1 - s), as it was, the noisy reading multiplies the state it measures, and least
        squares then reads the noise as scale (errors in variables). On `long_hall` with a perfect
        IMU the scale came out 0.6% short of the truth from the wheels' 5 mm/s noise alone (exact
        with noise-free wheels). Linearized at the estimate, re-linearized at every update, the
        coefficient is the IMU-smoothed speed and the fixed point is the model's maximum likelihood."""
        std = self.settings.wheel_speed_std_m_s
        s0 = float(self.x[-1])
        yaw = np.array([e.yaw for e in epochs])
        z = np.array([e.speed_m_s for e in epochs])
        forward = np.stack([np.cos(yaw), np.sin(yaw)], axis=1)
        u0 = np.einsum("ij,ij->i", forward, velocity)
        read = np.isfinite(z)
        row = np.where(read[:, None], np.concatenate([(1 + s0) * forward, u0[:, None]], axis=1), 0.0) / std
        target = np.where(read, z + u0 * s0, 0.0) / std
        info, linear = row[:, :, None] * row[:, None, :], row * target[:, None]
        for k, e in enumerate(epochs):
            e.velocity_info = e.constraint_info + info[k]
            e.velocity_linear = e.constraint_linear + linear[k]

    def _bias_prior(self, yaw: float, levelled_std_m_s2: float) -> np.ndarray:
        """Information on [body bias, world bias] at the start: each within `accel_bias_std_m_s2`, or,
        when the IMU was levelled on a still start at heading `yaw`, the body bias so and the two
        cancelling there (what levelling removed is exactly what the IMU felt at rest: c + R b = 0)."""
        s = self.settings
        if levelled_std_m_s2 <= 0:
            return np.eye(4) / s.accel_bias_std_m_s2**2
        both = np.concatenate([rotation(yaw), np.eye(2)], axis=1)  # c + R b
        info = both.T @ both / levelled_std_m_s2**2
        info[0:2, 0:2] += np.eye(2) / s.accel_bias_std_m_s2**2
        return info

    def _add_tag(self, tag_id: int, guess: np.ndarray) -> None:
        """A new tag's prior, inserted after the other tags' (before the biases)."""
        p = self._prior
        at = 4 + 2 * len(self.tag_ids)
        self.tag_ids.append(tag_id)
        info = np.insert(np.insert(p.info, [at, at], 0.0, axis=0), [at, at], 0.0, axis=1)
        info[at : at + 2, at : at + 2] = np.eye(2) * self.settings.tag_prior_std_m**-2
        self.prior = Prior(info, np.insert(p.mean, [at, at], guess), np.insert(p.grad, [at, at], 0.0))

    # -- the model ------------------------------------------------------------------------------

    def _bearings(self) -> _Bearings:
        """The window's bearings stacked (see _Bearings), rebuilt when the window's content changed."""
        epochs = self.epochs
        key = self._content()
        if self.stacked is not None and self.stacked.key == key:
            return self.stacked
        counts = np.array([len(e.tags) for e in epochs], dtype=int)
        starts = np.concatenate([[0], np.cumsum(counts)])
        epoch = np.repeat(np.arange(len(epochs)), counts)
        width = max((e.candidates.shape[1] for e in epochs if len(e.tags)), default=1)
        self.stacked = _Bearings(
            key=key,
            epoch=epoch,
            tag=np.concatenate([e.tags for e in epochs]).astype(int) if epochs else np.zeros(0, int),
            angles=padded_rows([e.candidates for e in epochs], width, np.nan),
            stds=padded_rows([e.candidate_std for e in epochs], width, 1.0),
            jumps=padded_rows([e.candidate_jumps for e in epochs], width, -1).astype(int),
            slot=epoch * self.slots + np.arange(len(epoch)) - starts[epoch],
            starts=starts,
        )
        return self.stacked

    def _rows(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per slot: epoch index, tag slot (-1 when empty), world bearing (2) of the chosen
        candidate, its std, filled flag."""
        shape = self.shape
        b = self._bearings()
        picked = np.arange(len(b.tag)), np.concatenate([e.choice for e in self.epochs]).astype(int)
        angle = b.angles[picked]
        tag = np.full(shape.rows, -1)
        bearing = np.zeros((shape.rows, 2))
        std = np.ones(shape.rows)
        tag[b.slot] = b.tag
        bearing[b.slot] = np.stack([np.cos(angle), np.sin(angle)], axis=1)
        std[b.slot] = b.stds[picked]
        active = np.array(self.active + [False], bool)
        return np.repeat(np.arange(shape.epochs), shape.slots), tag, bearing, std, (tag >= 0) & active[tag]

    def _select(self, x: np.ndarray) -> None:
        """Max-mixture: each bearing of a tag in use takes the candidate likeliest at the estimate x,
        the learned weights of the jump combinations included (a once-per-run combination soon dominates)."""
        if not any(self.active) or not self.epochs:
            return
        b = self._bearings()
        epoch, tag, angles, stds, jumps = b.epoch, b.tag, b.angles, b.stds, b.jumps
        if len(tag) == 0 or angles.shape[1] == 1:
            return
        offset = self._offsets(x, epoch, tag)
        predicted = np.arctan2(offset[:, 1], offset[:, 0])
        r = wrap(predicted[:, None] - angles) / stds
        prior = np.log(stds) - self._log_weights(tag, jumps)  # a wide candidate, a rare combination: less likely
        cost = 0.5 * np.minimum(r**2, SELECT_CAP_SIGMA**2) + prior
        cost = np.where(np.isfinite(r), cost, np.inf)
        free = np.argmin(cost, axis=1)
        rows = np.arange(len(free))
        held = np.full(len(self.tag_ids), -2)  # per tag slot: the combination it locked onto (-2: none)
        for t in np.unique(tag):
            lock = self.locked(int(t)) if self.active[t] else None
            held[t] = -2 if lock is None else lock
        own = (jumps == held[tag][:, None]) & np.isfinite(angles)
        choice = np.where(own.any(axis=1), np.argmax(own, axis=1), free)
        # odds of each candidate against the chosen one, uncapped and with the bursts' own stds (the
        # window's are scaled up for the errors consecutive bursts share, which is no doubt about a choice)
        raw = r * self.settings.aoa_std_scale
        likely = np.where(np.isfinite(raw), 0.5 * raw**2 + prior, np.inf)
        # normalized against each row's most likely candidate, so no exponent overflows (inf / inf)
        low = likely.min(axis=1, keepdims=True)
        finite = np.isfinite(likely)
        chance = np.exp(-(np.where(finite, likely, 0.0) - np.where(np.isfinite(low), low, 0.0))) * finite
        chance /= np.maximum(chance.sum(axis=1, keepdims=True), np.finfo(float).tiny)
        apart = np.where(np.isfinite(angles), wrap(angles - angles[rows, choice][:, None]), 0.0)
        doubt = np.sum(chance * apart**2, axis=1)
        use = np.array(self.active, bool)[tag]
        kept = [np.concatenate([getattr(e, name) for e in self.epochs]) for name in ("choice", "free_choice", "doubt")]
        choice, free, doubt = (np.where(use, new, old) for new, old in zip((choice, free, doubt), kept, strict=True))
        for k, e in enumerate(self.epochs):
            at = slice(b.starts[k], b.starts[k + 1])
            e.choice, e.free_choice, e.doubt = choice[at], free[at], doubt[at]

    def _log_weights(self, tag: np.ndarray, jumps: np.ndarray) -> np.ndarray:
        """log of each candidate's combination weight for its tag: its count among the tag's last
        LOCK_BEARINGS free choices plus one, normalized (recent only, so a later jump can be followed)."""
        combinations = max(int(jumps.max()) + 1, 1)
        table = np.zeros((len(self.tag_ids), combinations))  # per tag slot and combination
        for t in np.unique(tag):
            recent = np.asarray(self.recent_jumps.get(int(t), []), dtype=int)
            counts = np.bincount(recent[recent < combinations], minlength=combinations)
            table[t] = np.log((counts + 1.0) / (len(recent) + combinations))
        return np.where(jumps >= 0, table[tag[:, None], np.maximum(jumps, 0)], -math.log(combinations))

    def locked(self, tag_slot: int) -> int | None:
        """The jump combination a tag's chains hold (the free choice of LOCK_SHARE of its last
        LOCK_BEARINGS bearings), if any: its bearings then use that combination's candidate, the
        discrete state a jump once per run leaves; a later jump unlocks it as the free choices move."""
        recent = self.recent_jumps.get(tag_slot, [])
        if len(recent) < LOCK_BEARINGS:
            return None
        top = max(set(recent), key=recent.count)
        return top if recent.count(top) >= LOCK_SHARE * len(recent) else None

    def find_tags(self, steps: int | None = None) -> int:
        """Advance the searches for the tags waiting for their position by at most `steps` steps
        (None: until every search due has run); returns the steps taken. A search is due for a tag
        whose history grew by SEARCH_EVERY since its last one; the tag waiting longest goes first,
        one search at a time, each from the robot positions of when it started; a tag found is in
        use from the next update.

        Done between updates, not in them, a few steps at a time (tag_search.search_steps): a
        whole search costs several updates' time, and no pose need wait for it."""
        taken = 0
        while steps is None or taken < steps:
            if self.searching is None:
                self.searching = self._next_search()
                if self.searching is None:
                    break
            taken += 1
            try:
                next(self.searching.steps)
            except StopIteration as done:
                run, self.searching = self.searching, None
                if done.value is not None and done.value.clear(self.search):
                    self._activate(run.tag, done.value, run.stamps, run.robot, run.stds, run.jumps)
        return taken

    def _next_search(self) -> _Search | None:
        """The search of the tag waiting longest among those due, started (None: none is due)."""
        window_xy = {e.stamp_ns: self.x[4 * k : 4 * k + 2] for k, e in enumerate(self.epochs)}
        due = [
            t for t in self.history if not self.active[t] and self.heard[t] >= self.searched.get(t, 0) + SEARCH_EVERY
        ]
        for t in sorted(due, key=lambda t: self.searched.get(t, 0) - self.heard[t]):
            self.searched[t] = self.heard[t]
            rows = [
                (st, xy, row)
                for st, *row in self.history[t]
                if (xy := self.final_xy.get(st, window_xy.get(st))) is not None
            ]
            if len(rows) < self.search.min_bearings:
                continue
            width = max(len(row[0]) for _, _, row in rows)

            def padded(i: int, pad: float, rows=rows, width=width) -> np.ndarray:
                return padded_rows([row[i][None, :] for _, _, row in rows], width, pad)

            robot = np.array([xy for _, xy, _ in rows])
            angles, stds, jumps = padded(0, np.nan), padded(1, 1.0), padded(2, -1).astype(int)
            stamps = np.array([st for st, _, _ in rows])
            return _Search(t, stamps, robot, stds, jumps, search_steps(robot, angles, stds, self.search, jumps))
        return None

    def _activate(
        self, t: int, found: Found, stamps: np.ndarray, robot: np.ndarray, stds: np.ndarray, jumps: np.ndarray
    ) -> None:
        """Put a found tag in use: at its position, with the information of its bearings that already
        left the window as its prior (their robot positions taken as known, so weighed down), and
        its bearings' jump combinations as the first counts of its mixture weights."""
        e = len(self.epochs)
        self.x[4 * e + 2 * t : 4 * e + 2 * t + 2] = found.position
        oldest = self.epochs[0].stamp_ns if self.epochs else 0
        inlier = found.choice >= 0
        gone = inlier & (stamps < oldest)
        info = np.eye(2) * self.settings.tag_prior_std_m**-2
        if gone.any():
            d = found.position[None, :] - robot[gone]
            std = stds[gone, found.choice[gone]] * self.settings.aoa_std_scale
            jac = np.stack([-d[:, 1], d[:, 0]], axis=1) / (np.maximum(np.sum(d**2, axis=1), 1e-6) * std)[:, None]
            info = info + SEARCH_INFO_SCALE * jac.T @ jac
        p = self._prior
        at = 4 + 2 * t + np.arange(2)
        p.info[at, :] = 0.0
        p.info[:, at] = 0.0
        p.info[np.ix_(at, at)] = info
        p.mean[at] = found.position
        p.grad[at] = 0.0
        self.active[t] = True
        self.history.pop(t, None)
        agreed = jumps[np.flatnonzero(inlier), found.choice[inlier]]  # the search's evidence starts the weights
        self.recent_jumps[t] = [int(j) for j in agreed[agreed >= 0][-LOCK_BEARINGS:]]
        self.found.append((self.tag_ids[t], found))

    def _offsets(self, x: np.ndarray, epoch: np.ndarray, tag: np.ndarray) -> np.ndarray:
        """Robot-to-tag vectors b - mu per slot."""
        e = len(self.epochs)
        tags = x[4 * e : 4 * e + 2 * len(self.tag_ids)].reshape(-1, 2)
        if len(tags) == 0:
            return np.zeros((len(epoch), 2))
        return tags[np.maximum(tag, 0)] - x[: 4 * e].reshape(-1, 4)[epoch, 0:2]

    def _slot_coefficients(self, tag_part: np.ndarray, tag: np.ndarray) -> np.ndarray:
        """Row coefficients at the program's columns: -v on the epoch's position, +v on its tag's."""
        shape = self.shape
        out = np.zeros((shape.rows, 2 + 2 * shape.tags))
        out[:, 0:2] = -tag_part
        rows = np.nonzero(tag >= 0)[0]
        out[rows, 2 + 2 * tag[rows]] = tag_part[rows, 0]
        out[rows, 3 + 2 * tag[rows]] = tag_part[rows, 1]
        return out

    def _angles(self, x, epoch, tag, bearing, std, filled) -> tuple[np.ndarray, np.ndarray]:
        """Angle residuals in std units and their gradients with respect to the tag position."""
        residual, jb = angle_residuals(self._offsets(x, epoch, tag), bearing, std, self.settings.min_range_m)
        return np.where(filled, residual, 0.0), np.where(filled[:, None], jb, 0.0)

    def _content(self) -> tuple[int, int, int, int, int]:
        """What the window holds, as far as the stacked numbers go: epochs (how many, the first
        and last stamps), slots per epoch, tags."""
        epochs = self.epochs
        first, last = (epochs[0].stamp_ns, epochs[-1].stamp_ns) if epochs else (0, 0)
        return len(epochs), first, last, self.slots, len(self.tag_ids)

    def _model(self) -> _Model:
        """The update's fixed numbers, stacked once per window content (the wheel readings, when the
        scale is a state, at every update: they are re-linearized)."""
        key = self._content()
        if self.modelled is not None and self.modelled[0] == key:
            model = self.modelled[1]
            if self.scale:
                model = replace(
                    model,
                    velocity_info=np.stack([e.velocity_info for e in self.epochs]),
                    velocity_linear=np.stack([e.velocity_linear for e in self.epochs]),
                )
            return model
        ne = len(self.edges)
        chol = np.stack([e.chol for e in self.edges]) if ne else np.zeros((0, 4, 4))
        model = _Model(
            edge_l=edge_matrix(np.array([e.dt for e in self.edges])),
            edge_chol=chol,
            edge_whiten=np.linalg.inv(chol) if ne else chol,
            edge_delta=np.stack([e.delta for e in self.edges]) if ne else np.zeros((0, 4)),
            edge_bias=np.stack([e.bias_jacobian for e in self.edges]) if ne else np.zeros((0, 4, self.biases)),
            pairs=4 * np.arange(ne)[:, None] + np.arange(8),
            velocity_info=np.stack([e.velocity_info for e in self.epochs]),
            velocity_linear=np.stack([e.velocity_linear for e in self.epochs]),
            prior_index=prior_indices(self.shape),
        )
        self.modelled = (key, model)
        return model

    def _cost(self, model: _Model, x: np.ndarray, residual: np.ndarray) -> float:
        """The true cost: odometry, wheel, prior, and the Huber loss of the angle residuals."""
        bias = x[self.shape.bias_index]
        r = np.einsum("nij,nj->ni", model.edge_l, x[model.pairs]) + model.edge_bias @ bias - model.edge_delta
        odometry = 0.5 * float(np.sum(np.einsum("nij,nj->ni", model.edge_whiten, r) ** 2))
        y = x[velocity_columns(self.shape)]
        wheel = float(0.5 * np.einsum("ni,nij,nj->", y, model.velocity_info, y) - np.sum(model.velocity_linear * y))
        p = self._prior
        d = x[model.prior_index] - p.mean
        return (
            odometry
            + wheel
            + 0.5 * float(d @ p.info @ d)
            + float(p.grad @ d)
            + 0.5 * float(huber_cost(residual, self.settings.huber_sigma).sum())
        )

    # -- one update -----------------------------------------------------------------------------

    def update(self) -> Update:
        """Re-solve the window: convex passes with reweighted distances, then Gauss-Newton on angles."""
        s = self.settings
        shape = self.shape
        if self.program is None or self.program.shape != shape:
            self.program = self.program_type(shape)
        if self.scale:
            self._linearize_wheels(self.epochs, self.x[: 4 * shape.epochs].reshape(-1, 4)[:, 2:4])
        p = self._prior
        model = self._model()
        c = np.zeros(shape.states)
        c[model.prior_index] = p.info @ p.mean - p.grad
        np.add.at(c, velocity_columns(shape), model.velocity_linear)
        base: dict[str, Any] = dict(
            prior_info=p.info,
            velocity_info=model.velocity_info,
            c=c,
            edge_l=model.edge_l,
            edge_chol=model.edge_chol,
            edge_delta=model.edge_delta,
            edge_bias=model.edge_bias,
            huber_m=s.huber_sigma,
        )
        self._select(self.x)
        epoch, tag, bearing, std, filled = self._rows()
        perp = np.stack([-bearing[:, 1], bearing[:, 0]], axis=1)
        zeros_g = np.zeros((shape.rows, 2 + 2 * shape.tags))
        result = Update()
        x = self.x.copy()
        weight = np.ones(shape.rows)
        try:
            d = np.maximum(np.linalg.norm(self._offsets(x, epoch, tag), axis=1), s.min_range_m)
            localized = np.zeros(max(shape.tags, 1), bool)
            localized[: len(self.tag_covariance)] = self.observable()
            # with every tag in use localized, the last estimate is as good a start for the
            # Gauss-Newton steps as the convex program's (which is there to start tags it has not)
            known = not (filled & ~localized[np.maximum(tag, 0)]).any()
            for _ in range(0 if known else s.reweight_passes):
                scale = np.where(filled, 1.0 / (d * std), 0.0)
                x, iterations = self.program.solve(
                    UpdateData(
                        **base,
                        a=self._slot_coefficients(perp * scale[:, None], tag),
                        offset=np.zeros(shape.rows),
                        g=self._slot_coefficients(bearing * scale[:, None], tag),
                        hinge=s.hinge_weight * weight,
                    )
                )
                result.iterations += iterations
                offsets = self._offsets(x, epoch, tag)
                r = np.einsum("ij,ij->i", perp, offsets) * scale
                weight = huber_weight(r, s.huber_sigma)
                settled = d
                d = np.maximum(np.linalg.norm(offsets, axis=1), s.min_range_m)
                unsure = filled & (weight >= 1.0) & ~localized[np.maximum(tag, 0)]
                if np.all(np.abs(d - settled)[unsure] <= s.reweight_tolerance * settled[unsure]):
                    break
            self._select(x)
            epoch, tag, bearing, std, filled = self._rows()
            residual, jb = self._angles(x, epoch, tag, bearing, std, filled)
            cost = self._cost(model, x, residual[filled])
            res_p, jb_p = self._angles(self.x, epoch, tag, bearing, std, filled)
            cost_p = self._cost(model, self.x, res_p[filled])
            if cost_p < cost:
                x, residual, jb, cost = self.x.copy(), res_p, jb_p, cost_p
            for _ in range(s.refine_iterations):
                trial, iterations = self.program.solve(
                    UpdateData(
                        **base,
                        a=self._slot_coefficients(jb, tag),
                        offset=residual,
                        g=zeros_g,
                        hinge=np.full(shape.rows, GN_HINGE_WEIGHT),
                    )
                )
                result.iterations += iterations
                res_t, jb_t = self._angles(trial, epoch, tag, bearing, std, filled)
                cost_t = self._cost(model, trial, res_t[filled])
                if cost_t > cost:
                    break
                converged = np.max(np.abs(trial - x)) < s.refine_tolerance_m
                x, residual, jb, cost = trial, res_t, jb_t, cost_t
                if converged:
                    break
        except SolverFailed as exc:
            result.failed = str(exc)
            if not np.all(np.isfinite(x)):
                x = self.x.copy()
        residual, jb = self._angles(x, epoch, tag, bearing, std, filled)
        result.huber_active = int(np.sum(np.abs(residual[filled]) > s.huber_sigma))
        self.x = x
        self._check_consistency(tag[filled], np.abs(residual[filled]) > s.huber_sigma)
        self._covariances(epoch, tag, residual, jb, filled)
        return result

    def _check_consistency(self, tags: np.ndarray, active: np.ndarray) -> None:
        """Relax the prior of tags whose recent bearings keep disagreeing with their estimate."""
        s = self.settings
        if not s.reset_updates:
            return
        localized = np.zeros(len(self.tag_ids), bool)
        localized[: len(self.tag_covariance)] = self.observable()
        for t in range(len(self.tag_ids)):
            mine = tags == t
            if localized[t] and mine.sum() >= 3 and active[mine].mean() > 0.5:
                self.disagreement[t] = self.disagreement.get(t, 0) + 1
            elif mine.any():
                self.disagreement[t] = 0
            if self.disagreement.get(t, 0) >= s.reset_updates:
                p = self._prior
                keep = np.ones(len(p.mean))
                keep[4 + 2 * t : 6 + 2 * t] = math.sqrt(s.reset_factor)
                self.prior = Prior(p.info * np.outer(keep, keep), p.mean, p.grad * keep)
                self.disagreement[t] = 0
                self.resets += 1

    def _information(self, epoch, tag, residual, jb, filled) -> np.ndarray:
        """The Gauss-Newton information of the window at the estimate (Huber rows IRLS-weighted),
        dense: a window has a few hundred states, where building a sparse matrix costs more than
        factorizing the dense one."""
        shape = self.shape
        m = self.settings.huber_sigma
        w = np.where(filled, huber_weight(residual, m), 0.0)
        n = shape.states
        pri = prior_indices(shape)
        blocks = [(pri, self._prior.info[None])]  # (states of each block, the blocks): summed below
        if self.edges:
            edge = np.concatenate(
                [
                    4 * np.arange(len(self.edges))[:, None] + np.arange(8),
                    np.broadcast_to(shape.bias_index, (len(self.edges), shape.biases)),
                ],
                axis=1,
            )
            blocks.append((edge, np.stack([e.block for e in self.edges])))
        blocks.append((velocity_columns(shape), np.stack([e.velocity_info for e in self.epochs])))
        flat = np.concatenate(
            [(idx.reshape(-1, idx.shape[-1], 1) * n + idx.reshape(-1, 1, idx.shape[-1])).ravel() for idx, _ in blocks]
        )
        values = np.concatenate([b.ravel() for _, b in blocks])
        info = np.bincount(flat, weights=values, minlength=n * n).reshape(n, n)
        coeff = self._slot_coefficients(jb, tag) * np.sqrt(w)[:, None]
        rows = np.zeros((shape.rows, shape.states))
        rows[np.arange(shape.rows)[:, None], 4 * epoch[:, None] + np.arange(2)] = coeff[:, :2]
        rows[:, 4 * shape.epochs : 4 * shape.epochs + 2 * shape.tags] = coeff[:, 2:]
        return info + rows.T @ rows

    def _covariances(self, epoch, tag, residual, jb, filled) -> None:
        nt, nb = len(self.tag_ids), self.biases
        e = 4 * len(self.epochs)
        info = self._information(epoch, tag, residual, jb, filled)
        rhs = np.zeros((info.shape[0], 2 * nt + nb))
        rhs[e:, :] = np.eye(2 * nt + nb)
        try:
            cov = np.linalg.solve(info, rhs)[e:]
        except np.linalg.LinAlgError:
            cov = np.full((2 * nt + nb, 2 * nt + nb), np.inf)
        self.tag_covariance = np.array([cov[2 * i : 2 * i + 2, 2 * i : 2 * i + 2] for i in range(nt)]).reshape(-1, 2, 2)
        self.bias_covariance = cov[2 * nt :, 2 * nt :]

    def observable(self) -> np.ndarray:
        """Per tag: localized well enough to report (largest std below `observable_std_m`); worked
        out once per covariance."""
        if self.judged is not None and self.judged[0] is self.tag_covariance:
            return self.judged[1].copy()
        if len(self.tag_covariance) == 0:
            return np.zeros(0, bool)
        cov = np.nan_to_num(self.tag_covariance, nan=1e12, posinf=1e12)
        worst = np.linalg.eigvalsh(0.5 * (cov + cov.transpose(0, 2, 1)))[:, -1]
        result = np.sqrt(np.maximum(worst, 0)) <= self.settings.observable_std_m
        self.judged = (self.tag_covariance, result)
        return result.copy()

    # -- marginalization ------------------------------------------------------------------------

    def _marginalize_oldest(self) -> None:
        """Fold the oldest epoch into the prior: its Gaussian (prior and bearings, linearized at the
        estimate) carried through the odometry edge onto the next epoch, in covariance form (the
        edge is far more precise than anything else, which information form would square)."""
        s = self.settings
        old, edge = self.epochs[0], self.edges[0]
        e = len(self.epochs)
        nt = len(self.tag_ids)
        x = self.x
        nb = self.biases
        own = np.concatenate([np.arange(4), 4 * e + np.arange(2 * nt + nb)])
        p = self._prior
        info = p.info.copy()
        grad = p.info @ (x[own] - p.mean) + p.grad
        wheel = np.array([2, 3] + [len(own) - 1] * self.scale)  # the oldest epoch's velocity_columns, in `own`
        info[np.ix_(wheel, wheel)] += old.velocity_info
        grad[wheel] += old.velocity_info @ x[own][wheel] - old.velocity_linear
        if len(old.tags):
            delta = x[4 * e : 4 * e + 2 * nt].reshape(-1, 2)[old.tags] - x[0:2]
            r, jb = angle_residuals(delta, old.bearing, old.std, s.min_range_m)
            w = huber_weight(r, s.huber_sigma)
            for j, t in enumerate(old.tags):
                if not self.active[t]:
                    continue
                jump = int(old.candidate_jumps[j, old.free_choice[j]])
                if jump >= 0:
                    recent = self.recent_jumps.setdefault(int(t), [])
                    recent.append(jump)
                    del recent[:-LOCK_BEARINGS]
                cols = np.concatenate([[0, 1], 4 + 2 * t + np.arange(2)])
                row = np.concatenate([-jb[j], jb[j]])
                info[np.ix_(cols, cols)] += w[j] * np.outer(row, row)
                grad[cols] += w[j] * row * r[j]
        cov = np.linalg.inv(info)
        mean = x[own] - cov @ grad
        transfer = np.eye(4)
        transfer[0:2, 2:4] = edge.dt * np.eye(2)
        jac = np.eye(4 + 2 * nt + nb)
        jac[:4, :4] = transfer
        jac[:4, 4 + 2 * nt :] = -edge.bias_jacobian[PV_FROM_VP]
        new_cov = jac @ cov @ jac.T
        new_cov[:4, :4] += edge.covariance[np.ix_(PV_FROM_VP, PV_FROM_VP)]
        walk = 4 + 2 * nt + np.arange(nb)
        rates = np.array([s.accel_bias_walk_m_s2_rts] * self.accel_biases + [s.wheel_scale_walk_rts] * self.scale)
        new_cov[walk, walk] += rates**2 * edge.dt
        new_mean = jac @ mean
        new_mean[:4] += edge.delta[PV_FROM_VP]
        new_info = np.linalg.inv(new_cov)
        self.prior = Prior(0.5 * (new_info + new_info.T), new_mean, np.zeros(4 + 2 * nt + nb))
        self.finals.append((old.stamp_ns, float(x[0]), float(x[1]), old.yaw))
        self.final_xy[old.stamp_ns] = x[0:2].copy()
        self.left.append(old)
        self.epochs.pop(0)
        self.edges.pop(0)
        self.x = x[4:].copy()
