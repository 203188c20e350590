"""Message types: the project's .msg files registered, CDR round trips, header stamps without decoding."""

from __future__ import annotations

import numpy as np
import pytest

from rover.errors import BadInput
from rover.messages import (
    Raw,
    cdr_stamp_ns,
    deserialize,
    has_header,
    header,
    make,
    message_class,
    ros2_msgdef,
    serialize,
    stamp_ns,
)


def test_csiframe_is_exactly_the_design():
    assert "uint16 channel" in ros2_msgdef("rover_msgs/msg/CsiFrame")
    frame = make(
        "rover_msgs/msg/CsiFrame",
        header=header(1_234_567_890_123, "nic"),
        channel=149,
        bfee=np.arange(10, dtype=np.uint8),
    )
    back = deserialize(serialize(frame), "rover_msgs/msg/CsiFrame")
    assert back.channel == 149 and back.bfee.tolist() == list(range(10)) and back.header.frame_id == "nic"
    assert [
        name
        for name, _ in message_class("rover_msgs/msg/CsiFrame").__dataclass_fields__.items()
        if not name.startswith("__")
    ] == ["header", "channel", "bfee"]


def test_stamp_from_cdr_bytes_equals_the_decoded_header():
    msg = make("sensor_msgs/msg/Imu", header=header(1_700_000_001_500_000_123))
    payload = serialize(msg)
    assert cdr_stamp_ns(payload) == stamp_ns(msg) == 1_700_000_001_500_000_123
    assert stamp_ns(Raw("sensor_msgs/msg/Imu", payload)) == 1_700_000_001_500_000_123
    with pytest.raises(ValueError):
        cdr_stamp_ns(b"\x00\x01")


def test_header_detection():
    assert has_header("sensor_msgs/msg/Imu") and has_header("rover_msgs/msg/RigSetup")
    assert not has_header("geometry_msgs/msg/Point")


def test_make_fills_defaults_and_rejects_unknown_fields():
    odom = make("nav_msgs/msg/Odometry")
    assert odom.pose.covariance.shape == (36,) and odom.child_frame_id == ""
    with pytest.raises(TypeError):
        make("sensor_msgs/msg/Imu", nonsense=1)
    with pytest.raises(BadInput):
        make("nope_msgs/msg/Nope")


def test_make_takes_the_msg_files_defaults():
    """An unset quaternion is the identity, as a ROS 2 node's (`float64 w 1` in Quaternion.msg),
    nested ones too; a value given wins."""
    assert make("nav_msgs/msg/Odometry").pose.pose.orientation.w == 1.0
    assert make("geometry_msgs/msg/Quaternion", w=0.5).w == 0.5
    assert make("sensor_msgs/msg/Imu").orientation.w == 1.0
