"""The Python API without a pipeline: read a dataset, run the AoA front end's operators as plain
function calls, and print each tag's bearings.

    python examples/aoa_from_dataset.py run.mcap --seconds 30

Operators never touch files or the network, so `rover.testing.run_operator` can feed them a
list of messages and return what they emit, exactly as the pipeline would deliver them.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys

from rover.formats.bag import BagReader
from rover.formats.dataset import SETUP_METADATA
from rover.messages import deserialize, header, make
from rover.operators.aoa.operator import Aoa
from rover.operators.channel_sweep.operator import ChannelSweep
from rover.operators.csi_decode import CsiDecode
from rover.testing import run_operator


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", help="a Rover dataset (rover convert or rover simulate)")
    parser.add_argument("--seconds", type=float, default=30.0, help="how much of the dataset to read (default 30)")
    args = parser.parse_args(argv)

    with BagReader(args.dataset) as bag:
        setup_yaml = bag.metadata().get(SETUP_METADATA, {}).get("yaml")
        if setup_yaml is None:
            print(f"{args.dataset}: no rig description (rover.setup): convert it with --setup", file=sys.stderr)
            return 2
        frames = []
        for message in bag.messages(["/csi"]):
            if frames and message.log_time_ns - frames[0][0] > args.seconds * 1e9:
                break
            frames.append((message.log_time_ns, deserialize(message.data, message.schema)))
    if not frames:
        print(f"{args.dataset}: no /csi messages", file=sys.stderr)
        return 2
    setup = make("rover_msgs/msg/RigSetup", header=header(frames[0][0]), setup_yaml=setup_yaml)

    swept = run_operator(ChannelSweep(), {"frames": [msg for _, msg in frames], "setup": [setup]})
    labelled = [e.msg for e in swept if e.port == "labelled"]
    csi = [e.msg for e in run_operator(CsiDecode(), {"frames": labelled})]
    aoas = [e.msg for e in run_operator(Aoa(), {"csi": csi, "setup": [setup]})]

    print(f"{len(frames)} CSI frames, {len(csi)} decoded, {len(aoas)} AoA bursts")
    for tag in sorted({a.tag_id for a in aoas}):
        angles = [math.degrees(a.angle_rad) for a in aoas if a.tag_id == tag]
        stds = [math.degrees(a.std_rad) for a in aoas if a.tag_id == tag]
        print(
            f"tag {tag}: {len(angles)} bursts, first angle {angles[0]:+.1f} deg, "
            f"median std {statistics.median(stds):.1f} deg"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
