"""An epoch of the window: the robot's state at the stamp of a set of bearings, the bearings with
their candidates and the choice among them, the wheel and velocity terms on it; and the window's
bearings stacked, one row each, for the vectorized update."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class Epoch:
    stamp_ns: int
    yaw: float
    """heading from the gyro (world frame)"""
    tags: np.ndarray
    """tag slot of each bearing"""
    candidates: np.ndarray
    """world-frame angles (k, K) of each bearing's candidates (one per chain phase-jump combination), NaN-padded"""
    candidate_std: np.ndarray
    """their standard deviations (rad)"""
    candidate_jumps: np.ndarray
    """the jump combination each candidate assumes (-1: padding or unknown)"""
    choice: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    """the candidate each bearing uses now (candidates.choose at the current estimate)"""
    messages: list[Any] = field(default_factory=list)
    """what the bearings came from, handed back with the final choice (opaque here)"""
    doubt: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """per bearing: the variance (rad^2) the other candidates' chances add to the chosen one's angle"""
    velocity_info: np.ndarray = field(default_factory=lambda: np.zeros((2, 2)))
    """wheel odometry and the velocity constraints on this epoch: 0.5 y'Wy - w'y over y = its velocity
    (and the wheel scale, when the window estimates it: window_program.velocity_columns); with the
    scale a state, its wheel reading as last linearized (SlidingWindow._linearize_wheels)"""
    velocity_linear: np.ndarray = field(default_factory=lambda: np.zeros(2))
    constraint_info: np.ndarray = field(default_factory=lambda: np.zeros((2, 2)))
    """the part of velocity_info that needs no linearization: no sideways motion, zero velocity when
    turning in place, and the wheel reading when the scale is not a state"""
    constraint_linear: np.ndarray = field(default_factory=lambda: np.zeros(2))
    speed_m_s: float = math.nan
    """the wheel odometry's forward speed read at this epoch (NaN: none)"""

    def __post_init__(self) -> None:
        if len(self.choice) != len(self.tags):
            self.choice = np.zeros(len(self.tags), int)
        if len(self.doubt) != len(self.tags):
            self.doubt = np.zeros(len(self.tags))

    @property
    def bearing(self) -> np.ndarray:
        """World-frame unit vectors (k, 2) of the chosen candidates."""
        angle = self.candidates[np.arange(len(self.tags)), self.choice]
        return np.stack([np.cos(angle), np.sin(angle)], axis=1).reshape(-1, 2)

    @property
    def std(self) -> np.ndarray:
        return self.candidate_std[np.arange(len(self.tags)), self.choice]


@dataclass(frozen=True)
class Bearings:
    """The window's bearings stacked, one row each in epoch order: built once per window content
    (the epochs in it and the slots per epoch), not at every pass of every update."""

    key: tuple[int, int, int, int, int]
    epoch: np.ndarray
    tag: np.ndarray
    angles: np.ndarray
    """(rows, K) candidates, NaN-padded"""
    stds: np.ndarray
    jumps: np.ndarray
    slot: np.ndarray
    """each bearing's row in the program's slot layout (epoch * slots + its place in the epoch)"""
    starts: np.ndarray
    """the first row of each epoch, and the end"""


def padded_rows(blocks: list[np.ndarray], width: int, pad: float) -> np.ndarray:
    """The 2-D `blocks` stacked into one (rows, width) array, each row filled out with `pad`: one
    concatenation and one masked assignment, whatever the number of blocks (a slice assignment per
    block: 0.84 ms per tag search of 400 bearings, 0.60 this way)."""
    dtype = np.result_type(*blocks) if blocks else np.float64
    widths = np.repeat([b.shape[1] for b in blocks], [len(b) for b in blocks]).astype(int)
    out = np.full((len(widths), width), pad, dtype=dtype)
    if len(widths):
        out[np.arange(width)[None, :] < widths[:, None]] = np.concatenate([b.ravel() for b in blocks])
    return out


def stack_bearings(epochs: list[Epoch], slots: int, key: tuple[int, int, int, int, int]) -> Bearings:
    """The epochs' bearings stacked in epoch order, each placed in the program's slot layout
    (`slots` per epoch); `key` names the window content they are of."""
    counts = np.array([len(e.tags) for e in epochs], dtype=int)
    starts = np.concatenate([[0], np.cumsum(counts)])
    epoch = np.repeat(np.arange(len(epochs)), counts)
    width = max((e.candidates.shape[1] for e in epochs if len(e.tags)), default=1)
    return Bearings(
        key=key,
        epoch=epoch,
        tag=np.concatenate([e.tags for e in epochs]).astype(int) if epochs else np.zeros(0, int),
        angles=padded_rows([e.candidates for e in epochs], width, np.nan),
        stds=padded_rows([e.candidate_std for e in epochs], width, 1.0),
        jumps=padded_rows([e.candidate_jumps for e in epochs], width, -1).astype(int),
        slot=epoch * slots + np.arange(len(epoch)) - starts[epoch],
        starts=starts,
    )
