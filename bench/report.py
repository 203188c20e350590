"""Write docs/benchmarks.md from bench/results.json and bench/goals.yaml: `make bench` runs it last.

The page is generated, never edited by hand: each row is a figure read from results.json (a range
over seeds or repeats where the path selects several values), the goal from goals.yaml and whether
the figure meets it, and each section says where and when its benchmark last ran (the stamp
`run_all.py` writes into results.json's `measured`). `python bench/report.py --check` exits 1 when
the page on disk differs from what the two files give.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results.json"
GOALS = HERE / "goals.yaml"
PAGE = HERE.parent / "docs" / "benchmarks.md"

# unit -> (factor from the stored value, decimals, suffix)
UNITS: dict[str, tuple[float, int, str]] = {
    "cm": (100.0, 1, " cm"),
    "m": (1.0, 2, " m"),
    "ms": (1.0, 1, " ms"),
    "s": (1.0, 1, " s"),
    "x": (1.0, 2, "x"),
    "deg": (1.0, 1, " deg"),
    "percent": (100.0, 1, "%"),
    "rate": (1.0, 0, "/s"),
    "hz": (1.0, 1, " Hz"),
    "count": (1.0, 0, ""),
    "number": (1.0, 2, ""),
    "bool": (1.0, 0, ""),
}


class ReportError(Exception):
    """goals.yaml names a path results.json does not have, or a unit or key this script does not know."""


@dataclass(frozen=True)
class Goal:
    """A bound in the row's displayed unit: the worst value over the row must meet it."""

    max: float | None = None
    min: float | None = None
    text: str = ""

    def met(self, values: list[float]) -> bool | None:
        if self.max is not None:
            return max(values) <= self.max
        if self.min is not None:
            return min(values) >= self.min
        return None

    def describe(self, suffix: str) -> str:
        if self.text:
            return self.text
        if self.max is not None:
            return f"<= {self.max:,g}{suffix}"
        if self.min is not None:
            return f">= {self.min:,g}{suffix}"
        return ""


def select(node: Any, path: list[Any], where: str) -> Iterator[Any]:
    """Every value at `path` under `node`. A step is a key, `*` (every item of a list or dict), a list
    of keys (each of them, in that order) or `{key: value}` (the list items whose key has that value)."""
    if not path:
        yield node
        return
    step, rest = path[0], path[1:]
    if step == "*":
        items = node.values() if isinstance(node, dict) else node
        for item in items:
            yield from select(item, rest, where)
    elif isinstance(step, list):
        for key in step:
            yield from select(node, [key, *rest], where)
    elif isinstance(step, dict):
        ((key, value),) = step.items()
        matches = [item for item in node if isinstance(item, dict) and item.get(key) == value]
        if not matches:
            raise ReportError(f"{where}: no item with {key} = {value!r}")
        for item in matches:
            yield from select(item, rest, where)
    else:
        yield from select(_child(node, step, where), rest, where)


def _child(node: Any, key: Any, where: str) -> Any:
    if isinstance(node, dict) and str(key) in node:
        return node[str(key)]
    if isinstance(node, list) and isinstance(key, int) and -len(node) <= key < len(node):
        return node[key]
    raise ReportError(f"{where}: results.json has no {key!r} here")


def _flatten(values: list[Any]) -> list[Any]:
    out: list[Any] = []
    for value in values:
        out.extend(_flatten(value) if isinstance(value, list) else [value])
    return out


def render_row(section: str, row: dict[str, Any], figures: Any) -> str:
    where = f"goals.yaml: {section}: {row.get('figure', '?')}"
    unknown = set(row) - {"figure", "at", "unit", "show", "goal", "digits"}
    if unknown:
        raise ReportError(f"{where}: unknown keys {sorted(unknown)}")
    unit = row.get("unit", "number")
    if unit not in UNITS:
        raise ReportError(f"{where}: unknown unit {unit!r} (one of {', '.join(UNITS)})")
    factor, digits, suffix = UNITS[unit]
    digits = row.get("digits", digits)
    show = row.get("show", "range")
    raw = _flatten(list(select(figures, list(row["at"]), where)))
    if show == "count":
        return _line(row["figure"], f"{len(raw)}", "", None)
    if unit == "bool":
        text = "yes" if all(raw) else f"no ({sum(1 for v in raw if not v)} of {len(raw)})"
        return _line(row["figure"], text, "", None)
    values = [float(v) * factor for v in raw if v is not None]
    if not values:
        return _line(row["figure"], "not measured", "", None)

    def fmt(v: float) -> str:
        return f"{v:,.{digits}f}"

    if show == "each":
        text = " / ".join(fmt(v) for v in values) + suffix
    elif show in ("range", "range_mean"):
        low, high = min(values), max(values)
        text = fmt(low) + suffix if fmt(low) == fmt(high) else f"{fmt(low)}-{fmt(high)}{suffix}"
        if show == "range_mean" and len(values) > 1:
            text += f" (mean {fmt(statistics.fmean(values))})"
    else:
        raise ReportError(f"{where}: unknown show {show!r} (range, range_mean, each, count)")
    goal = Goal(**row["goal"]) if "goal" in row else None
    return _line(row["figure"], text, goal.describe(suffix) if goal else "", goal.met(values) if goal else None)


def _line(figure: str, value: str, goal: str, met: bool | None) -> str:
    verdict = "" if met is None else ("met" if met else "**not met**")
    cells = (cell.replace("|", "\\|") for cell in (figure, value, goal, verdict))
    return "| " + " | ".join(cells) + " |"


def render(results: dict[str, Any], goals: dict[str, Any]) -> str:
    stamps = results.get("measured", {})
    lines = [
        "# Benchmarks",
        "",
        "<!-- Generated by `make bench` (bench/report.py) from bench/results.json and bench/goals.yaml."
        " Do not edit: change goals.yaml or re-run the benchmark. -->",
        "",
        "**This page is generated** by `make bench` from `bench/results.json` (the figures) and",
        "`bench/goals.yaml` (which figures to show and their goals); edit those, not this page.",
        "A range is over the seeds or repeats the row names; a goal is met when the worst of them meets it.",
        "Timings move with the machine: compare them within one section, or side by side with `farm-bench`.",
        "One benchmark alone, as `make bench` runs it: `OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_slam.py`;",
        "`python bench/run_all.py slam decode` re-runs some and keeps the others' figures.",
        "",
    ]
    for name, section in goals["sections"].items():
        if name not in results:
            raise ReportError(f"goals.yaml: section {name!r} is not in results.json")
        stamp = stamps.get(name, {})
        lines += [f"## {section['title']}", ""]
        lines += [section["what"].strip(), ""]
        lines += [
            f"`bench/bench_{name}.py`, measured {stamp.get('date', 'on an unrecorded date')}"
            f" on {stamp.get('machine', 'an unrecorded machine')}"
            + (f" at commit `{stamp['commit']}`" if stamp.get("commit") else "")
            + ".",
            "",
            "| figure | measured | goal | |",
            "|---|---|---|---|",
        ]
        lines += [render_row(name, row, results[name]) for row in section["rows"]]
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if docs/benchmarks.md is out of date")
    args = parser.parse_args(argv)
    try:
        page = render(json.loads(RESULTS.read_text()), yaml.safe_load(GOALS.read_text()))
    except ReportError as error:
        print(f"bench/report.py: {error}", file=sys.stderr)
        return 2
    if args.check:
        if not PAGE.exists() or PAGE.read_text() != page:
            print(f"{PAGE} is out of date: run `python bench/report.py`", file=sys.stderr)
            return 1
        return 0
    PAGE.write_text(page)
    print(f"wrote {PAGE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
