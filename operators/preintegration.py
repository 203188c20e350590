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
from dataclasses import dataclass
from typing import Any

import numpy as np

from rover.errors import BadInput, SpecError
from rover.messages import header, make
from rover.operator import Emit, In, Operator, Out
from rover.rig import rig_from_text

log = logging.getLogger("rover.preintegration")


@dataclass(frozen=True)
class PreintegrationParams:
    gyro_noise_rad_s_rthz: float = math.radians(0.005)
    """gyro white-noise density (MicroStrain 3DM-GX4-45 datasheet)"""
    accel_noise_m_s2_rthz: float = 100e-6 * 9.80665
    """accelerometer white-noise density (same datasheet)"""
    stationary_s: float = 1.0
    """how much still time at the start is used for the gyro bias and gravity"""
    still_gyro_rad_s: float = 0.02
    """largest gyro spread (std, rad/s) that still counts as standing still"""
    gap_factor: float = 5.0
    """a sample interval this many times the nominal one is a gap (logged; integrated across)"""
    accel_bias_m_s2: float = 2e-3 * 9.80665
    """accelerometer bias left unknown (1 sigma): a drift the noise densities alone do not show"""
    gyro_bias_rad_s: float = math.radians(0.005)
    """gyro bias left after the stationary estimate (1 sigma)"""


def skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector w (Rodrigues)."""
    angle = float(np.linalg.norm(w))
    if angle < 1e-12:
        return np.eye(3) + skew(w)
    k = skew(w / angle)
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


def rpy_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    cr, sr, cp, sp, cy, sy = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def quaternion(r: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix."""
    w = math.sqrt(max(0.0, 1 + r[0, 0] + r[1, 1] + r[2, 2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1 + r[0, 0] - r[1, 1] - r[2, 2])) / 2, r[2, 1] - r[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1 - r[0, 0] + r[1, 1] - r[2, 2])) / 2, r[0, 2] - r[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1 - r[0, 0] - r[1, 1] + r[2, 2])) / 2, r[1, 0] - r[0, 1])
    return x, y, z, w


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

    @classmethod
    def zero(cls) -> _Increment:
        return cls(np.eye(3), np.zeros(3), np.zeros(3), np.zeros((9, 9)), np.zeros((3, 3)), np.zeros((3, 3)))

    def with_biases(self, accel_bias: float, gyro_bias: float) -> np.ndarray:
        """The covariance including the unknown biases, which act coherently over the interval."""
        jacobian = np.zeros((9, 6))
        jacobian[0:3, 3:6] = np.eye(3) * self.dt
        jacobian[3:6, 0:3] = self.bias_velocity
        jacobian[6:9, 0:3] = self.bias_position
        biases = np.diag([accel_bias ** 2] * 3 + [gyro_bias ** 2] * 3)
        return self.covariance + jacobian @ biases @ jacobian.T


class Preintegration(Operator):
    """Emits one Preintegration per AoA epoch (AoAs sharing a stamp are one epoch)."""

    inputs = {"imu": In("sensor_msgs/msg/Imu"), "epochs": In("rover_msgs/msg/Aoa"),
              "setup": In("rover_msgs/msg/RigSetup", required=False,
                          doc="for the IMU mounting rotation; identity without it")}
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
        self.dropped = {"duplicate": 0, "out of order": 0, "not finite": 0}
        self.gaps = 0

    def on_input(self, port: str, msg: Any, stamp_ns: int):
        if port == "setup":
            self._mounting(msg.setup_yaml)
        elif port == "imu":
            self._imu(msg, stamp_ns)
        else:
            yield from self._epoch(stamp_ns)

    def _mounting(self, text: str) -> None:
        try:
            rig = rig_from_text(text, "RigSetup")
        except SpecError as exc:
            raise BadInput(f"rig description on the setup input: {exc.diagnostics[0]}") from None
        self.mount = rpy_matrix(*np.radians(rig.imu.rotation_rpy_deg))

    def _imu(self, msg: Any, stamp: int) -> None:
        w = self.mount @ np.array([msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z])
        f = self.mount @ np.array([msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z])
        if not (np.isfinite(w).all() and np.isfinite(f).all()):
            self.dropped["not finite"] += 1
            return
        if self.last is not None and stamp <= self.last[0]:
            self.dropped["duplicate" if stamp == self.last[0] else "out of order"] += 1
            return
        if self.attitude is None:
            self._initialize(stamp, w, f)
            return
        self._integrate(self.last, stamp)
        self.last = (stamp, w, f)

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
            log.warning("preintegration: the run does not start with %.1f s standing still: gyro bias taken as "
                        "zero and the IMU as level", self.params.stationary_s)
            mean_f = np.array([0.0, 0.0, np.linalg.norm(mean_f)])
        else:
            self.bias = gyro.mean(axis=0)
            log.info("preintegration: gyro bias %s rad/s and gravity %.3f m/s^2 from %.1f s standing still",
                     np.array2string(self.bias, precision=5), np.linalg.norm(mean_f), span_s)
        roll = math.atan2(mean_f[1], mean_f[2])
        pitch = math.atan2(-mean_f[0], math.hypot(mean_f[1], mean_f[2]))
        self.attitude = rpy_matrix(roll, pitch, 0.0)
        self.gravity = np.array([0.0, 0.0, -float(np.linalg.norm(mean_f))])
        dts = np.diff([s[0] for s in self.still]) / 1e9
        self.nominal_dt = float(np.median(dts)) if len(dts) else None
        self.epoch_attitude = self.attitude.copy()
        self.last = self.still[-1]
        for (t0, w0, f0), (t1, _w, _f) in zip(self.still[:-1], self.still[1:]):
            if self.epoch_ns is None or t1 > self.epoch_ns:
                self._integrate((t0, w0, f0), t1)
        self.still = []

    def _integrate(self, sample: tuple[int, np.ndarray, np.ndarray], until: int) -> None:
        """Advance the increment and the attitude by one sample held from its stamp to `until`."""
        start, w, f = sample
        dt = (until - start) / 1e9
        if self.nominal_dt and dt > self.params.gap_factor * self.nominal_dt:
            self.gaps += 1
            if self.gaps == 1 or self.gaps % 100 == 0:
                log.warning("preintegration: %d gap(s) in the IMU stream (last %.3f s)", self.gaps, dt)
        inc = self.increment
        omega = w - self.bias
        step = exp_so3(omega * dt)
        p = self.params
        a = np.zeros((9, 9))
        a[0:3, 0:3] = step.T
        a[3:6, 0:3] = -inc.rotation @ skew(f) * dt
        a[3:6, 3:6] = np.eye(3)
        a[6:9, 0:3] = -0.5 * inc.rotation @ skew(f) * dt * dt
        a[6:9, 3:6] = np.eye(3) * dt
        a[6:9, 6:9] = np.eye(3)
        gyro_var = p.gyro_noise_rad_s_rthz ** 2 / max(dt, 1e-6)
        accel_var = p.accel_noise_m_s2_rthz ** 2 / max(dt, 1e-6)
        b_a = np.vstack([np.zeros((3, 3)), inc.rotation * dt, 0.5 * inc.rotation * dt * dt])
        inc.covariance = a @ inc.covariance @ a.T + b_a @ b_a.T * accel_var
        inc.covariance[0:3, 0:3] += np.eye(3) * gyro_var * dt * dt
        inc.bias_position = inc.bias_position + inc.bias_velocity * dt + 0.5 * inc.rotation * dt * dt
        inc.bias_velocity = inc.bias_velocity + inc.rotation * dt
        inc.position = inc.position + inc.velocity * dt + 0.5 * inc.rotation @ f * dt * dt
        inc.velocity = inc.velocity + inc.rotation @ f * dt
        inc.rotation = inc.rotation @ step
        inc.dt += dt
        inc.samples += 1
        self.attitude = self.attitude @ step

    def _epoch(self, stamp: int):
        if self.attitude is None or self.last is None or (self.epoch_ns is not None and stamp <= self.epoch_ns):
            return
        if stamp > self.last[0]:
            self._integrate(self.last, stamp)
            self.last = (stamp, self.last[1], self.last[2])
        inc = self.increment
        if self.epoch_ns is not None:
            r0 = self.epoch_attitude
            dv = r0 @ inc.velocity + self.gravity * inc.dt
            dp = r0 @ inc.position + 0.5 * self.gravity * inc.dt ** 2
            frame = np.eye(9)
            frame[3:6, 3:6] = r0
            frame[6:9, 6:9] = r0
            cov = frame @ inc.with_biases(self.params.accel_bias_m_s2, self.params.gyro_bias_rad_s) @ frame.T
            vec = lambda v: make("geometry_msgs/msg/Vector3", x=float(v[0]), y=float(v[1]), z=float(v[2]))
            quat = lambda r: make("geometry_msgs/msg/Quaternion", **dict(zip("xyzw", quaternion(r))))
            yield Emit("odometry", make(
                "rover_msgs/msg/Preintegration", header=header(stamp, "world"),
                start=header(self.epoch_ns).stamp, dt=inc.dt, orientation_start=quat(r0),
                orientation=quat(self.attitude), delta_velocity=vec(dv), delta_position=vec(dp),
                covariance=cov.ravel(), samples=inc.samples), stamp)
        self.epoch_ns = stamp
        self.epoch_attitude = self.attitude.copy()
        self.increment = _Increment.zero()

    def on_end(self):
        dropped = {k: v for k, v in self.dropped.items() if v}
        if dropped:
            log.warning("preintegration: dropped IMU samples: %s", ", ".join(f"{v} {k}" for k, v in dropped.items()))
        if self.attitude is None and self.still:
            log.warning("preintegration: the IMU stream ended during the stationary start (%d samples)",
                        len(self.still))
        return ()
