"""What `rover run` prints when it ends, like `ros2 bag info` or evo: the time processed, poses, tags
localized of those heard (and which not), the errors when the dataset has truth, and where the
outputs went; read back from the output folder, so it says what the files say."""

from __future__ import annotations

import csv
import json
from pathlib import Path


def run_summary(out: Path) -> list[str]:
    """Lines summarizing the run whose results are in `out` (none when it holds no run.json)."""
    run_file = out / "run.json"
    if not run_file.is_file():
        return []
    run = json.loads(run_file.read_text(encoding="utf-8"))
    lines = []
    stamps = [float(line.split()[0]) for line in _lines(out / "trajectory.tum")]
    span = f", {stamps[-1] - stamps[0]:.1f} s" if len(stamps) > 1 else ""
    lines.append(f"run {run.get('status', '?')}: {len(stamps):,} poses{span}, {run.get('received', 0):,} messages")
    tags = _tags(out / "tags.csv")
    if tags:
        known = [t for t, state, _ in tags if state == LOCALIZED]
        lost = [t for t, state, _ in tags if state == EARLIER]
        never = [t for t, state, _ in tags if state == NEVER]
        notes = [f"never localized: {', '.join(never)}"] if never else []
        notes += [f"localized earlier, not at the end: {', '.join(lost)}"] if lost else []
        shown = f" ({'; '.join(notes)})" if notes else ""
        lines.append(f"tags localized at the end: {len(known)} of {len(tags)} heard{shown}")
        lines += [f"  tag {t}: {why}" for t, state, why in tags if state != LOCALIZED and why]
    metrics_file = out / "metrics.json"
    if metrics_file.is_file():
        metrics = json.loads(metrics_file.read_text(encoding="utf-8"))
        robot = metrics.get("robot", {}).get("trajectory.tum", {}).get("unaligned", {})
        parts = [f"robot mean {robot['mean_m'] * 100:.1f} cm"] if "mean_m" in robot else []
        for kind, key in (("LOS", "los_tags_mean_m"), ("NLOS", "nlos_tags_mean_m")):
            if metrics.get(key) is not None:
                parts.append(f"{kind} tags mean {metrics[key] * 100:.1f} cm")
        if parts:
            lines.append("errors against the dataset's truth: " + ", ".join(parts))
    lines.append(f"wrote {out}/ ({', '.join(sorted(['run.json', *run.get('files', [])]))})")
    return lines


def _lines(path: Path) -> list[str]:
    if not path.is_file():
        return []
    return [line for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]


LOCALIZED, EARLIER, NEVER = "localized", "earlier", "never"
"""a tag at the run's end: published localized (tags.csv's observable), localized at some time
before but not at the end (a position, observable 0: the SLAM says why), or never localized"""


def _tags(path: Path) -> list[tuple[str, str, str]]:
    """(id, state, why: its status and reason, when the SLAM sent them) of every tag in a tags.csv."""
    if not path.is_file():
        return []
    with path.open(encoding="utf-8", newline="") as f:
        rows = list(csv.DictReader(f))
    return [
        (
            r["id"],
            LOCALIZED if r.get("observable") == "1" else EARLIER if r.get("x") else NEVER,
            f"{r['status']}: {r.get('reason', '')}" if r.get("status") else "",
        )
        for r in rows
    ]
