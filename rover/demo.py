"""`make demo`: run the default pipeline, through the real transport, and say what came out.

Until the simulator lands (issue 4) the demo plays the independent sample recording that
sits beside the repository in shared/data (or any dataset given with --dataset).
"""

from __future__ import annotations

import argparse
import os
import sys
from collections import Counter
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from rich.console import Console
from rich.table import Table

from rover import cli
from rover.messages import deserialize

SAMPLE = Path("recording_sample")


def default_dataset() -> tuple[Path, Path] | None:
    """The sample recording's bag and setup, when shared/data sits beside the repository."""
    root = Path(os.environ.get("ROVER_TEST_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
    bag, setup = root / SAMPLE / "bag" / "bag.mcap", root / SAMPLE / "setup.yaml"
    return (bag, setup) if bag.is_file() and setup.is_file() else None


def summarize(path: Path, console: Console) -> None:
    counts: Counter = Counter()
    tags: Counter = Counter()
    spread: dict[int, list[tuple[int, float]]] = {}
    first = last = None
    with path.open("rb") as f:
        for _schema, channel, message in make_reader(f).iter_messages(log_time_order=False):
            counts[channel.topic] += 1
            first = message.log_time if first is None else min(first, message.log_time)
            last = message.log_time if last is None else max(last, message.log_time)
            if channel.topic == "/rover/aoa":
                aoa = deserialize(message.data, "rover_msgs/msg/Aoa")
                tags[(aoa.tag_id, aoa.channel)] += 1
                spread.setdefault(aoa.tag_id, []).append((aoa.packets, np.degrees(aoa.std_rad)))
    duration_s = (last - first) / 1e9 if counts else 0.0
    table = Table(title=f"What the pipeline recorded ({duration_s:.1f} s of data)")
    table.add_column("topic")
    table.add_column("messages", justify="right")
    table.add_column("rate", justify="right")
    for topic, n in sorted(counts.items()):
        table.add_row(topic, f"{n:,}", f"{n / duration_s:.1f} Hz" if duration_s else "-")
    console.print(table)
    if tags:
        per_tag = Table(title="Angles of arrival per tag")
        for column in ("tag", "channel", "bursts", "packets per burst", "median std"):
            per_tag.add_column(column, justify="right")
        for (tag, ch), n in sorted(tags.items()):
            packets, std = np.array(spread[tag]).T
            per_tag.add_row(str(tag), str(ch), f"{n:,}", f"{np.median(packets):.0f}", f"{np.median(std):.1f} deg")
        console.print(per_tag)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m rover.demo", description=__doc__)
    ap.add_argument("--dataset", type=Path, default=None)
    ap.add_argument("--setup", type=Path, default=None, help="setup.yaml, for a dataset without a rig description")
    ap.add_argument("--output", type=Path, default=Path("rover-out") / "demo")
    args = ap.parse_args(argv)
    console = Console()
    found = default_dataset()
    dataset, setup = (args.dataset, args.setup) if args.dataset else found or (None, None)
    if dataset is None:
        console.print("rover demo: no dataset: pass --dataset PATH, or keep shared/data beside the repository "
                      "(set ROVER_TEST_DATA to point at it)", style="red")
        return 2
    command = ["run", "--dataset", str(dataset), "--output", str(args.output)]
    command += ["--set", f"setup={setup}"] if setup else []
    console.print(f"[bold]rover {' '.join(command)}[/]")
    status = cli.main(command)
    if status != 0:
        return status
    result = args.output / "results.mcap"
    summarize(result, console)
    console.print(f"Wrote {result}")
    console.print("Stages so far: dataset replay -> channel sweep -> CSI decoding -> AoA -> recorder, over Zenoh. "
                  "Draw the pipeline with `rover graph`.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
