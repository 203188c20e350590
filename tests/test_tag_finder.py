"""The window's side of the tag search (rover.operators.slam.tag_finder): what a tag not localized
says of why."""

from __future__ import annotations

import numpy as np

from rover.operators.slam.tag_finder import TagFinder, why_waiting
from rover.operators.slam.tag_search import Found, SearchSettings


def found(margin: float, inliers: float, parallax_deg: float) -> Found:
    return Found(np.array([1.234, -5.0]), np.zeros(3, int), np.eye(2), margin, inliers, parallax_deg)


def test_a_tag_not_localized_says_which_evidence_is_missing():
    s = SearchSettings()
    only_margin = why_waiting(found(13.4, 0.97, 44.0), s)
    assert only_margin == (
        "the search's best place (1.23, -5.00) m is not clear: another place fits within 13 of its cost (25 needed)"
    )
    everything = why_waiting(found(3.0, 0.5, 4.0), s)
    assert "13 of its cost" not in everything
    for part in ("within 3 of its cost (25 needed)", "50% of its bearings agree (80% needed)", "seen over 4 deg (10"):
        assert part in everything
    assert "did not triangulate" in why_waiting(None, s)
    assert found(25.0, 0.8, 10.0).clear(s), "at the thresholds nothing is missing"


def test_a_tag_is_started_until_localized_or_a_window_after_the_search_placed_or_reexamined_it():
    """The convex passes start a tag that is not localized: one the search placed, for a window's
    worth of epochs after it did or after the window last re-examined it; one it never placed,
    until it is localized."""
    finder = TagFinder()
    localized = np.array([False, False, True])
    finder.placed[0] = 100  # placed by the search at epoch 100; tag 1 never placed; tag 2 localized
    assert list(finder.starting(localized, 130, window_epochs=30)) == [True, True, False]
    assert list(finder.starting(localized, 131, window_epochs=30)) == [False, True, False]
    finder.reexamined(0, 140)
    finder.reexamined(1, 140)  # never placed: nothing to restart
    assert finder.placed == {0: 140}
    assert list(finder.starting(localized, 160, window_epochs=30)) == [True, True, False]
