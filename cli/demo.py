"""`make demo`: the paper's experiment end to end, through the real pipeline and transport.

Simulates the `paper` scenario once (cached), runs the default pipeline on it (replay, sweep,
decode, AoA, preintegration, SLAM, outputs; every stage over Zenoh), and prints the robot and
tag errors beside the paper's figures, and the files it wrote.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
from importlib import resources
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from rover import cli
from rover.evaluation.metrics import PAPER_LOS_TAGS_MEAN_M, PAPER_ROBOT_MEAN_M

PAPER_NLOS_TAG_M = 1.459


def cache_dir() -> Path:
    return Path(os.environ.get("ROVER_CACHE", Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "rover"))


def simulator_version() -> str:
    """A digest of the paper scenario and the simulator's code: a cached dataset is remade when either changes."""
    digest = hashlib.sha256()
    package = resources.files("rover.datasets")
    for name in ("scenarios/paper.yaml", "simulate.py", "radio.py", "motion.py", "imu_model.py", "scenario.py"):
        digest.update(package.joinpath(name).read_bytes())
    return digest.hexdigest()[:12]


def cached_dataset(seed: int, console: Console) -> Path:
    path = cache_dir() / f"paper-seed{seed}-{simulator_version()}.mcap"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        console.print(f"[bold]rover simulate --scenario paper --seed {seed}[/] (once; cached at {path})")
        status = cli.main(["-q", "simulate", "--scenario", "paper", "--seed", str(seed), "-o", str(path)])
        if status != 0:
            raise SystemExit(status)
    return path


def report(metrics: dict[str, Any], console: Console) -> None:
    def cm(v: float | None) -> str:
        return "-" if v is None else f"{v * 100:.1f} cm"

    table = Table(title="Rover on the paper's scenario (simulated), beside the paper")
    for column in ("", "Rover", "paper (Zhang et al.)"):
        table.add_column(column, justify="right" if column else "left")
    robot = metrics["robot"]["trajectory.tum"]["unaligned"]
    live = metrics["robot"].get("trajectory_live.tum", {}).get("unaligned")
    table.add_row("robot, mean error", cm(robot["mean_m"]), cm(PAPER_ROBOT_MEAN_M))
    table.add_row("robot, median error", cm(robot["median_m"]), "")
    if live:
        table.add_row("robot, mean error live", cm(live["mean_m"]), "")
    for tag_id, t in metrics["tags"].items():
        label = f"tag {tag_id}{' (NLOS)' if t['nlos'] else ''}"
        table.add_row(label, cm(t.get("error_m")) if t["localized"] else "never localized", "")
    table.add_row("LOS tags, mean", cm(metrics["los_tags_mean_m"]), cm(PAPER_LOS_TAGS_MEAN_M))
    table.add_row("NLOS tag", cm(metrics["nlos_tags_mean_m"]), cm(PAPER_NLOS_TAG_M))
    if "aoa" in metrics:
        for kind, paper in (("los", 9.3), ("nlos", 18.1)):
            a = metrics["aoa"][kind]
            if a["count"]:
                table.add_row(f"AoA median error, {kind.upper()}", f"{a['median_deg']:.1f} deg", f"{paper} deg")
    console.print(table)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m rover.cli.demo", description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--output", type=Path, default=Path("rover-out") / "demo")
    args = ap.parse_args(argv)
    console = Console()
    dataset = cached_dataset(args.seed, console)
    command = ["run", "--dataset", str(dataset), "--output", str(args.output)]
    console.print(f"[bold]rover {' '.join(command)}[/]")
    status = cli.main(command)
    if status != 0:
        return status
    metrics_path = args.output / "metrics.json"
    report(json.loads(metrics_path.read_text()), console)
    console.print("Wrote:")
    for path in sorted(args.output.iterdir()):
        if not path.name.startswith("."):
            console.print(f"  {path}")
    console.print(
        f"Open results.mcap in Foxglove; `rover eval {args.output}` prints every error "
        "(trajectory.tum is a TUM file evo reads too)."
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
