"""Where each state sits in the window's vector, and in its prior's: named slices instead of index
arithmetic, one place to change when a state is added.

    x = [ epoch 0 | epoch 1 | ... | tag 0 | tag 1 | ... | shared ]
          p_x p_y v_x v_y            b_x b_y             accelerometer biases (body x/y, world x/y),
                                                         then the wheel scale

The prior covers the oldest epoch, every tag and the shared states, in that order:
`prior_indices`. A new kind of shared state (one per tag, or per chain) goes after the wheel scale,
and `Shape.shared` counts it; the program and the marginalization take it from here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

EPOCH_STATES = 4
"""per epoch: position x/y, velocity x/y (m, m/s; world frame)"""
TAG_STATES = 2
"""per tag: position x/y (m, world frame)"""
ACCEL_BIAS_STATES = 4
"""the accelerometer biases, when estimated: body-frame x/y, world-frame x/y (m/s^2)"""


@dataclass(frozen=True)
class Shape:
    """What fixes the program's structure."""

    epochs: int
    slots: int
    """AoA slots per epoch"""
    tags: int
    biases: int = 0
    """states shared by the whole window, after the tags: the accelerometer biases, then the wheel
    scale (0: none estimated)"""
    scale: bool = False
    """the last shared state is the wheel odometry's scale error, which every epoch's wheel term holds"""

    @property
    def states(self) -> int:
        return EPOCH_STATES * self.epochs + TAG_STATES * self.tags + self.biases

    @property
    def epoch_states(self) -> slice:
        """Every epoch's states, oldest first."""
        return slice(0, EPOCH_STATES * self.epochs)

    @property
    def tag_states(self) -> slice:
        """Every tag's position, in slot order."""
        start = EPOCH_STATES * self.epochs
        return slice(start, start + TAG_STATES * self.tags)

    @property
    def shared_states(self) -> slice:
        """The states shared by the window: the accelerometer biases, then the wheel scale."""
        return slice(self.states - self.biases, self.states)

    @property
    def bias_index(self) -> np.ndarray:
        """The bias states' columns."""
        return EPOCH_STATES * self.epochs + TAG_STATES * self.tags + np.arange(self.biases)

    @property
    def rows(self) -> int:
        return self.epochs * self.slots

    def epoch(self, k: int) -> slice:
        """Epoch k's [position, velocity]."""
        return slice(EPOCH_STATES * k, EPOCH_STATES * (k + 1))

    def position(self, k: int) -> slice:
        return slice(EPOCH_STATES * k, EPOCH_STATES * k + 2)

    def tag(self, t: int) -> slice:
        """Tag slot t's position."""
        start = EPOCH_STATES * self.epochs + TAG_STATES * t
        return slice(start, start + TAG_STATES)


def positions(x: np.ndarray, epochs: int) -> np.ndarray:
    """The epochs' positions (epochs, 2) in a window vector."""
    return x[: EPOCH_STATES * epochs].reshape(-1, EPOCH_STATES)[:, 0:2]


def prior_tag(t: int) -> slice:
    """Tag slot t's position in the prior's vector (after the oldest epoch)."""
    return slice(EPOCH_STATES + TAG_STATES * t, EPOCH_STATES + TAG_STATES * (t + 1))


def prior_indices(shape: Shape) -> np.ndarray:
    """The states the prior covers: the oldest epoch, every tag and the biases."""
    return np.concatenate(
        [np.arange(EPOCH_STATES), EPOCH_STATES * shape.epochs + np.arange(TAG_STATES * shape.tags + shape.biases)]
    )


def velocity_columns(shape: Shape) -> np.ndarray:
    """Per epoch, the states its wheel term covers (epochs, 2 or 3): its velocity, and the wheel
    scale when the window estimates it."""
    vel = EPOCH_STATES * np.arange(shape.epochs)[:, None] + np.array([2, 3])
    if not shape.scale:
        return vel
    return np.concatenate([vel, np.full((shape.epochs, 1), shape.states - 1)], axis=1)


def slot_columns(shape: Shape) -> np.ndarray:
    """Per slot, the state columns of its row: the epoch's position, then every tag's position."""
    epoch = np.repeat(np.arange(shape.epochs), shape.slots)
    tags = EPOCH_STATES * shape.epochs + np.arange(TAG_STATES * shape.tags)
    return np.concatenate(
        [
            EPOCH_STATES * epoch[:, None] + np.arange(2)[None, :],
            np.broadcast_to(tags, (shape.rows, TAG_STATES * shape.tags)),
        ],
        axis=1,
    )
