"""The built-in operators: short names for `uses:`, as `module:Class` strings resolved on use."""

from __future__ import annotations

BUILTINS: dict[str, str] = {
    "dataset_replay": "rover.drivers.replay:DatasetReplay",
    "channel_sweep": "rover.operators.channel_sweep.operator:ChannelSweep",
    "csi_decode": "rover.operators.csi_decode:CsiDecode",
    "aoa": "rover.operators.aoa.operator:Aoa",
    "preintegration": "rover.operators.preintegration.operator:Preintegration",
    "slam": "rover.operators.slam.operator:Slam",
    "channel_hop": "rover.drivers.channel_hop:ChannelHop",
    "csi_netlink": "rover.drivers.csi_netlink:CsiNetlink",
    "create2": "rover.drivers.create2:Create2",
    "microstrain_imu": "rover.drivers.microstrain_imu:MicrostrainImu",
    "csi_file": "rover.drivers.csi_file:CsiFile",
    "rig_source": "rover.drivers.rig_source:RigSource",
    "recorder": "rover.drivers.recorder:Recorder",
    "dataset_recorder": "rover.drivers.dataset_recorder:DatasetRecorder",
    "run_outputs": "rover.drivers.run_outputs:RunOutputs",
    "foxglove_view": "rover.drivers.foxglove_view:FoxgloveView",
    "ros2_subscribe": "rover.drivers.ros2:Ros2Subscribe",
    "ros2_publish": "rover.drivers.ros2:Ros2Publish",
    "ros_outputs": "rover.drivers.ros_outputs:RosOutputs",
}
"""Short name -> `module:Class`; modules are imported only when a pipeline uses them."""
