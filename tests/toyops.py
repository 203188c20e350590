"""User operators for the tests, found by dotted path (`uses: toyops.Heading`), as a user's own would be."""

from __future__ import annotations

import dataclasses
import gc
import json
import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from rover.errors import OutputFailed
from rover.frozen import thaw
from rover.geometry import quaternion_from_yaw
from rover.messages import ANY, header, make
from rover.operator import COMPLETE, Emit, In, Operator, Out, Ports, RunOutcome, Source, Watermark


@dataclass(frozen=True)
class HeadingParams:
    gain: float = 1.0


class Heading(Operator):
    """Integrates the gyro's z rate into a heading; at each odometry message emits the pose so far.

    Two inputs, so the result depends on the order the runtime delivers them in."""

    inputs = {"imu": In("sensor_msgs/msg/Imu"), "odom": In("nav_msgs/msg/Odometry", required=False)}
    outputs = {"pose": Out("geometry_msgs/msg/PoseStamped")}
    Params = HeadingParams

    def __init__(self, params=None):
        super().__init__(params)
        self.yaw = 0.0
        self.last_ns: int | None = None

    def on_input(self, port, msg, stamp_ns):
        if port == "imu":
            if self.last_ns is not None:
                self.yaw += self.params.gain * msg.angular_velocity.z * (stamp_ns - self.last_ns) * 1e-9
            self.last_ns = stamp_ns
            return
        pose = make("geometry_msgs/msg/PoseStamped", header=header(stamp_ns, "world"), pose=thaw(msg.pose.pose))
        _, _, qz, qw = quaternion_from_yaw(self.yaw)
        pose.pose.orientation.z, pose.pose.orientation.w = float(qz), float(qw)
        yield Emit("pose", pose)


class Passthrough(Operator):
    inputs = {"imu": In("sensor_msgs/msg/Imu")}
    outputs = {"imu": Out("sensor_msgs/msg/Imu")}

    def on_input(self, port, msg, stamp_ns):
        yield Emit("imu", msg)


@dataclass(frozen=True)
class ScaleParams:
    gain: float = 1.0


class Scale(Operator):
    """The README's example: edits its input message in place (a writable port) and sends it on."""

    inputs = {"imu": In("sensor_msgs/msg/Imu", writable=True)}
    outputs = {"imu": Out("sensor_msgs/msg/Imu")}
    Params = ScaleParams

    def on_input(self, port, msg, stamp_ns):
        msg.angular_velocity.z *= self.params.gain
        yield Emit("imu", msg)


class ScaleShared(Scale):
    """The same edit on a port not declared writable: its input is the shared, read-only message."""

    inputs = {"imu": In("sensor_msgs/msg/Imu")}


class _Counting(Operator):
    """An IMU pass-through that counts the messages it has been given."""

    inputs = {"imu": In("sensor_msgs/msg/Imu")}
    outputs = {"imu": Out("sensor_msgs/msg/Imu")}

    def __init__(self, params=None):
        super().__init__(params)
        self.n = 0


class Thin(_Counting):
    """Passes every other message on; the others it drops, for the runtime to report."""

    def on_input(self, port, msg, stamp_ns):
        self.n += 1
        if self.n % 2:
            yield Emit("imu", msg)
        else:
            self.drop("messages of even rank")


class FrozenCheck(_Counting):
    """Passes messages on; drops those it handles while what the run built is still in the garbage
    collector's generations (the runtime freezes it before the run)."""

    def on_input(self, port, msg, stamp_ns):
        if gc.get_freeze_count() and not any(o is self for o in gc.get_objects()):
            yield Emit("imu", msg)
        else:
            self.drop("messages handled with the run's operators still collected")


class Explode(_Counting):
    """Raises on its third message: a buggy user operator."""

    def on_input(self, port, msg, stamp_ns):
        self.n += 1
        if self.n == 3:
            raise ZeroDivisionError("boom")
        yield Emit("imu", msg)


class NoDevice(Operator):
    """Fails in its constructor, as a driver whose device is missing and which says so badly."""

    inputs = {"imu": In("sensor_msgs/msg/Imu")}

    def __init__(self, params=None):
        super().__init__(params)
        raise FileNotFoundError("/dev/ttyUSB0")


@dataclass(frozen=True)
class TickerParams:
    rate_hz: float = 50.0
    count: int = 0
    """Messages to send before ending; 0 = until stopped."""
    delay_s: float = 0.0
    """Wall-clock time before the first message, as a driver waiting for its device."""
    stamp_step_s: float = 0.0
    """Event time between two messages (0: each is stamped with the wall clock)."""


class Ticker(Source):
    """A live IMU-like source stamped with wall-clock time, like a driver on the robot."""

    live = True

    outputs = {"imu": Out("sensor_msgs/msg/Imu"), "silent": Out("sensor_msgs/msg/Imu")}
    Params = TickerParams

    def run(self, stop: threading.Event):
        period = 1.0 / self.params.rate_hz
        n = 0
        if stop.wait(self.params.delay_s):
            return
        start = time.time_ns()
        while not stop.is_set() and (self.params.count == 0 or n < self.params.count):
            now = start + round(n * self.params.stamp_step_s * 1e9) if self.params.stamp_step_s else time.time_ns()
            gyro = make("geometry_msgs/msg/Vector3", z=0.1 * n)
            yield Emit("imu", make("sensor_msgs/msg/Imu", header=header(now, "imu_link"), angular_velocity=gyro))
            yield Watermark(now)
            n += 1
            stop.wait(period)


AHEAD_DONE = threading.Event()
"""set by AheadWork when its work ahead is done: GatedTicker then sends its next message"""
AHEAD_UNITS = 3
"""units of work ahead each AheadWork input makes"""


class GatedTicker(Ticker):
    """Sends its next message only once AheadWork did all its work ahead (one process), so that the
    operator's inbox is empty while the work remains: the runtime must call `on_idle` until it is done."""

    def run(self, stop: threading.Event):
        for item in super().run(stop):
            if isinstance(item, Emit):
                AHEAD_DONE.clear()
            yield item
            if isinstance(item, Watermark) and not AHEAD_DONE.wait(10.0):
                self.drop("messages whose work ahead was not done in 10 s")


class AheadWork(Operator):
    """Passes messages on; each makes AHEAD_UNITS units of work it does ahead, one per `on_idle`."""

    inputs = {"imu": In("sensor_msgs/msg/Imu")}
    outputs = {"imu": Out("sensor_msgs/msg/Imu")}

    def __init__(self, params=None):
        super().__init__(params)
        self.units = 0

    def has_idle_work(self) -> bool:
        return self.units > 0

    def on_idle(self):
        self.units -= 1
        if self.units == 0:
            AHEAD_DONE.set()
        return ()

    def on_input(self, port, msg, stamp_ns):
        self.units += AHEAD_UNITS
        yield Emit("imu", msg)


class Pairs(Operator):
    """Sends each message once the next one arrived, as the AoA closes a burst when the next
    dwell's frames come; says what it holds (`held_since_ns`)."""

    inputs = {"imu": In("sensor_msgs/msg/Imu")}
    outputs = {"out": Out("sensor_msgs/msg/Imu")}

    def __init__(self, params=None):
        super().__init__(params)
        self.held: tuple[object, int] | None = None

    def held_since_ns(self) -> float:
        return self.held[1] if self.held else math.inf

    def on_input(self, port, msg, stamp_ns):
        if self.held is not None:
            yield Emit("out", self.held[0], self.held[1])
        self.held = (msg, stamp_ns)


class Merge(Operator):
    """Forwards both inputs in event-time order: a silent input must not hold the other back."""

    inputs = {"a": In("sensor_msgs/msg/Imu"), "b": In("sensor_msgs/msg/Imu")}
    outputs = {"out": Out("sensor_msgs/msg/Imu")}

    def on_input(self, port, msg, stamp_ns):
        yield Emit("out", msg)


@dataclass(frozen=True)
class UnwritableParams:
    path: str = "out/written.txt"


class Unwritable(Operator):
    """Takes anything and writes one file at the end, as an output writer does; pointed at a folder,
    the write fails and so does the run."""

    variadic = In(ANY, raw=True)
    Params = UnwritableParams

    def close(self, outcome: RunOutcome = COMPLETE) -> None:
        if outcome.keeps_outputs:
            try:
                Path(self.params.path).write_text("done\n")
            except OSError as exc:
                raise OutputFailed(f"{self.params.path}: cannot write: {exc.strerror}") from None


@dataclass(frozen=True)
class SlowParams:
    delay_s: float = 0.002
    release: str = ""
    """a file whose appearance ends a stall on the first message ("" for no stall)"""


class Slow(Operator):
    """A slow sink: takes `delay_s` per message and, with `release`, holds its first message until
    that file exists (a consumer stalled: what its producers do then is the backpressure)."""

    inputs = {"imu": In("sensor_msgs/msg/Imu")}
    Params = SlowParams

    def __init__(self, params=None):
        super().__init__(params)
        self.n = 0

    def on_input(self, port, msg, stamp_ns):
        self.n += 1
        if self.n == 1 and self.params.release:
            while not Path(self.params.release).exists():
                time.sleep(0.01)
        time.sleep(self.params.delay_s)
        return ()


@dataclass(frozen=True)
class FanParams:
    outputs: dict[str, str] = field(default_factory=dict)
    """output port -> message type: the ports are named by the params, as a ROS 2 bridge's topics are"""


class Fan(Operator):
    """Sends each IMU message on every output its params declare."""

    inputs = {"imu": In("sensor_msgs/msg/Imu")}
    Params = FanParams

    @classmethod
    def declared_ports(cls, params: FanParams) -> Ports:
        if not params.outputs:
            raise ValueError("param 'outputs' declares no output port")
        return Ports(cls.inputs, {name: Out(typename) for name, typename in params.outputs.items()})

    def on_input(self, port, msg, stamp_ns):
        for name in self.params.outputs:
            yield Emit(name, msg)


@dataclass(frozen=True)
class ProfileProbeParams:
    path: str = "profile.json"
    close_s: float = 0.1
    """how long its `close` takes"""


class ProfileProbe(Operator):
    """A sink that takes `close_s` to close and writes the run's profile, as `report` is given it."""

    inputs = {"imu": In("sensor_msgs/msg/Imu")}
    Params = ProfileProbeParams

    def on_input(self, port, msg, stamp_ns):
        return ()

    def close(self, outcome: RunOutcome = COMPLETE) -> None:
        time.sleep(self.params.close_s)

    def report(self, outcome: RunOutcome) -> None:
        profile = {name: dataclasses.asdict(p) for name, p in outcome.profile.items()}
        Path(self.params.path).write_text(json.dumps(profile))
