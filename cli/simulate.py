"""`rover simulate`: a dataset with ground truth from a scenario."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from rover.cli.args import seed
from rover.errors import BadInput


def add_parser(sub: Any, common: argparse.ArgumentParser) -> None:
    """`rover simulate` and its options."""
    p = sub.add_parser("simulate", parents=[common], help="a dataset with ground truth from a scenario")
    p.add_argument("--scenario", default="paper", help="a built-in scenario name or a scenario .yaml file")
    p.add_argument("--seed", type=seed, default=0, help="a whole number from 0 (the same seed gives the same bytes)")
    p.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE", help="override a scenario value")
    p.add_argument("-o", "--output", required=True, help="the dataset to write (.mcap)")
    p.add_argument("--force", action="store_true", help="replace an existing output")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import shlex

    from rover.datasets.scenario import load_scenario
    from rover.datasets.scenario_size import check_size
    from rover.datasets.simulate import simulate
    from rover.formats.bag import check_output

    overrides = {}
    for item in args.set or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise BadInput(f"--set {item!r}: expected SECTION.KEY=VALUE")
        overrides[key] = value
    check_output(args.output, force=args.force)  # before the scenario is read or anything simulated
    if Path(args.scenario).exists() and Path(args.scenario).resolve() == Path(args.output).resolve():
        raise BadInput(f"{args.output}: is also the scenario file; simulating onto it would destroy it")
    scenario = load_scenario(args.scenario, overrides)
    sets = "".join(f" --set {key}={value}" for key, value in overrides.items())
    check_size(scenario, f"scenario {args.scenario}{sets}")
    report = simulate(scenario, args.seed, args.output, shlex.join(["rover", *sys.argv[1:]]), force=args.force)
    per_tag = ", ".join(f"tag {t}: {n:,}" for t, n in report.packets_per_tag.items())
    print(f"simulated {report.duration_s:.1f} s, {report.path_length_m:.2f} m of path; CSI packets {per_tag}")
    print(f"wrote {report.output}")
    return 0
