"""Errors of an estimated trajectory and tag map against ground truth, the way evo computes them.

The estimator's world frame starts at the robot's first pose (x along its initial heading), so the
truth is first expressed in that frame ("unaligned" errors: what the robot itself believes). The
"aligned" errors fit one 2-D rigid transform (rotation and translation, never a scale) of the
estimate onto the truth by least squares over the associated poses (Umeyama 1991, as `evo_ape -a`)
and apply the same transform to the tags.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rover.errors import BadInput


@dataclass(frozen=True)
class Poses2D:
    """Planar poses: stamps (ns), positions (n, 2), yaws (rad)."""

    stamp_ns: np.ndarray
    xy: np.ndarray
    yaw: np.ndarray


@dataclass(frozen=True)
class Rigid2D:
    rotation: np.ndarray
    translation: np.ndarray

    def apply(self, xy: np.ndarray) -> np.ndarray:
        return xy @ self.rotation.T + self.translation


def yaw_from_quaternion(qx, qy, qz, qw):
    return np.arctan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))


def associate(reference: Poses2D, estimate: Poses2D, max_diff_s: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (reference, estimate) of the nearest stamps within `max_diff_s` (evo's --t_max_diff)."""
    ref = reference.stamp_ns
    j = np.clip(np.searchsorted(ref, estimate.stamp_ns), 1, len(ref) - 1)
    nearer = np.where(np.abs(ref[j - 1] - estimate.stamp_ns) <= np.abs(ref[j] - estimate.stamp_ns), j - 1, j)
    ok = np.abs(ref[nearer] - estimate.stamp_ns) <= max_diff_s * 1e9
    return nearer[ok], np.nonzero(ok)[0]


def start_frame(truth: Poses2D, first_stamp_ns: int) -> Rigid2D:
    """The transform taking the truth's frame to the estimator's (origin at the pose at `first_stamp_ns`)."""
    k = int(np.argmin(np.abs(truth.stamp_ns - first_stamp_ns)))
    c, s = math.cos(truth.yaw[k]), math.sin(truth.yaw[k])
    rotation = np.array([[c, s], [-s, c]])
    return Rigid2D(rotation, -rotation @ truth.xy[k])


def fit_rigid(source: np.ndarray, target: np.ndarray) -> Rigid2D:
    """Least-squares rotation and translation taking `source` points onto `target` (no scale)."""
    if len(source) < 2:
        raise BadInput("alignment needs at least two associated poses")
    ms, mt = source.mean(axis=0), target.mean(axis=0)
    cov = (target - mt).T @ (source - ms)
    u, _, vt = np.linalg.svd(cov)
    d = np.diag([1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ d @ vt
    return Rigid2D(rotation, mt - rotation @ ms)


def error_stats(errors: np.ndarray) -> dict[str, float]:
    return {"mean_m": float(np.mean(errors)), "median_m": float(np.median(errors)),
            "rmse_m": float(np.sqrt(np.mean(errors ** 2))), "max_m": float(np.max(errors)), "poses": int(len(errors))}


@dataclass(frozen=True)
class TrajectoryErrors:
    unaligned: dict[str, float]
    aligned: dict[str, float]
    alignment: Rigid2D
    """estimate -> truth-in-start-frame"""
    to_start: Rigid2D
    """truth frame -> estimator frame"""


def trajectory_errors(truth: Poses2D, estimate: Poses2D, max_diff_s: float = 0.01) -> TrajectoryErrors:
    if len(estimate.stamp_ns) == 0:
        raise BadInput("the estimated trajectory is empty")
    to_start = start_frame(truth, int(estimate.stamp_ns[0]))
    i, j = associate(truth, estimate, max_diff_s)
    if len(i) == 0:
        raise BadInput(f"no estimated pose has a ground-truth pose within {max_diff_s} s")
    reference = to_start.apply(truth.xy[i])
    est = estimate.xy[j]
    alignment = fit_rigid(est, reference)
    return TrajectoryErrors(error_stats(np.linalg.norm(est - reference, axis=1)),
                            error_stats(np.linalg.norm(alignment.apply(est) - reference, axis=1)), alignment, to_start)
