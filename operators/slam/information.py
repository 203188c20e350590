"""The window's Gauss-Newton information at the estimate, for the covariances it reports: dense, as
a window has a few hundred states, where building a sparse matrix costs more than factorizing the
dense one."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

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
