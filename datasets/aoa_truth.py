"""A dataset's CSI frames and its true angles of arrival (`/groundtruth/aoa`): what `rover calibrate`
needs from an MCAP dataset, read once, undecoded."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from rover.errors import BadInput
from rover.formats.bag import BagReader
from rover.messages import stamp_ns


@dataclass
class AoaTruth:
    """The frames of `/csi` in file order and the true angles, by stamp."""

    setup_yaml: str | None
    """the rig the dataset was recorded with (`rover.setup` metadata), when it says"""
    stamps_ns: list[int] = field(default_factory=list)
    channels: list[int] = field(default_factory=list)
    """a frame's channel; 0 where the frame does not say"""
    bfee: list[bytes] = field(default_factory=list)
    """each frame's CSI Tool record"""
    angles: dict[int, list[tuple[int, float]]] = field(default_factory=dict)
    """stamp -> (channel, true angle in rad) of every `/groundtruth/aoa` message with that stamp"""


def read_aoa_truth(path: Path) -> AoaTruth:
    """The `/csi` frames and `/groundtruth/aoa` angles of a dataset; BadInput when either is missing."""
    with BagReader(path, "not a readable MCAP dataset") as bag:
        found = AoaTruth(bag.metadata().get("rover.setup", {}).get("yaml"))
        for message in bag.messages(["/csi", "/groundtruth/aoa"]):
            if message.topic == "/csi":
                frame = bag.decode(message, "rover_msgs/msg/CsiFrame")
                found.stamps_ns.append(stamp_ns(frame))
                found.channels.append(int(frame.channel))
                found.bfee.append(bytes(frame.bfee))
            else:
                aoa = bag.decode(message, "rover_msgs/msg/Aoa")
                found.angles.setdefault(stamp_ns(aoa), []).append((int(aoa.channel), float(aoa.angle_rad)))
    if not found.angles:
        raise BadInput(f"{path}: no ground-truth angles (/groundtruth/aoa); a CSI log with --angle-deg instead?")
    if not found.bfee:
        raise BadInput(f"{path}: no CSI frames (/csi)")
    return found
