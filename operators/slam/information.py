"""The window's Gauss-Newton information at the estimate, and the covariances it reports from it: dense, as
a window has a few hundred states, where building a sparse matrix costs more than factorizing the
dense one."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.linalg.lapack import dpotrf, dpotrs

from rover.operators.slam.epoch import Epoch
from rover.operators.slam.factors import Edge
from rover.operators.slam.layout import EPOCH_STATES, Shape, prior_indices, velocity_columns


def window_information(
    shape: Shape,
    prior_info: np.ndarray,
    edges: Sequence[Edge],
    epochs: Sequence[Epoch],
    epoch: np.ndarray,
    coeff: np.ndarray,
) -> np.ndarray:
    """The information over every state: the prior's, each odometry edge's block, each epoch's wheel
    term, and the bearing rows `coeff` (per slot, at the program's columns, already weighted) of
    the slots' epochs `epoch`."""
    n = shape.states
    pri = prior_indices(shape)
    blocks = [(pri, prior_info[None])]  # (states of each block, the blocks): summed below
    if edges:
        edge = np.concatenate(
            [
                EPOCH_STATES * np.arange(len(edges))[:, None] + np.arange(2 * EPOCH_STATES),
                np.broadcast_to(shape.bias_index, (len(edges), shape.biases)),
            ],
            axis=1,
        )
        blocks.append((edge, np.stack([e.block for e in edges])))
    blocks.append((velocity_columns(shape), np.stack([e.velocity_info for e in epochs])))
    flat = np.concatenate(
        [(idx.reshape(-1, idx.shape[-1], 1) * n + idx.reshape(-1, 1, idx.shape[-1])).ravel() for idx, _ in blocks]
    )
    values = np.concatenate([b.ravel() for _, b in blocks])
    info = np.bincount(flat, weights=values, minlength=n * n).reshape(n, n)
    rows = np.zeros((shape.rows, shape.states))
    rows[np.arange(shape.rows)[:, None], EPOCH_STATES * epoch[:, None] + np.arange(2)] = coeff[:, :2]
    rows[:, shape.tag_states] = coeff[:, 2:]
    return info + rows.T @ rows


def covariances(info: np.ndarray, shape: Shape) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """From the window's information: each tag's 2x2 covariance (tags, 2, 2), the shared states', and
    the newest epoch's position's 2x2 (all infinite when the information is not positive definite).
    One Cholesky solve."""
    nt, nb = shape.tags, shape.biases
    e = shape.tag_states.start
    newest = shape.position(shape.epochs - 1)
    rhs = np.zeros((info.shape[0], 2 * nt + nb + 2))
    rhs[e:, : 2 * nt + nb] = np.eye(2 * nt + nb)
    rhs[newest, 2 * nt + nb :] = np.eye(2)
    factor, failed = dpotrf(info, lower=0, clean=0)
    solved = dpotrs(factor, rhs, lower=0)[0] if failed == 0 else np.full(rhs.shape, np.inf)
    cov = solved[e:, : 2 * nt + nb]
    tags = np.array([cov[2 * i : 2 * i + 2, 2 * i : 2 * i + 2] for i in range(nt)]).reshape(-1, 2, 2)
    return tags, cov[2 * nt :, 2 * nt :], solved[newest, 2 * nt + nb :]


def largest_std_m(tag_covariance: np.ndarray) -> np.ndarray:
    """Each tag's largest standard deviation (m), along its covariance's major axis."""
    if len(tag_covariance) == 0:
        return np.zeros(0)
    cov = np.nan_to_num(tag_covariance, nan=1e12, posinf=1e12)
    worst = np.linalg.eigvalsh(0.5 * (cov + cov.transpose(0, 2, 1)))[:, -1]
    return np.sqrt(np.maximum(worst, 0))
