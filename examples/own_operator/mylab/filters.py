# mylab/filters.py  (importable: on PYTHONPATH or installed)
from dataclasses import dataclass

from rover.operator import Emit, In, Operator, Out


@dataclass(frozen=True)
class ScaleParams:
    gain: float = 1.0


class Scale(Operator):
    inputs = {"imu": In("sensor_msgs/msg/Imu", writable=True)}  # it edits its input
    outputs = {"imu": Out("sensor_msgs/msg/Imu")}
    Params = ScaleParams

    def on_input(self, port, msg, stamp_ns):
        msg.angular_velocity.z *= self.params.gain
        yield Emit("imu", msg)
