"""Why each tag is or is not published as localized: a state (rover_msgs/msg/TagStatus's constants)
and a sentence with the figures that set it, from the tag search, the integrity check and the
published covariance. The SLAM sends a tag's status when its state changes and logs every tag's
that is not localized at the run's end, so an ambiguous tag says so instead of a confident place."""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from rover.operators.slam.information import largest_std_m
from rover.operators.slam.sliding_window import SlidingWindow
from rover.operators.slam.tag_finder import why_waiting


class TagState(IntEnum):
    """rover_msgs/msg/TagStatus's states, in the order a tag goes through them."""

    HEARD = 0
    AMBIGUOUS = 1
    JUDGING = 2
    CONTRADICTED = 3
    UNCERTAIN = 4
    LOCALIZED = 5


@dataclass(frozen=True)
class TagStatus:
    state: TagState
    reason: str


def tag_status(window: SlidingWindow, slot: int, covariance: np.ndarray, localized: bool) -> TagStatus:
    """Tag slot `slot`'s status, given its covariance (2, 2) as published and whether it is published
    as localized (the SLAM operator's `_published`)."""
    finder, integrity, settings = window.finder, window.integrity, window.settings
    if not window.active[slot]:
        if slot not in finder.last:
            heard = finder.heard.get(slot, 0)
            needed = finder.search.min_bearings
            return TagStatus(TagState.HEARD, f"{heard} of its bearings heard, {needed} needed before the search")
        return TagStatus(TagState.AMBIGUOUS, why_waiting(finder.last[slot], finder.search))
    if (scatter := integrity.contradicted(slot)) is not None:
        return TagStatus(TagState.CONTRADICTED, scatter)
    if (lacking := integrity.verdict(slot)) is not None:
        return TagStatus(TagState.JUDGING, lacking)
    std_m = float(largest_std_m(covariance[None])[0])
    if not localized:
        scale = integrity.scale.get(slot, 1.0)
        return TagStatus(
            TagState.UNCERTAIN,
            f"its position's largest std is {std_m:.2f} m ({settings.observable_std_m:.2f} m at most)"
            + (f", the window's scaled by {math.sqrt(scale):.1f} by the integrity check" if scale > 1 else "")
            + (f", with source_std_m {settings.source_std_m:g} m added" if settings.source_std_m else ""),
        )
    return TagStatus(
        TagState.LOCALIZED,
        f"its position's largest std is {std_m:.2f} m; its bearings span {integrity.parallax[slot]:.0f} deg seen "
        "from it and its place explains them",
    )
