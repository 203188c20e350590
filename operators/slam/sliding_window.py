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
or, once every tag in use is localized or was placed by the search a window ago, from the last
estimate alone (the convex passes are there to start tags: TagFinder.starting).
The distances in the weights have a floor (no tag is closer than `min_range_m` to the antennas).

This module holds the epochs and orchestrates an update; its parts (layout, factors, candidates,
marginalization, ...) are listed in docs/slam.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from rover.operators.slam.candidates import Choice, JumpMemory, choose
from rover.operators.slam.epoch import Bearings, Epoch, stack_bearings
from rover.operators.slam.factors import (
    GN_HINGE_WEIGHT,
    Edge,
    angle_residuals,
    bias_jacobian,
    bias_prior,
    huber_cost,
    huber_weight,
    velocity_terms,
    wheel_rows,
)
from rover.operators.slam.gauss_newton import DIRECT_MAX_STATES, DirectStep
from rover.operators.slam.information import covariances, largest_std_m, window_information
from rover.operators.slam.integrity import TagIntegrity, disagreeing
from rover.operators.slam.layout import (
    ACCEL_BIAS_STATES,
    EPOCH_STATES,
    TAG_STATES,
    Shape,
    positions,
    prior_indices,
    prior_tag,
    velocity_columns,
)
from rover.operators.slam.marginalization import Leaving, Prior, marginalize_oldest
from rover.operators.slam.settings import WindowSettings
from rover.operators.slam.tag_finder import TagFinder
from rover.operators.slam.tag_placement import find_tags
from rover.operators.slam.window_program import Program, SolverFailed, UpdateData, WindowProgram, edge_matrix

__all__ = ["Edge", "Epoch", "SlidingWindow", "Update", "WindowSettings", "bias_jacobian"]


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


@dataclass
class SlidingWindow:
    """Sliding-window estimator: add epochs, read the estimates; the oldest epochs leave as final."""

    settings: WindowSettings = field(default_factory=WindowSettings)
    epochs: list[Epoch] = field(default_factory=list)
    edges: list[Edge] = field(default_factory=list)
    tag_ids: list[int] = field(default_factory=list)
    x: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """the states, laid out as `layout` says for `shape`"""
    prior: Prior | None = None
    slots: int = 1
    program: Program | None = None
    program_type: Callable[[Shape], Program] = WindowProgram
    """the hand-compiled program (the hot path) or its CVXPY specification (`slam`'s batch mode)"""
    direct: DirectStep | None = field(default=None, repr=False)
    """the Gauss-Newton steps' direct solve (the program when it declines, or for large windows)"""
    finals: list[tuple[int, float, float, float]] = field(default_factory=list)
    """(stamp, x, y, yaw) of the epochs that left the window, in order"""
    tag_covariance: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    bias_covariance: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    """of the shared states (the accelerometer biases, then the wheel scale), at the last update"""
    position_covariance: np.ndarray = field(default_factory=lambda: np.full((2, 2), np.inf))
    """the newest epoch's position's 2x2 covariance at the last update (m^2)"""
    disagreement: dict[int, int] = field(default_factory=dict)
    """per tag slot: consecutive updates in which most of its bearings were Huber-active"""
    resets: int = 0
    active: list[bool] = field(default_factory=list)
    """per tag slot: its bearings are used (a tag whose bearings carry several candidates waits
    until the search has found where it is)"""
    finder: TagFinder = field(default_factory=TagFinder)
    """the tags waiting for the search, and what it found"""
    jumps: JumpMemory = field(default_factory=JumpMemory)
    """per tag slot: the jump combinations of its recent bearings (where a window starts, the switch rate)"""
    integrity: TagIntegrity = field(default_factory=TagIntegrity)
    """per tag slot: its bearings that left the window, whose jackknife scales its covariance up"""
    left: list[Epoch] = field(default_factory=list)
    """epochs that left the window since the owner last emptied this list (their choices are final)"""
    stacked: Bearings | None = field(default=None, repr=False)
    modelled: tuple[tuple[int, int, int, int, int], _Model] | None = field(default=None, repr=False)
    judged: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)
    """the last observable() and the covariance it judged (the object itself: replaced, not edited)"""

    @property
    def _prior(self) -> Prior:
        """The prior, there from the first epoch on."""
        if self.prior is None:
            raise RuntimeError("the window has no epoch yet")
        return self.prior

    @property
    def accel_biases(self) -> int:
        """Accelerometer bias states: a body-frame and a world-frame bias, 2D each (or none)."""
        return ACCEL_BIAS_STATES if self.settings.accel_bias else 0

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
        return self.x[self.shape.tag_states].reshape(-1, TAG_STATES)

    def bias(self) -> np.ndarray:
        """The accelerometer bias states' estimate: [body x, body y, world x, world y] (m/s^2), or none."""
        return self._shared()[: self.accel_biases]

    def wheel_scale(self) -> float:
        """The wheel scale state's estimate: the fraction by which the wheel odometry over-reads (it
        reads the true speed times 1 + this), 0 when not estimated."""
        return float(self.x[-1]) if self.scale else 0.0

    def _shared(self) -> np.ndarray:
        return self.x[len(self.x) - self.biases :]

    def poses(self) -> list[tuple[int, float, float, float]]:
        """(stamp, x, y, yaw) of the epochs in the window, oldest first."""
        xy = positions(self.x, len(self.epochs))
        return [(e.stamp_ns, float(xy[k, 0]), float(xy[k, 1]), e.yaw) for k, e in enumerate(self.epochs)]

    def locked(self, tag_slot: int) -> int | None:
        """The jump combination a tag's chains hold, if any (JumpMemory.locked)."""
        return self.jumps.locked(tag_slot)

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
                    shared = EPOCH_STATES + np.arange(self.accel_biases)
                    info[np.ix_(shared, shared)] = bias_prior(s, yaw, levelled_std_m_s2)
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
                edge = edge.with_bias_columns(1)
            last = self.x[self.shape.epoch(len(self.epochs) - 1)]
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
                self.finder.hear(t, stamp_ns, candidates[j], raw_std[j], jumps[j])
        self.x = np.concatenate([self.x[self.shape.epoch_states], state, tags.ravel(), self._shared()])
        epoch = Epoch(
            stamp_ns, yaw, np.array(slots, dtype=int), candidates, candidate_std, jumps, messages=list(messages or [])
        )
        epoch.constraint_info, epoch.constraint_linear = velocity_terms(s, self.scale, yaw, speed_m_s, turning_in_place)
        epoch.velocity_info, epoch.velocity_linear = epoch.constraint_info, epoch.constraint_linear
        epoch.speed_m_s = math.nan if speed_m_s is None else float(speed_m_s)
        if self.scale:
            self._linearize_wheels([epoch], state[2:4][None, :])
        self.epochs.append(epoch)
        if len(self.epochs) > s.window:
            self._marginalize_oldest()
        self.slots = max(len(e.tags) for e in self.epochs) or 1

    def _add_tag(self, tag_id: int, guess: np.ndarray) -> None:
        """A new tag's prior, inserted after the other tags' (before the biases)."""
        p = self._prior
        at = prior_tag(len(self.tag_ids)).start
        self.tag_ids.append(tag_id)
        info = np.insert(np.insert(p.info, [at, at], 0.0, axis=0), [at, at], 0.0, axis=1)
        info[at : at + 2, at : at + 2] = np.eye(2) * self.settings.tag_prior_std_m**-2
        self.prior = Prior(info, np.insert(p.mean, [at, at], guess), np.insert(p.grad, [at, at], 0.0))

    def _linearize_wheels(self, epochs: list[Epoch], velocity: np.ndarray) -> None:
        """Each epoch's wheel term re-linearized at the velocities `velocity` (epochs, 2) and the
        window's scale (factors.wheel_rows), on top of its fixed constraints."""
        yaw = np.array([e.yaw for e in epochs])
        z = np.array([e.speed_m_s for e in epochs])
        info, linear = wheel_rows(yaw, z, velocity, float(self.x[-1]), self.settings.wheel_speed_std_m_s)
        for k, e in enumerate(epochs):
            e.velocity_info = e.constraint_info + info[k]
            e.velocity_linear = e.constraint_linear + linear[k]

    # -- the model ------------------------------------------------------------------------------

    def _bearings(self) -> Bearings:
        """The window's bearings stacked (see Bearings), rebuilt when the window's content changed."""
        key = self._content()
        if self.stacked is None or self.stacked.key != key:
            self.stacked = stack_bearings(self.epochs, self.slots, key)
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
        std[b.slot] = b.stds[picked] * self.integrity.std_factor(b.tag)
        active = np.array(self.active + [False], bool)
        return np.repeat(np.arange(shape.epochs), shape.slots), tag, bearing, std, (tag >= 0) & active[tag]

    def _select(self, x: np.ndarray) -> None:
        """Each bearing of a tag in use takes its candidate at the estimate x: the tag's jump state
        decoded over its bearings (candidates.choose)."""
        if not any(self.active) or not self.epochs:
            return
        b = self._bearings()
        if len(b.tag) == 0 or b.angles.shape[1] == 1:
            return
        kept = Choice(*(np.concatenate([getattr(e, name) for e in self.epochs]) for name in ("choice", "doubt")))
        offset = self._offsets(x, b.epoch, b.tag)
        new = choose(
            offset, b.tag, b.angles, b.stds, b.jumps, self.active, self.jumps, self.settings.aoa_std_scale, kept
        )
        for k, e in enumerate(self.epochs):
            at = slice(b.starts[k], b.starts[k + 1])
            e.choice, e.doubt = new.choice[at], new.doubt[at]

    def find_tags(self, steps: int | None = None) -> int:
        """Advance the tag searches due (a waiting tag's, or the check of a tag in use) by at most
        `steps` steps (None: until every search due has run); returns the steps taken
        (tag_placement.find_tags: what a search ends in is applied there)."""
        return find_tags(self, steps)

    def _offsets(self, x: np.ndarray, epoch: np.ndarray, tag: np.ndarray) -> np.ndarray:
        """Robot-to-tag vectors b - mu per slot."""
        shape = self.shape
        tags = x[shape.tag_states].reshape(-1, TAG_STATES)
        if len(tags) == 0:
            return np.zeros((len(epoch), 2))
        return tags[np.maximum(tag, 0)] - positions(x, shape.epochs)[epoch]

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
            pairs=EPOCH_STATES * np.arange(ne)[:, None] + np.arange(2 * EPOCH_STATES),
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
            self.direct = DirectStep(shape) if shape.states <= DIRECT_MAX_STATES else None
        if self.scale:
            self._linearize_wheels(self.epochs, self.x[shape.epoch_states].reshape(-1, EPOCH_STATES)[:, 2:4])
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
        steps = dict(base, g=np.zeros((shape.rows, 2 + 2 * shape.tags)), hinge=np.full(shape.rows, GN_HINGE_WEIGHT))
        result = Update()
        x = self.x.copy()
        weight = np.ones(shape.rows)
        try:
            d = np.maximum(np.linalg.norm(self._offsets(x, epoch, tag), axis=1), s.min_range_m)
            localized = np.zeros(max(shape.tags, 1), bool)
            localized[: len(self.tag_covariance)] = self.observable()
            start = self.finder.starting(localized, len(self.finals) + len(self.epochs), s.window)
            known = not (filled & start[np.maximum(tag, 0)]).any()  # else the last estimate is as good
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
            if not known:  # the convex passes moved x: its candidates again (else as chosen above)
                self._select(x)
                epoch, tag, bearing, std, filled = self._rows()
            residual, jb = self._angles(x, epoch, tag, bearing, std, filled)
            cost = self._cost(model, x, residual[filled])
            if not known:  # the Gauss-Newton steps start from the better of the two
                res_p, jb_p = self._angles(self.x, epoch, tag, bearing, std, filled)
                cost_p = self._cost(model, self.x, res_p[filled])
                if cost_p < cost:
                    x, residual, jb, cost = self.x.copy(), res_p, jb_p, cost_p
            for _ in range(s.refine_iterations):
                step = UpdateData(**steps, a=self._slot_coefficients(jb, tag), offset=residual)
                trial, iterations = (self.direct and self.direct.solve(step)) or self.program.solve(step)
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
        localized = np.zeros(len(self.tag_ids), bool)
        localized[: len(self.tag_covariance)] = self.observable()
        for t in disagreeing(self.disagreement, tags, active, localized, s.reset_updates):
            self.prior = self._prior.relaxed(prior_tag(t), s.reset_factor)
            self.resets += 1
            self.finder.reexamined(t, len(self.finals) + len(self.epochs))

    def _covariances(self, epoch, tag, residual, jb, filled) -> None:
        """The tags' and shared states' covariances from the Gauss-Newton information at the estimate
        (Huber rows IRLS-weighted)."""
        s = self.settings
        w = np.where(filled, huber_weight(residual, s.huber_sigma), 0.0)
        coeff = self._slot_coefficients(jb, tag) * np.sqrt(w)[:, None]
        info = window_information(self.shape, self._prior.info, self.edges, self.epochs, epoch, coeff)
        self.tag_covariance, self.bias_covariance, self.position_covariance = covariances(info, self.shape)
        xy = positions(self.x, len(self.epochs))
        for t, cov in enumerate(self.tag_covariance):
            if self.active[t]:
                seen_from = xy[epoch[filled & (tag == t)]]
                k = self.integrity.judge(t, self.x[self.shape.tag(t)], cov, seen_from, s.huber_sigma, s.aoa_std_scale)
                if k != 1.0:  # what its bearings told the prior counts as they now do
                    self.prior = self._prior.relaxed(prior_tag(t), 1.0 / k)

    def observable(self) -> np.ndarray:
        """Per tag: localized well enough to report (largest std below `observable_std_m`); worked
        out once per covariance."""
        if self.judged is not None and self.judged[0] is self.tag_covariance:
            return self.judged[1].copy()
        result = largest_std_m(self.tag_covariance) <= self.settings.observable_std_m
        self.judged = (self.tag_covariance, result)
        return result.copy()

    # -- marginalization ------------------------------------------------------------------------

    def _marginalize_oldest(self) -> None:
        """Fold the oldest epoch into the prior (marginalization.marginalize_oldest); its bearings'
        free choices teach the tags' jump memory; it leaves the window as final."""
        old, edge = self.epochs[0], self.edges[0]
        x = self.x
        own = x[prior_indices(self.shape)]
        use = np.array([self.active[t] for t in old.tags], bool)
        for j in np.flatnonzero(use):
            jump = int(old.candidate_jumps[j, old.choice[j]])
            if jump >= 0:
                self.jumps.learn(int(old.tags[j]), jump)
            self.integrity.add(int(old.tags[j]), x[0:2], old.candidates[j, old.choice[j]], old.std[j])
        std = old.std[use] * self.integrity.std_factor(old.tags[use])
        leaving = Leaving(old.velocity_info, old.velocity_linear, old.tags[use], old.bearing[use], std)
        self.prior = marginalize_oldest(self._prior, own, leaving, edge, self.settings, self.accel_biases, self.scale)
        self.finals.append((old.stamp_ns, float(x[0]), float(x[1]), old.yaw))
        self.finder.final_xy[old.stamp_ns] = x[0:2].copy()
        self.left.append(old)
        self.epochs.pop(0)
        self.edges.pop(0)
        self.x = x[EPOCH_STATES:].copy()
