"""Ground-truth motion of a wheeled robot through waypoints: straight runs with smooth speed
ramps and turns in place at the corners, after standing still at the start (and, with `pause_s`,
at every waypoint)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rover.datasets.scenario import Trajectory
from rover.geometry import wrap_angle


@dataclass(frozen=True)
class Segment:
    start_s: float
    duration_s: float
    kind: str  # "still", "straight", "turn"
    origin: tuple[float, float]
    heading: float
    length_m: float = 0.0  # straight: distance; turn: signed angle (rad)
    peak: float = 0.0  # straight: top speed (m/s); turn: top yaw rate (rad/s)
    ramp_s: float = 0.0


@dataclass
class State:
    """Poses and derivatives at an array of times, room frame."""

    xy: np.ndarray  # (N, 2)
    yaw: np.ndarray  # (N,)
    vel: np.ndarray  # (N, 2) world velocity
    acc: np.ndarray  # (N, 2) world acceleration
    yaw_rate: np.ndarray  # (N,)
    along_m: np.ndarray  # (N,) distance travelled since the start


class Motion:
    """Piecewise-analytic motion; `state(t)` evaluates it at any times (seconds from the start)."""

    def __init__(self, spec: Trajectory):
        self.segments: list[Segment] = []
        t = 0.0
        pos = (spec.start_m[0], spec.start_m[1])
        heading = math.radians(spec.heading_deg)
        if spec.stationary_s > 0:
            self.segments.append(Segment(t, spec.stationary_s, "still", pos, heading))
            t += spec.stationary_s
        turn_rate = math.radians(spec.turn_rate_deg_s)
        for _ in range(spec.laps):
            for target in spec.waypoints_m:
                dx, dy = target[0] - pos[0], target[1] - pos[1]
                length = math.hypot(dx, dy)
                if length < 1e-9:
                    continue
                wanted = math.atan2(dy, dx)
                turn = float(wrap_angle(wanted - heading))
                if turn >= math.pi:
                    turn = -math.pi  # a half turn goes clockwise
                if abs(turn) > 1e-6:
                    duration = 2 * abs(turn) / turn_rate
                    self.segments.append(Segment(t, duration, "turn", pos, heading, turn, turn_rate))
                    t += duration
                    heading = wanted
                ramp = spec.ramp_s
                top = min(spec.speed_m_s, length / ramp) if ramp > 0 else spec.speed_m_s
                cruise = length / top - ramp
                duration = 2 * ramp + cruise
                self.segments.append(Segment(t, duration, "straight", pos, heading, length, top, ramp))
                t += duration
                pos = (float(target[0]), float(target[1]))
                if spec.pause_s > 0:
                    self.segments.append(Segment(t, spec.pause_s, "still", pos, heading))
                    t += spec.pause_s
        self.segments.append(Segment(t, 1.0, "still", pos, heading))
        self.duration_s = t + 1.0
        self.path_length_m = sum(s.length_m for s in self.segments if s.kind == "straight")

    def state(self, t: np.ndarray) -> State:
        t = np.clip(np.asarray(t, dtype=np.float64), 0.0, self.duration_s)
        n = len(t)
        out = State(np.zeros((n, 2)), np.zeros(n), np.zeros((n, 2)), np.zeros((n, 2)), np.zeros(n), np.zeros(n))
        starts = np.array([s.start_s for s in self.segments])
        travelled = np.cumsum([0.0] + [s.length_m if s.kind == "straight" else 0.0 for s in self.segments])
        index = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(self.segments) - 1)
        for k, seg in enumerate(self.segments):
            mask = index == k
            if not mask.any():
                continue
            tau = np.clip(t[mask] - seg.start_s, 0.0, seg.duration_s)
            out.xy[mask] = seg.origin
            out.yaw[mask] = seg.heading
            out.along_m[mask] = travelled[k]
            if seg.kind == "straight":
                dist, speed, acc = _ramped(tau, seg.length_m, seg.peak, seg.ramp_s)
                u = np.array([math.cos(seg.heading), math.sin(seg.heading)])
                out.xy[mask] += dist[:, None] * u
                out.vel[mask] = speed[:, None] * u
                out.acc[mask] = acc[:, None] * u
                out.along_m[mask] += dist
            elif seg.kind == "turn":
                d = seg.duration_s
                sign = math.copysign(1.0, seg.length_m)
                out.yaw_rate[mask] = sign * seg.peak * (1 - np.cos(2 * np.pi * tau / d)) / 2
                out.yaw[mask] += sign * seg.peak / 2 * (tau - d / (2 * np.pi) * np.sin(2 * np.pi * tau / d))
        out.yaw = wrap_angle(out.yaw)
        return out


def _ramped(tau: np.ndarray, length: float, top: float, ramp: float) -> tuple[np.ndarray, ...]:
    """Distance, speed and acceleration along a straight run with raised-cosine speed ramps."""
    cruise = length / top - ramp
    dist, speed, acc = np.zeros_like(tau), np.zeros_like(tau), np.zeros_like(tau)
    up = tau < ramp
    mid = (tau >= ramp) & (tau < ramp + cruise)
    down = tau >= ramp + cruise
    w = np.pi / ramp if ramp > 0 else 0.0
    x = tau[up]
    speed[up] = top * (1 - np.cos(w * x)) / 2
    dist[up] = top / 2 * (x - np.sin(w * x) / w) if ramp > 0 else 0.0
    acc[up] = top * w / 2 * np.sin(w * x)
    speed[mid] = top
    dist[mid] = top * ramp / 2 + top * (tau[mid] - ramp)
    x = tau[down] - ramp - cruise
    speed[down] = top * (1 + np.cos(w * x)) / 2
    dist[down] = top * ramp / 2 + top * cruise + top / 2 * (x + np.sin(w * x) / w) if ramp > 0 else length
    acc[down] = -top * w / 2 * np.sin(w * x)
    return dist, speed, acc
