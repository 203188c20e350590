"""`preintegration`: IMU motion between epochs against the simulator's ground truth, and its start-up logic."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
from helpers import T0_NS, read_bag

from rover.datasets.scenario import load_scenario
from rover.datasets.simulate import simulate
from rover.geometry import rpy_matrix, wrap_angle, yaw_from_quaternion
from rover.messages import deserialize, header, make
from rover.operators.preintegration.operator import Preintegration, PreintegrationParams

EPOCH_NS = 400_000_000


def imu_and_truth(path) -> tuple[list, dict]:
    """A simulated dataset's IMU samples and its true poses (x, y, yaw) by stamp."""
    imu, poses = [], {}
    for topic, stamp, data in read_bag(path):
        if topic == "/imu/data":
            imu.append((stamp, deserialize(data, "sensor_msgs/msg/Imu")))
        elif topic == "/groundtruth/pose":
            p = deserialize(data, "geometry_msgs/msg/PoseStamped").pose
            poses[stamp] = (p.position.x, p.position.y, float(yaw_of(p.orientation)))
    return imu, poses


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    path = tmp_path_factory.mktemp("pre") / "sim.mcap"
    simulate(load_scenario("paper", {"trajectory.laps": "1"}), 21, path)
    return imu_and_truth(path)


def feed(op: Preintegration, imu, epoch_ns: int = EPOCH_NS, mount: np.ndarray | None = None):
    """IMU samples and an epoch every `epoch_ns`, in stamp order. Not rover.testing.run_operator: these epochs
    fall on IMU stamps, and there the runtime (ties by port name) delivers the epoch first, after which the
    operator drops the IMU sample of the same stamp as a duplicate; here the sample goes first."""
    out, next_epoch = [], imu[0][0] + epoch_ns
    for stamp, msg in imu:
        while stamp > next_epoch:
            out += list(op.on_input("epochs", make("rover_msgs/msg/Aoa", header=header(next_epoch)), next_epoch))
            next_epoch += epoch_ns
        if mount is not None:
            w = mount.T @ [msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z]
            a = mount.T @ [msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z]
            msg = make(
                "sensor_msgs/msg/Imu",
                header=msg.header,
                angular_velocity=make("geometry_msgs/msg/Vector3", x=w[0], y=w[1], z=w[2]),
                linear_acceleration=make("geometry_msgs/msg/Vector3", x=a[0], y=a[1], z=a[2]),
            )
        out += list(op.on_input("imu", msg, stamp))
    return [e.msg for e in out] + [e.msg for e in op.on_end()]


def yaw_of(q) -> float:
    return float(yaw_from_quaternion(q.x, q.y, q.z, q.w))


def check_against_truth(out, poses):
    stamps = np.array(sorted(poses))
    truth = np.array([poses[s] for s in stamps])

    def at(t: int) -> np.ndarray:
        return truth[min(int(np.searchsorted(stamps, t)), len(stamps) - 1)]

    errors, yaw_errors = [], []
    for o in out:
        start = o.start.sec * 10**9 + o.start.nanosec
        end = o.header.stamp.sec * 10**9 + o.header.stamp.nanosec
        a, b, a2 = at(start), at(end), at(start + 10_000_000)
        velocity = (a2[:2] - a[:2]) / 0.01
        predicted = a[:2] + velocity * o.dt + [o.delta_position.x, o.delta_position.y]
        errors.append(np.linalg.norm(predicted - b[:2]))
        yaw_errors.append(abs(wrap_angle(yaw_of(o.orientation) - b[2])))
    return np.array(errors), np.array(yaw_errors)


@pytest.mark.slow
def test_increments_match_the_ground_truth(run, caplog):
    imu, poses = run
    with caplog.at_level(logging.INFO):
        out = feed(Preintegration(), imu)
    assert "gyro bias" in caplog.text and "standing still" in caplog.text
    assert len(out) > 200
    errors, yaw_errors = check_against_truth(out, poses)
    assert np.median(errors) < 0.01 and errors.max() < 0.03
    assert math.degrees(yaw_errors.max()) < 2.0
    cov = np.array(out[50].covariance).reshape(9, 9)
    assert np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > -1e-15)
    assert 1e-4 < math.sqrt(cov[6, 6]) < 0.02


def test_the_mounting_rotation_from_the_setup(run):
    imu, poses = run
    mount = rpy_matrix(0.0, 0.0, math.radians(90))
    op = Preintegration()
    setup = (
        "receiver: {antenna_positions_m: [[0, 0], [0.02, 0]]}\nexcitation: {channel: 165}\ntags: []\n"
        "imu: {rotation_rpy_deg: [0, 0, 90]}\n"
    )
    list(op.on_input("setup", make("rover_msgs/msg/RigSetup", setup_yaml=setup), 0))
    errors, yaw_errors = check_against_truth(feed(op, imu, mount=mount), poses)
    assert np.median(errors) < 0.01 and math.degrees(yaw_errors.max()) < 2.0


def drifting(overrides: dict[str, str], tmp_path) -> tuple[list, dict]:
    """Two laps of `paper` whose gyro bias moves 0.5 deg/s after the still start (a 2-minute warm-up)."""
    path = tmp_path / "drift.mcap"
    settings = {"trajectory.laps": "2", "imu.gyro_bias_drift_deg_s": "0.5", "imu.gyro_bias_drift_tau_s": "120"}
    simulate(load_scenario("paper", {**settings, **overrides}), 22, path)
    return imu_and_truth(path)


@pytest.mark.slow
@pytest.mark.parametrize(
    "shaking",
    [{}, {"imu.vibration_deg_s": "1.0", "imu.vibration_mg": "50", "trajectory.pause_s": "2"}],
    ids=["smooth floor", "shaking base that stops at its waypoints"],
)
def test_a_drifting_gyro_bias_is_followed_and_the_heading_kept(shaking, tmp_path, caplog):
    """Untracked, the drift turns the heading by more than 40 deg in the run; tracked, by a tenth of that
    at most. A base that shakes while it drives gives quiet spans only where it stops (every 25 s or
    so): the bias moves on between stops, 0.1 deg/s before the first one (2.7 deg; 0.2 on a smooth floor)."""
    imu, poses = drifting(shaking, tmp_path)
    with caplog.at_level(logging.INFO):
        tracked = feed(Preintegration(), imu)
    untracked = feed(Preintegration(PreintegrationParams(track_gyro_bias=False)), imu)
    assert "re-estimated on" in caplog.text
    _, yaw_tracked = check_against_truth(tracked, poses)
    _, yaw_untracked = check_against_truth(untracked, poses)
    assert math.degrees(yaw_untracked.max()) > 40.0
    assert yaw_tracked.max() < 0.1 * yaw_untracked.max()


def test_no_stationary_start_warns_and_falls_back(run, caplog):
    imu, _ = run
    moving = [s for s in imu if s[0] > T0_NS + 27_500_000_000]  # in the first corner turn
    with caplog.at_level(logging.WARNING):
        out = feed(Preintegration(), moving)
    assert "does not start with 1.0 s standing still" in caplog.text
    assert len(out) > 100


def test_duplicates_out_of_order_and_gaps_are_counted(run, caplog):
    imu, _ = run
    stream = list(imu[:2000])
    stream.insert(500, stream[499])
    stream.insert(900, stream[850])
    del stream[1200:1300]
    op = Preintegration()
    with caplog.at_level(logging.WARNING):
        out = feed(op, stream)
    assert op.drops == {"duplicate IMU samples": 1, "IMU samples out of order": 1}
    assert "gap(s) in the IMU stream" in caplog.text
    assert len(out) > 10


# -- synthetic IMU streams: bias, turns in place, a level floor (issue 18) -----------------------------

RATE_HZ = 200
G_M_S2 = 9.80665


def vec3(v) -> object:
    return make("geometry_msgs/msg/Vector3", x=float(v[0]), y=float(v[1]), z=float(v[2]))


def stream(seconds: float, gyro, force, start_ns: int = T0_NS) -> list[tuple[int, object]]:
    """IMU samples at RATE_HZ: gyro (rad/s) and specific force (m/s^2, body frame, gravity included)
    as functions of the time since `start_ns`."""
    out = []
    for k in range(int(seconds * RATE_HZ)):
        t = k / RATE_HZ
        stamp = start_ns + round(t * 1e9)
        msg = make(
            "sensor_msgs/msg/Imu",
            header=header(stamp, "imu_link"),
            angular_velocity=vec3(gyro(t)),
            linear_acceleration=vec3(force(t)),
        )
        out.append((stamp, msg))
    return out


STILL_S = 1.5
"""the still start the preintegration levels on"""


def turning(speed_m_s: float, rate_rad_s: float, bias=(0.0, 0.0, 0.0), gyro_bias=(0.0, 0.0, 0.0), seconds=6.0):
    """Still for STILL_S, then turning at `rate_rad_s` while moving forward at `speed_m_s` (0: on the
    spot): the body feels speed * rate sideways. An accelerometer `bias` throughout; a gyro bias
    from the moment the robot moves (what the still start could not have estimated)."""
    bias, gyro_bias = np.asarray(bias), np.asarray(gyro_bias)

    def gyro(t):
        moving = t >= STILL_S
        return np.array([0.0, 0.0, rate_rad_s * moving]) + gyro_bias * moving

    def force(t):
        return np.array([0.0, speed_m_s * rate_rad_s * (t >= STILL_S), G_M_S2]) + bias

    return stream(seconds, gyro, force)


def test_a_turn_in_place_is_flagged_and_an_arc_at_the_same_rate_is_not():
    bias = (0.03, -0.02, 0.01)  # 3 mg: levelling on the still start removes it
    on_the_spot = feed(Preintegration(), turning(0.0, 0.6, bias), epoch_ns=100_000_000)
    arc = feed(Preintegration(), turning(0.3, 0.6, bias), epoch_ns=100_000_000)
    moving = [o for o in on_the_spot if o.start.sec * 10**9 + o.start.nanosec >= T0_NS + STILL_S * 1e9]
    assert moving and all(o.turning_in_place for o in moving)
    assert not any(o.turning_in_place for o in arc)
    assert not any(o.turning_in_place for o in on_the_spot if o not in moving), "standing still is not turning"


def dead_reckoning(out) -> np.ndarray:
    p, v = np.zeros(2), np.zeros(2)
    for o in out:
        p = p + v * o.dt + [o.delta_position.x, o.delta_position.y]
        v = v + [o.delta_velocity.x, o.delta_velocity.y]
    return p


def test_on_a_level_floor_a_roll_gyro_bias_does_not_tilt_gravity_into_the_motion():
    """Standing still for 20 s with a 0.05 deg/s roll-rate bias appearing after the start: integrated
    in 3-D it tilts the attitude and gravity leaks into the motion (metres); planar, nothing moves."""
    samples = turning(0.0, 0.0, gyro_bias=(math.radians(0.05), 0.0, 0.0), seconds=20.0)
    planar = dead_reckoning(feed(Preintegration(), samples))
    tilting = dead_reckoning(feed(Preintegration(PreintegrationParams(planar=False)), samples))
    assert np.linalg.norm(planar) < 1e-6
    assert np.linalg.norm(tilting) > 1.0


def test_the_bias_jacobian_gives_what_a_bias_does_to_the_deltas():
    """The same arc with and without an accelerometer bias that appears once the robot moves (so
    levelling cannot remove it): the deltas differ by the message's Jacobian times the bias."""
    bias = np.array([0.02, -0.03, 0.0])
    plain = feed(Preintegration(), turning(0.3, 0.4), epoch_ns=100_000_000)
    samples = turning(0.3, 0.4)
    biased_samples = []
    for stamp, msg in samples:
        if stamp >= T0_NS + STILL_S * 1e9:
            f = msg.linear_acceleration
            msg = make(
                "sensor_msgs/msg/Imu",
                header=msg.header,
                angular_velocity=msg.angular_velocity,
                linear_acceleration=vec3(np.array([f.x, f.y, f.z]) + bias),
            )
        biased_samples.append((stamp, msg))
    biased = feed(Preintegration(), biased_samples, epoch_ns=100_000_000)
    compared = 0
    for a, b in zip(plain, biased, strict=True):
        if a.start.sec * 10**9 + a.start.nanosec < T0_NS + STILL_S * 1e9:
            continue
        jacobian = np.asarray(a.accel_bias_jacobian).reshape(6, 3)
        moved = np.array(
            [
                b.delta_velocity.x - a.delta_velocity.x,
                b.delta_velocity.y - a.delta_velocity.y,
                b.delta_velocity.z - a.delta_velocity.z,
                b.delta_position.x - a.delta_position.x,
                b.delta_position.y - a.delta_position.y,
                b.delta_position.z - a.delta_position.z,
            ]
        )
        np.testing.assert_allclose(moved, jacobian @ bias, atol=1e-12)
        assert a.accel_bias_std > 0 and a.levelling_std > 0
        compared += 1
    assert compared > 30


def test_a_shaking_imu_widens_the_increments_covariance_to_what_it_shows(caplog):
    """A base that shakes while it drives (1 deg/s and 50 mg a sample, white), told the datasheet's
    densities: the increments' yaw and velocity variances grow by what the shake implies (within a
    fifth) over those of the same drive without it, the datasheet's densities 200 and 1,200 times
    smaller. The run logs what it measured."""
    shake_rad_s, shake_m_s2 = math.radians(1.0), 50e-3 * G_M_S2

    def drive(shake: float):
        rng = np.random.default_rng(11)

        def gyro(t):
            return (t >= STILL_S) * (np.array([0.0, 0.0, 0.3]) + shake * rng.normal(0, shake_rad_s, 3))

        def force(t):
            return np.array([0.0, 0.0, G_M_S2]) + (t >= STILL_S) * (
                np.array([0.0, 0.3 * 0.3, 0.0]) + shake * rng.normal(0, shake_m_s2, 3)
            )

        out = feed(Preintegration(), stream(8.0, gyro, force), epoch_ns=200_000_000)
        return [o for o in out if o.start.sec * 10**9 + o.start.nanosec >= T0_NS + (STILL_S + 2.5) * 1e9]

    quiet = drive(0.0)
    with caplog.at_level(logging.INFO, logger="rover.preintegration"):
        shaken = drive(1.0)
    assert len(shaken) == len(quiet) > 10
    dt_s = 1 / RATE_HZ
    for a, b in zip(quiet, shaken, strict=True):
        grown = np.asarray(b.covariance).reshape(9, 9) - np.asarray(a.covariance).reshape(9, 9)
        assert grown[2, 2] == pytest.approx(shake_rad_s**2 * dt_s * b.dt, rel=0.2)  # white rate noise, integrated
        assert grown[3, 3] == pytest.approx(shake_m_s2**2 * dt_s * b.dt, rel=0.2)
    told = Preintegration().params
    assert shake_rad_s**2 * dt_s > 150 * told.gyro_noise_rad_s_rthz**2
    assert shake_m_s2**2 * dt_s > 1000 * told.accel_noise_m_s2_rthz**2
    assert "IMU noise measured on its samples" in caplog.text
