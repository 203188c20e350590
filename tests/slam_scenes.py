"""Synthetic SLAM inputs with exact odometry: a robot that starts from rest, and tags around it."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from rover.operators.slam.sliding_window import Edge, SlidingWindow, WindowSettings, bias_jacobian

EXACT_COVARIANCE = np.diag([1e-8, 1e-8, 1e-10, 1e-10])
"""[dv, dp] covariance of an exact odometry edge (velocity first, as the Preintegration message)"""
EXACT_IMU = {"accel_bias": False}
"""WindowSettings for tests about something else than the IMU: this odometry has no bias, and bias
states would leave the scale to the bearings (less sharp than exact odometry)"""
INDEPENDENT_BURSTS: dict[str, Any] = {"aoa_std_scale": 1.0}
"""WindowSettings for tests of the window's numbers at a known noise: a scene draws each bearing's
noise on its own, with the std the window is told, so there is no multipath shared between
consecutive bursts for the shipped `aoa_std_scale` to stand for"""


@dataclass
class Scene:
    t: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    yaw: np.ndarray
    tags: np.ndarray


def scene(
    seconds: float = 15.0,
    epoch_s: float = 0.1,
    speed_m_s: float = 0.3,
    radius_m: float | None = 2.0,
    tags=((3.0, 2.0), (-1.0, 2.5), (4.0, -1.5), (1.0, -2.0)),
) -> Scene:
    """Ramp from rest to `speed_m_s` in 1 s, then along a circle of `radius_m` (None: a straight line)."""
    t = np.arange(0.0, seconds, epoch_s)
    s = np.where(t < 1.0, 0.5 * speed_m_s * t**2, 0.5 * speed_m_s + speed_m_s * (t - 1.0))
    ds = np.where(t < 1.0, speed_m_s * t, speed_m_s)
    if radius_m is None:
        heading = np.zeros_like(t)
        position = np.stack([s, np.zeros_like(s)], axis=1)
    else:
        heading = s / radius_m
        position = np.stack([radius_m * np.sin(heading), radius_m * (1 - np.cos(heading))], axis=1)
    velocity = ds[:, None] * np.stack([np.cos(heading), np.sin(heading)], axis=1)
    return Scene(t, position, velocity, heading, np.array(tags, float))


def true_angle(sc: Scene, k: int, tag: int) -> float:
    d = sc.tags[tag] - sc.position[k]
    return math.atan2(d[1], d[0]) - sc.yaw[k]


def edge(sc: Scene, k: int, bias: np.ndarray | None = None, covariance: np.ndarray = EXACT_COVARIANCE) -> Edge:
    """The exact odometry from epoch k-1 to k, plus what an accelerometer `bias` ([body x, body y,
    world x, world y], m/s^2) adds to it, said to be as uncertain as `covariance`."""
    dt = sc.t[k] - sc.t[k - 1]
    delta = np.concatenate(
        [sc.velocity[k] - sc.velocity[k - 1], sc.position[k] - sc.position[k - 1] - sc.velocity[k - 1] * dt]
    )
    jacobian = bias_jacobian(sc.yaw[k - 1], sc.yaw[k], float(dt))
    if bias is not None:
        delta = delta + jacobian @ bias
    return Edge(float(dt), delta, covariance, jacobian)


def angles(sc: Scene, noise_deg: float = 0.0, outliers: float = 0.0, seed: int = 0) -> list[tuple[int, float]]:
    """(tag index, robot-frame AoA) per epoch, tags in turn; a fraction of outliers at random angles."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(len(sc.t)):
        tag = k % len(sc.tags)
        angle = true_angle(sc, k, tag) + math.radians(noise_deg) * rng.normal()
        if rng.random() < outliers:
            angle = rng.uniform(-math.pi, math.pi)
        out.append((tag, angle))
    return out


def estimate(
    sc: Scene,
    settings: WindowSettings,
    measured: list[tuple[int, float]],
    std_deg: float,
    update_every: int = 1,
    bias: np.ndarray | None = None,
    levelled_std_m_s2: float = 0.0,
    wheel_reads: float | None = None,
    wheel_noise_m_s: float = 0.0,
    seed: int = 0,
    covariance: np.ndarray = EXACT_COVARIANCE,
) -> tuple[SlidingWindow, np.ndarray]:
    """Run the window over the scene (its odometry with an accelerometer `bias` and said to be as
    uncertain as `covariance`, see `edge`; with `wheel_reads`, wheel odometry reading that many times
    the true speed, plus white noise of `wheel_noise_m_s` while moving, drawn from `seed`); returns it
    and the robot positions as finally estimated."""
    w = SlidingWindow(settings)
    speed = np.linalg.norm(sc.velocity, axis=1)
    noise = np.random.default_rng(seed).normal(0.0, wheel_noise_m_s, len(speed)) * (speed > 0)
    for k, (tag, angle) in enumerate(measured):
        w.add_epoch(
            int(sc.t[k] * 1e9),
            float(sc.yaw[k]),
            [tag + 1],
            np.array([angle]),
            np.array([math.radians(std_deg)]),
            edge(sc, k, bias, covariance) if k else None,
            levelled_std_m_s2=levelled_std_m_s2,
            speed_m_s=None if wheel_reads is None else wheel_reads * float(speed[k]) + float(noise[k]),
        )
        if k % update_every == 0 or k == len(measured) - 1:
            w.find_tags()
            w.update()
    final = np.array([f[1:3] for f in w.finals] + [p[1:3] for p in w.poses()])
    return w, final


def tag_errors(sc: Scene, w: SlidingWindow) -> np.ndarray:
    order = [w.tag_ids.index(i + 1) for i in range(len(sc.tags)) if i + 1 in w.tag_ids]
    return np.linalg.norm(w.tag_positions()[order] - sc.tags[: len(order)], axis=1)
