"""Angles and rotations shared by the operators, the simulator and the evaluation: the one angle wrap,
yaw and quaternions, planar rotations, and the SO(3) maps the IMU preintegration needs.

Yaw is the rotation about z, counter-clockwise from x; quaternions are (x, y, z, w), the order
of geometry_msgs/Quaternion and of scipy's Rotation.
"""

from __future__ import annotations

import math

import numpy as np


def wrap_angle(angle: np.ndarray | float) -> np.ndarray:
    """Angles (rad) wrapped into [-pi, pi] elementwise: the atan2 of their sine and cosine.

    Bit for bit np.angle(np.exp(1j * angle)) without complex numbers. The modulo form
    (angle + pi) % (2 pi) - pi rounds differently (in the last bit, for many angles), so the two are
    not interchangeable where outputs are compared byte for byte."""
    angle = np.asarray(angle)
    wrapped: np.ndarray = np.arctan2(np.sin(angle), np.cos(angle))
    return wrapped


def yaw_from_quaternion(
    qx: np.ndarray | float, qy: np.ndarray | float, qz: np.ndarray | float, qw: np.ndarray | float
) -> np.ndarray:
    """Yaw (rad) of quaternions given component by component (scalars or arrays), in [-pi, pi]."""
    yaw: np.ndarray = np.arctan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))
    return yaw


def quaternion_from_yaw(yaw: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(x, y, z, w) of rotations about z by `yaw` (rad), elementwise."""
    half = np.asarray(yaw) / 2
    return np.zeros_like(half), np.zeros_like(half), np.sin(half), np.cos(half)


def rotation_2d(yaw: float) -> np.ndarray:
    """The 2x2 rotation from the body's x/y to the world's at heading `yaw`."""
    return np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])


def skew_batch(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices of vectors (N, 3)."""
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return out


def exp_so3_batch(w: np.ndarray) -> np.ndarray:
    """Rotation matrices of rotation vectors (N, 3), Rodrigues with a series near zero."""
    angle = np.linalg.norm(w, axis=1)
    k = skew_batch(w)
    small = angle < 1e-8
    safe = np.where(small, 1.0, angle)
    s = np.where(small, 1.0 - angle**2 / 6, np.sin(safe) / safe)
    c = np.where(small, 0.5 - angle**2 / 24, (1 - np.cos(safe)) / safe**2)
    rotations: np.ndarray = np.eye(3)[None] + s[:, None, None] * k + c[:, None, None] * (k @ k)
    return rotations


def rpy_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """The rotation matrix of roll, pitch, yaw (rad; about x, then y, then z, fixed axes): R = Rz Ry Rx."""
    cr, sr, cp, sp, cy, sy = (
        math.cos(roll),
        math.sin(roll),
        math.cos(pitch),
        math.sin(pitch),
        math.cos(yaw),
        math.sin(yaw),
    )
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def quaternion_from_matrix(r: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix."""
    w = math.sqrt(max(0.0, 1 + r[0, 0] + r[1, 1] + r[2, 2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1 + r[0, 0] - r[1, 1] - r[2, 2])) / 2, r[2, 1] - r[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1 - r[0, 0] + r[1, 1] - r[2, 2])) / 2, r[0, 2] - r[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1 - r[0, 0] - r[1, 1] + r[2, 2])) / 2, r[1, 0] - r[0, 1])
    return x, y, z, w


def smallest_arc(angles: np.ndarray) -> float:
    """The smallest arc (rad) that holds all the angles (the parallax of a place seen from these
    directions)."""
    a = np.sort(np.mod(angles, 2 * math.pi))
    gaps = np.diff(np.concatenate([a, [a[0] + 2 * math.pi]]))
    return float(2 * math.pi - gaps.max())


def parallax_deg(position: np.ndarray, seen_from: np.ndarray) -> float:
    """Spread (deg) of the directions from which `position` (2,) was seen from `seen_from` (n, 2);
    0 without any."""
    seen = position[None, :] - seen_from
    return math.degrees(smallest_arc(np.arctan2(seen[:, 1], seen[:, 0]))) if len(seen) else 0.0


def ellipses(centers: np.ndarray, covariances: np.ndarray, sigma: float, points: int) -> np.ndarray:
    """Points (n, points, 2) of the `sigma` ellipses of n 2x2 covariances around `centers` (n, 2): the
    unit circle scaled by the square roots of the eigenvalues and turned onto the eigenvectors."""
    values, vectors = np.linalg.eigh(0.5 * (covariances + np.swapaxes(covariances, 1, 2)))
    t = np.linspace(0.0, 2 * math.pi, points, endpoint=False)
    circle = np.stack([np.cos(t), np.sin(t)])  # (2, points)
    axes = vectors * (sigma * np.sqrt(np.maximum(values, 0.0)))[:, None, :]  # columns scaled
    loops: np.ndarray = centers[:, None, :] + np.swapaxes(axes @ circle, 1, 2)
    return loops
