"""`preintegration`: the IMU's motion between consecutive AoA epochs, for the SLAM's odometry rows.

On-manifold preintegration (Forster et al., RSS 2015; Lupton and Sukkarieh, 2012): between two
epochs the gyro's rotation increments are composed and the specific force rotated into the first
epoch's body frame and integrated, while the 9x9 covariance of [rotation, velocity, position] is
propagated from the sensor noise densities. The attitude comes from the gyro, started level from
the stationary start's gravity direction, with the gyro bias estimated there too; the increments
are then expressed in that gravity-aligned frame with gravity removed, which keeps the SLAM's
odometry rows linear in positions and velocities.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rover.formats.rig import RigInput
from rover.geometry import exp_so3_batch, quaternion_from_matrix, rpy_matrix, skew_batch
from rover.messages import header, make
from rover.operator import Emit, In, Operator, Out
from rover.operators.preintegration.gyro_bias import BiasModel, GyroBias
from rover.operators.preintegration.noise_floor import NoiseFloor
from rover.operators.preintegration.scan import prefix_products, propagated
from rover.pipeline.params import Checked, NonNegativeFloat, PositiveFloat

log = logging.getLogger("rover.preintegration")


@dataclass(frozen=True)
class PreintegrationParams(Checked):
    gyro_noise_rad_s_rthz: PositiveFloat = math.radians(0.005)
    """gyro white-noise density (MicroStrain 3DM-GX4-45 datasheet): the least the odometry's
    covariance uses; the noise its samples show while the robot drives counts when larger
    (noise_floor.py: a real Jackal's gyro read 10-50 times its datasheet)"""
    accel_noise_m_s2_rthz: PositiveFloat = 100e-6 * 9.80665
    """accelerometer white-noise density (same datasheet), the least used, as the gyro's"""
    stationary_s: NonNegativeFloat = 1.0
    """how much still time at the start is used for the gyro bias and gravity"""
    still_gyro_rad_s: PositiveFloat = 0.02
    """largest gyro spread (std, rad/s) that still counts as standing still"""
    gap_factor: PositiveFloat = 5.0
    """a sample interval this many times the nominal one is a gap (logged; integrated across)"""
    accel_bias_m_s2: NonNegativeFloat = 2e-3 * 9.80665
    """accelerometer bias left unknown (1 sigma): a drift the noise densities alone do not show"""
    gyro_bias_rad_s: NonNegativeFloat = math.radians(0.005)
    """gyro bias left after the stationary estimate (1 sigma): the least the increments carry"""
    track_gyro_bias: bool = True
    """re-estimate the gyro bias on every span in which the gyro holds still (gyro_bias.py): a
    bias that drifts after the start (a consumer IMU warming up) otherwise turns the heading"""
    gyro_bias_walk_rad_s_rts: PositiveFloat = math.radians(0.001)
    """the tracked bias's own random walk (1 sigma per root second; the 3DM-GX4-45's is 0.0005)"""
    gyro_bias_rate_rad_s2: NonNegativeFloat = math.radians(0.005)
    """how fast the bias may be moving at the start (1 sigma): a consumer IMU's warm-up moves it by
    0.3 deg/s with a time constant of a minute or more"""
    gyro_bias_rate_walk_rad_s2_rts: PositiveFloat = math.radians(1e-4)
    """how fast the bias's rate of change may change (1 sigma per root second): a consumer IMU's
    warm-up (0.3-1 deg/s over minutes) is followed; a bias that turns faster falls out of the gate"""
    quiet_span_s: PositiveFloat = 0.5
    """the gyro is judged still or not over spans this long"""
    quiet_factor: PositiveFloat = 2.0
    """a span is still when each axis's gyro spread is at most this times the still start's"""
    planar: bool = True
    """the robot moves on a level floor: it turns only about the vertical it was levelled to at the
    start, so the gyro's roll and pitch rates are left out (their bias left after the still start,
    about 0.005 deg/s, would otherwise tilt gravity into the motion: 1.7 mg after 20 s, metres of
    drift within a minute). Off for a platform that tilts (a drone, a handheld)"""
    turn_in_place_rad_s: PositiveFloat = 0.3
    """an interval turning at least this fast (mean yaw rate) ..."""
    still_speed_m_s: PositiveFloat = 0.05
    """... whose horizontal specific force (body frame, levelled at the start) implies at most this
    speed (centripetal force / yaw rate) is flagged a turn in place: a robot arcing at speed feels
    v * yaw rate sideways, one turning on the spot nothing (an IMU off the turning axis feels
    yaw rate^2 * lever arm, which makes such a turn look like an arc: missed, never invented)"""


@dataclass
class _Increment:
    """The running preintegration since the last epoch, in that epoch's body frame."""

    rotation: np.ndarray
    velocity: np.ndarray
    position: np.ndarray
    covariance: np.ndarray
    bias_velocity: np.ndarray
    """d(velocity)/d(accelerometer bias)"""
    bias_position: np.ndarray
    """d(position)/d(accelerometer bias)"""
    dt: float = 0.0
    samples: int = 0
    yaw: float = 0.0
    """the integral of the yaw rate (rad)"""
    force: np.ndarray = field(default_factory=lambda: np.zeros(2))
    """the integral of the horizontal specific force in the levelled body frame (m/s)"""

    @classmethod
    def zero(cls) -> _Increment:
        return cls(np.eye(3), np.zeros(3), np.zeros(3), np.zeros((9, 9)), np.zeros((3, 3)), np.zeros((3, 3)))

    def turning_in_place(self, min_rate_rad_s: float, max_speed_m_s: float) -> bool:
        """Turning at least `min_rate_rad_s` on average with a sideways force implying at most
        `max_speed_m_s` (see PreintegrationParams.still_speed_m_s)."""
        if self.dt <= 0:
            return False
        rate = abs(self.yaw) / self.dt
        return rate >= min_rate_rad_s and float(np.linalg.norm(self.force)) / self.dt <= max_speed_m_s * rate

    def with_biases(self, accel_bias: float, gyro_bias: float) -> np.ndarray:
        """The covariance including the unknown biases, which act coherently over the interval."""
        jacobian = np.zeros((9, 6))
        jacobian[0:3, 3:6] = np.eye(3) * self.dt
        jacobian[3:6, 0:3] = self.bias_velocity
        jacobian[6:9, 0:3] = self.bias_position
        biases = np.diag([accel_bias**2] * 3 + [gyro_bias**2] * 3)
        return self.covariance + jacobian @ biases @ jacobian.T


class Preintegration(Operator):
    """Emits one Preintegration per AoA epoch (AoAs sharing a stamp are one epoch)."""

    cpu_weight = 1.7

    inputs = {
        "imu": In("sensor_msgs/msg/Imu"),
        "epochs": In("rover_msgs/msg/Aoa"),
        "setup": In(
            "rover_msgs/msg/RigSetup", required=False, doc="for the IMU mounting rotation; identity without it"
        ),
    }
    outputs = {"odometry": Out("rover_msgs/msg/Preintegration")}
    Params = PreintegrationParams

    def __init__(self, params: PreintegrationParams | None = None):
        super().__init__(params)
        self.mount = np.eye(3)
        self.still: list[tuple[int, np.ndarray, np.ndarray]] = []
        self.bias = np.zeros(3)
        self.gravity = np.array([0.0, 0.0, -9.80665])
        self.attitude: np.ndarray | None = None
        self.last: tuple[int, np.ndarray, np.ndarray] | None = None
        self.nominal_dt: float | None = None
        self.increment = _Increment.zero()
        self.epoch_attitude: np.ndarray | None = None
        self.epoch_ns: int | None = None
        self.pending: list[tuple[int, np.ndarray, np.ndarray, int]] = []
        self.setup = RigInput()
        self.gaps = 0
        self.level = np.eye(3)
        """the body frame levelled at the start (roll and pitch): turns in place are judged there"""
        self.levelling_std = 0.0
        """the specific force levelling left at the start heading (1 sigma; 0: not levelled on a still start)"""
        self.turns = 0
        self.tracker: GyroBias | None = None
        """the gyro bias re-estimated on quiet spans (None: no still start to measure the quiet by)"""
        self.noise: NoiseFloor | None = None
        """the IMU's white noise measured on its latest samples (noise_floor.py), once levelled"""

    def on_input(self, port: str, msg: Any, stamp_ns: int):
        if port == "setup":
            self._mounting(msg)
        elif port == "imu":
            self._imu(msg, stamp_ns)
        else:
            yield from self._epoch(stamp_ns)

    def _mounting(self, msg: Any) -> None:
        rig = self.setup.update(msg)
        self.mount = rpy_matrix(*np.radians(rig.imu.rotation_rpy_deg))

    def _imu(self, msg: Any, stamp: int) -> None:
        w = self.mount @ np.array([msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z])
        f = self.mount @ np.array([msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z])
        if not (np.isfinite(w).all() and np.isfinite(f).all()):
            self.drop("IMU samples that are not finite")
            return
        if self.last is not None and stamp <= self.last[0]:
            self.drop("duplicate IMU samples" if stamp == self.last[0] else "IMU samples out of order")
            return
        if self.attitude is None:
            self._initialize(stamp, w, f)
            return
        assert self.last is not None, "set with the attitude"
        self.pending.append((*self.last, stamp))
        self.last = (stamp, w, f)
        if self.tracker is not None:
            self.tracker.add(stamp, w)

    def _initialize(self, stamp: int, w: np.ndarray, f: np.ndarray) -> None:
        """Collect the stationary start; then estimate gyro bias and gravity and start integrating."""
        self.still.append((stamp, w, f))
        span_s = (stamp - self.still[0][0]) / 1e9
        gyro = np.array([s[1] for s in self.still])
        moving = len(self.still) > 10 and gyro.std(axis=0).max() > self.params.still_gyro_rad_s
        if span_s < self.params.stationary_s and not moving:
            return
        accel = np.array([s[2] for s in self.still])
        mean_f = accel.mean(axis=0)
        if moving:
            log.warning(
                "preintegration: the run does not start with %.1f s standing still: gyro bias taken as "
                "zero and the IMU as level",
                self.params.stationary_s,
            )
            mean_f = np.array([0.0, 0.0, np.linalg.norm(mean_f)])
        else:
            self.bias = gyro.mean(axis=0)
            self.levelling_std = self.params.accel_noise_m_s2_rthz / math.sqrt(max(span_s, 1e-3))
            log.info(
                "preintegration: gyro bias %s rad/s and gravity %.3f m/s^2 from %.1f s standing still",
                np.array2string(self.bias, precision=5),
                np.linalg.norm(mean_f),
                span_s,
            )
        roll = math.atan2(mean_f[1], mean_f[2])
        pitch = math.atan2(-mean_f[0], math.hypot(mean_f[1], mean_f[2]))
        self.attitude = rpy_matrix(roll, pitch, 0.0)
        self.level = self.attitude.copy()
        self.gravity = np.array([0.0, 0.0, -float(np.linalg.norm(mean_f))])
        dts = np.diff([s[0] for s in self.still]) / 1e9
        self.nominal_dt = float(np.median(dts)) if len(dts) else None
        if self.nominal_dt:
            self.noise = NoiseFloor.for_rate(self.level, self.nominal_dt)
        if not moving:
            self._track(gyro, stamp)
        self.epoch_attitude = self.attitude.copy()
        self.pending = [(*a, b[0]) for a, b in zip(self.still[:-1], self.still[1:], strict=True)]
        self.last = self.still[-1]
        self.still = []

    def _track(self, gyro: np.ndarray, stamp: int) -> None:
        """Start tracking the gyro bias from the still start's samples (N, 3)."""
        if not self.params.track_gyro_bias or not self.nominal_dt:
            return
        p = self.params
        dt_s = self.nominal_dt
        model = BiasModel(
            p.gyro_bias_walk_rad_s_rts,
            p.gyro_bias_rate_walk_rad_s2_rts,
            p.gyro_bias_rate_rad_s2,
            p.quiet_factor,
            block=max(2, round(p.quiet_span_s / dt_s)),
            noise_rad_s=p.gyro_noise_rad_s_rthz / math.sqrt(dt_s),
        )
        self.tracker = GyroBias.from_still_start(gyro, stamp, model)

    def gyro_bias_std(self, stamp: int) -> float:
        """The gyro bias left unknown at `stamp` (rad/s) about the vertical (planar) or the worst
        axis: at least gyro_bias_rad_s."""
        if self.tracker is None:
            return self.params.gyro_bias_rad_s
        variance = self.tracker.bias_variance(stamp)
        worst = float(variance @ self.level[2] ** 2) if self.params.planar else float(variance.max())
        return max(self.params.gyro_bias_rad_s, math.sqrt(worst))

    def _integrate(self, intervals: list[tuple[int, np.ndarray, np.ndarray, int]]) -> None:
        """Advance the increment over samples each held from its stamp to the next, all at once."""
        if not intervals:
            return
        starts = np.array([i[0] for i in intervals], dtype=np.int64)
        ends = np.array([i[3] for i in intervals], dtype=np.int64)
        raw = np.array([i[1] for i in intervals])
        f = np.array([i[2] for i in intervals])
        densities = (self.params.gyro_noise_rad_s_rthz, self.params.accel_noise_m_s2_rthz)
        if self.noise is not None and self.nominal_dt:
            self.noise.add(raw, f)
            densities = self.noise.densities(*densities, self.nominal_dt)
        w = raw - (self.bias if self.tracker is None else self.tracker.at(starts))
        if self.params.planar:  # only the rate about the levelled vertical (see PreintegrationParams.planar)
            up = self.level[2]
            w = np.outer(w @ up, up)
        dt = (ends - starts) / 1e9
        if self.nominal_dt:
            gaps = int(np.sum(dt > self.params.gap_factor * self.nominal_dt))
            if gaps:
                self.gaps += gaps
                log.warning(
                    "preintegration: %d gap(s) in the IMU stream so far (longest now %.3f s)",
                    self.gaps,
                    float(dt.max()),
                )
        inc = self.increment
        steps = exp_so3_batch(w * dt[:, None])
        rotations, current = prefix_products(inc.rotation, steps)
        accel = np.einsum("kij,kj->ki", rotations, f)
        dv = accel * dt[:, None]
        velocity_before = inc.velocity + np.cumsum(dv, axis=0) - dv
        inc.position = inc.position + np.sum(velocity_before * dt[:, None] + 0.5 * accel * dt[:, None] ** 2, axis=0)
        inc.velocity = inc.velocity + dv.sum(axis=0)
        dj = rotations * dt[:, None, None]
        jv_before = inc.bias_velocity + np.cumsum(dj, axis=0) - dj
        inc.bias_position = inc.bias_position + np.sum(
            jv_before * dt[:, None, None] + 0.5 * dj * dt[:, None, None], axis=0
        )
        inc.bias_velocity = inc.bias_velocity + dj.sum(axis=0)
        inc.covariance = self._propagate(inc.covariance, steps, rotations, f, dt, *densities)
        inc.rotation = current
        inc.dt += float(dt.sum())
        inc.samples += len(dt)
        inc.yaw += float(np.sum((w @ self.level[2]) * dt))
        inc.force = inc.force + np.sum((f @ self.level.T)[:, 0:2] * dt[:, None], axis=0)
        self.attitude = self.epoch_attitude @ current

    def _propagate(self, cov: np.ndarray, steps, rotations, f, dt, gyro_rthz: float, accel_rthz: float) -> np.ndarray:
        """Forster's error-state covariance propagation through each sample (9x9 per step, composed
        a whole interval at a time), with these noise densities (the larger of told and measured)."""
        n = len(dt)
        rf = np.einsum("kij,kjl->kil", rotations, skew_batch(f))
        a = np.zeros((n, 9, 9))
        a[:, 0:3, 0:3] = steps.transpose(0, 2, 1)
        a[:, 3:6, 0:3] = -rf * dt[:, None, None]
        a[:, 6:9, 0:3] = -0.5 * rf * (dt**2)[:, None, None]
        a[:, 3:6, 3:6] = np.eye(3)
        a[:, 6:9, 3:6] = np.eye(3) * dt[:, None, None]
        a[:, 6:9, 6:9] = np.eye(3)
        safe = np.maximum(dt, 1e-6)
        b = np.concatenate([rotations * dt[:, None, None], 0.5 * rotations * (dt**2)[:, None, None]], axis=1)
        noise = np.zeros((n, 9, 9))
        noise[:, 3:9, 3:9] = b @ b.transpose(0, 2, 1) * (accel_rthz**2 / safe)[:, None, None]
        noise[:, 0:3, 0:3] = np.eye(3) * (gyro_rthz**2 / safe * dt**2)[:, None, None]
        return propagated(cov, a, noise)

    def _epoch(self, stamp: int):
        if self.attitude is None or self.last is None or (self.epoch_ns is not None and stamp <= self.epoch_ns):
            return
        if stamp > self.last[0]:
            self.pending.append((*self.last, stamp))
            self.last = (stamp, self.last[1], self.last[2])
        self._integrate(self.pending)
        self.pending = []
        inc = self.increment
        if self.epoch_ns is not None:
            r0 = self.epoch_attitude
            assert r0 is not None, "set with the first epoch"
            dv = r0 @ inc.velocity + self.gravity * inc.dt
            dp = r0 @ inc.position + 0.5 * self.gravity * inc.dt**2
            frame = np.eye(9)
            frame[3:6, 3:6] = r0
            frame[6:9, 6:9] = r0
            cov = frame @ inc.with_biases(self.params.accel_bias_m_s2, self.gyro_bias_std(stamp)) @ frame.T
            turning = inc.turning_in_place(self.params.turn_in_place_rad_s, self.params.still_speed_m_s)
            self.turns += turning

            def vec(v: np.ndarray) -> Any:
                return make("geometry_msgs/msg/Vector3", x=float(v[0]), y=float(v[1]), z=float(v[2]))

            def quat(r: np.ndarray) -> Any:
                return make("geometry_msgs/msg/Quaternion", **dict(zip("xyzw", quaternion_from_matrix(r), strict=True)))

            yield Emit(
                "odometry",
                make(
                    "rover_msgs/msg/Preintegration",
                    header=header(stamp, "world"),
                    start=header(self.epoch_ns).stamp,
                    dt=inc.dt,
                    orientation_start=quat(r0),
                    orientation=quat(self.attitude),
                    delta_velocity=vec(dv),
                    delta_position=vec(dp),
                    covariance=cov.ravel(),
                    samples=inc.samples,
                    accel_bias_jacobian=np.concatenate([r0 @ inc.bias_velocity, r0 @ inc.bias_position]).ravel(),
                    accel_bias_std=self.params.accel_bias_m_s2,
                    turning_in_place=turning,
                    levelling_std=self.levelling_std,
                ),
                stamp,
            )
        self.epoch_ns = stamp
        self.epoch_attitude = self.attitude.copy()
        self.increment = _Increment.zero()

    def on_end(self):
        if self.attitude is None and self.still:
            log.warning(
                "preintegration: the IMU stream ended during the stationary start (%d samples)", len(self.still)
            )
        log.info("preintegration: %d interval(s) turning in place", self.turns)
        if self.noise is not None and self.nominal_dt:
            gyro, accel = self.noise.worst * math.sqrt(self.nominal_dt)
            p = self.params
            log.info(
                "preintegration: IMU noise measured on its samples, at most gyro %.4f deg/s/rtHz (told %.4f), "
                "accelerometer %.5f m/s^2/rtHz (told %.5f): the odometry's covariance used the larger",
                math.degrees(gyro),
                math.degrees(p.gyro_noise_rad_s_rthz),
                accel,
                p.accel_noise_m_s2_rthz,
            )
        if self.tracker is not None:
            log.info(
                "preintegration: gyro bias re-estimated on %d still span(s), now %s rad/s",
                self.tracker.spans,
                np.array2string(self.tracker.bias, precision=5),
            )
        return ()
