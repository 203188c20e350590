"""Work done once per test run and shared by every pytest-xdist worker: a simulated dataset, a run
of the pipeline. The first worker to ask makes it under a lock; the others wait for it and reuse it."""

from __future__ import annotations

import fcntl
import json
from collections.abc import Callable
from pathlib import Path

import pytest

DONE = "done.json"


def shared_root(factory: pytest.TempPathFactory) -> Path:
    """The folder every worker of this run sees: pytest's base temporary folder (a worker's is one
    level below it)."""
    base = factory.getbasetemp()
    return base.parent if base.name.startswith("popen-gw") else base


def once(factory: pytest.TempPathFactory, name: str, make: Callable[[Path], dict]) -> tuple[Path, dict]:
    """`make(folder)` run once per test run for `name`, in a folder of its own; its result (JSON) and
    the folder are returned to every caller. A `make` that failed is not retried: its error is raised
    again, for every test that needs it."""
    folder = shared_root(factory) / "shared" / name
    folder.mkdir(parents=True, exist_ok=True)
    with (folder.parent / f"{name}.lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        done = folder / DONE
        if not done.exists():
            try:
                result = {"ok": make(folder)}
            except Exception as exc:  # recorded, so that the other workers fail alike instead of retrying
                result = {"error": {"message": f"{type(exc).__name__}: {exc}"}}
            done.write_text(json.dumps(result))
        result = json.loads(done.read_text())
    if "error" in result:
        raise AssertionError(f"shared {name} failed: {result['error']['message']}")
    return folder, result["ok"]
