"""Finding a tag not yet localized from its bearings' jump candidates over the robot's path
(rover.operators.slam.tag_search). The candidates are physical (tests/test_jumps.py): a plane wave
from the tag reaches the triangle in the robot frame, its chains carry a jump combination, receiver
noise is added (at the level that gives the true angle a 3 deg std); each candidate is the angle of
the plane wave that best explains the response with one combination undone, turned to the world.
Undoing the carried combination gives the noisy truth; the others give the ghosts the card would."""

from __future__ import annotations

import itertools
import math
from dataclasses import replace

import numpy as np
from slam_scenes import scene
from test_jumps import angle_gap_deg, burst_candidates

from rover.geometry import wrap_angle
from rover.operators.slam import tag_search
from rover.operators.slam.search_scores import FREE, Bearings, model_costs, model_rates
from rover.operators.slam.tag_search import SearchSettings, by_combination, search

STD = math.radians(3.0)
TAG = np.array([2.0, 2.5])
COMBINATIONS = 4
"""5 GHz, three chains: chains 1 and 2 each jump by 0 or pi"""
BEARING_GAP_S = 0.4
"""time between a tag's bearings: one per sweep of four channels"""


def straight_then_turn(n: int = 80, straight_m: float = 4.0, radius_m: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Robot positions (n, 2) and headings along 4 m of the x axis then a quarter turn to the left."""
    arc = math.pi / 2 * radius_m
    s = np.linspace(0.0, straight_m + arc, n)
    turn = np.clip(s - straight_m, 0.0, None) / radius_m
    x = np.where(s <= straight_m, s, straight_m + radius_m * np.sin(turn))
    y = np.where(s <= straight_m, 0.0, radius_m * (1 - np.cos(turn)))
    return np.stack([x, y], axis=1), turn


def bearings(robot: np.ndarray, yaw: np.ndarray, carried: np.ndarray, seed: int = 0, tag: np.ndarray = TAG) -> Bearings:
    """BEARING_GAP_S apart, world candidate angles, stds and jump combinations (n, 4): one
    candidate per combination the AoA undoes, in a shuffled order per bearing, from a noisy burst
    whose chains carry the combination `carried` (n,); the true candidate's std is STD."""
    rng = np.random.default_rng(seed)
    d = tag[None, :] - robot
    local = np.arctan2(d[:, 1], d[:, 0]) - yaw
    jumps = np.array([rng.permutation(COMBINATIONS) for _ in robot])
    angles = yaw[:, None] + burst_candidates(local, np.asarray(carried), jumps, STD, rng)
    return Bearings(np.arange(len(robot)) * BEARING_GAP_S, robot, angles, np.full(angles.shape, STD), jumps)


def test_the_ghosts_are_not_near_the_truth():
    """The inputs are what the tests claim: the true combination's candidate is the noisy truth
    (but for a rare burst the triangle's back lobe wins), the others are far from it: a jump is
    not a small angle error."""
    robot, yaw = straight_then_turn()
    b = bearings(robot, yaw, np.full(len(robot), 3))
    d = TAG[None, :] - robot
    gap = angle_gap_deg(b.angles, np.arctan2(d[:, 1], d[:, 0])[:, None])
    true = gap[b.jumps == 3]
    assert np.mean(true < 5 * 3.0) >= 0.95
    assert np.all(gap[b.jumps != 3][np.repeat(true < 5 * 3.0, COMBINATIONS - 1)] > 30.0)


def used(found, b: Bearings) -> np.ndarray:
    """The combination of the candidate each inlier bearing uses."""
    inlier = found.choice >= 0
    return b.jumps[np.flatnonzero(inlier), found.choice[inlier]]


def test_a_jump_held_all_run_is_found_with_its_combination():
    robot, yaw = straight_then_turn()
    s = SearchSettings()
    for carried in (1, 2, 3):
        b = bearings(robot, yaw, np.full(len(robot), carried), seed=carried)
        found = search(b, s)
        assert found is not None and found.clear(s)
        assert found.combination == carried
        assert np.linalg.norm(found.position - TAG) < 0.2
        assert np.mean(found.choice >= 0) >= s.min_inliers
        assert np.all(used(found, b) == carried), "the true candidates are used"


def test_a_chain_stepping_twice_is_found_with_the_candidates_before_and_after():
    """The chains carry combination 1, step to 3 a third of the way and to 0 two thirds of the way
    (CSI Tool issues #23, #295): no one combination fits all the bearings, each bearing's best
    candidate leaves ghosts room; the sequence with two steps settles it, each bearing with the
    candidate of its own time."""
    robot, yaw = straight_then_turn(n=90)
    s = SearchSettings()
    carried = np.repeat([1, 3, 0], 30)
    b = bearings(robot, yaw, carried, seed=11)
    found = search(b, s)
    assert found is not None and found.clear(s), found
    assert np.linalg.norm(found.position - TAG) < 0.2
    assert found.combination == -1 and np.isfinite(found.redraw_rate)
    assert np.mean(used(found, b) == carried[found.choice >= 0]) > 0.95


def test_a_jump_at_every_retune_is_found_with_a_free_choice():
    robot, yaw = straight_then_turn()
    s = SearchSettings()
    carried = np.random.default_rng(7).integers(0, COMBINATIONS, len(robot))
    b = bearings(robot, yaw, carried, seed=8)
    found = search(b, s)
    assert found is not None and found.clear(s)
    assert found.combination == -1 and found.redraw_rate == FREE
    assert np.linalg.norm(found.position - TAG) < 0.3
    assert np.mean(used(found, b) == carried[found.choice >= 0]) > 0.9


def test_without_parallax_nothing_is_settled():
    """The robot turning on the spot (within 2 cm): the rays from one place cross anywhere along them."""
    _, yaw = straight_then_turn()
    robot = np.random.default_rng(3).normal(0.0, 0.01, (len(yaw), 2))
    s = SearchSettings()
    for carried in (np.full(len(yaw), 2), np.random.default_rng(4).integers(0, COMBINATIONS, len(yaw))):
        b = bearings(robot, yaw * 2, carried, seed=5)
        found = search(b, s)
        assert found is None or not found.clear(s)
        still = search(replace(b, robot=np.zeros_like(robot)), s)
        assert still is None or not still.clear(s)


def test_too_few_bearings_are_not_searched():
    robot, yaw = straight_then_turn()
    s = SearchSettings()
    b = bearings(robot, yaw, np.full(len(robot), 1))
    assert search(b.take(np.linspace(0, len(robot) - 1, s.min_bearings - 1).round().astype(int)), s) is None
    assert search(b.take(np.linspace(0, len(robot) - 1, s.min_bearings).round().astype(int)), s) is not None


def test_by_combination_keeps_every_candidate_of_a_bearing_that_lost_its_own():
    """A bearing whose candidate for the combination was merged into another's fits either way;
    a combination per bearing picks each one's own."""
    angles = np.array([[0.1, 0.2, 0.3, 0.4], [1.1, 1.2, 1.3, np.nan], [2.1, 2.2, np.nan, np.nan]])
    stds = np.array([[0.01, 0.02, 0.03, 0.04], [0.05, 0.06, 0.07, 1.0], [0.08, 0.09, 1.0, 1.0]])
    jumps = np.array([[0, 2, 1, 3], [0, 1, 3, -1], [2, 0, -1, -1]])
    a, s, source = by_combination(angles, stds, jumps, 2)
    assert a[0, 0] == 0.2 and s[0, 0] == 0.02 and np.all(np.isnan(a[0, 1:])) and source[0, 0] == 1
    np.testing.assert_array_equal(a[1], angles[1])  # no candidate of combination 2: all of them
    np.testing.assert_array_equal(s[1, :3], stds[1, :3])
    np.testing.assert_array_equal(source[1], [0, 1, 2, 3])
    assert a[2, 0] == 2.1 and np.all(np.isnan(a[2, 1:])) and source[2, 0] == 0
    a, s, source = by_combination(angles, stds, jumps, np.array([3, -1, 0]))
    assert a[0, 0] == 0.4 and source[0, 0] == 3
    np.testing.assert_array_equal(source[1], [0, 1, 2, 3])
    assert a[2, 0] == 2.2 and source[2, 0] == 1


def residuals2(q: np.ndarray, b: Bearings, cap: float) -> np.ndarray:
    """(n, K) each candidate's squared residual in stds at position q, capped; a padding one at the cap."""
    d = q[None, :] - b.robot
    r = ((np.arctan2(d[:, 1], d[:, 0])[:, None] - b.angles + np.pi) % (2 * np.pi) - np.pi) / b.stds
    return np.where(np.isfinite(r), np.minimum(r**2, cap**2), cap**2)


def free_cost(q: np.ndarray, b: Bearings, cap: float = 3.0) -> float:
    """The search's documented objective at position q with a combination drawn per bearing: over
    the bearings, the best candidate's squared residual in stds, capped, and log C a transition
    (written here from search_scores' docstring)."""
    combos = max(int(b.jumps.max()) + 1, 1)
    return float(residuals2(q, b, cap).min(axis=1).sum() + (len(b) - 1) * 2 * math.log(combos))


def sequence_cost(q: np.ndarray, b: Bearings, redraws_per_s: float, cap: float = 3.0) -> float:
    """The documented objective under a redraw rate, by brute force over every combination
    sequence (all C^n of them, as one array): each bearing its candidate of its combination (its
    best without one), each transition twice the -log of its chance: p / C to each other one,
    p = 1 - exp(-rate gap)."""
    r2 = residuals2(q, b, cap)
    combos = int(b.jumps.max()) + 1
    own = np.array(
        [
            [r2[k, b.jumps[k] == c][0] if (b.jumps[k] == c).any() else r2[k].min() for c in range(combos)]
            for k in range(len(b))
        ]
    )  # (n, C): each bearing's cost under each combination
    paths = np.array(list(itertools.product(range(combos), repeat=len(b))))  # (C^n, n)
    p = 1 - np.exp(-redraws_per_s * np.diff(b.times_s))
    stay, switch = -2 * np.log(1 - p * (combos - 1) / combos), -2 * np.log(p / combos)
    moved = paths[:, 1:] != paths[:, :-1]
    costs = own[np.arange(len(b)), paths].sum(axis=1) + np.where(moved, switch, stay).sum(axis=1)
    return float(costs.min())


def test_many_bearings_from_one_place_do_not_make_a_wrong_place_clear():
    """A robot that stood still for 200 bearings of the tag, then set off (2 s from rest): too
    little motion to settle anything, so whatever the search calls clear must be the tag.
    Failed with the search's first version: with a free choice per bearing, a place near the
    start fits the 200 bearings from one spot and a few of the drive's, and its margin was
    measured only against unrefined triangulations."""
    tag = np.array([3.0, 2.0])
    drive = scene(seconds=2.0, tags=(tuple(tag),))
    robot = np.concatenate([np.zeros((200, 2)), drive.position])
    yaw = np.concatenate([np.zeros(200), drive.yaw])
    s = SearchSettings()
    wrong = []
    for seed in range(10):
        b = bearings(robot, yaw, np.full(len(robot), 3), seed=seed, tag=tag)
        found = search(b, s)
        if found is not None and found.clear(s) and np.linalg.norm(found.position - tag) > 0.5:
            wrong.append(
                f"seed {seed}: clear at {found.position.round(2)} (combination {found.combination}, margin "
                f"{found.margin:.0f}), cost there {free_cost(found.position, b):.0f} "
                f"vs {free_cost(tag, b):.0f} at the tag"
            )
    assert not wrong, "\n".join(wrong)


def test_the_scores_are_the_documented_objective():
    """The search's vectorized scoring equals its objective written plainly, with candidates
    NaN-padded, angles given beyond +-pi, and a position on a robot position: for each step rate
    by brute force over every combination sequence (7 bearings, uneven gaps, a bearing without a
    candidate of its own for a combination), and for a combination per bearing."""
    robot, yaw = straight_then_turn()
    b = bearings(robot, yaw, np.repeat([1, 3], [40, len(robot) - 40]))
    angles = b.angles.copy()
    angles[::3, 2:] = np.nan
    angles[1::4] += 2 * np.pi * np.random.default_rng(1).integers(-2, 3, (len(angles[1::4]), 1))
    stds = b.stds * np.random.default_rng(2).uniform(0.5, 2.0, b.stds.shape)
    jumps = np.where(np.isfinite(angles), b.jumps, -1)
    b = replace(b, angles=angles, stds=stds, jumps=jumps)
    q = np.concatenate([np.random.default_rng(3).uniform(-3.0, 6.0, (30, 2)), TAG[None], robot[5:6]])
    rates = model_rates(COMBINATIONS)
    assert rates[-1] == FREE
    np.testing.assert_allclose(model_costs(q, b, 3.0)[-1], [free_cost(p, b) for p in q], rtol=1e-12)
    short = b.take(np.array([30, 33, 36, 39, 40, 41, 55]))
    short = replace(short, times_s=np.array([0.0, 0.4, 0.8, 5.0, 5.4, 65.0, 65.4]))
    for m, rate in enumerate(rates[:-1]):
        expected = [sequence_cost(p, short, rate) for p in q[::4]]
        np.testing.assert_allclose(model_costs(q[::4], short, 3.0)[m], expected, rtol=1e-9)


def test_a_tag_heard_long_is_scored_on_a_bounded_share_of_its_bearings(monkeypatch):
    """400 bearings: the hypotheses are scored on score_bearings of them spread over the path (the
    work of a search is bounded however long a tag waits), the winner refined on all of them."""
    robot, yaw = straight_then_turn(n=400)
    s = SearchSettings()
    b = bearings(robot, yaw, np.full(len(robot), 2), seed=4)
    scored: list[int] = []

    def spy(q, scored_bearings, cap):
        scored.append(len(scored_bearings))
        return score_steps(q, scored_bearings, cap)

    score_steps = tag_search.score_steps
    monkeypatch.setattr(tag_search, "score_steps", spy)
    found = search(b, s)
    assert scored and max(scored) <= s.score_bearings
    assert found is not None and found.clear(s) and found.combination == 2
    assert len(found.choice) == len(robot) and found.inliers >= s.min_inliers
    assert np.linalg.norm(found.position - TAG) < 0.2
    assert np.all(used(found, b) == 2)


def mirrored(robot: np.ndarray, yaw: np.ndarray, seed: int = 0) -> Bearings:
    """A 2-antenna card's bearings of TAG (half a wavelength apart, the axis along the robot's
    heading), its second chain off by pi all run: each burst two combinations' candidates, each an
    angle and its mirror image across the heading, in a random order. Undoing the pi (combination 1)
    gives the noisy truth; combination 0 the direction whose cosine to the axis is one off."""
    rng = np.random.default_rng(seed)
    d = TAG[None, :] - robot
    local = np.arctan2(d[:, 1], d[:, 0]) - yaw + rng.normal(0.0, STD, len(robot))
    ghost = np.arccos(np.clip(np.cos(local) - np.sign(np.cos(local)), -1.0, 1.0))
    angles = yaw[:, None] + np.stack([local, -local, ghost, -ghost], axis=1)
    jumps = np.tile([1, 1, 0, 0], (len(robot), 1))
    order = np.argsort(rng.uniform(size=angles.shape), axis=1)
    angles, jumps = np.take_along_axis(angles, order, axis=1), np.take_along_axis(jumps, order, axis=1)
    return Bearings(np.arange(len(robot)) * BEARING_GAP_S, robot, angles, np.full(angles.shape, STD), jumps)


def test_a_pairs_mirror_image_is_told_apart_by_the_turn():
    """Driving straight, the mirror image of a tag across the path fits the bearings as well as the
    tag: nothing is settled; the quarter turn after it tells them apart, and the tag is found with
    each bearing's candidate that points at it, the chains' combination held all along (each
    combination scored by the better of its two candidates, not each bearing's best of four)."""
    robot, yaw = straight_then_turn()
    s = SearchSettings()
    straight = np.flatnonzero(yaw == 0.0)
    d = TAG[None, :] - robot
    true = np.arctan2(d[:, 1], d[:, 0])
    for seed in range(3):
        b = mirrored(robot, yaw, seed)
        before = search(b.take(straight), s)
        assert before is not None and not before.clear(s), seed
        found = search(b, s)
        assert found is not None and found.clear(s), seed
        assert found.combination == 1 and found.redraw_rate != FREE, seed
        assert np.linalg.norm(found.position - TAG) < 0.2, (seed, found.position)
        used = b.angles[np.arange(len(b)), found.choice]
        inlier = found.choice >= 0
        assert np.all(np.abs(wrap_angle(used[inlier] - true[inlier])) < 4 * STD), seed
