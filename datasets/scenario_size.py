"""How big a scenario's dataset is, worked out before anything is simulated: the simulator holds
every message in memory until it writes them in time order, so a scenario past MAX_MESSAGES is
refused (BadInput, exit 2) instead of taking the machine's memory."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from rover.datasets.motion import Motion
from rover.datasets.scenario import Scenario
from rover.errors import BadInput

TRUTH_RATE_HZ = 100.0
"""ground-truth poses per second (the simulator's)"""
MAX_MESSAGES = 2_000_000
"""messages simulated at once at most: about 1.6 KB of memory each (measured on `paper`, 180 s and
360 s: 300 and 440 MB peak), so about 3.5 GB; an hour at the paper's rates is 1.7 million"""


class ScenarioTooBig(BadInput):
    """The scenario's dataset would not fit in memory."""


@dataclass(frozen=True)
class ScenarioSize:
    duration_s: float
    messages: int
    """an upper bound: IMU samples, ground-truth poses, odometry, the sweep's windows, and CSI packets
    with their true angles as if every tag were heard all the time"""


def scenario_size(scenario: Scenario) -> ScenarioSize:
    """The simulated duration and message count of `scenario`, from the plan of one and two laps
    (every lap after the first is the same), without planning every lap."""
    trajectory = scenario.trajectory
    one = Motion(replace(trajectory, laps=1)).duration_s
    lap = Motion(replace(trajectory, laps=2)).duration_s - one
    duration = one + (trajectory.laps - 1) * lap
    rx = scenario.receiver
    # the sweep's windows cover whole dwells (rover.datasets.simulate._windows): with a dwell longer
    # than the run, its one window (and its packets) outlasts the run by that much
    windows = math.floor(duration / rx.dwell_s) + 1.0 if math.isfinite(duration / rx.dwell_s) else math.inf
    packets = windows * rx.packet_rate_hz * max(rx.dwell_s - rx.hop_gap_s, 0.0)
    per_s = scenario.imu.rate_hz + TRUTH_RATE_HZ + (scenario.odometry.rate_hz if scenario.odometry.enabled else 0.0)
    messages = duration * per_s + windows + 2 * packets
    return ScenarioSize(duration, int(min(messages, 2**62)) if math.isfinite(messages) else 2**62)


def check_size(scenario: Scenario, where: str) -> ScenarioSize:
    """BadInput naming `where` (the scenario and its overrides) when the scenario is too big to simulate."""
    size = scenario_size(scenario)
    if size.messages > MAX_MESSAGES:
        raise ScenarioTooBig(
            f"{where}: the scenario would simulate {size.duration_s:,.0f} s as {size.messages:,} messages; "
            f"at most {MAX_MESSAGES:,} (about 3.5 GB of memory): fewer laps, lower rates, or a receiver.dwell_s "
            "shorter than the run"
        )
    return size
