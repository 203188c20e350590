"""The default pipeline on three hosts against one process: three network namespaces joined by a
bridge (tests/netns.py), as they are, under `security:` (mutual TLS and the access control
generated from the wiring), and with 1 % packet loss (nftables) and 50 ms added each way (a
delaying relay), on the `paper` scenario, seed 1.

Prints the wall-clock time of each run, its real-time factor, and whether the outputs are the same
bytes as one process's. Needs root (network namespaces); without it, says so and records nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

from netns import ADDRESSES, Lab, lab_certs, pipeline_file, rover_env  # noqa: E402

COMPARED = ("results.mcap", "trajectory.tum", "trajectory_live.tum", "tags.csv", "metrics.json")
PORT, RELAY_PORT = 7447, 7448
HOSTS = ("laptop", "base", "nuc")
LOSS_PERCENT = 1
DELAY_S = 0.05
RUN_S = 900.0


def rover(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "rover.cli", *args], capture_output=True, text=True, env=rover_env(), timeout=RUN_S
    )


def one_process(dataset: Path, out: Path) -> float:
    started = time.monotonic()
    done = rover("run", "--dataset", str(dataset), "--output", str(out), "--workers", "1")
    if done.returncode != 0:
        raise SystemExit(f"one process failed ({done.returncode}): {done.stderr[-2000:]}")
    return time.monotonic() - started


def three_hosts(dataset: Path, out: Path, work: Path, impaired: bool, tls: bool = False) -> float:
    with Lab() as lab:
        ports = {h: PORT for h in HOSTS}
        if impaired:
            lab.relay("nuc", RELAY_PORT, f"{ADDRESSES['nuc']}:{PORT}", DELAY_S)
            lab.loss(LOSS_PERCENT)
            ports.update(base=RELAY_PORT, laptop=RELAY_PORT)
        pipeline = pipeline_file(work, certs=lab_certs(work / f"certs-{out.name}") if tls else None)
        started = time.monotonic()
        procs = {
            h: lab.popen(
                h,
                "run",
                str(pipeline),
                "--host",
                h,
                "--dataset",
                str(dataset),
                "--output",
                str(out),
                "--set",
                f"port={ports[h]}",
            )
            for h in HOSTS
        }
        for host, proc in procs.items():
            _out, err = proc.communicate(timeout=RUN_S)
            if proc.returncode != 0:
                raise SystemExit(f"host {host} failed ({proc.returncode}): {err[-2000:]}")
        return time.monotonic() - started


def same(a: Path, b: Path) -> bool:
    return all((a / name).read_bytes() == (b / name).read_bytes() for name in COMPARED)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--json", help="write the figures to this file")
    args = parser.parse_args()
    if os.geteuid() != 0:
        print("bench_hosts: skipped: network namespaces need root")
        if args.json:
            Path(args.json).write_text(json.dumps({"skipped": "needs root"}) + "\n")
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        dataset = work / "paper-1.mcap"
        made = rover("simulate", "--scenario", "paper", "--seed", "1", "-o", str(dataset))
        if made.returncode != 0:
            raise SystemExit(made.stderr)
        duration_s = float(json.loads(rover("info", "--json", str(dataset)).stdout)["duration_s"])
        figures: dict[str, dict[str, float | bool]] = {}
        one_s = one_process(dataset, work / "one")
        figures["one_process"] = {"wall_s": one_s, "real_time_x": duration_s / one_s}
        runs = (
            ("three_hosts", False, False),
            ("three_hosts_tls", False, True),
            ("three_hosts_loss_delay", True, False),
        )
        for name, impaired, tls in runs:
            out = work / name
            wall = three_hosts(dataset, out, work, impaired, tls)
            figures[name] = {
                "wall_s": wall,
                "real_time_x": duration_s / wall,
                "vs_one_process": wall / one_s,
                "identical_outputs": same(work / "one", out),
            }
    print(f"paper scenario, seed 1: {duration_s:.1f} s of data")
    print(f"{'run':<26}{'wall s':>8}{'x real time':>13}{'vs one':>8}  identical")
    for name, f in figures.items():
        ratio = f"{f['vs_one_process']:.2f}" if "vs_one_process" in f else "-"
        ident = str(f.get("identical_outputs", "-"))
        print(f"{name:<26}{f['wall_s']:>8.1f}{f['real_time_x']:>13.1f}{ratio:>8}  {ident}")
    print(f"(loss {LOSS_PERCENT} % of every host's outgoing packets, {DELAY_S * 1000:.0f} ms each way NUC<->others;")
    print(" tls: mutual TLS with the access control generated from the wiring)")
    if args.json:
        Path(args.json).write_text(json.dumps({"duration_s": duration_s, **figures}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
