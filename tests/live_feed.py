"""A simulated run played as live hardware, for the live end-to-end test: the IMU's samples and the
wheels' angles as functions of wall time for the pty emulators (tests/mip_device.py,
tests/create2_device.py), and a CSI Tool log written as the NIC would fill it.

The NIC hears only the channel it is tuned to. `channel_hop` retunes it with a command; here that
command writes the channel into a file (`tune_command`), and `CsiLogFeeder` watches that file: at
each hop to channel C it appends the simulated dwell on C nearest in time, its frames paced within
the first `window_s` of the dwell, in `log_to_file`'s format (a 2-byte big-endian length, then the
record's code byte and notification).
"""

from __future__ import annotations

import os
import shlex
import struct
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rover.formats.bag import BagReader

STANDARD_GRAVITY_M_S2 = 9.80665
WHEEL_RADIUS_M = 0.036
WHEEL_BASE_M = 0.235
"""the Create 2's, as the `create2` driver assumes by default"""
POLL_S = 0.002
DWELL_GAP_S = 0.02
"""frames of one channel further apart than this belong to different dwells of the simulated sweep"""


def _yaw(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q.T
    return np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


@dataclass
class Recorded:
    """The streams of a simulated dataset, times in seconds from its first message."""

    imu_t: np.ndarray
    accel: np.ndarray
    """REP-103 body frame, m/s^2"""
    gyro: np.ndarray
    pose_t: np.ndarray
    xy: np.ndarray
    yaw: np.ndarray
    csi: list[tuple[float, int, bytes]]
    """(time, channel, record)"""
    setup_yaml: str

    def __post_init__(self) -> None:
        step = np.diff(self.xy, axis=0)
        forward = step[:, 0] * np.cos(self.yaw[:-1]) + step[:, 1] * np.sin(self.yaw[:-1])
        self.distance = np.concatenate([[0.0], np.cumsum(forward)])
        """distance travelled forward along the path (m), at each pose"""

    @classmethod
    def read(cls, path: Path) -> Recorded:
        imu_t, accel, gyro, pose_t, xy, quat, csi = [], [], [], [], [], [], []
        with BagReader(path) as bag:
            setup = bag.metadata()["rover.setup"]["yaml"]
            start = None
            for m in bag.messages(["/imu/data", "/groundtruth/pose", "/csi"]):
                start = m.log_time_ns if start is None else start
                t = (m.log_time_ns - start) / 1e9
                if m.topic == "/imu/data":
                    imu = bag.decode(m, "sensor_msgs/msg/Imu")
                    a, w = imu.linear_acceleration, imu.angular_velocity
                    imu_t.append(t)
                    accel.append((a.x, a.y, a.z))
                    gyro.append((w.x, w.y, w.z))
                elif m.topic == "/groundtruth/pose":
                    pose = bag.decode(m, "geometry_msgs/msg/PoseStamped").pose
                    pose_t.append(t)
                    xy.append((pose.position.x, pose.position.y))
                    o = pose.orientation
                    quat.append((o.x, o.y, o.z, o.w))
                else:
                    frame = bag.decode(m, "rover_msgs/msg/CsiFrame")
                    csi.append((t, int(frame.channel), bytes(frame.bfee)))
        return cls(
            np.array(imu_t),
            np.array(accel),
            np.array(gyro),
            np.array(pose_t),
            np.array(xy),
            np.unwrap(_yaw(np.array(quat))),
            csi,
            setup,
        )

    def imu_device(self, t_s: float) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """The sample at `t_s` as the 3DM-GX4-45 reports it: g and rad/s in its own axes (z down, a half
        turn about x from REP-103)."""
        i = min(int(np.searchsorted(self.imu_t, t_s)), len(self.imu_t) - 1)
        a, w = self.accel[i] / STANDARD_GRAVITY_M_S2, self.gyro[i]
        return (float(a[0]), float(-a[1]), float(-a[2])), (float(w[0]), float(-w[1]), float(-w[2]))

    def wheel_angles(self, t_s: float) -> tuple[float, float]:
        """Left and right wheel angles (rad) of a differential drive following the true path."""
        distance = float(np.interp(t_s, self.pose_t, self.distance))
        turn = float(np.interp(t_s, self.pose_t, self.yaw)) - float(self.yaw[0])
        half = turn * WHEEL_BASE_M / 2
        return (distance - half) / WHEEL_RADIUS_M, (distance + half) / WHEEL_RADIUS_M


def tune_command(tuned: Path) -> str:
    """A `channel_hop` command template that 'retunes' by writing the channel into `tuned`."""
    return f"sh -c {shlex.quote(f'echo {{channel}} > {tuned}')}"


class CsiLogFeeder:
    """Appends the recorded dwells to `log` as `channel_hop` tunes through the channels (see module doc).
    Times are wall-clock seconds since `t0`, the start of the recording."""

    def __init__(self, recorded: Recorded, log: Path, tuned: Path, t0: float, window_s: float = 0.03):
        self.log, self.tuned, self.t0, self.window_s = log, tuned, t0, window_s
        self.dwells: dict[int, list[list[tuple[float, bytes]]]] = {}
        for t, channel, record in recorded.csi:
            runs = self.dwells.setdefault(channel, [])
            if runs and t - runs[-1][-1][0] <= DWELL_GAP_S:
                runs[-1].append((t, record))
            else:
                runs.append([(t, record)])
        self.starts = {c: np.array([d[0][0] for d in runs]) for c, runs in self.dwells.items()}
        self.hops = 0
        self.records = 0
        self._stop = threading.Event()
        log.touch()
        self._thread = threading.Thread(target=self._main, name="csi-feeder", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)

    def __enter__(self) -> CsiLogFeeder:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def _main(self) -> None:
        seen = None
        with self.log.open("ab", buffering=0) as out:
            while not self._stop.wait(POLL_S):
                try:
                    stamp, text = os.stat(self.tuned).st_mtime_ns, self.tuned.read_text().strip()
                except FileNotFoundError:
                    continue
                if not text or stamp == seen:
                    continue
                seen = stamp
                self.hops += 1
                self._dwell(out, int(text), time.time())

    def _dwell(self, out, channel: int, hop_s: float) -> None:
        starts = self.starts.get(channel)
        if starts is None:
            return
        runs = self.dwells[channel]
        dwell = runs[int(np.argmin(np.abs(starts - (hop_s - self.t0))))]
        span = dwell[-1][0] - dwell[0][0]
        scale = min(1.0, self.window_s / span) if span > 0 else 1.0
        for t, record in dwell:
            due = hop_s + (t - dwell[0][0]) * scale
            if self._stop.wait(max(0.0, due - time.time())):
                return
            out.write(struct.pack(">H", len(record)) + record)
            self.records += 1
