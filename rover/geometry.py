"""Planar angle helpers shared by the operators, the simulator and the evaluation.

Yaw is the rotation about z, counter-clockwise from x; quaternions are (x, y, z, w), the order
of geometry_msgs/Quaternion and of scipy's Rotation.
"""

from __future__ import annotations

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
