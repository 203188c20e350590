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

from mcap.reader import make_reader
from rich.console import Console
from rich.table import Table

from rover import cli
from rover.messages import deserialize

SAMPLE = Path("recording_sample") / "bag" / "bag.mcap"


def default_dataset() -> Path | None:
    root = Path(os.environ.get("ROVER_TEST_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
    path = root / SAMPLE
    return path if path.is_file() else None


def summarize(path: Path, console: Console) -> None:
    counts: Counter = Counter()
    channels: Counter = Counter()
    first = last = None
    with path.open("rb") as f:
        for _schema, channel, message in make_reader(f).iter_messages(log_time_order=False):
            counts[channel.topic] += 1
            first = message.log_time if first is None else min(first, message.log_time)
            last = message.log_time if last is None else max(last, message.log_time)
            if channel.topic == "/csi":
                channels[deserialize(message.data, "rover_msgs/msg/CsiFrame").channel] += 1
    duration_s = (last - first) / 1e9 if counts else 0.0
    table = Table(title=f"What the pipeline recorded ({duration_s:.1f} s of data)")
    table.add_column("topic")
    table.add_column("messages", justify="right")
    table.add_column("rate", justify="right")
    for topic, n in sorted(counts.items()):
        table.add_row(topic, f"{n:,}", f"{n / duration_s:.1f} Hz" if duration_s else "-")
    console.print(table)
    if channels:
        per_channel = ", ".join(f"channel {ch}: {n:,}" for ch, n in sorted(channels.items()))
        console.print(f"CSI frames by WiFi channel (one tag per channel): {per_channel}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m rover.demo", description=__doc__)
    ap.add_argument("--dataset", type=Path, default=None)
    ap.add_argument("--output", type=Path, default=Path("rover-out") / "demo")
    args = ap.parse_args(argv)
    console = Console()
    dataset = args.dataset or default_dataset()
    if dataset is None:
        console.print("rover demo: no dataset: pass --dataset PATH, or keep shared/data beside the repository "
                      "(set ROVER_TEST_DATA to point at it)", style="red")
        return 2
    console.print(f"[bold]rover run[/] --dataset {dataset} --output {args.output}")
    status = cli.main(["run", "--dataset", str(dataset), "--output", str(args.output)])
    if status != 0:
        return status
    result = args.output / "replay.mcap"
    summarize(result, console)
    console.print(f"Wrote {result}")
    console.print("Stages so far: dataset replay -> recorder, over Zenoh. Draw the pipeline with `rover graph`.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
