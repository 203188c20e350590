"""Whether a localized tag's covariance covers its error (rover.operators.slam.integrity): the block
jackknife over the places its bearings were taken from, against a plain implementation and in the
statistics it is for."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import least_squares

from rover.geometry import parallax_deg
from rover.operators.slam.integrity import (
    CELL_M,
    CELLS_M,
    CONFIRM_INFLATION,
    MAX_VARIANCE_FACTOR,
    MAX_WEIGHT,
    MIN_CELLS,
    MIN_PARALLAX_DEG,
    MIN_VERDICT_BEARINGS,
    WEIGHT_STEP,
    TagIntegrity,
    disagreeing,
    inflation,
    jackknife_covariance,
    jackknife_spread,
    small_sample_factor,
    variance_factor,
)

TAG = np.array([3.0, 2.0])
HUBER = 1.5
NOWHERE = np.zeros((0, 2))
"""no bearings of the tag in the window"""


def rectangle(step_m: float = 0.1) -> np.ndarray:
    """Robot positions every `step_m` around a 6 x 4 m rectangle about the tag."""
    corners = np.array([[0.0, 0.0], [6.0, 0.0], [6.0, 4.0], [0.0, 4.0], [0.0, 0.0]])
    points = []
    for a, b in zip(corners[:-1], corners[1:], strict=True):
        n = round(np.linalg.norm(b - a) / step_m)
        points.append(a + np.outer(np.arange(n) / n, b - a))
    return np.concatenate(points)


def bearings(robot: np.ndarray, tag: np.ndarray, noise_rad: np.ndarray) -> np.ndarray:
    d = tag[None, :] - robot
    return np.arctan2(d[:, 1], d[:, 0]) + noise_rad


def fit(robot: np.ndarray, angles: np.ndarray, stds: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Weighted least squares on the angles (scipy), the estimate."""

    def residual(q: np.ndarray) -> np.ndarray:
        d = q[None, :] - robot
        return (np.angle(np.exp(1j * (np.arctan2(d[:, 1], d[:, 0]) - angles)))) / stds

    return least_squares(residual, start, xtol=1e-12, ftol=1e-12, gtol=1e-12).x


def naive_covariance(q: np.ndarray, robot: np.ndarray, stds: np.ndarray) -> np.ndarray:
    """The covariance that takes the bearings as independent: the inverse of J^T W J."""
    d = q[None, :] - robot
    jac = np.stack([-d[:, 1], d[:, 0]], axis=1) / (np.sum(d**2, axis=1) * stds)[:, None]
    return np.linalg.inv(jac.T @ jac)


def test_the_jackknife_is_the_leave_one_cell_out_spread_written_plainly():
    """Against scipy's least squares on each cell left out in turn (no bearing beyond the Huber
    threshold here, so every weight is its std's)."""
    rng = np.random.default_rng(1)
    robot = rectangle()
    stds = np.full(len(robot), math.radians(2.0))
    angles = bearings(robot, TAG, rng.normal(0.0, math.radians(1.0), len(robot)))
    estimate = fit(robot, angles, stds, TAG)
    cells = np.floor(robot / CELL_M).astype(int)
    keys = np.unique(cells, axis=0)
    left_out = []
    for key in keys:
        keep = ~np.all(cells == key, axis=1)
        left_out.append(fit(robot[keep], angles[keep], stds[keep], estimate))
    dev = np.array(left_out) - np.mean(left_out, axis=0)
    expected = (len(keys) - 1) / len(keys) * dev.T @ dev * small_sample_factor(len(keys))
    got = jackknife_covariance(estimate, robot, angles, stds, HUBER)
    assert got is not None
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-12)


def test_with_independent_errors_the_covariance_needs_no_inflation():
    """Bearings erring independently: the jackknife (without its small-sample factor) agrees with
    the covariance that takes them as independent, within its own sampling spread."""
    robot = rectangle()
    stds = np.full(len(robot), math.radians(2.0))
    ratios = []
    for seed in range(20):
        rng = np.random.default_rng(seed)
        angles = bearings(robot, TAG, rng.normal(0.0, math.radians(2.0), len(robot)))
        estimate = fit(robot, angles, stds, TAG)
        jack = jackknife_covariance(estimate, robot, angles, stds, HUBER)
        assert jack is not None
        cells = len(np.unique(np.floor(robot / CELL_M).astype(int), axis=0))
        ratios.append(np.trace(jack) / small_sample_factor(cells) / np.trace(naive_covariance(estimate, robot, stds)))
    assert 0.6 < np.median(ratios) < 1.6


def shared_offset_sigmas(offset_cell_m: float, runs: int = 200) -> np.ndarray:
    """(runs, 3): the estimate's error in sigmas of the covariance that takes the bearings as
    independent, of it scaled to cover the 1 m jackknife, and scaled to cover the jackknives at
    every size of CELLS_M; each square cell of side `offset_cell_m` bends its bearings by an offset
    of its own (3 deg, as clutter near the robot does) on top of independent 1 deg noise, stated as
    2 deg."""
    assert CELLS_M[0] == CELL_M == 1.0
    robot = rectangle()
    stds = np.full(len(robot), math.radians(2.0))
    cells = np.unique(np.floor(robot / offset_cell_m).astype(int), axis=0, return_inverse=True)[1].ravel()
    sigmas = []
    for seed in range(runs):
        rng = np.random.default_rng(seed)
        offset = rng.normal(0.0, math.radians(3.0), cells.max() + 1)[cells]
        angles = bearings(robot, TAG, offset + rng.normal(0.0, math.radians(1.0), len(robot)))
        estimate = fit(robot, angles, stds, TAG)
        cov = naive_covariance(estimate, robot, stds)
        error = estimate - TAG
        k = [inflation(cov, jackknife_covariance(estimate, robot, angles, stds, HUBER, cell)) for cell in CELLS_M]
        sigmas.append([math.sqrt(error @ np.linalg.solve(scale * cov, error)) for scale in (1.0, k[0], max(k))])
    return np.array(sigmas)


def test_errors_shared_within_a_place_are_covered_once_inflated():
    """Offsets shared by 1 m cells: taken as independent, the covariance leaves a third of the
    estimates beyond 3 sigma; scaled to cover the jackknife, about a 2-D Gaussian's 1.1%."""
    beyond = np.mean(shared_offset_sigmas(1.0) > 3, axis=0)
    assert beyond[0] > 0.3
    assert beyond[1] <= 0.02 and beyond[2] <= 0.02


def test_errors_shared_over_longer_stretches_are_covered_at_the_larger_cells():
    """Offsets shared by 2 m cells (a scatterer's bend lasting longer at walking speed): the 1 m
    jackknife sees half of them move together with their neighbour and leaves more than a
    Gaussian's share beyond 3 sigma; scaled to cover the jackknives at every size in CELLS_M,
    about a 2-D Gaussian's 1.1% again."""
    beyond = np.mean(shared_offset_sigmas(2.0) > 3, axis=0)
    assert beyond[1] > 0.03
    assert beyond[2] <= 0.02


def test_the_small_sample_factor_is_hotellings():
    """Simulated: with B cells, a 2-D error measured in a covariance estimated on B - 1 degrees of
    freedom and scaled by the factor is beyond 3 sigma as often as a Gaussian's is in its own."""
    rng = np.random.default_rng(5)
    for cells in (6, 12, 30):
        error = rng.standard_normal((20_000, 2))
        samples = rng.standard_normal((20_000, cells - 1, 2))
        estimate = np.einsum("tki,tkj->tij", samples, samples) / (cells - 1) * small_sample_factor(cells)
        sigmas2 = np.einsum("ti,ti->t", error, np.linalg.solve(estimate, error[..., None])[..., 0])
        assert np.mean(sigmas2 > 9) == pytest.approx(math.exp(-4.5), abs=0.003), cells
    assert small_sample_factor(20) == pytest.approx(1.37, abs=0.01)


def test_few_places_say_nothing_and_leave_the_covariance_as_it_is():
    robot = rectangle()[:40]  # 4 m of one side: 4 cells
    assert len(np.unique(np.floor(robot / CELL_M).astype(int), axis=0)) < MIN_CELLS
    stds = np.full(len(robot), 0.03)
    assert jackknife_covariance(TAG, robot, bearings(robot, TAG, np.zeros(len(robot))), stds, HUBER) is None
    assert inflation(np.eye(2), None) == 1.0
    assert inflation(np.eye(2), np.eye(2) * 0.5) == 1.0
    assert inflation(np.eye(2), np.diag([0.5, 4.0])) == pytest.approx(4.0)
    assert inflation(np.eye(2), np.full((2, 2), np.inf)) == math.inf


def test_a_tag_is_judged_on_the_bearings_it_has_when_due():
    """Started from the search's bearings the jackknife is due at once; then every EVERY_BEARINGS."""
    from rover.operators.slam.integrity import EVERY_BEARINGS

    robot = rectangle()
    angles = bearings(robot, TAG, np.random.default_rng(3).normal(0.0, 0.05, len(robot)))
    stds = np.full(len(robot), 0.03)
    trust = TagIntegrity()
    trust.start(0, robot[:100], angles[:100], stds[:100])
    cov = np.eye(2) * 1e-6
    trust.judge(0, TAG, cov, NOWHERE, HUBER, 1.0)
    first = trust.scale[0]
    assert first > 1.0 and trust.due[0] == EVERY_BEARINGS
    np.testing.assert_allclose(trust.scaled(np.stack([cov, cov]), 0.0)[0], first * cov)
    np.testing.assert_array_equal(trust.scaled(np.stack([cov, cov]), 0.0)[1], cov)  # a tag not judged keeps its own
    source = trust.scaled(np.stack([cov, cov]), 0.05)
    np.testing.assert_allclose(source, [first * cov + 0.05**2 * np.eye(2), cov + 0.05**2 * np.eye(2)])
    for r, a, s in zip(robot[100 : 100 + EVERY_BEARINGS - 1], angles[100:], stds[100:], strict=False):
        trust.add(0, r, float(a), float(s))
    trust.judge(0, TAG, cov, NOWHERE, HUBER, 1.0)
    assert trust.scale[0] == first, "not due yet: the last jackknife holds"
    trust.add(0, robot[150], float(angles[150]), float(stds[150]))
    assert trust.due[0] == 0
    trust.judge(0, TAG, cov, NOWHERE, HUBER, 1.0)
    assert trust.due[0] == EVERY_BEARINGS and len(trust.seen[0]) == 100 + EVERY_BEARINGS
    trust.scale[0] = math.inf
    assert np.all(np.isinf(trust.scaled(cov[None], 0.05)[0])), "a tag the jackknife cannot pin is published unlocalized"


def test_a_tag_is_published_only_once_judged_from_enough_places_and_parallax():
    """A tag in use from its first bearing (one candidate each) has no verdict until
    MIN_VERDICT_BEARINGS left the window; then its bearings, judged and in the window, must span
    MIN_PARALLAX_DEG seen from it, and the judged ones come from MIN_CELLS places (before that the
    jackknife cannot check its covariance)."""
    robot = rectangle()
    first = MIN_VERDICT_BEARINGS  # the first 1.2 m of the rectangle: 2 cells
    cov = np.eye(2) * 1e-4

    def judged(tag: np.ndarray, gone: int, window: np.ndarray = NOWHERE) -> TagIntegrity:
        trust = TagIntegrity()
        for r in robot[:gone]:
            trust.add(0, r, float(bearings(r[None], tag, np.zeros(1))[0]), 0.03)
        trust.judge(0, tag, cov, window, HUBER, 1.0)
        return trust

    far, near = np.array([3.0, 12.0]), np.array([0.6, 0.8])
    assert judged(far, first - 1).verdict(0) == (
        f"{first - 1} of its bearings left the window, {MIN_VERDICT_BEARINGS} needed to judge it"
    )
    seen = parallax_deg(far, robot[:first])
    assert seen < MIN_PARALLAX_DEG, "from 1.2 m of path the far tag is seen over a few degrees"
    assert (
        judged(far, first).verdict(0)
        == f"its bearings span {seen:.0f} deg seen from it ({MIN_PARALLAX_DEG:.0f} needed)"
    )
    assert parallax_deg(near, robot[:first]) >= MIN_PARALLAX_DEG
    assert (
        judged(near, first).verdict(0)
        == f"its judged bearings were taken from fewer than {MIN_CELLS} places (1 m cells)"
    )
    assert judged(far, first, robot[first:60]).verdict(0) is not None, "the window's bearings add parallax, not places"
    assert judged(far, 60).verdict(0) is None, "6 m of path: 6 places, and 23 deg"


def test_a_first_jackknife_that_must_inflate_much_waits_for_a_second():
    """Bearings erring alike per 1 m cell: the first jackknife must inflate the window's covariance
    (taken as independent) more than CONFIRM_INFLATION, so the tag waits for a second one; exact
    bearings need nothing, and the first look lets them out."""
    robot = rectangle()[:80]  # 8 m: 8 places
    stds = np.full(len(robot), math.radians(2.0))
    cells = np.floor(robot / 1.0).astype(int)
    _, cell = np.unique(cells, axis=0, return_inverse=True)
    shared = np.random.default_rng(7).normal(0.0, math.radians(6.0), cell.max() + 1)[cell.ravel()]
    verdicts = {}
    for name, noise in (("alike", shared), ("exact", np.zeros(len(robot)))):
        angles = bearings(robot, TAG, noise)
        trust = TagIntegrity()
        cov = naive_covariance(TAG, robot[:60], stds[:60])
        for r, a in zip(robot[:60], angles[:60], strict=True):
            trust.add(0, r, float(a), float(stds[0]))
        trust.judge(0, TAG, cov, NOWHERE, HUBER, 1.0)
        first = trust.verdict(0)
        for r, a in zip(robot[60:], angles[60:], strict=True):
            trust.add(0, r, float(a), float(stds[0]))
        trust.judge(0, TAG, cov, NOWHERE, HUBER, 1.0)
        verdicts[name] = (first, trust.verdict(0), trust.inflated[0])
    first, second, k = verdicts["alike"]
    assert k > CONFIRM_INFLATION
    assert first is not None and "first jackknife inflated its covariance" in first
    assert second is None, "a second jackknife has looked: the covariance it scales is published"
    assert verdicts["exact"][0] is None


def test_a_window_converged_near_the_robot_is_not_published_and_the_true_place_may_be():
    """A window fed bearings with persistent errors from a short stretch of path can converge to a
    wrong crossing near the robot, where a small covariance is easy (a real building's bearings
    replayed: 6-11 m off at 0.05-0.2 m stds, the bearings' median residual 60 deg there against 6 at
    the true place). Its verdict says its place does not explain them, where its covariance alone
    (taking the bearings as independent) is under 0.1 m; the true place's verdict, residuals within
    their stds, lets it be published."""
    path = np.stack([np.linspace(0.0, 8.0, 80), np.zeros(80)], axis=1)  # 6 m judged, then 2 m more
    robot = path[:60]
    truth, wrong = np.array([4.0, 5.0]), np.array([1.0, 0.6])
    std = math.radians(6.0)
    angles = bearings(path, truth, np.random.default_rng(5).normal(0.0, std, len(path)))
    verdicts = []
    for place in (wrong, truth):
        trust = TagIntegrity()
        cov = naive_covariance(place, robot, np.full(len(robot), std))
        for part in (slice(0, 60), slice(60, None)):  # two jackknives, the second 20 bearings on
            for r, a in zip(path[part], angles[part], strict=True):
                trust.add(0, r, float(a), std)
            trust.judge(0, place, cov, NOWHERE, HUBER, 1.0)
        verdicts.append(trust.verdict(0))
    assert math.sqrt(np.linalg.eigvalsh(naive_covariance(wrong, robot, np.full(len(robot), std))).max()) < 0.1
    assert verdicts[0] is not None and "its place does not explain them" in verdicts[0]
    assert verdicts[1] is None


def test_a_tag_whose_bearings_keep_disagreeing_is_re_examined():
    counts: dict[int, int] = {}
    tags = np.array([0, 0, 0, 1, 1, 1])
    most = np.array([True, True, False, False, False, True])
    localized = np.array([True, True])
    for _ in range(2):
        assert disagreeing(counts, tags, most, localized, 3) == []
    assert counts == {0: 2, 1: 0}
    assert disagreeing(counts, tags, most, localized, 3) == [0] and counts[0] == 0
    assert disagreeing(counts, tags, most, np.array([False, True]), 3) == [] and counts[0] == 0
    assert disagreeing(counts, tags, most, localized, 0) == []


def test_the_variance_factor_says_how_much_wider_the_bearings_scatter_than_stated():
    """Residuals twice as wide as the bursts' stds say give about 4 (the window's stds are the
    bursts' times the scale); a tenth of them wild (a wall's image) moves it by less than half
    where a mean square would be 50 times over; as stated, about 1. About: within 3 of the spread
    of a median-based variance from 1,000 bearings (its relative std sqrt(5.4 / n) = 7%)."""
    robot = rectangle(step_m=0.02)
    rng = np.random.default_rng(9)
    burst = np.full(len(robot), math.radians(2.0))
    wide = rng.normal(0.0, math.radians(4.0), len(robot))
    clean = variance_factor(TAG, robot, bearings(robot, TAG, wide), burst * 4, 4.0)
    assert clean == pytest.approx(4.0, rel=0.22)
    wide[::10] = rng.uniform(-math.pi, math.pi, len(wide[::10]))
    wild = variance_factor(TAG, robot, bearings(robot, TAG, wide), burst * 4, 4.0)
    assert clean < wild < 1.5 * clean
    assert np.mean((wide / burst) ** 2) > 50 * clean
    stated = rng.normal(0.0, math.radians(2.0), len(robot))
    assert variance_factor(TAG, robot, bearings(robot, TAG, stated), burst, 1.0) == pytest.approx(1.0, rel=0.22)
    assert variance_factor(TAG, robot[:0], np.zeros(0), np.zeros(0), 4.0) == 0.0


def test_a_tag_whose_bearings_err_alike_is_weighed_down_by_what_its_jackknife_says():
    """Offsets shared by 1 m cells: the jackknife's spread is several times the covariance that
    takes the bearings as independent. Judged again and again with the window's covariance at the
    weight it set (the window's bearings' variance times `weight`), the weight climbs by at most
    WEIGHT_STEP a verdict and settles where that covariance covers the jackknives' spreads (at
    every size of CELLS_M); with independent errors it stays about 1; it is never below 1, nor
    above MAX_WEIGHT."""

    robot = rectangle()
    stds = np.full(len(robot), math.radians(2.0))
    cells = np.unique(np.floor(robot / CELL_M).astype(int), axis=0, return_inverse=True)[1].ravel()
    rng = np.random.default_rng(7)
    shared = rng.normal(0.0, math.radians(3.0), cells.max() + 1)[cells]
    for offset, settles in ((shared, True), (np.zeros(len(robot)), False)):
        angles = bearings(robot, TAG, offset + rng.normal(0.0, math.radians(1.0), len(robot)))
        estimate = fit(robot, angles, stds, TAG)
        naive = naive_covariance(estimate, robot, stds)
        spreads = [jackknife_spread(estimate, robot, angles, stds, HUBER, cell) for cell in CELLS_M]
        assert all(s is not None for s in spreads)
        target = max(np.linalg.eigvals(np.linalg.solve(naive, s[0])).real.max() for s in spreads if s is not None)
        trust = TagIntegrity()
        trust.start(0, robot, angles, stds)
        weights = []
        for _ in range(12):
            trust.due[0] = 0
            trust.judge(0, estimate, naive * trust.weight.get(0, 1.0), NOWHERE, HUBER, 1.0)
            weights.append(trust.weight[0])
        steps = np.diff([1.0, *weights])
        assert np.all(np.array(weights) >= 1.0) and np.all(np.array(weights) <= MAX_WEIGHT)
        assert np.all(np.array(weights[1:]) / np.array(weights[:-1]) <= WEIGHT_STEP + 1e-9)
        if settles:
            assert target > WEIGHT_STEP, "the shared offsets make the jackknife more than one step above the naive"
            assert weights[0] == pytest.approx(WEIGHT_STEP) and steps[0] > 0
            assert weights[-1] == pytest.approx(target, rel=1e-6)
        else:
            assert weights[-1] == pytest.approx(max(1.0, min(target, WEIGHT_STEP)), rel=1e-6) and target < 2.0
        np.testing.assert_allclose(trust.std_factor(np.array([0, 0, 1])), [math.sqrt(weights[-1])] * 2 + [1.0])


def test_a_tag_whose_place_does_not_explain_its_bearings_is_not_weighed_down():
    """Half its bearings beyond 3 of their stds (a variance factor above MAX_VARIANCE_FACTOR): the
    estimate is wrong, not its covariance, and the bearings that would move it keep their weight."""
    robot = rectangle()
    stds = np.full(len(robot), math.radians(1.0))
    angles = bearings(robot, TAG, np.zeros(len(robot)))
    wrong = TAG + np.array([1.5, -1.0])
    trust = TagIntegrity()
    trust.start(0, robot, angles, stds)
    trust.judge(0, wrong, np.eye(2) * 1e-6, NOWHERE, HUBER, 1.0)
    assert trust.factor[0] > MAX_VARIANCE_FACTOR and trust.weight.get(0, 1.0) == 1.0


def test_a_tag_on_its_way_keeps_its_weight_until_it_settles():
    """An estimate that moved since its last jackknife by more than one std of what the jackknives
    say it is uncertain by is still on its way (the robot positions they hold fixed were pulled
    with it): its weight is not lowered then, and is once it holds still."""
    robot = rectangle()
    stds = np.full(len(robot), math.radians(2.0))
    angles = bearings(robot, TAG, np.random.default_rng(3).normal(0.0, math.radians(1.0), len(robot)))
    estimate = fit(robot, angles, stds, TAG)
    wide = naive_covariance(estimate, robot, stds) * 50.0
    """a window covariance that covers the jackknives many times over: the weight would go down"""
    trust = TagIntegrity()
    trust.start(0, robot, angles, stds)
    trust.weight[0] = 64.0
    trust.judge(0, estimate - np.array([0.3, 0.0]), wide, NOWHERE, HUBER, 1.0)
    assert trust.weight[0] == pytest.approx(64.0 / WEIGHT_STEP), "the first jackknife has nothing to compare with"
    trust.due[0] = 0
    trust.judge(0, estimate, wide, NOWHERE, HUBER, 1.0)
    assert trust.weight[0] == pytest.approx(64.0 / WEIGHT_STEP), "moved 30 cm against a jackknife of centimetres: held"
    trust.due[0] = 0
    trust.judge(0, estimate, wide, NOWHERE, HUBER, 1.0)
    assert trust.weight[0] == pytest.approx(64.0 / WEIGHT_STEP**2), "still: lowered by a step"
    narrow = naive_covariance(estimate, robot, stds) / 50.0
    """a window covariance the jackknives are far beyond: the weight goes up, moving or not"""
    trust.due[0] = 0
    trust.judge(0, estimate + np.array([0.3, 0.0]), narrow, NOWHERE, HUBER, 1.0)
    assert trust.weight[0] == pytest.approx(64.0 / WEIGHT_STEP), "on its way, and raised"
