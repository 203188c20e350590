"""`make bench`: run every benchmark under bench/, print their figures, and collect them in bench/results.json."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
BENCHES = sorted(p for p in HERE.glob("bench_*.py"))


def main() -> int:
    results: dict = {
        "date": time.strftime("%Y-%m-%d"),
        "machine": f"{platform.machine()}, {platform.processor() or platform.system()}, "
        f"{os.cpu_count()} cores, Python {platform.python_version()}",
    }
    status = 0
    for bench in BENCHES:
        with tempfile.NamedTemporaryFile(suffix=".json") as out:
            print(f"== {bench.name}", flush=True)
            # one OpenBLAS thread, as the `rover` command sets (cli/__init__.py): the benches run operators in-process
            env = {"OPENBLAS_NUM_THREADS": "1", **os.environ}
            proc = subprocess.run([sys.executable, str(bench), "--json", out.name], env=env)
            if proc.returncode != 0:
                print(f"{bench.name} failed with status {proc.returncode}", file=sys.stderr)
                status = 1
                continue
            text = Path(out.name).read_text()
            results[bench.stem.removeprefix("bench_")] = json.loads(text) if text else {}
    (HERE / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {HERE / 'results.json'}")
    return status


if __name__ == "__main__":
    sys.exit(main())
