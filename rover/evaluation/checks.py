"""Whether an evaluation compares like with like: the truth given is the run's own, and it covers the
run's poses. `rover eval` warns and says so in its metrics when not, instead of printing errors that
measure the wrong thing."""

from __future__ import annotations

from typing import Any

import numpy as np

from rover.evaluation.metrics import Poses2D

MIN_MATCHED_SHARE = 0.9
"""a truth that pairs with fewer of the run's final poses than this is not the run's truth"""
SAME_POSITION_M = 0.01
"""two truths that place the robot further apart than this at a common stamp are different truths"""


def same_trajectory(a: Poses2D, b: Poses2D) -> bool:
    """Whether two true trajectories agree where both have a pose (and have one in common)."""
    common, ia, ib = np.intersect1d(a.stamp_ns, b.stamp_ns, return_indices=True)
    if not len(common):
        return False
    return bool(np.max(np.linalg.norm(a.xy[ia] - b.xy[ib], axis=1)) <= SAME_POSITION_M)


def evaluation_notes(
    metrics: dict[str, Any],
    final_poses: int,
    truth_source: str,
    dataset: str | None,
    own: Poses2D | None,
    given: Poses2D,
) -> list[str]:
    """What makes these metrics doubtful: a truth that is not the run's dataset's own, or one that pairs
    with too few of the run's final poses."""
    notes = []
    if own is not None and not same_trajectory(own, given):
        notes.append(f"the truth {truth_source} is not the ground truth of the run's dataset {dataset}")
    matched = metrics["robot"]["trajectory.tum"]["unaligned"].get("poses", 0)
    if final_poses and matched < MIN_MATCHED_SHARE * final_poses:
        notes.append(
            f"the truth pairs with {matched:,} of the run's {final_poses:,} final poses "
            f"({matched / final_poses:.0%}; at least {MIN_MATCHED_SHARE:.0%} expected): is it this run's truth?"
        )
    return notes
