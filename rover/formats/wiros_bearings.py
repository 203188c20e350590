"""Bearings from WiROS's AoA node: `rf_msgs/msg/Bearing` (on `/bearing`) in a ROS 1 bag, a ROS 2 bag
folder or an MCAP file, as the SLAM's bearings (`bearings_csv.Bearings`): a user whose AoA front
end is WiROS's runs Rover's map and its integrity from what it recorded.

A message is one packet's bearing: its header's stamp, the transmitter's MAC (`txmac`), and `aoa`,
one angle (rad) per transmit antenna in the receiving radio's frame (all equal when the CSI was
averaged over them). Here:

- the tag's id is the MAC's last four bytes as an unsigned integer (`02:00:00:00:00:07` is tag 7),
  the id a truth's tags.csv gives it; two transmitters that share their last four bytes are refused;
- the angle is the circular mean of `aoa`'s finite values, turned by `radio_yaw_rad` (where the
  radio faces on the robot, counterclockwise from its x axis) into the robot's frame;
- the message carries no std: each bearing gets `std_rad`.

A message without a finite angle, or whose MAC is not 6 bytes, is dropped and counted. The message
is decoded with the bag's own definition where it carries one, Rover's copy otherwise
(`csi_sources/rf_msgs/Bearing.msg`).
"""

from __future__ import annotations

import math
from collections import Counter
from pathlib import Path

import numpy as np

from rover.errors import BadInput
from rover.formats.bearings_csv import Bearings
from rover.formats.csi_sources.wiros import BEARING_TYPE, MAC_BYTES, messages_of, tag_ids
from rover.geometry import wrap_angle


def read_wiros_bearings(
    path: str | Path, std_rad: float, radio_yaw_rad: float = 0.0, topic: str | None = None
) -> tuple[Bearings, Counter[str]]:
    """The bag's bearings in the robot's frame, sorted by time, and what was dropped, per reason;
    BadInput naming the file (and topic) when it holds none or is not a bag of them."""
    path = Path(path)
    if not math.isfinite(std_rad) or std_rad <= 0:
        raise BadInput(f"{path}: the bearings' std must be positive, got {std_rad}")
    messages, chosen = messages_of(path, topic, BEARING_TYPE, choose="replay.bearings_topic")
    missing = [f for f in ("header", "txmac", "aoa") if messages and not hasattr(messages[0], f)]
    if missing:
        raise BadInput(f"{path}: {chosen}: its {BEARING_TYPE} has no {', '.join(missing)}: not WiROS's layout")
    dropped: Counter[str] = Counter()
    stamps, macs, angles = [], [], []
    for msg in messages:
        mac = bytes(np.asarray(msg.txmac, dtype=np.uint8))
        aoa = np.asarray(msg.aoa, dtype=np.float64)
        aoa = aoa[np.isfinite(aoa)]
        if len(mac) != MAC_BYTES:
            dropped[f"{chosen} bearings whose txmac is not {MAC_BYTES} bytes"] += 1
        elif len(aoa) == 0:
            dropped[f"{chosen} bearings without a finite aoa"] += 1
        else:
            stamps.append(int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec))
            macs.append(mac)
            angles.append(math.atan2(float(np.sin(aoa).mean()), float(np.cos(aoa).mean())))
    if not stamps:
        raise BadInput(f"{path}: {chosen}: no bearing with a transmitter and a finite angle ({len(messages)} messages)")
    tags = tag_ids(path, macs)
    order = np.argsort(np.array(stamps, dtype=np.int64), kind="stable")
    bearings = Bearings(
        stamp_ns=np.array(stamps, dtype=np.int64)[order],
        tag=tags[order],
        angle_rad=wrap_angle(np.array(angles)[order] + radio_yaw_rad),
        std_rad=np.full(len(order), std_rad),
    )
    return bearings, dropped
