"""A WiROS recording end to end: `rover convert` of a robot's ROS 2 bag whose CSI is WiROS's
rf_msgs/msg/Wifi (a 4x4 router on a 19 mm square, 80 MHz on channel 155, hearing four transmitters
in turn), then `rover run` of the dataset with the default pipeline, against the truth.

The robot's IMU, odometry and truth are a simulated lap of the paper's room (`rover simulate`); the
CSI is written here from the physics, not by Rover: from each transmitter at its true place, the
direct path and its image in a wall half a metre beyond the tags on one side (reflection coefficient
0.5), each a plane wave at every
subcarrier's own frequency seen by the antennas at the robot's true pose, with the receiver's random
common phase and timing offset per packet and noise 20 dB under the direct path; recorded as WiROS's
CSI node records it (test_wiros.recorded: fft-shifted bins, the lower 64 rotated, Fortran order)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from helpers import LAP, run_rover
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Ros2Writer
from test_aoa_capture import C_M_S, SPACING_HZ, SQUARE_19MM
from test_wiros import BINS, CENTRE_HZ, CHANNEL, EMPTY, ROUTER, recorded, store

from rover.formats.bag import BagReader
from rover.formats.truth import read_dataset_truth

PACKETS_PER_S = 20.0
"""each transmitter's packets a second, at random moments"""
WALL_REFLECTION = 0.5
NOISE = 0.1
"""noise amplitude per subcarrier and antenna, the direct path's 1 at the robot (20 dB under it)"""


def mac_of(tag: int) -> bytes:
    """A transmitter's MAC: its last four bytes are the tag's id (rover.formats.csi_sources.wiros.tag_ids)."""
    return bytes([2, 0]) + tag.to_bytes(4, "big")


def pose_at(trajectory, stamps_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(P, 2) positions and (P,) yaws of the true trajectory at the stamps, interpolated."""
    t = trajectory.stamp_ns
    xy = np.stack([np.interp(stamps_ns, t, trajectory.xyz[:, k]) for k in range(2)], axis=1)
    q = trajectory.quat_xyzw
    yaw = np.unwrap(np.arctan2(2 * (q[:, 3] * q[:, 2] + q[:, 0] * q[:, 1]), 1 - 2 * (q[:, 1] ** 2 + q[:, 2] ** 2)))
    return xy, np.interp(stamps_ns, t, yaw)


def paths_csi(robot_xy: np.ndarray, yaw: np.ndarray, source_xy: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """(P, 256, 4) the CSI of one path a packet: from `source_xy` (P, 2) with amplitude `gain` (P,)
    over its length, its delay the path's length, each antenna at its place on the robot."""
    offset = source_xy - robot_xy
    distance = np.linalg.norm(offset, axis=1)
    angle = np.arctan2(offset[:, 1], offset[:, 0]) - yaw  # the source's direction in the robot's frame
    u = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    lead_s = u @ SQUARE_19MM.T / C_M_S  # (P, 4): how much earlier each antenna sees the wave
    f = CENTRE_HZ + BINS * SPACING_HZ
    delay_s = distance / C_M_S
    phase = 2 * np.pi * f[None, :, None] * (lead_s[:, None, :] - delay_s[:, None, None])
    return (gain / distance)[:, None, None] * np.exp(1j * phase)


def wiros_packets(trajectory, tags, rng: np.random.Generator):
    """(stamps, macs, csi (P, 256, 4, 1)) of every transmitter's packets over the run, in time order."""
    start, end = int(trajectory.stamp_ns[0]), int(trajectory.stamp_ns[-1])
    stamps, owners = [], []
    for k, _tag in enumerate(tags):
        count = rng.poisson(PACKETS_PER_S * (end - start) / 1e9)
        stamps.append(np.sort(rng.integers(start, end, count)))
        owners.append(np.full(count, k))
    order = np.argsort(np.concatenate(stamps), kind="stable")
    stamp = np.concatenate(stamps)[order]
    owner = np.concatenate(owners)[order]
    robot, yaw = pose_at(trajectory, stamp)
    place = np.array([t.xyz[:2] for t in tags])[owner]
    direct = np.linalg.norm(place - robot, axis=1)
    wall_y = min(place[:, 1].min(), robot[:, 1].min()) - 0.5  # a wall beyond every tag and the path
    image = np.stack([place[:, 0], 2 * wall_y - place[:, 1]], axis=1)  # the source seen in it
    h = paths_csi(robot, yaw, place, direct) + paths_csi(robot, yaw, image, WALL_REFLECTION * direct)
    p = len(stamp)
    common = np.exp(1j * rng.uniform(-np.pi, np.pi, p))[:, None, None]
    timing = np.exp(-2j * np.pi * BINS[None, :, None] * SPACING_HZ * rng.normal(0, 30e-9, p)[:, None, None])
    noise = NOISE * (rng.normal(size=h.shape) + 1j * rng.normal(size=h.shape)) / math.sqrt(2)
    csi = h * common * timing + noise
    csi[:, np.isin(BINS, EMPTY)] = 0
    return stamp, [mac_of(tags[k].id) for k in owner], csi[..., None]


def write_recording(folder: Path, dataset: Path, rng: np.random.Generator) -> int:
    """A recording folder as a user delivers it: `bag/` (ROS 2, MCAP: /csi of WiROS's Wifi, the
    dataset's /imu/data and /odom), setup.yaml, truth_robot.tum, truth_tags.csv; returns the packets."""
    trajectory, tags = read_dataset_truth(dataset)
    assert trajectory is not None and len(tags) == 4
    stamps, macs, csi = wiros_packets(trajectory, tags, rng)
    s = store()
    wifi, header_cls, time_cls = (
        s.types[t] for t in ("rf_msgs/msg/Wifi", "std_msgs/msg/Header", "builtin_interfaces/msg/Time")
    )
    raw = recorded(csi)
    with Ros2Writer(folder / "bag", version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {
            "/csi": writer.add_connection("/csi", "rf_msgs/msg/Wifi", typestore=s),
            "/imu/data": writer.add_connection("/imu/data", "sensor_msgs/msg/Imu", typestore=s),
            "/odom": writer.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=s),
        }
        with BagReader(dataset) as bag:
            rows = [(m.log_time_ns, m.topic, m.data, -1) for m in bag.messages(["/imu/data", "/odom"])]
        rows += [(int(t), "/csi", b"", p) for p, t in enumerate(stamps)]
        for stamp, topic, data, item in sorted(rows, key=lambda r: r[0]):
            if topic != "/csi":
                writer.write(conns[topic], stamp, data)
                continue
            flat = raw[item].reshape(-1, order="F")
            msg = wifi(
                header=header_cls(stamp=time_cls(sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id="asus"),
                ap_id=0, txmac=np.frombuffer(macs[item], np.uint8), chan=CHANNEL, n_sub=256, n_rows=4, n_cols=1,
                bw=80, mcs=0, rssi=-50, fc=0x88, seq_num=item % 4096, csi_real=np.ascontiguousarray(flat.real),
                csi_imag=np.ascontiguousarray(flat.imag), rx_id=ROUTER, msg_id=item,
            )  # fmt: skip
            writer.write(conns["/csi"], stamp, s.serialize_cdr(msg, "rf_msgs/msg/Wifi"))
    (folder / "setup.yaml").write_text(
        f"receiver:\n  antenna_positions_m: {SQUARE_19MM.tolist()}\n"
        f"tags: [{', '.join(f'{{id: {t.id}, channel: {CHANNEL}}}' for t in tags)}]\n"
    )
    (folder / "truth_robot.tum").write_text(
        "".join(
            f"{t / 1e9:.9f} {' '.join(f'{v:.9f}' for v in (*p, *q))}\n"
            for t, p, q in zip(trajectory.stamp_ns.tolist(), trajectory.xyz, trajectory.quat_xyzw, strict=True)
        )
    )
    (folder / "truth_tags.csv").write_text(
        "id,channel,x,y,z,nlos\n" + "".join(f"{t.id},{CHANNEL},{t.xyz[0]},{t.xyz[1]},{t.xyz[2]},0\n" for t in tags)
    )
    return len(stamps)


@pytest.mark.slow
def test_a_wiros_recording_converts_and_runs_to_the_truth(simulated, tmp_path):
    """Every transmitter localized within 30 cm, the robot within 10 cm, none published beyond 3
    sigma more often than the trust issue allows (1%); the dataset holds every packet as Rover's Csi."""
    folder = tmp_path / "recording"
    folder.mkdir()
    packets = write_recording(folder, simulated(*LAP), np.random.default_rng(11))
    dataset = tmp_path / "wiros.mcap"
    converted = run_rover("convert", str(folder), "-o", str(dataset), timeout=300)
    assert converted.returncode == 0, converted.stderr
    assert "csi: /csi -> /csi/capture" in converted.stdout
    assert f"wrote {packets:,} messages on /csi/capture" in converted.stdout
    out = tmp_path / "run"
    run = run_rover("run", "--dataset", str(dataset), "--output", str(out), timeout=600)
    assert run.returncode == 0, run.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    errors = {t: e["error_m"] for t, e in metrics["tags"].items() if e["localized"]}
    assert len(errors) == 4 and max(errors.values()) < 0.3, metrics["tags"]
    assert metrics["robot"]["trajectory.tum"]["unaligned"]["mean_m"] < 0.10
    assert all(p["beyond_3_sigma"] <= 0.01 for p in metrics["published"].values() if p.get("estimates"))
