"""The sliding-window estimator on synthetic scenes with exact odometry and known AoA noise."""

from __future__ import annotations

import copy
import dataclasses
import math

import numpy as np
from slam_scenes import EXACT_IMU, INDEPENDENT_BURSTS, Scene, angles, edge, estimate, scene, tag_errors, true_angle
from test_jumps import burst_candidates

from rover.operators.slam.layout import prior_tag
from rover.operators.slam.sliding_window import SlidingWindow, WindowSettings
from rover.operators.slam.tag_finder import CHECK_EVERY, SEARCH_HISTORY


def test_noise_free_matches_truth_to_millimetres():
    sc = scene(seconds=12.0)
    w, final = estimate(sc, WindowSettings(window=30, **INDEPENDENT_BURSTS), angles(sc), std_deg=1.0)
    assert tag_errors(sc, w).max() < 0.005
    assert np.abs(final - sc.position).max() < 0.01
    assert w.observable().all()


def test_single_tag_from_a_straight_line_is_triangulated():
    sc = scene(seconds=10.0, radius_m=None, tags=((3.0, 2.0),))
    w, final = estimate(sc, WindowSettings(window=30), angles(sc), std_deg=1.0)
    assert tag_errors(sc, w)[0] < 0.01


def test_a_tag_seen_from_one_place_is_not_reported_known():
    sc = scene(seconds=5.0, speed_m_s=0.0, tags=((3.0, 2.0),))
    w, _ = estimate(sc, WindowSettings(window=30), angles(sc, noise_deg=2.0), std_deg=2.0)
    assert not w.observable()[0]
    major = math.sqrt(np.linalg.eigvalsh(w.tag_covariance[0])[-1])
    assert major > 5 * tag_errors(sc, w)[0] or major > 1.0


def test_huber_resists_wrong_path_bearings():
    sc = scene(seconds=15.0)
    measured = angles(sc, noise_deg=2.0, outliers=0.2, seed=3)
    robust, _ = estimate(sc, WindowSettings(window=30, **INDEPENDENT_BURSTS), measured, std_deg=2.0, update_every=2)
    plain = estimate(
        sc, WindowSettings(window=30, huber_sigma=1e4, **INDEPENDENT_BURSTS), measured, 2.0, update_every=2
    )[0]
    assert tag_errors(sc, robust).mean() < 0.5 * tag_errors(sc, plain).mean()


def test_marginalized_window_matches_the_full_batch():
    """Without bias states (this odometry is exact): with them, a 12 s circle leaves the scale to 1
    degree bearings, and the bearings the window linearized early hold it where it was then."""
    sc = scene(seconds=12.0)
    measured = angles(sc, noise_deg=1.0, seed=5)
    window, _ = estimate(sc, WindowSettings(window=15, **EXACT_IMU), measured, std_deg=1.0)
    batch, _ = estimate(sc, WindowSettings(window=10_000, **EXACT_IMU), measured, std_deg=1.0, update_every=10)
    assert np.abs(window.tag_positions() - batch.tag_positions()).max() < 0.06


def test_an_accelerometer_bias_is_estimated_and_taken_out():
    """Odometry from an IMU with a 2.5 mg bias, levelled on a still start (the world-frame part
    cancels the body-frame part at the start heading): the bias states find it and the trajectory
    holds; without them it drifts by metres."""
    sc = scene(seconds=25.0)
    body = np.array([0.02, -0.015])
    bias = np.concatenate([body, -body])  # heading 0 at the start: c + R(0) b = 0
    measured = angles(sc, noise_deg=1.0, seed=5)
    runs = {
        on: estimate(sc, WindowSettings(window=30, accel_bias=on), measured, 1.0, bias=bias, levelled_std_m_s2=1e-3)
        for on in (True, False)
    }
    (w, final), (_, drifted) = runs[True], runs[False]
    assert np.abs(w.bias() - bias).max() < 1e-3
    assert np.linalg.norm(final - sc.position, axis=1).max() < 0.15
    assert tag_errors(sc, w).max() < 0.1
    assert np.linalg.norm(drifted - sc.position, axis=1).max() > 1.0


def test_a_wheel_scale_error_is_estimated_through_the_marginalization():
    """Wheels reading 4% over the true speed, a 15-epoch window over 20 s of a circle: the scale state
    finds it from the IMU's speed (it keeps what left the window) and the path follows the IMU's
    scale; with the error taken for noise instead, the wheels pull the path out by their 4%."""
    sc = scene(seconds=20.0)
    measured = angles(sc, noise_deg=1.0, seed=5)
    (w, final), (plain, pulled) = (
        estimate(
            sc,
            WindowSettings(**EXACT_IMU, window=15, wheel_speed_std_m_s=1e-3, wheel_scale=on),
            measured,
            1.0,
            wheel_reads=1.04,
        )
        for on in (True, False)
    )
    std = math.sqrt(w.bias_covariance[-1, -1])
    assert abs(w.wheel_scale() - 0.04) < max(3 * std, 1e-3) and std < 0.003
    assert plain.wheel_scale() == 0.0 and plain.biases == 0
    assert np.linalg.norm(final - sc.position, axis=1).max() < 0.05
    assert np.linalg.norm(pulled - sc.position, axis=1).max() > 2 * np.linalg.norm(final - sc.position, axis=1).max()


def test_noisy_wheel_readings_do_not_bias_the_scale():
    """Wheels reading 4% over, with 5 mm/s of white noise, and an IMU that keeps the speed to 1 mm/s
    an epoch: over eight noise draws the scale's mean is the Bayesian estimate's (the truth shrunk
    toward the prior's 0 by the share of information the data holds). Taken as the coefficient of
    the scale (f'v = z (1 - s)), the noisy reading makes least squares read noise as scale (errors in
    variables): that landed 0.7% above it, beyond three standard errors of the mean."""
    sc = scene(seconds=20.0)
    measured = angles(sc, noise_deg=1.0, seed=5)
    settings = WindowSettings(**EXACT_IMU, window=15)
    covariance = np.diag([1e-6, 1e-6, 1e-8, 1e-8])
    found, stds = [], []
    for seed in range(8):
        w, _ = estimate(
            sc,
            settings,
            measured,
            1.0,
            wheel_reads=1.04,
            wheel_noise_m_s=0.005,
            seed=seed,
            covariance=covariance,
            update_every=5,
        )
        found.append(w.wheel_scale())
        stds.append(math.sqrt(w.bias_covariance[-1, -1]))
    data_share = 1 - np.mean(stds) ** 2 / settings.wheel_scale_std**2
    expected = data_share * 0.04
    assert abs(np.mean(found) - expected) < 3 * np.std(found) / math.sqrt(len(found))


def test_ranges_are_not_biased_short_at_10_degrees():
    """The pseudolinear cross product shrinks ranges as noise grows; the atan2 refinement must not.
    (Exact odometry and no bias states: the scale is the odometry's, the ranges the bearings'.)"""
    ratios = []
    for seed in range(3):
        sc = scene(seconds=15.0)
        settings = WindowSettings(window=30, **EXACT_IMU)
        w, final = estimate(sc, settings, angles(sc, noise_deg=10.0, seed=seed), std_deg=10.0, update_every=2)
        order = [w.tag_ids.index(i + 1) for i in range(len(sc.tags))]
        tags = w.tag_positions()[order]
        est = np.linalg.norm(tags[None] - final[:, None], axis=2).mean(axis=0)
        true = np.linalg.norm(sc.tags[None] - sc.position[:, None], axis=2).mean(axis=0)
        ratios.append(est / true)
    assert np.mean(ratios) > 0.95


# -- bearings with phase-jump candidates (issue 14) ---------------------------------------------------

JUMP_STD = math.radians(3.0)


def jump_bearing(sc: Scene, k: int, carried: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Robot-frame candidates (1, 4) of tag 0 at epoch k, one per jump combination undone (shuffled),
    from a noisy burst whose chains carry `carried` (tests/test_jumps.py), and their combinations."""
    jumps = rng.permutation(4)[None, :]
    return burst_candidates(true_angle(sc, k, 0), carried, jumps, JUMP_STD, rng), jumps


def run_with_jumps(carried: np.ndarray, seed: int = 0, update_every: int = 2, seconds: float = 15.0):
    """An arc of `seconds` with tag 1 (jump candidates) and tag 2 (one angle, no jumps) heard in
    turn; the window and, after each update, tag 1's (active, covariance, position, bearings waiting)."""
    sc = scene(seconds=seconds, tags=((3.0, 2.0), (-1.0, 2.5)))
    rng = np.random.default_rng(seed)
    w = SlidingWindow(WindowSettings(window=30, **EXACT_IMU))
    trace = []
    for k in range(len(sc.t)):
        if k % 2 == 0:
            candidates, jumps = jump_bearing(sc, k, int(carried[k]), rng)
            tag_id = 1
        else:
            candidates, jumps = np.array([[true_angle(sc, k, 1) + rng.normal(0.0, JUMP_STD)]]), None
            tag_id = 2
        stds = np.full(candidates.shape, JUMP_STD)
        w.add_epoch(
            int(sc.t[k] * 1e9), float(sc.yaw[k]), [tag_id], candidates, stds, edge(sc, k) if k else None, jumps=jumps
        )
        if k % update_every == 0 or k == len(sc.t) - 1:
            w.find_tags()
            w.update()
            t = w.tag_ids.index(1)
            trace.append(
                (w.active[t], w.tag_covariance[t].copy(), w.tag_positions()[t].copy(), len(w.finder.history.get(t, [])))
            )
    return sc, w, trace


def window_choices(w: SlidingWindow, slot: int) -> tuple[np.ndarray, np.ndarray]:
    """The jump combination of the candidate each of the tag's bearings in the window uses now, and
    the index of its epoch in the window."""
    used, where = [], []
    for k, e in enumerate(w.epochs):
        for j in np.flatnonzero(e.tags == slot):
            used.append(e.candidate_jumps[j, e.choice[j]])
            where.append(k)
    return np.array(used), np.array(where)


def test_a_tag_with_jump_candidates_waits_for_the_search_then_holds_its_combination():
    """Once-per-run jumps: the tag's bearings are not used (its covariance stays the prior, its
    estimate its first guess) until the search has found it; then it is used, lands near the
    truth, and the max-mixture settles on the combination the chains carry."""
    carried = 3
    sc, w, trace = run_with_jumps(np.full(150, carried))
    t, other = w.tag_ids.index(1), w.tag_ids.index(2)
    assert w.active[other], "a tag with one candidate per bearing is used from the start"
    waiting = [row for row in trace if not row[0]]
    assert 0 < len(waiting) < len(trace), "the tag waits, and is found before the end"
    prior = WindowSettings().tag_prior_std_m ** 2 * np.eye(2)
    for _, cov, position, _ in waiting:
        np.testing.assert_allclose(cov, prior, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(position, waiting[0][2], rtol=0, atol=1e-9)
    assert [row[3] for row in waiting] == sorted(row[3] for row in waiting)
    assert waiting[-1][3] >= w.finder.search.min_bearings
    assert all(row[0] for row in trace[len(waiting) :]), "once found, used for good"
    assert [i for i, _ in w.finder.found] == [1] and w.finder.found[0][1].combination == carried
    # a single 3 deg bearing at 3 m is 0.16 m off sideways: dozens over the arc do better
    assert np.linalg.norm(w.tag_positions()[t] - sc.tags[0]) < 0.16
    assert w.locked(t) == carried
    assert max(set(w.jumps.recent[t]), key=w.jumps.recent[t].count) == carried
    used, _ = window_choices(w, t)
    assert len(used) > 10 and np.mean(used == carried) >= 0.9
    assert w.observable()[t]


STEP_DWELLS = 2
"""a chain stepping mid-run is followed within this many of the tag's dwells"""


def test_a_chain_stepping_mid_run_is_followed_and_the_tag_stays_within_3_sigma():
    """The chains carry combination 3 for 15 s, then one chain steps (combination 1) and stays so for
    15 s more: the bearings after the step take the new combination's candidate within STEP_DWELLS
    of the tag's dwells, and the published estimate stays within 3 standard deviations of its own
    covariance throughout (a hard lock onto the held combination kept the old one, and the tag
    drifted off with a tight covariance)."""
    carried = np.r_[np.full(150, 3), np.full(150, 1)]
    sc, w, trace = run_with_jumps(carried, seconds=30.0)
    t = w.tag_ids.index(1)
    final = [
        (round(e.stamp_ns / 1e8), int(e.candidate_jumps[j, e.choice[j]]))
        for e in [*w.left, *w.epochs]
        for j in np.flatnonzero(e.tags == t)
    ]
    after = [combination for k, combination in final if k >= 150]
    wrong = [i for i, combination in enumerate(after) if combination != 1]
    assert len(after) > 50 and (not wrong or max(wrong) < STEP_DWELLS), wrong
    sigmas = [math.sqrt((p - sc.tags[0]) @ np.linalg.solve(cov, p - sc.tags[0])) for on, cov, p, _ in trace if on]
    assert len(sigmas) > 50 and max(sigmas) <= 3.0, max(sigmas)
    assert np.linalg.norm(w.tag_positions()[t] - sc.tags[0]) < 0.16


def test_a_tag_whose_jumps_change_at_every_retune_is_found_but_holds_none():
    carried = np.random.default_rng(11).integers(0, 4, 150)
    sc, w, trace = run_with_jumps(carried, seed=1)
    t = w.tag_ids.index(1)
    assert not trace[0][0] and trace[-1][0]
    assert w.finder.found[0][1].combination == -1, "no combination is shared by its bearings"
    assert np.linalg.norm(w.tag_positions()[t] - sc.tags[0]) < 0.16
    assert w.locked(t) is None
    used, where = window_choices(w, t)
    epoch_index = {e.stamp_ns: round(e.stamp_ns / 1e8) for e in w.epochs}
    truth = carried[[epoch_index[w.epochs[k].stamp_ns] for k in where]]
    assert len(used) > 10 and np.mean(used == truth) >= 0.9, "each bearing picks the combination it carries"


def test_a_tag_waiting_longer_than_the_search_history_is_still_searched():
    """The robot stands still for more bearings of the tag than the search keeps (no parallax: not
    found), then drives; the next search must still happen and find it."""
    still_s = (SEARCH_HISTORY + 50) * 0.1
    drive = scene(seconds=15.0, tags=((3.0, 2.0),))
    n = int(round(still_s / 0.1))
    sc = Scene(
        np.concatenate([np.arange(n) * 0.1, still_s + drive.t]),
        np.concatenate([np.zeros((n, 2)), drive.position]),
        np.concatenate([np.zeros((n, 2)), drive.velocity]),
        np.concatenate([np.zeros(n), drive.yaw]),
        drive.tags,
    )
    rng = np.random.default_rng(2)
    w = SlidingWindow(WindowSettings(window=10, **EXACT_IMU))
    for k in range(len(sc.t)):
        candidates, jumps = jump_bearing(sc, k, 1, rng)
        w.add_epoch(
            int(sc.t[k] * 1e9),
            float(sc.yaw[k]),
            [1],
            candidates,
            np.full(candidates.shape, JUMP_STD),
            edge(sc, k) if k else None,
            jumps=jumps,
        )
        if k < n and k % 10 == 0:
            w.find_tags()  # searched while still: nothing settles
            assert not w.active[0]
    assert w.find_tags() > 0  # one search that sees the whole drive
    assert w.active[0] and w.finder.found[0][1].combination == 1
    assert np.linalg.norm(w.tag_positions()[0] - sc.tags[0]) < 0.16


def test_searches_go_a_few_steps_at_a_time_the_longest_waiting_first():
    """Two tags with jump candidates wait unsearched, tag 1 heard more often: a call of
    find_tags(steps=2) takes two steps of tag 1's search; the search goes on from where it was
    at the next calls (tag 2's after it), and ends where an uninterrupted search ends."""
    sc = scene(seconds=12.0, tags=((3.0, 2.0), (-1.0, 2.5)))
    rng = np.random.default_rng(5)
    w = SlidingWindow(WindowSettings(window=30, **EXACT_IMU))
    for k in range(len(sc.t)):
        tag = 0 if k % 3 else 1  # tag 1 at two epochs of three
        jumps = rng.permutation(4)[None, :]
        candidates = burst_candidates(true_angle(sc, k, tag), 1, jumps, JUMP_STD, rng)
        w.add_epoch(
            int(sc.t[k] * 1e9),
            float(sc.yaw[k]),
            [tag + 1],
            candidates,
            np.full(candidates.shape, JUMP_STD),
            edge(sc, k) if k else None,
            jumps=jumps,
        )
    whole = copy.deepcopy(w)
    assert whole.find_tags() > 4 and whole.finder.found, "the uninterrupted searches find a tag"
    one, two = w.tag_ids.index(1), w.tag_ids.index(2)
    assert w.finder.heard[one] > w.finder.heard[two] >= w.finder.search.min_bearings and not w.finder.searched
    assert w.find_tags(steps=2) == 2
    assert w.finder.searching is not None and w.finder.searching.tag == one and list(w.finder.searched) == [one]
    calls = 1
    while w.find_tags(steps=2):
        calls += 1
        assert w.finder.searching is None or w.finder.searching.tag in (one, two)
    assert calls > 2 and sorted(w.finder.searched) == sorted([one, two])
    assert w.active == whole.active and [i for i, _ in w.finder.found] == [i for i, _ in whole.finder.found]
    for (_, a), (_, b) in zip(w.finder.found, whole.finder.found, strict=True):
        np.testing.assert_array_equal(a.position, b.position)


def test_the_covariances_are_the_blocks_of_the_informations_inverse():
    """Tags, shared states and the newest epoch's position (the pose's covariance) from one solve:
    each the matching block of the inverse of a dense information matrix."""
    from rover.operators.slam.information import covariances
    from rover.operators.slam.layout import Shape

    shape = Shape(epochs=5, slots=2, tags=3, biases=2)
    rng = np.random.default_rng(3)
    root = rng.normal(size=(shape.states, shape.states))
    info = root @ root.T + shape.states * np.eye(shape.states)
    inverse = np.linalg.inv(info)
    tags, shared, newest = covariances(info, shape)
    for t in range(shape.tags):
        block = shape.tag(t)
        np.testing.assert_allclose(tags[t], inverse[block, block], rtol=1e-10)
    np.testing.assert_allclose(shared, inverse[shape.shared_states, shape.shared_states], rtol=1e-10)
    last = shape.position(shape.epochs - 1)
    np.testing.assert_allclose(newest, inverse[last, last], rtol=1e-10)


def test_information_with_a_direction_nothing_holds_gives_infinite_covariances():
    from rover.operators.slam.information import covariances
    from rover.operators.slam.layout import Shape

    shape = Shape(epochs=2, slots=1, tags=1)
    info = np.eye(shape.states)
    info[shape.tag(0), shape.tag(0)] = 0.0
    tags, _shared, newest = covariances(info, shape)
    assert np.isinf(tags).all() and np.isinf(newest).all()


def test_a_tags_prior_scaled_down_and_back_is_as_it_was():
    """The window scales a tag's part of the prior with its bearings' weight, either way
    (integrity.TagIntegrity.weight): by 1/k, only the tag's own block and its ties lose information,
    and scaled back by k the prior is as it was, so a jackknife's passing overestimate takes
    nothing from the tag for good."""
    sc = scene(seconds=12.0)
    w, _ = estimate(sc, WindowSettings(window=15, **EXACT_IMU), angles(sc, noise_deg=1.0, seed=2), std_deg=1.0)
    before = w.prior
    assert before is not None
    tag = prior_tag(1)
    down = before.relaxed(tag, 1.0 / 4.0)
    np.testing.assert_allclose(down.info[tag, tag], before.info[tag, tag] / 4.0)
    np.testing.assert_allclose(down.info[0:4, 0:4], before.info[0:4, 0:4])
    back = down.relaxed(tag, 4.0)
    np.testing.assert_allclose(back.info, before.info, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(back.grad, before.grad, rtol=1e-12, atol=1e-12)


def checked_after_moving(place_offset_m: np.ndarray, **search: float):
    """A tag with once-per-run jumps found and in use (15 s of arc); then its estimate set
    `place_offset_m` from where the window had it (as chosen candidates fitting a wrong place would
    hold it) and a check search due and run, with `search` overriding the search settings."""
    sc, w, _ = run_with_jumps(np.full(150, 3))
    t = w.tag_ids.index(1)
    assert w.active[t] and len(w.finder.found) == 1
    w.finder.search = dataclasses.replace(w.finder.search, **search)
    before = w.tag_positions()[t] + place_offset_m
    w.x[w.shape.tag(t)] = before
    w.finder.checked[t] = w.finder.heard[t] - CHECK_EVERY
    assert w.find_tags() > 0 and w.finder.searching is None
    return sc, w, t, before


def test_a_check_search_moves_a_tag_in_use_whose_place_its_bearings_contradict():
    """Every CHECK_EVERY bearings the search runs again over a tag in use, every candidate weighed:
    a place 2 m off, which the window's chosen candidates would hold, is contradicted, and where the
    search's own place is clear the tag is put there, as a found tag."""
    sc, w, t, before = checked_after_moving(np.array([2.0, -1.0]))
    assert len(w.finder.found) == 2, "placed again"
    assert np.linalg.norm(w.tag_positions()[t] - sc.tags[0]) < 0.16
    assert t not in w.integrity.doubts


def test_a_contradicted_tag_the_search_cannot_settle_is_not_published():
    """The same, with a search that cannot call its own place clear (it would need every bearing an
    inlier): the tag stays where the window had it, and says why it is not localized."""
    _, w, t, before = checked_after_moving(np.array([2.0, -1.0]), min_inliers=1.01)
    assert len(w.finder.found) == 1
    np.testing.assert_array_equal(w.tag_positions()[t], before)
    reason = w.integrity.verdict(t)
    assert reason is not None and reason.startswith("a search over its") and "m away" in reason


def test_a_check_search_leaves_a_right_place_alone():
    sc, w, t, before = checked_after_moving(np.zeros(2))
    assert len(w.finder.found) == 1 and t not in w.integrity.doubts
    np.testing.assert_array_equal(w.tag_positions()[t], before)
