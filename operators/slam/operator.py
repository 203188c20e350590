"""`slam`: the convex sliding-window AoA-IMU SLAM (the paper's Section III), re-solved every epoch.

An epoch is the stamp of an AoA burst for which the preintegration emitted the motion since the
previous one; the AoAs sharing that stamp are its bearings. Each epoch appends to the window
(rover.operators.slam.sliding_window), which is re-solved with Clarabel and refined; the oldest epoch then
leaves the window as final. Outputs: the live pose at every epoch, each epoch's final pose as it
leaves the window, the path now and then, the tags with their covariance, and solver diagnostics.
"""

from __future__ import annotations

import copy
import logging
import math
import time
from dataclasses import dataclass
from typing import Annotated, Any

import numpy as np

from rover.geometry import quaternion_from_yaw, yaw_from_quaternion
from rover.messages import header, make
from rover.operator import Emit, In, Operator, Out
from rover.operators.slam.information import largest_std_m
from rover.operators.slam.sliding_window import Edge, Epoch, SlidingWindow, WindowSettings, bias_jacobian
from rover.operators.slam.tag_status import TagState, TagStatus, tag_status
from rover.pipeline.params import PositiveFloat, Range

log = logging.getLogger("rover.slam")

PREINTEGRATION_XY = [3, 4, 6, 7]
"""velocity x/y and position x/y in the Preintegration covariance's [rotation, velocity, position]"""
YAW_VARIANCE = 2 * 9 + 2
"""the rotation about z's variance in the Preintegration covariance (row-major 9x9)"""
DELTA_XY = [0, 1, 3, 4]
"""velocity x/y and position x/y in its accel_bias_jacobian's rows [velocity, position]"""
COVARIANCE_FLOOR = 1e-12
"""smallest eigenvalue kept in an odometry covariance (m^2, (m/s)^2): keeps it positive definite"""
BATCH_PASSES = 3
"""convex passes and Gauss-Newton steps at least, in batch mode's single solve"""
SEARCH_STEPS_PER_EPOCH = 4
"""tag search steps each epoch takes after its update at most (a step scores a chunk of hypotheses
or refines one: a chunk of 65,536 residuals took 4-6 ms alone on the project's machine, four steps
up to 24 ms, and 20-50 ms on a live three-host laptop): a search starts and ends at the same epochs
on any machine, whatever its work. The steps are computed ahead while the operator waits for its
next input (`on_idle`, steps_ahead.py), so an epoch does only those not done yet"""


@dataclass(frozen=True)
class SlamParams(WindowSettings):
    batch: bool = False
    """solve the whole run at once at its end (a reference for the sliding window), no live output,
    with the program's CVXPY specification (operators/slam/window_model.py)"""
    path_every_s: PositiveFloat = 10.0
    """event time between path messages (the last one, at the end, is complete)"""
    path_max_poses: Annotated[int, Range(ge=100)] = 2000
    """poses in a path message before the end at most: the final ones evenly thinned out, the
    window's all (a path is for display; `trajectory` has every pose). Bounds the work of each
    path: its serialization grows with the run (53 ms at 3000 poses, measured)"""
    wheel: bool = True
    """fuse the wheel odometry when the input is wired and carries data"""
    bearings: bool = True
    """fuse the tags' AoAs (false: the robot from its odometry alone, the AoAs still setting the
    epochs and going out on `bearings` as not used: what the bearings add, measured)"""
    wheel_max_age_s: PositiveFloat = 0.2
    """a wheel speed older than this at an epoch is not used"""


def yaw_of(q: Any) -> float:
    """Yaw (rad) of a geometry_msgs/Quaternion."""
    return float(yaw_from_quaternion(q.x, q.y, q.z, q.w))


def pose_message(stamp: int, x: float, y: float, yaw: float) -> Any:
    position = make("geometry_msgs/msg/Point", x=x, y=y, z=0.0)
    qx, qy, qz, qw = (float(v) for v in quaternion_from_yaw(yaw))
    orientation = make("geometry_msgs/msg/Quaternion", x=qx, y=qy, z=qz, w=qw)
    return make(
        "geometry_msgs/msg/PoseStamped",
        header=header(stamp, "world"),
        pose=make("geometry_msgs/msg/Pose", position=position, orientation=orientation),
    )


def candidates_of(msg: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An Aoa message's candidate angles, stds and jump combinations (its single angle when it has none)."""
    if len(msg.candidate_angles_rad):
        return (
            np.asarray(msg.candidate_angles_rad, float),
            np.asarray(msg.candidate_stds_rad, float),
            np.asarray(msg.candidate_jumps, int),
        )
    return np.array([msg.angle_rad]), np.array([msg.std_rad]), np.array([-1])


def edge_of(msg: Any, bias_states: bool) -> Edge:
    """The x/y odometry of a Preintegration message. With `bias_states` the window estimates the
    accelerometer bias: the edge then carries how its deltas move with the body-frame and the
    world-frame bias, and the covariance the preintegration added for an unknown bias is taken out."""
    delta = np.array([msg.delta_velocity.x, msg.delta_velocity.y, msg.delta_position.x, msg.delta_position.y])
    cov = np.asarray(msg.covariance, float).reshape(9, 9)[np.ix_(PREINTEGRATION_XY, PREINTEGRATION_XY)]
    bias = np.zeros((4, 0))
    if bias_states:
        body = np.asarray(msg.accel_bias_jacobian, float).reshape(6, 3)[DELTA_XY]
        cov = cov - msg.accel_bias_std**2 * body @ body.T
        bias = bias_jacobian(yaw_of(msg.orientation_start), yaw_of(msg.orientation), float(msg.dt))
        if body.any():  # the preintegration's own (a producer that does not say leaves the estimate)
            bias[:, 0:2] = body[:, 0:2]
    values, vectors = np.linalg.eigh(0.5 * (cov + cov.T))
    cov = (vectors * np.maximum(values, COVARIANCE_FLOOR)) @ vectors.T
    return Edge(float(msg.dt), delta, cov, bias)


class Slam(Operator):
    """Robot and tag positions from AoAs and preintegrated IMU motion."""

    cpu_weight = 8.8

    inputs = {
        "aoa": In("rover_msgs/msg/Aoa"),
        "odometry": In("rover_msgs/msg/Preintegration"),
        "wheel": In(
            "nav_msgs/msg/Odometry",
            required=False,
            doc="wheel odometry: forward speed and no sideways motion (fused when `wheel` is on)",
        ),
    }
    outputs = {
        "pose": Out("geometry_msgs/msg/PoseStamped", doc="the newest epoch's pose, as estimated at its own time"),
        "pose_covariance": Out(
            "geometry_msgs/msg/PoseWithCovarianceStamped",
            doc="the same pose with its covariance: x and y from the window; yaw from the gyro integration the "
            "odometry states (the window has no yaw state); z, roll and pitch left at 0 (a planar estimate)",
        ),
        "trajectory": Out("geometry_msgs/msg/PoseStamped", doc="each epoch's final pose, when it leaves the window"),
        "path": Out(
            "nav_msgs/msg/Path",
            doc="the best path so far (final poses, thinned to path_max_poses but at the end, then the window)",
        ),
        "tags": Out("rover_msgs/msg/TagArray", doc="every tag heard, with its 2x2 covariance"),
        "status": Out(
            "rover_msgs/msg/TagStatus",
            doc="a tag's state and why (heard, ambiguous, judging, contradicted, uncertain, localized) when it "
            "changes, just before the tags that show it, and every tag's at the end",
        ),
        "diagnostics": Out("rover_msgs/msg/SlamDiagnostics"),
        "timing": Out("rover_msgs/msg/Timing", doc="wall-clock time of each update, every reweighting pass included"),
        "bearings": Out(
            "rover_msgs/msg/Aoa",
            doc="each AoA as its epoch leaves the window, with the candidate used (`chosen`; -1: tag not yet found)",
        ),
    }
    Params = SlamParams

    def __init__(self, params: SlamParams | None = None):
        super().__init__(params)
        settings = {f: getattr(self.params, f) for f in WindowSettings.__dataclass_fields__}
        if self.params.batch:
            settings["window"] = 2**31
            settings["reweight_passes"] = max(self.params.reweight_passes, BATCH_PASSES)
            settings["refine_iterations"] = max(self.params.refine_iterations, BATCH_PASSES)
        settings["wheel_scale"] = self.params.wheel_scale and self.params.wheel  # nothing to scale without
        self.window = SlidingWindow(WindowSettings(**settings))
        if self.params.batch:  # one solve of the whole run: the CVXPY model, the program as specified
            from rover.operators.slam.window_model import WindowModel  # cvxpy only when asked for

            self.window.program_type = WindowModel
        self.pending: dict[int, list[Any]] = {}
        self.unused: list[Any] = []
        """AoAs taken at an epoch but not fused (`bearings` false), to send as not used"""
        self.channels: dict[int, int] = {}
        self.final_poses: list[Any] = []
        """the trajectory's final poses as sent, in order (the path reuses them)"""
        self.last_path_ns: int | None = None
        self.speed: tuple[int, float] | None = None
        self.updates = 0
        self.failures = 0
        self.unchained = 0
        self.found_sent = 0
        self.status_sent: dict[int, TagStatus] = {}
        """per tag id: the status last sent"""
        self.yaw_variance = 0.0
        """the heading's variance (rad^2) since the first epoch, summed from the odometry increments"""

    def on_input(self, port: str, msg: Any, stamp_ns: int):
        if port == "aoa":
            self._bearing(msg, stamp_ns)
            return
        if port == "wheel":
            speed = msg.twist.twist.linear.x
            if math.isfinite(speed):
                self.speed = (stamp_ns, speed)
            else:
                self.drop("wheel odometry messages with a non-finite speed")
            return
        yield from self._odometry(msg, stamp_ns)

    def has_idle_work(self) -> bool:
        searching = self.window.finder.searching
        return searching is not None and searching.steps.pending

    def on_idle(self):
        """Compute a step of the tag search under way ahead of the epoch that takes it (StepsAhead)."""
        searching = self.window.finder.searching
        if searching is not None:
            searching.steps.ahead()
        return ()

    def _bearing(self, msg: Any, stamp: int) -> None:
        if not len(msg.candidate_angles_rad) == len(msg.candidate_stds_rad) == len(msg.candidate_jumps):
            self.drop("AoAs whose candidate arrays differ in length")
            return
        angles, stds, _ = candidates_of(msg)
        if not (np.isfinite(angles).all() and np.isfinite(stds).all() and (stds > 0).all()):
            self.drop("AoAs with a non-finite angle or std")
            return
        self.channels[msg.tag_id] = msg.channel
        self.pending.setdefault(stamp, []).append(msg)

    def _take(self, stamp: int) -> dict[str, Any]:
        """The AoAs at this epoch as add_epoch's arguments; older ones that never became an epoch are
        counted as dropped."""
        late = [s for s in self.pending if s < stamp]
        for s in late:
            self.drop("AoAs without an IMU epoch", len(self.pending.pop(s)))
        msgs = self.pending.pop(stamp, [])
        if not self.params.bearings:  # not fused: they go out as bearings not used (`chosen` -1)
            self.unused += msgs
            msgs = []
        rows = [candidates_of(m) for m in msgs]
        width = max((len(a) for a, _, _ in rows), default=1)

        def padded(i: int, pad: float) -> np.ndarray:
            return np.array([np.pad(r[i], (0, width - len(r[i])), constant_values=pad) for r in rows]).reshape(
                -1, width
            )

        return dict(
            tag_ids=[m.tag_id for m in msgs],
            angles_rad=padded(0, np.nan),
            stds_rad=padded(1, 1.0),
            jumps=padded(2, -1).astype(int),
            messages=msgs,
        )

    def _odometry(self, msg: Any, stamp: int):
        start = msg.start.sec * 1_000_000_000 + msg.start.nanosec
        w = self.window
        if not w.epochs and not w.finals:
            w.add_epoch(
                start,
                yaw_of(msg.orientation_start),
                edge=None,
                levelled_std_m_s2=float(msg.levelling_std),
                **self._take(start),
            )
        elif w.epochs and start != w.epochs[-1].stamp_ns:
            self.unchained += 1
        if msg.dt <= 0 or not np.isfinite(np.asarray(msg.covariance)).all():
            self.drop("odometry increments with no duration or a non-finite covariance")
            return
        self.yaw_variance += float(msg.covariance[YAW_VARIANCE])
        w.add_epoch(
            stamp,
            yaw_of(msg.orientation),
            edge=edge_of(msg, self.params.accel_bias),
            turning_in_place=bool(msg.turning_in_place),
            speed_m_s=self._speed_at(stamp),
            **self._take(stamp),
        )
        if self.params.batch:
            return
        yield from self._finals(stamp)
        yield from self._update(stamp)
        if self.last_path_ns is None or stamp - self.last_path_ns >= self.params.path_every_s * 1e9:
            self.last_path_ns = stamp
            yield Emit("path", self._path(stamp), stamp)
        yield from self._find_tags(stamp)

    def _find_tags(self, stamp: int):
        """A few tag search steps after this epoch's outputs are out (its pose need not wait for them);
        its timing is of those not computed ahead in idle time."""
        started = time.perf_counter()
        if self.window.find_tags(steps=SEARCH_STEPS_PER_EPOCH):
            wall_s = time.perf_counter() - started
            yield Emit(
                "timing",
                make("rover_msgs/msg/Timing", header=header(stamp, "world"), stage="slam.search", wall_s=wall_s),
                stamp,
            )

    def _speed_at(self, stamp: int) -> float | None:
        if not self.params.wheel or self.speed is None:
            return None
        return self.speed[1] if stamp - self.speed[0] <= self.params.wheel_max_age_s * 1e9 else None

    def _update(self, stamp: int):
        w = self.window
        started = time.perf_counter()
        result = w.update()
        elapsed = time.perf_counter() - started
        self.updates += 1
        if result.failed:
            self.failures += 1
            log.debug("%s at %.3f s", result.failed, stamp / 1e9)
        newest = w.epochs[-1]
        x, y = w.x[w.shape.position(len(w.epochs) - 1)]
        pose = pose_message(newest.stamp_ns, float(x), float(y), newest.yaw)
        yield Emit("pose", pose, stamp)
        covariance = np.zeros((6, 6))
        covariance[:2, :2] = 0.5 * (w.position_covariance + w.position_covariance.T)
        covariance[5, 5] = self.yaw_variance
        with_covariance = make("geometry_msgs/msg/PoseWithCovarianceStamped", header=pose.header)
        with_covariance.pose.pose, with_covariance.pose.covariance = pose.pose, covariance.ravel()
        yield Emit("pose_covariance", with_covariance, stamp)
        covariance, localized = self._published()
        yield from self._statuses(stamp, covariance, localized, changed=lambda old, new: old.state != new.state)
        yield Emit("tags", self._tags(stamp, covariance, localized), stamp)
        yield Emit(
            "diagnostics",
            make(
                "rover_msgs/msg/SlamDiagnostics",
                header=header(stamp, "world"),
                iterations=result.iterations,
                window_epochs=len(w.epochs),
                tags=len(w.tag_ids),
                huber_active_rows=result.huber_active,
            ),
            stamp,
        )
        timing = make("rover_msgs/msg/Timing", header=header(stamp, "world"), stage="slam.update", wall_s=elapsed)
        yield Emit("timing", timing, stamp)

    def _finals(self, stamp: int):
        """Poses that left the window since the last call, and their AoAs with the candidate used,
        stamped now on the wire."""
        for s, x, y, yaw in self.window.finals[len(self.final_poses) :]:
            pose = pose_message(s, x, y, yaw)
            self.final_poses.append(pose)
            yield Emit("trajectory", pose, stamp)
        for t, found in self.window.finder.found[self.found_sent :]:
            if found.combination >= 0:
                held = f"jump combination {found.combination} all along"
            elif math.isinf(found.redraw_rate):
                held = "a jump combination drawn per bearing"
            else:
                held = f"jump steps, of the order of {found.redraw_rate * 60:g} a minute"
            log.info(
                "slam: tag %d found at (%.2f, %.2f) m (%s): %.0f%% of its bearings agree, seen over %.0f deg, "
                "margin %.0f",
                t,
                *found.position,
                held,
                100 * found.inliers,
                found.parallax_deg,
                found.margin,
            )
        self.found_sent = len(self.window.finder.found)
        for epoch in self.window.left:
            yield from self._bearings(epoch, stamp)
        self.window.left.clear()
        for msg in self.unused:
            out = copy.copy(msg)
            out.chosen = -1
            yield Emit("bearings", out, stamp)
        self.unused.clear()

    def _bearings(self, epoch: Epoch, stamp: int):
        active = self.window.active
        for j, msg in enumerate(epoch.messages):
            used = bool(active[epoch.tags[j]])
            angles, stds, _ = candidates_of(msg)
            choice = int(epoch.choice[j]) if used else -1
            out = copy.copy(msg)
            if choice >= 0:  # the std widened by the other candidates' chances: a doubtful choice says so
                out.angle_rad = float(angles[choice])
                out.std_rad = float(min(math.sqrt(stds[choice] ** 2 + epoch.doubt[j]), math.pi))
            out.chosen = choice
            yield Emit("bearings", out, stamp)

    def _published(self) -> tuple[np.ndarray, np.ndarray]:
        """The tags' covariances as published and whether each is localized: the window's scaled up by
        the integrity check (integrity.TagIntegrity) plus `source_std_m` in every direction, localized
        once it has a verdict and its largest
        std is within `observable_std_m`; the window itself goes on with its own."""
        w = self.window
        covariance = w.integrity.scaled(w.tag_covariance, w.settings.source_std_m)
        judged = np.array([w.integrity.verdict(t) is None for t in range(len(covariance))], bool)
        return covariance, judged & (largest_std_m(covariance) <= w.settings.observable_std_m)

    def _statuses(self, stamp: int, covariance: np.ndarray, localized: np.ndarray, changed: Any):
        """Each tag's status where `changed(last sent, now)` says so, or none was sent yet."""
        for slot, tag_id in enumerate(self.window.tag_ids):
            status = tag_status(self.window, slot, covariance[slot], bool(localized[slot]))
            last = self.status_sent.get(tag_id)
            if last is None or changed(last, status):
                self.status_sent[tag_id] = status
                msg = make(
                    "rover_msgs/msg/TagStatus",
                    header=header(stamp, "world"),
                    id=tag_id,
                    state=int(status.state),
                    reason=status.reason,
                )
                yield Emit("status", msg, stamp)

    def _tags(self, stamp: int, covariance: np.ndarray, observable: np.ndarray) -> Any:
        w = self.window
        tags = []
        for i, (tag_id, (x, y)) in enumerate(zip(w.tag_ids, w.tag_positions(), strict=True)):
            cov = np.nan_to_num(covariance[i], nan=1e12, posinf=1e12)
            tags.append(
                make(
                    "rover_msgs/msg/Tag",
                    id=tag_id,
                    channel=self.channels.get(tag_id, 0),
                    position=make("geometry_msgs/msg/Point", x=float(x), y=float(y), z=0.0),
                    covariance_xy=cov.ravel().astype(np.float64),
                    observable=bool(observable[i]),
                )
            )
        return make("rover_msgs/msg/TagArray", header=header(stamp, "world"), tags=tags)

    def _path(self, stamp: int, complete: bool = False) -> Any:
        """The trajectory: the final poses as sent (made once; unless `complete`, evenly thinned out
        to `path_max_poses` with the window's), then the window's."""
        finals = [*self.final_poses, *(pose_message(*p) for p in self.window.finals[len(self.final_poses) :])]
        window = [pose_message(*p) for p in self.window.poses()]
        room = max(self.params.path_max_poses - len(window), 2)
        if not complete and len(finals) > room:
            finals = [finals[i] for i in np.unique(np.linspace(0, len(finals) - 1, room).round().astype(int))]
        return make("nav_msgs/msg/Path", header=header(stamp, "world"), poses=finals + window)

    def on_end(self):
        w = self.window
        if not w.epochs:
            log.warning("slam: no epoch to estimate (no odometry arrived)")
            return
        stamp = w.epochs[-1].stamp_ns
        if self.params.batch:
            # the robot positions the tag search triangulates from are the solved ones, not dead
            # reckoning: solve once, search for every tag, then the update proper
            w.update()
            w.find_tags()
            yield from self._update(stamp)
        yield Emit("path", self._path(stamp, complete=True), stamp)
        published, localized = self._published()
        yield from self._statuses(stamp, published, localized, changed=lambda old, new: old != new)
        yield Emit("tags", self._tags(stamp, published, localized), stamp)
        w.finals.extend(w.poses())
        w.left.extend(w.epochs)
        yield from self._finals(stamp)
        if self.pending:
            self.drop("AoAs after the last IMU epoch", sum(len(v) for v in self.pending.values()))
        if self.params.wheel and self.speed is None:
            log.warning(
                "slam: no wheel odometry arrived: the speed came from the IMU and the bearings alone "
                "(set slam.wheel=false when that is intended; docs/benchmarks.md gives the accuracy of both)"
            )
        std = np.sqrt(np.maximum(np.diag(w.bias_covariance), 0.0)) if w.bias_covariance.size else np.full(5, np.inf)
        if w.scale and self.speed is not None:
            log.info("slam: wheel odometry scale error %+.2f%% +- %.2f%%", 100 * w.wheel_scale(), 100 * std[-1])
        if w.accel_biases:
            mg = 1e3 / 9.80665
            bias = w.bias()
            log.info(
                "slam: accelerometer bias left by the preintegration: body (%.2f, %.2f) +- (%.2f, %.2f) mg, "
                "world (%.2f, %.2f) +- (%.2f, %.2f) mg",
                *(bias[0:2] * mg),
                *(std[0:2] * mg),
                *(bias[2:4] * mg),
                *(std[2:4] * mg),
            )
        if self.unchained:
            log.warning(
                "slam: %d odometry increment(s) did not start at the previous epoch (chained anyway)", self.unchained
            )
        for slot, tag_id in enumerate(w.tag_ids):
            combination = w.locked(slot)
            if combination is not None:
                log.info("slam: tag %d's chains held jump combination %d all run", tag_id, combination)
            status = self.status_sent[tag_id]
            if status.state != TagState.LOCALIZED:
                state = status.state.name.lower()
                log.warning("slam: tag %d not localized at the end (%s): %s", tag_id, state, status.reason)
        if self.failures:
            log.warning(
                "slam: %d of %d updates did not converge (kept the previous estimate)", self.failures, self.updates
            )
