"""The prior over the oldest epoch, the tags and the shared states, and how the oldest epoch leaves
the window into it (Schur complement, in covariance form)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rover.operators.slam.factors import Edge, angle_residuals, huber_weight
from rover.operators.slam.layout import EPOCH_STATES, prior_tag
from rover.operators.slam.settings import WindowSettings

PV_FROM_VP = [2, 3, 0, 1]
"""reorders an edge's [dv, dp] (velocity first) to the state's [position, velocity]"""


@dataclass
class Prior:
    """0.5 (x - mean)' H (x - mean) + grad' (x - mean) over the oldest epoch and the tags."""

    info: np.ndarray
    mean: np.ndarray
    grad: np.ndarray

    def relaxed(self, states: slice, factor: float) -> Prior:
        """The prior with `factor` of its information on `states` kept (a tag whose bearings keep
        disagreeing with it: the prior of a tag first seen through wrong-path bearings would hold it;
        a tag whose bearings' weight changed, `factor` then above 1 when it fell)."""
        keep = np.ones(len(self.mean))
        keep[states] = math.sqrt(factor)
        return Prior(self.info * np.outer(keep, keep), self.mean, self.grad * keep)


@dataclass(frozen=True)
class Leaving:
    """What the oldest epoch brings into the prior besides the prior itself: its wheel term over its
    velocity (and the wheel scale), and its bearings of tags in use, at the estimate."""

    velocity_info: np.ndarray
    velocity_linear: np.ndarray
    tags: np.ndarray
    """tag slot of each bearing in use"""
    bearing: np.ndarray
    """(k, 2) world-frame unit vectors of their chosen candidates"""
    std: np.ndarray


def marginalize_oldest(
    prior: Prior, own: np.ndarray, leaving: Leaving, edge: Edge, s: WindowSettings, accel_biases: int, scale: bool
) -> Prior:
    """The prior after the oldest epoch left: its Gaussian (prior, wheel term and bearings, linearized
    at the estimate `own`: the states the prior covers) carried through the odometry edge onto the
    next epoch, in covariance form (the edge is far more precise than anything else, which
    information form would square)."""
    nb = accel_biases + scale
    nt = (len(own) - EPOCH_STATES - nb) // 2
    info = prior.info.copy()
    grad = prior.info @ (own - prior.mean) + prior.grad
    wheel = np.array([2, 3] + [len(own) - 1] * scale)  # the oldest epoch's velocity_columns, in `own`
    info[np.ix_(wheel, wheel)] += leaving.velocity_info
    grad[wheel] += leaving.velocity_info @ own[wheel] - leaving.velocity_linear
    if len(leaving.tags):
        delta = own[EPOCH_STATES : EPOCH_STATES + 2 * nt].reshape(-1, 2)[leaving.tags] - own[0:2]
        r, jb = angle_residuals(delta, leaving.bearing, leaving.std, s.min_range_m)
        w = huber_weight(r, s.huber_sigma)
        for j, t in enumerate(leaving.tags):
            tag = prior_tag(int(t))
            cols = np.array([0, 1, tag.start, tag.start + 1])
            row = np.concatenate([-jb[j], jb[j]])
            info[np.ix_(cols, cols)] += w[j] * np.outer(row, row)
            grad[cols] += w[j] * row * r[j]
    cov = np.linalg.inv(info)
    mean = own - cov @ grad
    transfer = np.eye(4)
    transfer[0:2, 2:4] = edge.dt * np.eye(2)
    jac = np.eye(4 + 2 * nt + nb)
    jac[:4, :4] = transfer
    jac[:4, 4 + 2 * nt :] = -edge.bias_jacobian[PV_FROM_VP]
    new_cov = jac @ cov @ jac.T
    new_cov[:4, :4] += edge.covariance[np.ix_(PV_FROM_VP, PV_FROM_VP)]
    walk = 4 + 2 * nt + np.arange(nb)
    rates = np.array([s.accel_bias_walk_m_s2_rts] * accel_biases + [s.wheel_scale_walk_rts] * scale)
    new_cov[walk, walk] += rates**2 * edge.dt
    new_mean = jac @ mean
    new_mean[:4] += edge.delta[PV_FROM_VP]
    new_info = np.linalg.inv(new_cov)
    return Prior(0.5 * (new_info + new_info.T), new_mean, np.zeros(4 + 2 * nt + nb))
