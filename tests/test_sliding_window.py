"""The sliding-window estimator on synthetic scenes with exact odometry and known AoA noise."""

from __future__ import annotations

import math

import numpy as np
from slam_scenes import angles, estimate, scene, tag_errors

from rover.operators.slam.sliding_window import WindowSettings


def test_noise_free_matches_truth_to_millimetres():
    sc = scene(seconds=12.0)
    w, final = estimate(sc, WindowSettings(window=30), angles(sc), std_deg=1.0)
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
    robust, _ = estimate(sc, WindowSettings(window=30), measured, std_deg=2.0, update_every=2)
    plain, _ = estimate(sc, WindowSettings(window=30, huber_sigma=1e4), measured, std_deg=2.0, update_every=2)
    assert tag_errors(sc, robust).mean() < 0.5 * tag_errors(sc, plain).mean()


def test_marginalized_window_matches_the_full_batch():
    sc = scene(seconds=12.0)
    measured = angles(sc, noise_deg=1.0, seed=5)
    window, _ = estimate(sc, WindowSettings(window=15), measured, std_deg=1.0)
    batch, _ = estimate(sc, WindowSettings(window=10_000), measured, std_deg=1.0, update_every=10)
    assert np.abs(window.tag_positions() - batch.tag_positions()).max() < 0.06


def test_ranges_are_not_biased_short_at_10_degrees():
    """The pseudolinear cross product shrinks ranges as noise grows; the atan2 refinement must not."""
    ratios = []
    for seed in range(3):
        sc = scene(seconds=15.0)
        w, final = estimate(
            sc, WindowSettings(window=30), angles(sc, noise_deg=10.0, seed=seed), std_deg=10.0, update_every=2
        )
        order = [w.tag_ids.index(i + 1) for i in range(len(sc.tags))]
        tags = w.tag_positions()[order]
        est = np.linalg.norm(tags[None] - final[:, None], axis=2).mean(axis=0)
        true = np.linalg.norm(sc.tags[None] - sc.position[:, None], axis=2).mean(axis=0)
        ratios.append(est / true)
    assert np.mean(ratios) > 0.95
