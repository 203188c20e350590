"""Finding a tag not yet localized from its bearings' jump candidates over the robot's path
(rover.operators.slam.tag_search). The candidates are physical (tests/test_jumps.py): a plane wave
from the tag reaches the triangle in the robot frame, its chains carry a jump combination, receiver
noise is added (at the level that gives the true angle a 3 deg std); each candidate is the angle of
the plane wave that best explains the response with one combination undone, turned to the world.
Undoing the carried combination gives the noisy truth; the others give the ghosts the card would."""

from __future__ import annotations

import math

import numpy as np
from slam_scenes import scene
from test_jumps import angle_gap_deg, burst_candidates

from rover.operators.slam import tag_search
from rover.operators.slam.tag_search import SearchSettings, _scores, by_combination, search

STD = math.radians(3.0)
TAG = np.array([2.0, 2.5])
COMBINATIONS = 4
"""5 GHz, three chains: chains 1 and 2 each jump by 0 or pi"""


def straight_then_turn(n: int = 80, straight_m: float = 4.0, radius_m: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Robot positions (n, 2) and headings along 4 m of the x axis then a quarter turn to the left."""
    arc = math.pi / 2 * radius_m
    s = np.linspace(0.0, straight_m + arc, n)
    turn = np.clip(s - straight_m, 0.0, None) / radius_m
    x = np.where(s <= straight_m, s, straight_m + radius_m * np.sin(turn))
    y = np.where(s <= straight_m, 0.0, radius_m * (1 - np.cos(turn)))
    return np.stack([x, y], axis=1), turn


def bearings(robot: np.ndarray, yaw: np.ndarray, carried: np.ndarray, seed: int = 0, tag: np.ndarray = TAG):
    """World candidate angles, stds and jump combinations (n, 4): one candidate per combination the
    AoA undoes, in a shuffled order per bearing, from a noisy burst whose chains carry the
    combination `carried` (n,); the true candidate's std is STD."""
    rng = np.random.default_rng(seed)
    d = tag[None, :] - robot
    local = np.arctan2(d[:, 1], d[:, 0]) - yaw
    jumps = np.array([rng.permutation(COMBINATIONS) for _ in robot])
    angles = yaw[:, None] + burst_candidates(local, np.asarray(carried), jumps, STD, rng)
    return angles, np.full(angles.shape, STD), jumps


def test_the_ghosts_are_not_near_the_truth():
    """The inputs are what the tests claim: the true combination's candidate is the noisy truth
    (but for a rare burst the triangle's back lobe wins), the others are far from it: a jump is
    not a small angle error."""
    robot, yaw = straight_then_turn()
    angles, _, jumps = bearings(robot, yaw, np.full(len(robot), 3))
    d = TAG[None, :] - robot
    gap = angle_gap_deg(angles, np.arctan2(d[:, 1], d[:, 0])[:, None])
    true = gap[jumps == 3]
    assert np.mean(true < 5 * 3.0) >= 0.95
    assert np.all(gap[jumps != 3][np.repeat(true < 5 * 3.0, COMBINATIONS - 1)] > 30.0)


def test_a_jump_held_all_run_is_found_with_its_combination():
    robot, yaw = straight_then_turn()
    s = SearchSettings()
    for carried in (1, 2, 3):
        angles, stds, jumps = bearings(robot, yaw, np.full(len(robot), carried), seed=carried)
        found = search(robot, angles, stds, s, jumps)
        assert found is not None and found.clear(s)
        assert found.combination == carried
        assert np.linalg.norm(found.position - TAG) < 0.2
        inlier = found.choice >= 0
        assert inlier.mean() >= s.min_inliers
        assert np.all(jumps[np.flatnonzero(inlier), found.choice[inlier]] == carried), "the true candidates are used"


def test_a_jump_at_every_retune_is_found_with_a_free_choice():
    robot, yaw = straight_then_turn()
    s = SearchSettings()
    carried = np.random.default_rng(7).integers(0, COMBINATIONS, len(robot))
    angles, stds, jumps = bearings(robot, yaw, carried, seed=8)
    found = search(robot, angles, stds, s, jumps)
    assert found is not None and found.clear(s)
    assert found.combination == -1
    assert np.linalg.norm(found.position - TAG) < 0.3
    inlier = found.choice >= 0
    right = jumps[np.flatnonzero(inlier), found.choice[inlier]] == carried[inlier]
    assert right.mean() > 0.9


def test_without_parallax_nothing_is_settled():
    """The robot turning on the spot (within 2 cm): the rays from one place cross anywhere along them."""
    _, yaw = straight_then_turn()
    robot = np.random.default_rng(3).normal(0.0, 0.01, (len(yaw), 2))
    s = SearchSettings()
    for carried in (np.full(len(yaw), 2), np.random.default_rng(4).integers(0, COMBINATIONS, len(yaw))):
        angles, stds, jumps = bearings(robot, yaw * 2, carried, seed=5)
        found = search(robot, angles, stds, s, jumps)
        assert found is None or not found.clear(s)
        still = search(np.zeros_like(robot), angles, stds, s, jumps)
        assert still is None or not still.clear(s)


def test_too_few_bearings_are_not_searched():
    robot, yaw = straight_then_turn()
    s = SearchSettings()
    angles, stds, jumps = bearings(robot, yaw, np.full(len(robot), 1))
    pick = np.linspace(0, len(robot) - 1, s.min_bearings - 1).round().astype(int)
    assert search(robot[pick], angles[pick], stds[pick], s, jumps[pick]) is None
    pick = np.linspace(0, len(robot) - 1, s.min_bearings).round().astype(int)
    assert search(robot[pick], angles[pick], stds[pick], s, jumps[pick]) is not None


def test_by_combination_keeps_every_candidate_of_a_bearing_that_lost_its_own():
    """A bearing whose candidate for the combination was merged into another's fits either way."""
    angles = np.array([[0.1, 0.2, 0.3, 0.4], [1.1, 1.2, 1.3, np.nan], [2.1, 2.2, np.nan, np.nan]])
    stds = np.array([[0.01, 0.02, 0.03, 0.04], [0.05, 0.06, 0.07, 1.0], [0.08, 0.09, 1.0, 1.0]])
    jumps = np.array([[0, 2, 1, 3], [0, 1, 3, -1], [2, 0, -1, -1]])
    a, s, source = by_combination(angles, stds, jumps, 2)
    assert a[0, 0] == 0.2 and s[0, 0] == 0.02 and np.all(np.isnan(a[0, 1:])) and source[0, 0] == 1
    np.testing.assert_array_equal(a[1], angles[1])  # no candidate of combination 2: all of them
    np.testing.assert_array_equal(s[1, :3], stds[1, :3])
    np.testing.assert_array_equal(source[1], [0, 1, 2, 3])
    assert a[2, 0] == 2.1 and np.all(np.isnan(a[2, 1:])) and source[2, 0] == 0


def free_cost(q: np.ndarray, robot: np.ndarray, angles: np.ndarray, stds: np.ndarray, cap: float = 3.0) -> float:
    """The search's documented objective at position q: over the bearings, the best candidate's
    squared residual in stds, capped (written here from the module docstring)."""
    d = q[None, :] - robot
    r = ((np.arctan2(d[:, 1], d[:, 0])[:, None] - angles + np.pi) % (2 * np.pi) - np.pi) / stds
    return float(np.sum(np.minimum(np.nanmin(np.where(np.isfinite(r), r**2, np.inf), axis=1), cap**2)))


def test_many_bearings_from_one_place_do_not_make_a_wrong_place_clear():
    """A robot that stood still for 200 bearings of the tag, then set off (2 s from rest): too
    little motion to settle anything, so whatever the search calls clear must be the tag.
    Fails with tag_search as written: with a free choice per bearing, a place near the start fits
    the 200 bearings from one spot and a few of the drive's; its margin is measured only against
    unrefined triangulations and not against the per-combination results (one of which scores
    the true place lower), so it is called clear although the cost at the tag is lower."""
    tag = np.array([3.0, 2.0])
    drive = scene(seconds=2.0, tags=(tuple(tag),))
    robot = np.concatenate([np.zeros((200, 2)), drive.position])
    yaw = np.concatenate([np.zeros(200), drive.yaw])
    s = SearchSettings()
    wrong = []
    for seed in range(10):
        angles, stds, jumps = bearings(robot, yaw, np.full(len(robot), 3), seed=seed, tag=tag)
        found = search(robot, angles, stds, s, jumps)
        if found is not None and found.clear(s) and np.linalg.norm(found.position - tag) > 0.5:
            wrong.append(
                f"seed {seed}: clear at {found.position.round(2)} (combination {found.combination}, margin "
                f"{found.margin:.0f}), cost there {free_cost(found.position, robot, angles, stds):.0f} "
                f"vs {free_cost(tag, robot, angles, stds):.0f} at the tag"
            )
    assert not wrong, "\n".join(wrong)


def test_the_scores_are_the_documented_objective():
    """The search's vectorized scoring equals its objective written plainly (free_cost), with
    candidates NaN-padded, angles given beyond +-pi, and a position on a robot position."""
    robot, yaw = straight_then_turn()
    angles, stds, _ = bearings(robot, yaw, np.full(len(robot), 1))
    angles[::3, 2:] = np.nan
    angles[1::4] += 2 * np.pi * np.random.default_rng(1).integers(-2, 3, (len(angles[1::4]), 1))
    stds = stds * np.random.default_rng(2).uniform(0.5, 2.0, stds.shape)
    q = np.concatenate([np.random.default_rng(3).uniform(-3.0, 6.0, (50, 2)), TAG[None], robot[5:6]])
    expected = [free_cost(p, robot, angles, stds) for p in q]
    np.testing.assert_allclose(_scores(q, robot, angles, stds, 3.0), expected, rtol=1e-12, atol=1e-9)


def test_a_tag_heard_long_is_scored_on_a_bounded_share_of_its_bearings(monkeypatch):
    """400 bearings: the hypotheses are scored on score_bearings of them spread over the path (the
    work of a search is bounded however long a tag waits), the winner refined on all of them."""
    robot, yaw = straight_then_turn(n=400)
    s = SearchSettings()
    angles, stds, jumps = bearings(robot, yaw, np.full(len(robot), 2), seed=4)
    scored: list[int] = []

    def spy(q, robot_xy, *rest):
        scored.append(len(robot_xy))
        return score_steps(q, robot_xy, *rest)

    score_steps = tag_search._score_steps
    monkeypatch.setattr(tag_search, "_score_steps", spy)
    found = search(robot, angles, stds, s, jumps)
    assert scored and max(scored) <= s.score_bearings
    assert found is not None and found.clear(s) and found.combination == 2
    assert len(found.choice) == len(robot) and found.inliers >= s.min_inliers
    assert np.linalg.norm(found.position - TAG) < 0.2
    inlier = found.choice >= 0
    assert np.all(jumps[np.flatnonzero(inlier), found.choice[inlier]] == 2)
