"""The simulator's clutter (rover.datasets.clutter): scatterers and the direct path's shadowing,
which give the bearings the heavy, persistent errors of a real building."""

from __future__ import annotations

import math

import numpy as np
from helpers import read_bag
from test_simulate import TINY, bartlett

from rover.datasets.clutter import PATH_CLEARANCE_M, WALL_MARGIN_M, Scatterers, place_scatterers, shadowing_db
from rover.datasets.radio import backscatter_csi, true_aoa
from rover.datasets.scenario import load_scenario
from rover.datasets.simulate import antenna_positions, simulate
from rover.geometry import wrap_angle


def test_shadowing_has_its_std_and_decorrelates_over_its_distance():
    """Gudmundson's model: a stationary Gaussian, correlation exp(-d / distance) along the path."""
    along = np.arange(0.0, 20_000.0, 0.05)
    shadow = shadowing_db(along, 4.0, 1.5, np.random.default_rng(1))
    assert abs(np.mean(shadow)) < 0.2 and abs(np.std(shadow) - 4.0) < 0.2
    for lag_m in (0.5, 1.5, 4.5):
        k = round(lag_m / 0.05)
        r = np.corrcoef(shadow[:-k], shadow[k:])[0, 1]
        assert abs(r - math.exp(-lag_m / 1.5)) < 0.05, (lag_m, r)
    assert np.all(shadowing_db(along[:10], 0.0, 1.5, np.random.default_rng(1)) == 0)


def test_scatterers_stand_in_the_room_with_a_log_normal_reflectivity():
    s = place_scatterers((9.0, 5.0), 4000, 0.15, 6.0, np.random.default_rng(2))
    assert s.xy.shape == (4000, 2)
    assert s.xy.min() >= WALL_MARGIN_M and np.all(s.xy.max(axis=0) <= np.array([9.0, 5.0]) - WALL_MARGIN_M)
    power_db = 20 * np.log10(s.reflectivity_m / 0.15)
    assert abs(np.median(power_db)) < 0.5 and abs(np.std(power_db) - 6.0) < 0.3


def test_scatterers_keep_clear_of_the_robots_path():
    """The robot drives around furniture: a scatterer on its path made a ghost source the robot
    drove through (`paper` seed 6: a tag found 1.75 m off at 6.6 sigma). A lane along the room's
    middle stays empty; a path leaving no room leaves no scatterer."""
    lane = np.stack([np.linspace(0.0, 9.0, 400), np.full(400, 2.5)], axis=1)
    s = place_scatterers((9.0, 5.0), 200, 0.15, 6.0, np.random.default_rng(4), lane)
    assert len(s.xy) == 200 and np.all(np.abs(s.xy[:, 1] - 2.5) >= PATH_CLEARANCE_M)
    everywhere = np.stack(np.meshgrid(np.arange(0.0, 9.1, 0.2), np.arange(0.0, 5.1, 0.2)), axis=-1).reshape(-1, 2)
    assert len(place_scatterers((9.0, 5.0), 5, 0.15, 6.0, np.random.default_rng(4), everywhere).xy) == 0


def test_a_shadowed_direct_path_lets_a_near_scatterer_take_the_bearing():
    """The physics of a heavy error: in a room without walls to reflect, a scatterer 1 m from the
    robot, 20 dB under the direct path, bends the bearing by less than 5 deg; as the direct path is
    shadowed the bearing swings toward the scatterer (three antennas do not resolve the two: the
    bearing is their blend), to within 15 deg of it at 30 dB."""
    antennas = antenna_positions(load_scenario("paper"))
    tag, robot, yaw = np.array([5.0, 2.0]), np.array([[1.0, 1.0]]), np.zeros(1)
    scatterer = Scatterers(np.array([[1.0, 2.0]]), np.array([0.1]))
    bearings = []
    for shadow_db in (0.0, 10.0, 20.0, 30.0):
        csi, _ = backscatter_csi(
            np.array([4.5, 4.6]), tag, robot, yaw, antennas, 165, 149, (9, 5), 0.0, shadow_db, scatterer
        )
        bearings.append(bartlett(csi[0], 149, antennas))
    to_tag, to_scatterer = true_aoa(tag, robot, yaw)[0], true_aoa(scatterer.xy[0], robot, yaw)[0]
    assert math.degrees(abs(wrap_angle(bearings[0] - to_tag))) < 5.0
    assert np.all(np.diff(bearings) > 0), "toward the scatterer, more the more the direct path is shadowed"
    assert math.degrees(abs(wrap_angle(bearings[-1] - to_scatterer))) < 15.0


def test_clutter_changes_the_csi_and_nothing_else(tmp_path):
    """It draws from a stream of its own: the motion, the IMU, the wheels and the truth stay
    byte-identical, the CSI is stamped alike but differs."""
    plain, cluttered = tmp_path / "plain.mcap", tmp_path / "cluttered.mcap"
    simulate(load_scenario("paper", TINY), 3, plain)
    clutter = {"room.scatterers": "10", "room.shadowing_db": "4"}
    simulate(load_scenario("paper", {**TINY, **clutter}), 3, cluttered)
    a, b = read_bag(plain), read_bag(cluttered)
    for topic in ("/imu/data", "/odom", "/groundtruth/pose", "/groundtruth/aoa", "/groundtruth/tags"):
        assert [(s, d) for t, s, d in a if t == topic] == [(s, d) for t, s, d in b if t == topic]
    assert [s for t, s, _ in a if t == "/csi"] == [s for t, s, _ in b if t == "/csi"]
    assert [d for t, _, d in a if t == "/csi"] != [d for t, _, d in b if t == "/csi"]
