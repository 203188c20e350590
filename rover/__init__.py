"""Rover: localize a robot and WiFi backscatter tags with AoA-IMU SLAM over a Zenoh dataflow."""

__version__ = "0.1.0"
