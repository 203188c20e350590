"""`make bench`: run the benchmarks under bench/, collect their figures in bench/results.json, and
write docs/benchmarks.md from them (bench/report.py).

`python bench/run_all.py slam decode` runs only those (bench_slam.py, bench_decode.py) and keeps
the other sections' figures as they were. Each section is stamped in results.json's `measured`
with the date, the machine and the commit it ran on, so the page says when each figure is from.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import report

HERE = Path(__file__).resolve().parent
BENCHES = {p.stem.removeprefix("bench_"): p for p in sorted(HERE.glob("bench_*.py"))}


def machine() -> str:
    return (
        f"{platform.machine()}, {platform.processor() or platform.system()}, "
        f"{os.cpu_count()} cores, Python {platform.python_version()}"
    )


def commit() -> str:
    """The commit the benchmarks ran on, `-dirty` when the work tree had changes."""

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=HERE, capture_output=True, text=True).stdout.strip()

    head = git("rev-parse", "--short", "HEAD")
    return f"{head}-dirty" if head and git("status", "--porcelain", "--untracked-files=no") else head


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", help=f"benchmarks to run (default: all): {', '.join(BENCHES)}")
    args = parser.parse_args(argv)
    unknown = [name for name in args.names if name not in BENCHES]
    if unknown:
        print(f"run_all.py: no benchmark {', '.join(unknown)} (one of {', '.join(BENCHES)})", file=sys.stderr)
        return 2
    results_path = HERE / "results.json"
    results: dict = json.loads(results_path.read_text()) if results_path.exists() else {}
    stamps = results.setdefault("measured", {})
    stamp = {"date": time.strftime("%Y-%m-%d"), "machine": machine(), "commit": commit()}
    status = 0
    for name in args.names or list(BENCHES):
        with tempfile.NamedTemporaryFile(suffix=".json") as out:
            print(f"== {BENCHES[name].name}", flush=True)
            # one OpenBLAS thread, as the `rover` command sets (cli/__init__.py): the benches run operators in-process
            env = {"OPENBLAS_NUM_THREADS": "1", **os.environ}
            proc = subprocess.run([sys.executable, str(BENCHES[name]), "--json", out.name], env=env)
            if proc.returncode != 0:
                print(f"{BENCHES[name].name} failed with status {proc.returncode}", file=sys.stderr)
                status = 1
                continue
            text = Path(out.name).read_text()
            results[name] = json.loads(text) if text else {}
            stamps[name] = stamp
            results_path.write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {results_path}")
    return report.main([]) or status


if __name__ == "__main__":
    sys.exit(main())
