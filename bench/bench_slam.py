"""SLAM accuracy and latency on the simulated `paper` scenario, several seeds.

The front end (replay, sweep, decode, AoA, preintegration) runs once per seed through the real
pipeline; the `slam` operator is then re-run on its recorded AoAs and preintegrations for each
variant: the paper's own sensors (AoA + IMU only, no wheeled-robot assumption; the issue 18 goal:
robot mean <= 39.3 cm and LOS tags <= 74.6 cm on seeds 1-6), the same on a wheeled robot without
encoders, the same without bias states, with wheel odometry (the default), and the full batch of
the whole run. Latency: from an epoch's data to its pose, for the operator alone at real time on
one core (pose_latency), every run, with a 10-minute `paper` run and `long_hall` beside the seeds,
and for several window sizes; p50, p99, p99.9 and max. Goals: robot mean <= 20 cm, LOS tags
<= 35 cm, NLOS tag <= 80 cm (issue 6); latency p99 <= 20 ms (issue 18).
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from rover.evaluation.metrics import Poses2D, poses_of_messages, trajectory_errors
from rover.formats.bag import iter_messages
from rover.formats.run_dir import load_truth
from rover.geometry import wrap_angle, yaw_from_quaternion
from rover.messages import deserialize, serialize, stamp_ns
from rover.operators.slam.operator import Slam, SlamParams
from rover.runtime.scheduler import EventTimeMerger

PAPER = {"robot_mean_m": 0.393, "los_tags_mean_m": 0.746, "nlos_tag_m": 1.459}
PORTS = {"/rover/aoa": "aoa", "/rover/preintegration": "odometry", "/odom": "wheel"}
ORDER = {"/rover/aoa": 0, "/rover/preintegration": 1, "/odom": 2}


def read(path: Path, topics: list[str]) -> list[tuple[str, int, object]]:
    return [(m.topic, m.log_time_ns, deserialize(m.data, m.schema)) for m in iter_messages(path, topics)]


def front_end(dataset: Path, out: Path) -> Path:
    proc = subprocess.run(
        [sys.executable, "-m", "rover.cli", "-q", "run", "--dataset", str(dataset), "--output", str(out)],
        capture_output=True,
        text=True,
    )
    if proc.returncode != 0:
        raise SystemExit(f"rover run failed: {proc.stderr.strip()}")
    return out / "results.mcap"


def inputs(results: Path, dataset: Path) -> list[tuple[str, int, object]]:
    items = read(results, ["/rover/aoa", "/rover/preintegration"]) + read(dataset, ["/odom"])
    return sorted(items, key=lambda i: (i[1], ORDER[i[0]]))


def run_slam(items, params: SlamParams, limit_epochs: int | None = None) -> tuple[list, float, Slam, np.ndarray]:
    """The operator over the items (up to the first `limit_epochs` epochs), delivered as the runtime
    would (event-time order); what it emitted, its CPU time, the operator (its window as the run
    left it), and each epoch's pose latency at real time (ms, see `pose_latency`)."""
    epochs = [k for k, (topic, _stamp, _msg) in enumerate(items) if topic == "/rover/preintegration"]
    if limit_epochs is not None and len(epochs) > limit_epochs:
        items = items[: epochs[limit_epochs]]
    ports = sorted({PORTS[topic] for topic, _s, _m in items})
    merger = EventTimeMerger(ports)
    for topic, _stamp, msg in items:
        merger.push(PORTS[topic], stamp_ns(msg), msg)
    for port in ports:
        merger.end(port)
    op = Slam(params)
    out: list = []
    served: list[tuple[int, float, float | None]] = []  # (arrival stamp, service s, pose after s)
    # the inputs (every seed's, held here at once) would be another process's in a pipeline: out of
    # the garbage collector's full scans, which took up to 0.9 s over them (seen as latency spikes)
    gc.freeze()
    start = time.process_time()
    for port, stamp, msg in merger.pop_ready():
        began = time.perf_counter()
        pose_s = None
        for emit in op.on_input(port, msg, stamp) or ():
            serialize(emit.msg)  # as the runtime does before sending it
            if emit.port == "pose" and pose_s is None:
                pose_s = time.perf_counter() - began
            out.append(emit)
        served.append((stamp, time.perf_counter() - began, pose_s))
    out.extend(op.on_end() or ())
    cpu_s = time.process_time() - start
    gc.unfreeze()
    return out, cpu_s, op, pose_latency(served)


def pose_latency(served: list[tuple[int, float, float | None]]) -> np.ndarray:
    """Each epoch's latency (ms) from its data's arrival to its pose, for the operator alone at real
    time on one core: an input arrives at its stamp, waits while the operator is still busy with
    earlier ones (a tag search after the last pose, the periodic path included), and its pose is
    out when the operator has yielded it and it is serialized. The service times (the handler and
    the serialization of what it emits, as the runtime's task does) are the ones measured in this
    run; the transport is not included (bench_end_to_end, bench_live)."""
    busy_until = -math.inf
    t0 = served[0][0] if served else 0
    latency = []
    for stamp, service_s, pose_s in served:
        arrival = (stamp - t0) / 1e9
        begin = max(arrival, busy_until)
        if pose_s is not None:
            latency.append(begin + pose_s - arrival)
        busy_until = begin + service_s
    return np.array(latency) * 1e3


def tails(ms: np.ndarray) -> dict[str, float | int | None]:
    """p50, p99, p99.9 and max of latencies (ms)."""
    if not len(ms):
        return {"n": 0, "p50_ms": None, "p99_ms": None, "p99_9_ms": None, "max_ms": None}
    p50, p99, p999 = np.percentile(ms, [50, 99, 99.9])
    return {
        "n": len(ms),
        "p50_ms": float(p50),
        "p99_ms": float(p99),
        "p99_9_ms": float(p999),
        "max_ms": float(ms.max()),
    }


def stage_ms(out, stage: str) -> np.ndarray:
    """The wall times (ms) of one stage's Timing messages (slam.update, slam.search)."""
    return np.array([e.msg.wall_s for e in out if e.port == "timing" and e.msg.stage == stage]) * 1e3


def tails_text(t: dict) -> str:
    if not t["n"]:
        return "none"
    return f"p50 {t['p50_ms']:.1f}, p99 {t['p99_ms']:.1f}, p99.9 {t['p99_9_ms']:.1f}, max {t['max_ms']:.1f} ms"


MG_M_S2 = 9.80665e-3


def observability(items, op: Slam) -> dict:
    """What made scale and bias observable in a run: the epochs flagged turning in place (zero
    velocity), the accelerometer bias states' estimate and std at the end (mg), and the wheel
    scale's (the fraction by which the wheels over-read)."""
    pre = [m for topic, _s, m in items if topic == "/rover/preintegration"]
    w = op.window
    out: dict = {"turning_in_place_s": float(sum(m.dt for m in pre if m.turning_in_place))}
    std = np.sqrt(np.maximum(np.diag(w.bias_covariance), 0.0)) if w.bias_covariance.size else None
    if w.accel_biases and std is not None:
        out["bias_mg"] = (w.bias() / MG_M_S2).tolist()
        out["bias_std_mg"] = (std[: w.accel_biases] / MG_M_S2).tolist()
    if w.scale and std is not None:
        out["wheel_scale"] = w.wheel_scale()
        out["wheel_scale_std"] = float(std[-1])
    return out


def true_wheel_scale(items, truth: Poses2D) -> float | None:
    """The fraction by which the run's wheels over-read (the wheel_scale state's truth): the wheel
    speeds regressed on the true forward speed where the robot moves, z = (1 + s) u."""
    odom = [(stamp, m.twist.twist.linear.x) for topic, stamp, m in items if topic == "/odom"]
    if not odom:
        return None
    stamps, speed = np.array([o[0] for o in odom], float), np.array([o[1] for o in odom])
    t = truth.stamp_ns.astype(float)
    velocity = np.gradient(truth.xy, t / 1e9, axis=0)
    forward = np.interp(stamps, t, velocity[:, 0] * np.cos(truth.yaw) + velocity[:, 1] * np.sin(truth.yaw))
    moving = forward > 0.05
    k = float(np.sum(speed[moving] * forward[moving]) / np.sum(forward[moving] ** 2))
    return k - 1


def score(out, truth: Poses2D, truth_tags: dict, nlos: set[int]) -> dict:
    final = poses_of_messages([e.msg for e in out if e.port == "trajectory"])
    live = poses_of_messages([e.msg for e in out if e.port == "pose"])
    errors = trajectory_errors(truth, final)
    live_errors = trajectory_errors(truth, live) if len(live.stamp_ns) > 1 else None
    arrays = [e.msg for e in out if e.port == "tags"]
    t0 = final.stamp_ns[0]
    tags = {}
    for tag in arrays[-1].tags:
        where = errors.to_start.apply(np.array([truth_tags[tag.id]]))[0]
        heard = next(stamp_ns(a) for a in arrays if any(t.id == tag.id for t in a.tags))
        localized = next((stamp_ns(a) for a in arrays if any(t.id == tag.id and t.observable for t in a.tags)), None)
        tags[tag.id] = {
            "error_m": float(math.hypot(tag.position.x - where[0], tag.position.y - where[1])),
            "nlos": tag.id in nlos,
            "observable": bool(tag.observable),
            "first_heard_s": (heard - t0) / 1e9,
            "first_localized_s": None if localized is None else (localized - t0) / 1e9,
        }
    los = [t["error_m"] for t in tags.values() if not t["nlos"]]
    nl = [t["error_m"] for t in tags.values() if t["nlos"]]
    return {
        "robot_mean_m": errors.unaligned["mean_m"],
        "robot_median_m": errors.unaligned["median_m"],
        "robot_live_mean_m": live_errors.unaligned["mean_m"] if live_errors else None,
        "robot_aligned_mean_m": errors.aligned["mean_m"],
        "los_tags_mean_m": float(np.mean(los)) if los else None,
        "nlos_tag_m": float(np.mean(nl)) if nl else None,
        "tags": tags,
        "update_ms": tails(stage_ms(out, "slam.update")),
        "search_ms": tails(stage_ms(out, "slam.search")),
    }


def truth_of(dataset: Path) -> tuple[Poses2D, dict[int, np.ndarray], set[int]]:
    truth = load_truth(dataset)
    if truth is None:
        raise SystemExit(f"{dataset} has no ground truth")
    return (
        truth.trajectory,
        {i: xy for i, (xy, _nlos) in truth.tags.items()},
        {i for i, (_xy, n) in truth.tags.items() if n},
    )


def heading_drift_deg(items, truth: Poses2D) -> float:
    """Largest gap between the gyro heading the SLAM uses and the true heading (start-frame)."""
    pre = [m for t, _s, m in items if t == "/rover/preintegration"]
    stamps = np.array([stamp_ns(m) for m in pre])
    yaw = np.array(
        [yaw_from_quaternion(m.orientation.x, m.orientation.y, m.orientation.z, m.orientation.w) for m in pre]
    )
    k = np.clip(np.searchsorted(truth.stamp_ns, stamps), 0, len(truth.stamp_ns) - 1)
    k0 = int(np.clip(np.searchsorted(truth.stamp_ns, stamps[0]), 0, len(truth.stamp_ns) - 1))
    gap = wrap_angle(yaw - (truth.yaw[k] - truth.yaw[k0]))
    return float(np.degrees(np.abs(gap).max()))


def simulate(tmp: Path, scenario: str, seed: int, *sets: str) -> Path:
    dataset = tmp / f"{Path(scenario).stem}-{seed}{'-'.join(['', *sets]).replace('=', '')}.mcap"
    command = [sys.executable, "-m", "rover.cli", "-q", "simulate", "--scenario", scenario, "--seed", str(seed)]
    for item in sets:
        command += ["--set", item]
    subprocess.run([*command, "-o", str(dataset)], check=True)
    return dataset


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6])
    ap.add_argument("--windows", type=int, nargs="+", default=[10, 30, 100, 300])
    ap.add_argument("--no-long", action="store_true", help="skip the 10-minute `paper` and the `long_hall` runs")
    ap.add_argument("--json")
    args = ap.parse_args()
    figures: dict = {"paper": PAPER, "variants": {}, "latency": {}, "long_runs": {}}
    variants = {
        "AoA + IMU only (the paper's sensors; wheel=false, nonholonomic=false)": SlamParams(
            wheel=False, nonholonomic=False
        ),
        "AoA + IMU on a wheeled robot without encoders (wheel=false)": SlamParams(wheel=False),
        "AoA + IMU only, no bias states (accel_bias=false)": SlamParams(
            wheel=False, nonholonomic=False, accel_bias=False
        ),
        "with wheel odometry (default)": SlamParams(),
        "full batch, wheel odometry": SlamParams(batch=True),
    }
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        per_seed = []
        for seed in args.seeds:
            dataset = simulate(tmp, "paper", seed)
            items = inputs(front_end(dataset, tmp / f"run-{seed}"), dataset)
            truth, tags, nlos = truth_of(dataset)
            per_seed.append((seed, items, truth, tags, nlos))
            figures.setdefault("heading_drift_deg", []).append(heading_drift_deg(items, truth))
        for name, params in variants.items():
            rows = []
            for seed, items, truth, tags, nlos in per_seed:
                out, cpu_s, op, latency = run_slam(items, params)
                row = score(out, truth, tags, nlos)
                seen = observability(items, op)
                if "wheel_scale" in seen:
                    seen["wheel_scale_true"] = true_wheel_scale(items, truth)
                row.update(seed=seed, cpu_s=cpu_s, observability=seen, pose_ms=tails(latency))
                rows.append(row)
            figures["variants"][name] = rows
            print(f"{name}:")
            for r in rows:
                tag_text = ", ".join(
                    f"{i}{'*' if t['nlos'] else ''} {t['error_m'] * 100:.0f} cm"
                    f" (localized {t['first_localized_s']:.0f} s)"
                    if t["first_localized_s"] is not None
                    else f"{i} {t['error_m'] * 100:.0f} cm (never localized)"
                    for i, t in sorted(r["tags"].items())
                )
                live = f" (live {r['robot_live_mean_m'] * 100:.1f} cm)" if r["robot_live_mean_m"] is not None else ""
                seen = r["observability"]
                bias = (
                    "; bias body ({:.2f}, {:.2f}) world ({:.2f}, {:.2f}) mg".format(*seen["bias_mg"])
                    + " +- ({:.2f}, {:.2f}, {:.2f}, {:.2f})".format(*seen["bias_std_mg"])
                    if "bias_mg" in seen
                    else ""
                )
                if "wheel_scale" in seen:
                    bias += f"; wheel scale {seen['wheel_scale']:+.2%} +- {seen['wheel_scale_std']:.2%}"
                    if seen.get("wheel_scale_true") is not None:
                        bias += f" (true {seen['wheel_scale_true']:+.2%})"
                print(
                    f"  seed {r['seed']}: robot mean {r['robot_mean_m'] * 100:.1f} cm, median "
                    f"{r['robot_median_m'] * 100:.1f} cm{live}; tags {tag_text}; {r['cpu_s']:.1f} s CPU; "
                    f"turning in place {seen['turning_in_place_s']:.1f} s{bias}"
                )
                if not params.batch:
                    print(f"    pose latency {tails_text(r['pose_ms'])}; tag searches {tails_text(r['search_ms'])}")
            mean = {
                key: float(np.mean([r[key] for r in rows if r[key] is not None]))
                for key in ("robot_mean_m", "los_tags_mean_m", "nlos_tag_m")
            }
            print(
                f"  mean over seeds: robot {mean['robot_mean_m'] * 100:.1f} cm (paper 39.3), LOS tags "
                f"{mean['los_tags_mean_m'] * 100:.1f} cm (paper 74.6), NLOS tag {mean['nlos_tag_m'] * 100:.1f} cm "
                f"(paper 145.9)"
            )
        print(f"gyro heading drift over a run (max): {max(figures['heading_drift_deg']):.2f} deg")
        if not args.no_long:
            long_runs: dict[str, tuple[str, int, list[str]]] = {
                "paper, 10 minutes (7 laps), seed 1": ("paper", 1, ["trajectory.laps=7"]),
                "long_hall, seed 1": ("long_hall", 1, []),
            }
            for name, (scenario, seed, sets) in long_runs.items():
                dataset = simulate(tmp, scenario, seed, *sets)
                items = inputs(front_end(dataset, tmp / f"run-{dataset.stem}"), dataset)
                out, cpu_s, _op, latency = run_slam(items, SlamParams())
                row = score(out, *truth_of(dataset))
                row.update(cpu_s=cpu_s, pose_ms=tails(latency))
                figures["long_runs"][name] = row
                print(
                    f"{name}: robot mean {row['robot_mean_m'] * 100:.1f} cm, LOS tags "
                    f"{(row['los_tags_mean_m'] or 0) * 100:.1f} cm; pose latency {tails_text(row['pose_ms'])}; "
                    f"updates {tails_text(row['update_ms'])}; tag searches {tails_text(row['search_ms'])}"
                )
        _seed, items, *_ = per_seed[0]
        for window in args.windows:
            out, _cpu, _op, latency = run_slam(items, SlamParams(window=window), limit_epochs=window + 150)
            figures["latency"][window] = {
                "pose": tails(latency[window:]),
                "update": tails(stage_ms(out, "slam.update")[window:]),
            }
            print(f"window {window:4d} epochs: pose latency {tails_text(figures['latency'][window]['pose'])}")
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
