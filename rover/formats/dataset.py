"""What a Rover dataset is, for everything that writes or reads one (`rover convert`, `rover simulate`,
`rover record`, `dataset_replay`, `rover info`).

A dataset is one MCAP file that is also a ROS 2 bag: `/csi` (CSI Tool records, each with the channel
it was received on) or `/csi/capture` (another tool's CSI, decoded), `/imu/data`, optional `/odom`,
optional ground truth, and MCAP metadata: the rig
description (`rover.setup`), where the data came from (`rover.provenance`) and, for a live recording,
what arrived late (`rover.record`).
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from pathlib import Path

import yaml

import rover
from rover.formats.rig import DEFAULT_TOPICS, Rig

TOPICS = dict(DEFAULT_TOPICS)
"""role -> the dataset's topic"""
TYPES = {"csi": "rover_msgs/msg/CsiFrame", "imu": "sensor_msgs/msg/Imu", "odom": "nav_msgs/msg/Odometry"}
"""role -> the message type of its topic"""
CAPTURE_TOPIC = "/csi/capture"
"""another tool's CSI (`rover convert` of a WiROS bag): rover_msgs/msg/Csi, a transmitter per tag_id"""
CAPTURE_TYPE = "rover_msgs/msg/Csi"
SETUP_METADATA = "rover.setup"
PROVENANCE_METADATA = "rover.provenance"
RECORD_METADATA = "rover.record"


def setup_yaml(rig: Rig) -> str:
    """The rig description stored in a dataset: the rig file with its topics renamed to the dataset's own
    (a role the rig switches off, such as `odom: null`, stays off)."""
    data = yaml.safe_load(rig.text) or {}
    data["topics"] = {role: (TOPICS[role] if rig.topics.get(role, "") is not None else None) for role in TOPICS}
    return yaml.safe_dump(data, sort_keys=False)


def sha256(path: Path) -> str:
    """Digest of a file, or of a folder's files in name order (a ROS 2 bag folder)."""
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    digest = hashlib.sha256()
    for file in files:
        with file.open("rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


def provenance(command_line: str, sources: Sequence[Path] | str) -> dict[str, str]:
    """The `rover.provenance` metadata: the tool, its command line, and the input files with their
    digests (or a description of a source that is not a file, such as a simulated scenario)."""
    if isinstance(sources, str):
        return {"tool": f"rover {rover.__version__}", "command": command_line, "sources": sources}
    listed = yaml.safe_dump([{"path": str(p), "sha256": sha256(p)} for p in sources])
    return {"tool": f"rover {rover.__version__}", "command": command_line, "sources": listed}
