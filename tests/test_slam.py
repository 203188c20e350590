"""`slam` operator: messages in, poses/tags/diagnostics out; degenerate inputs never crash."""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np
import pytest
from slam_scenes import EXACT_COVARIANCE, angles, edge, scene, true_angle
from test_jumps import burst_candidates

from rover.geometry import quaternion_from_yaw
from rover.messages import header, make, serialize
from rover.operators.slam.operator import Slam, SlamParams
from rover.operators.slam.tag_status import TagState
from rover.testing import run_operator

START_NS = 1_000_000_000


def preintegration(sc, k: int):
    e = edge(sc, k)
    cov = np.zeros((9, 9))
    cov[np.ix_([3, 4, 6, 7], [3, 4, 6, 7])] = EXACT_COVARIANCE
    cov[[0, 1, 2, 5, 8], [0, 1, 2, 5, 8]] = 1e-10

    def vec(v: np.ndarray) -> Any:
        return make("geometry_msgs/msg/Vector3", x=float(v[0]), y=float(v[1]), z=0.0)

    def quat(yaw: float) -> Any:
        xyzw = map(float, quaternion_from_yaw(yaw))
        return make("geometry_msgs/msg/Quaternion", **dict(zip("xyzw", xyzw, strict=True)))

    return make(
        "rover_msgs/msg/Preintegration",
        header=header(stamp(sc, k), "world"),
        start=header(stamp(sc, k - 1)).stamp,
        dt=e.dt,
        orientation_start=quat(sc.yaw[k - 1]),
        orientation=quat(sc.yaw[k]),
        delta_velocity=vec(e.delta[0:2]),
        delta_position=vec(e.delta[2:4]),
        covariance=cov.ravel(),
        samples=20,
    )


def stamp(sc, k: int) -> int:
    return START_NS + int(round(sc.t[k] * 1e9))


def feed(op: Slam, sc, measured, with_aoa: bool = True):
    """An AoA at every epoch of the scene and the odometry from the previous one, as the runtime delivers them."""
    aoas = [
        make(
            "rover_msgs/msg/Aoa",
            header=header(stamp(sc, k), "base_link"),
            tag_id=tag + 1,
            channel=149 + 4 * tag,
            angle_rad=angle,
            std_rad=math.radians(1.0),
            packets=7,
        )
        for k, (tag, angle) in enumerate(measured)
    ]
    odometry = [preintegration(sc, k) for k in range(1, len(measured))]
    return run_operator(op, {"aoa": aoas if with_aoa else [], "odometry": odometry})


def statuses_agree_with_tags(out: list[Any]) -> dict[int, list[Any]]:
    """Each tag's status messages, checked against the tags published: at every TagArray the status
    last sent for each of its tags says localized exactly when it is published observable, and a
    status is sent when the state changes (the end's may repeat a state with a new reason)."""
    latest: dict[int, Any] = {}
    sent: dict[int, list[Any]] = {}
    for e in out:
        if e.port == "status":
            latest[e.msg.id] = e.msg
            sent.setdefault(e.msg.id, []).append(e.msg)
        elif e.port == "tags":
            for t in e.msg.tags:
                assert (latest[t.id].state == TagState.LOCALIZED) == t.observable, (t.id, latest[t.id].reason)
    for msgs in sent.values():
        states = [m.state for m in msgs[:-1]]
        assert all(a != b for a, b in zip(states, states[1:], strict=False)) and all(m.reason for m in msgs)
    return sent


def test_outputs_per_epoch_and_tags_localized():
    """26 s: each tag's bearings that left the window must come from 5 places (1 m cells) for a
    verdict; in 20 s of the 2 m circle only the first tag's do."""
    sc = scene(seconds=26.0)
    out = feed(Slam(SlamParams(window=20, aoa_std_scale=1.0)), sc, angles(sc))  # exact bearings, nothing shared
    by_port: dict[str, list[Any]] = {}
    for e in out:
        by_port.setdefault(e.port, []).append(e)
    n = len(sc.t)
    assert len(by_port["pose"]) == n - 1 and len(by_port["diagnostics"]) == n - 1
    assert len(by_port["trajectory"]) == n
    stamps = [p.msg.header.stamp.sec * 10**9 + p.msg.header.stamp.nanosec for p in by_port["trajectory"]]
    assert stamps == sorted(stamps) and stamps[0] == START_NS
    assert [e.stamp_ns for e in out] == sorted(e.stamp_ns for e in out)
    final = by_port["tags"][-1].msg.tags
    assert sorted(t.id for t in final) == [1, 2, 3, 4]
    for t in final:
        truth = sc.tags[t.id - 1]
        assert math.hypot(t.position.x - truth[0], t.position.y - truth[1]) < 0.01
        assert t.observable and t.channel == 149 + 4 * (t.id - 1)
    d = by_port["diagnostics"][-1].msg
    assert d.window_epochs == 20 and d.tags == 4 and d.iterations > 0
    timing = [e.msg for e in by_port["timing"]]
    assert len(timing) == len(by_port["diagnostics"]) and all(t.stage == "slam.update" and t.wall_s > 0 for t in timing)
    path = by_port["path"][-1].msg
    assert len(path.poses) == n
    sent = statuses_agree_with_tags(out)
    assert {i: msgs[-1].state for i, msgs in sent.items()} == dict.fromkeys([1, 2, 3, 4], TagState.LOCALIZED)


def test_each_pose_goes_out_with_its_covariance():
    """pose_covariance: the pose as sent; x and y's covariance symmetric, positive definite, and
    growing from the first pose (the world frame is that pose's) as the robot leaves it; yaw's the
    running sum of the odometry's rotation variance (1e-10 per increment here); z, roll and pitch 0."""
    sc = scene(seconds=12.0)
    out = feed(Slam(SlamParams(window=20, aoa_std_scale=1.0)), sc, angles(sc))
    poses = [e.msg for e in out if e.port == "pose"]
    with_cov = [e.msg for e in out if e.port == "pose_covariance"]
    assert len(with_cov) == len(poses) == len(sc.t) - 1
    for k, (pose, msg) in enumerate(zip(poses, with_cov, strict=True), start=1):
        assert msg.header == pose.header and msg.pose.pose == pose.pose
        cov = np.asarray(msg.pose.covariance).reshape(6, 6)
        assert np.all(np.linalg.eigvalsh(cov[:2, :2]) > 0) and cov[0, 1] == cov[1, 0]
        assert cov[5, 5] == pytest.approx(1e-10 * k, rel=1e-9)
        assert not cov[2:5].any() and not cov[:, 2:5].any()
    first, last = (np.asarray(m.pose.covariance).reshape(6, 6)[:2, :2] for m in (with_cov[0], with_cov[-1]))
    assert np.trace(last) > np.trace(first)


def test_a_tag_seen_over_too_little_parallax_is_not_published_localized(caplog):
    """8 s of the scene see the first tag over 8 deg: its window covariance is small (exact
    bearings) but it has no verdict, so it is published unlocalized, and the run's end says why."""
    sc = scene(seconds=8.0)
    op = Slam(SlamParams(window=20, aoa_std_scale=1.0))
    with caplog.at_level(logging.WARNING):
        out = feed(op, sc, angles(sc))
    first = next(t for t in [e for e in out if e.port == "tags"][-1].msg.tags if t.id == 1)
    assert math.hypot(first.position.x - sc.tags[0][0], first.position.y - sc.tags[0][1]) < 0.01
    assert math.sqrt(max(np.linalg.eigvalsh(op.window.tag_covariance[0]))) < 0.5
    assert not first.observable
    why = "its bearings span 8 deg seen from it (10 needed)"
    assert f"slam: tag 1 not localized at the end (judging): {why}" in caplog.text
    last = statuses_agree_with_tags(out)[1][-1]
    assert (last.state, last.reason) == (TagState.JUDGING, why)


def test_imu_only_and_stationary_runs_do_not_crash(caplog):
    sc = scene(seconds=3.0, speed_m_s=0.0)
    out = feed(Slam(SlamParams(window=10)), sc, angles(sc), with_aoa=False)
    assert not [e for e in out if e.port == "tags" and e.msg.tags]
    poses = [e.msg.pose.position for e in out if e.port == "trajectory"]
    assert len(poses) == len(sc.t) and max(abs(p.x) + abs(p.y) for p in poses) < 1e-3
    still = feed(Slam(SlamParams(window=10)), sc, angles(sc, noise_deg=1.0))
    assert not any(t.observable for t in [e for e in still if e.port == "tags"][-1].msg.tags)


def test_without_bearings_the_robot_is_its_odometry_alone():
    """`bearings: false` (the baseline of what the bearings add): the same poses as a run given no
    AoA at all, and no tag; with them the estimate differs."""
    sc = scene(seconds=4.0)
    measured = angles(sc, noise_deg=1.0)

    def poses(out):
        return [(p.msg.pose.position.x, p.msg.pose.position.y) for p in out if p.port == "trajectory"]

    off = feed(Slam(SlamParams(window=10, bearings=False)), sc, measured)
    alone = feed(Slam(SlamParams(window=10)), sc, measured, with_aoa=False)
    fused = feed(Slam(SlamParams(window=10)), sc, measured)
    assert poses(off) == poses(alone) and len(poses(off)) == len(sc.t)
    assert not any(e.msg.tags for e in off if e.port == "tags")
    sent = [e.msg for e in off if e.port == "bearings"]
    assert len(sent) == len(sc.t) and all(m.chosen == -1 for m in sent), "every AoA goes out, as not used"
    assert poses(fused) != poses(off)


def test_no_odometry_at_all_and_bad_angles_are_counted(caplog):
    op = Slam()
    bad = make("rover_msgs/msg/Aoa", header=header(START_NS), tag_id=1, angle_rad=float("nan"), std_rad=0.1)
    good = make("rover_msgs/msg/Aoa", header=header(START_NS + 1), tag_id=1, angle_rad=0.3, std_rad=0.1)
    with caplog.at_level(logging.WARNING):
        out = run_operator(op, {"aoa": [bad, good]})
    assert out == []
    assert "no epoch to estimate" in caplog.text
    assert op.drops == {"AoAs with a non-finite angle or std": 1}


def searched_tag_inputs() -> dict[str, list[Any]]:
    """20 s of one tag at (3, 2) whose bearings carry jump candidates (each burst's four
    combinations in a random order), and the odometry."""
    sc = scene(seconds=20.0, tags=((3.0, 2.0),))
    rng = np.random.default_rng(3)
    std = math.radians(3.0)
    aoas = []
    for k in range(len(sc.t)):
        jumps = rng.permutation(4)[None, :]
        candidates = burst_candidates(true_angle(sc, k, 0), 2, jumps, std, rng)[0]
        aoas.append(
            make(
                "rover_msgs/msg/Aoa",
                header=header(stamp(sc, k), "base_link"),
                tag_id=1,
                channel=149,
                angle_rad=float(candidates[0]),
                std_rad=std,
                packets=7,
                candidate_angles_rad=candidates.astype(np.float64),
                candidate_stds_rad=np.full(4, std),
                candidate_powers=np.full(4, 0.25),
                candidate_jumps=jumps[0].astype(np.uint16),
            )
        )
    return {"aoa": aoas, "odometry": [preintegration(sc, k) for k in range(1, len(sc.t))]}


def test_a_tag_search_runs_after_the_epochs_pose_and_is_timed():
    """A tag whose bearings carry jump candidates: the operator searches for it after the epoch's
    pose is out (one search per epoch at most, timed as `slam.search`), and finds it (20 s: its
    first jackknife sets its covariance, so a second one confirms it before it is published)."""
    out = run_operator(Slam(SlamParams(window=30, accel_bias=False)), searched_tag_inputs())
    searches = [(i, e) for i, e in enumerate(out) if e.port == "timing" and e.msg.stage == "slam.search"]
    assert searches and all(e.msg.wall_s > 0 for _, e in searches)
    pose_at = {e.stamp_ns: i for i, e in enumerate(out) if e.port == "pose"}
    assert all(pose_at[e.stamp_ns] < i for i, e in searches), "the pose goes out before the search"
    assert len({e.stamp_ns for _, e in searches}) == len(searches), "one search per epoch at most"
    final = [e.msg for e in out if e.port == "tags"][-1].tags
    assert [t.id for t in final if t.observable] == [1]
    assert math.hypot(final[0].position.x - 3.0, final[0].position.y - 2.0) < 0.2
    states = [m.state for m in statuses_agree_with_tags(out)[1]]
    assert states[0] == TagState.HEARD and states[-1] == TagState.LOCALIZED and TagState.JUDGING in states


class IdleCounted(Slam):
    idle_calls = 0

    def on_idle(self):
        self.idle_calls += 1
        return super().on_idle()


def test_search_steps_computed_ahead_in_idle_time_change_no_output():
    """The runtime calls `on_idle` while no input waits: the operator computes its search's steps
    ahead there, and the epochs that take them send what they would have sent without it."""
    inputs = searched_tag_inputs()
    inline = run_operator(Slam(SlamParams(window=30, accel_bias=False)), inputs)
    idle = IdleCounted(SlamParams(window=30, accel_bias=False))
    ahead = run_operator(idle, inputs, idle=True)
    assert idle.idle_calls > 10 and not idle.has_idle_work()

    def sent(out):
        return [(e.port, e.stamp_ns, serialize(e.msg)) for e in out if e.port != "timing"]

    assert sent(ahead) == sent(inline)
    assert [e.msg.tags[0].observable for e in ahead if e.port == "tags"][-1]


def test_paths_before_the_end_are_thinned_to_their_bound_and_the_last_is_whole():
    sc = scene(seconds=30.0)
    out = feed(Slam(SlamParams(window=20, path_every_s=1.0, path_max_poses=100)), sc, angles(sc))
    paths = [e.msg for e in out if e.port == "path"]
    trajectory = [e.msg for e in out if e.port == "trajectory"]
    assert len(sc.t) > 200 and len(paths) > 20
    for path in paths[:-1]:
        assert len(path.poses) <= 100
        stamps = [p.header.stamp.sec * 10**9 + p.header.stamp.nanosec for p in path.poses]
        assert stamps == sorted(stamps) and stamps[0] == START_NS, "thinned, in order, from the start"
    assert len(paths[-2].poses) == 100, "as many as allowed once the run is long enough"
    assert [p.header.stamp for p in paths[-1].poses] == [p.header.stamp for p in trajectory], "the last is whole"
