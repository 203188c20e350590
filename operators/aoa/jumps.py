"""The Intel 5300's chain phase jumps as the AoA sees them: the combinations of jumps a burst may
carry relative to the calibration, and how to undo one.

Across a restart or a retune (and at 2.4 GHz from packet to packet) each receive chain's phase
moves by a multiple of a step (rover.formats.wifi.phase_jump_step_rad). Only the chains' phases
relative to the first one matter to an angle, so a combination gives chain k >= 1 a multiple
m_k in 0..levels-1 (levels = 2 pi / step) and is numbered sum_k m_k levels^(k-1).
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from rover.formats.wifi import phase_jump_step_rad


def jump_levels(channel: int) -> int:
    """Distinct phases a chain can jump to on this channel (2 at 5 GHz, 4 at 2.4 GHz)."""
    return round(2 * math.pi / phase_jump_step_rad(channel))


def jump_phases(channel: int, chains: int, jumps: bool = True) -> np.ndarray:
    """(C, M) phase (rad) each combination adds to each chain, in combination-number order;
    only the identity (no jump) when `jumps` is off."""
    levels = jump_levels(channel) if jumps else 1
    step = phase_jump_step_rad(channel)
    multiples = np.array([m[::-1] for m in itertools.product(range(levels), repeat=chains - 1)], dtype=float)
    return np.concatenate([np.zeros((len(multiples), 1)), multiples * step], axis=1)


def combination_multiples(number: int, channel: int, chains: int) -> np.ndarray:
    """The multiples (M,) of the jump step of combination `number` (chain 0 always 0)."""
    levels = jump_levels(channel)
    return np.array([0] + [(number // levels**k) % levels for k in range(chains - 1)])
