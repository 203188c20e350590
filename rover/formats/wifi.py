"""WiFi facts the front end needs: channel numbers and centre frequencies, the Intel 5300's channel
list, and the subcarriers the CSI Tool reports."""

from __future__ import annotations

import math

import numpy as np

SUBCARRIER_SPACING_HZ = 312_500.0
CHANNEL_WIDTH_HZ = 20e6
SPEED_OF_LIGHT_M_S = 299_792_458.0

INTEL5300_CHANNELS_5GHZ = (
    36,
    40,
    44,
    48,
    52,
    56,
    60,
    64,
    100,
    104,
    108,
    112,
    116,
    120,
    124,
    128,
    132,
    136,
    140,
    149,
    153,
    157,
    161,
    165,
)
"""The 20 MHz channels of the 5 GHz band the Intel 5300 tunes to."""

SUBCARRIERS_20MHZ = np.array([*range(-28, -1, 2), -1, 1, *range(3, 28, 2), 28])
"""Subcarrier indices the CSI Tool reports at 20 MHz (grouping Ng = 2): not evenly spaced near DC."""
SUBCARRIERS_40MHZ = np.array([*range(-58, -1, 4), *range(2, 59, 4)])


def channel_freq_hz(channel: int) -> float:
    """Centre frequency of a WiFi channel (2.4 GHz channels 1-14, 5 GHz channels 32-177)."""
    if channel == 14:
        return 2484e6
    if 1 <= channel <= 13:
        return 2407e6 + 5e6 * channel
    if 32 <= channel <= 177:
        return 5000e6 + 5e6 * channel
    raise ValueError(f"no WiFi channel {channel}")


def phase_jump_step_rad(channel: int) -> float:
    """The step by which the Intel 5300's receive chains jump in phase across a restart, a retune or
    (at 2.4 GHz) a packet: pi at 5 GHz (CSI Tool issues #113, #446), pi/2 at 2.4 GHz (issue #6)."""
    return math.pi / 2 if channel_freq_hz(channel) < 3e9 else math.pi


def freq_channel(freq_hz: float) -> int | None:
    """The 5 GHz channel number centred exactly on `freq_hz`, if any."""
    channel = channel_of(freq_hz)
    return channel if channel is not None and channel >= 32 else None


def channel_of(freq_hz: float) -> int | None:
    """The channel number whose centre is `freq_hz` (2.4 GHz channels 1-14, 5 GHz 32-177), if any."""
    if abs(freq_hz - 2484e6) < 1:
        return 14
    for base, lo, hi in ((2407e6, 1, 13), (5000e6, 32, 177)):
        number = (freq_hz - base) / 5e6
        if abs(number - round(number)) < 1e-6 and lo <= round(number) <= hi:
            return int(round(number))
    return None


RATE_HT40 = 0x800
"""The 40 MHz flag of the Intel 5300's rate_n_flags (iwlwifi's RATE_MCS_HT40_MSK)."""


def subcarrier_freqs_hz(channel: int, width_hz: float = CHANNEL_WIDTH_HZ) -> np.ndarray:
    """Absolute frequencies of the 30 reported subcarriers of a channel."""
    index = SUBCARRIERS_20MHZ if width_hz == CHANNEL_WIDTH_HZ else SUBCARRIERS_40MHZ
    return channel_freq_hz(channel) + index * SUBCARRIER_SPACING_HZ
