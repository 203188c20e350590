"""Why a tag is or is not published as localized (rover.operators.slam.tag_status): each state from
the evidence that sets it, and the states as rover_msgs/msg/TagStatus numbers them. The operator's
tests (test_slam.py) check that the states sent agree with the tags published."""

from __future__ import annotations

import numpy as np

from rover.drivers.run_outputs import STATES
from rover.messages import typestore
from rover.operators.slam.integrity import MAX_VARIANCE_FACTOR
from rover.operators.slam.sliding_window import SlidingWindow
from rover.operators.slam.tag_search import Found
from rover.operators.slam.tag_status import TagState, tag_status

SMALL = np.eye(2) * 0.1**2


def window(active: bool) -> SlidingWindow:
    w = SlidingWindow()
    w.tag_ids.append(7)
    w.active.append(active)
    return w


def test_the_states_are_the_messages_constants_and_the_csvs_names():
    constants = {name: value for name, _type, value in typestore.fielddefs["rover_msgs/msg/TagStatus"][0]}
    assert constants == {s.name: s.value for s in TagState}
    assert tuple(s.name.lower() for s in TagState) == STATES


def test_a_tag_waiting_for_the_search_says_how_many_bearings_or_what_its_best_place_lacks():
    w = window(active=False)
    w.finder.heard[0] = 5
    heard = tag_status(w, 0, SMALL, localized=False)
    assert heard.state == TagState.HEARD and heard.reason.startswith("5 of its bearings heard")
    w.finder.last[0] = Found(np.array([1.0, 2.0]), np.zeros(3, int), np.eye(2), 12.0, 0.95, 40.0)
    ambiguous = tag_status(w, 0, SMALL, localized=False)
    assert ambiguous.state == TagState.AMBIGUOUS and "within 12 of its cost" in ambiguous.reason


def test_a_placed_tag_is_judged_then_contradicted_uncertain_or_localized():
    w = window(active=True)
    judging = tag_status(w, 0, SMALL, localized=False)
    assert judging.state == TagState.JUDGING and "left the window" in judging.reason
    w.integrity.parallax[0] = 40.0
    w.integrity.factor[0] = 1.0
    w.integrity.jackknife[0] = [SMALL, SMALL]
    w.integrity.checks[0] = 2
    uncertain = tag_status(w, 0, np.eye(2) * 0.8**2, localized=False)
    assert uncertain.state == TagState.UNCERTAIN and "largest std is 0.80 m" in uncertain.reason
    localized = tag_status(w, 0, SMALL, localized=True)
    assert localized.state == TagState.LOCALIZED and "span 40 deg" in localized.reason
    w.integrity.factor[0] = 4 * MAX_VARIANCE_FACTOR
    contradicted = tag_status(w, 0, SMALL, localized=False)
    assert contradicted.state == TagState.CONTRADICTED and "does not explain them" in contradicted.reason
