"""The candidate choice: a hidden Markov model per tag over its bearings' jump combinations."""

from __future__ import annotations

import math

import numpy as np

from rover.operators.slam.candidates import Choice, JumpMemory, choose

GHOST_RAD = math.radians(70.0)
"""how far the other combination's candidate lies from the true bearing"""


Bearings = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def bearings(carried: list[int], stray: frozenset[int] = frozenset()) -> Bearings:
    """One tag straight ahead (bearing 0) seen by `len(carried)` bursts, each with two candidates,
    combination 0 and 1; the carried combination's candidate is the true bearing (the other is a
    ghost), except the `stray` bursts, where neither is near (multipath)."""
    n = len(carried)
    angles = np.empty((n, 2))
    for i, c in enumerate(carried):
        angles[i, c], angles[i, 1 - c] = 0.01 * ((-1) ** i), GHOST_RAD
        if i in stray:
            angles[i] = (-GHOST_RAD, 2 * GHOST_RAD)
    stds = np.full((n, 2), math.radians(5.0)) * 4.0  # window stds, scaled by aoa_std_scale
    jumps = np.tile([0, 1], (n, 1))
    offset = np.tile([2.0, 0.0], (n, 1))
    return offset, np.zeros(n, dtype=int), angles, stds, jumps


def chosen(carried: list[int], memory: JumpMemory, stray: frozenset[int] = frozenset()) -> list[int]:
    offset, tag, angles, stds, jumps = bearings(carried, stray)
    kept = Choice(np.zeros(len(tag), dtype=int), np.zeros(len(tag)))
    got = choose(offset, tag, angles, stds, jumps, [True], memory, 4.0, kept)
    return [int(jumps[i, k]) for i, k in enumerate(got.choice)]


def held(combination: int, bearings: int = 200) -> JumpMemory:
    memory = JumpMemory()
    for _ in range(bearings):
        memory.learn(0, combination)
    return memory


def test_a_step_in_the_window_splits_it_at_the_step():
    carried = [1] * 6 + [0] * 6
    assert chosen(carried, held(1)) == carried


def test_a_step_is_followed_by_the_window_end_after_two_bearings():
    assert chosen([1] * 10 + [0] * 2, held(1))[-2:] == [0, 0]


def test_one_stray_bearing_does_not_switch_a_held_combination():
    carried = [1] * 12
    assert chosen(carried, held(1), stray=frozenset({5})) == carried


def test_the_switch_rate_is_learned_from_the_bearings_that_left():
    steady, redrawn = held(1), JumpMemory()
    for j in np.random.default_rng(3).integers(0, 4, 200):
        redrawn.learn(0, int(j))
    assert steady.switch_rate(0) < 0.01 < 0.5 < redrawn.switch_rate(0)
    carried = [int(j) for j in np.random.default_rng(4).integers(0, 2, 12)]
    assert chosen(carried, redrawn) == carried, "a tag redrawn at every dwell chooses freely"


def test_a_doubtful_choice_says_so():
    offset, tag, angles, stds, jumps = bearings([0] * 3)
    angles[:, 1] = math.radians(8.0)  # the other candidate is nearly as likely
    kept = Choice(np.zeros(3, dtype=int), np.zeros(3))
    fresh = JumpMemory()
    got = choose(offset, tag, angles, stds, jumps, [True], fresh, 4.0, kept)
    offset, tag, ghost_angles, stds, jumps = bearings([0] * 3)
    far = choose(offset, tag, ghost_angles, stds, jumps, [True], fresh, 4.0, kept)
    assert np.all(got.doubt > 2 * far.doubt), "a candidate 1.5 std away adds more doubt than a ghost 70 deg off"
    assert np.all(got.doubt < math.radians(8.0) ** 2 / 2), "the chosen one stays the likelier"


def test_bearings_of_tags_not_in_use_keep_their_choice():
    offset, tag, angles, stds, jumps = bearings([1] * 4)
    kept = Choice(np.zeros(4, dtype=int), np.full(4, 0.5))
    got = choose(offset, tag, angles, stds, jumps, [False], JumpMemory(), 4.0, kept)
    assert np.array_equal(got.choice, kept.choice) and np.array_equal(got.doubt, kept.doubt)


def test_a_mirror_image_of_the_same_combination_is_chosen_only_where_it_points_at_the_tag():
    """A collinear array's bursts: each combination has two candidates, a direction and its mirror
    image. The one nearer the estimate's bearing is used whichever comes first, and the
    combinations' sequence is decoded as with one candidate each (a step is still followed); a
    mirror image as likely as the chosen candidate (a bearing near the array's axis) adds doubt."""
    carried = [1] * 6 + [0] * 6
    offset, tag, angles, stds, jumps = bearings(carried)
    mirrored = np.concatenate([-angles - 1.0, angles], axis=1)  # each combination's mirror image first
    mirrored[::2, :2] = mirrored[::2, 2:] + 1.2  # elsewhere for every other bearing
    paired = np.tile(jumps, 2)
    kept = Choice(np.zeros(len(tag), dtype=int), np.zeros(len(tag)))
    got = choose(offset, tag, mirrored, np.tile(stds, 2), paired, [True], held(1), 4.0, kept)
    assert [int(paired[i, k]) for i, k in enumerate(got.choice)] == carried
    assert np.all(got.choice >= 2), "the candidate pointing at the tag, not its mirror image listed first"
    single = choose(offset, tag, angles, stds, jumps, [True], held(1), 4.0, kept)
    near = np.concatenate([angles, angles + math.radians(5.0)], axis=1)
    doubtful = choose(offset, tag, near, np.tile(stds, 2), paired, [True], held(1), 4.0, kept)
    assert [int(paired[i, k]) for i, k in enumerate(doubtful.choice)] == carried
    assert np.all(doubtful.doubt > single.doubt + math.radians(2.0) ** 2)
    away = np.delete(doubtful.doubt, [5, 6])  # the bearings around the step doubt their combination too
    assert np.all(away < math.radians(5.0) ** 2 / 2), "the chosen one stays the likelier"
