"""Type-check the package with mypy, as it is installed: `rover`, `rover.operators`, `rover.cli`, ...

mypy follows neither setuptools' editable import hook nor pyproject's `package-dir` mapping
(`rover.operators` lives in `operators/`, `rover.cli` in `cli/`, ...). So this builds a link
tree from that mapping, `build/typecheck/rover/`, whose entries are symlinks to the folders'
own entries, runs mypy there on the package plus `tests/`, `bench/` and `tools/` (their modules
are top-level: `from conftest import ...`), and prints mypy's findings with the repository's paths.

Usage: python tools/typecheck.py [extra mypy arguments]; the exit status is mypy's.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TREE = ROOT / "build" / "typecheck"
SCRIPTS = ("tests", "bench", "tools")
"""Folders of top-level modules and scripts, checked beside the package."""
SKIP = {"__pycache__"}


def package_dirs() -> dict[str, Path]:
    """pyproject's package-dir mapping: package name -> repository folder."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    return {package: ROOT / folder for package, folder in config.items()}


def _link(path: Path, target: Path) -> None:
    """Make `path` a symlink to `target`, leaving it alone when it already is one (runs may overlap)."""
    if path.is_symlink() and Path(os.readlink(path)) == target:
        return
    _remove(path)
    try:
        path.symlink_to(target)
    except FileExistsError:
        if not (path.is_symlink() and Path(os.readlink(path)) == target):
            raise


def _remove(path: Path) -> None:
    if path.is_symlink() or path.is_file():
        path.unlink(missing_ok=True)
    elif path.is_dir():
        shutil.rmtree(path, ignore_errors=True)


def build_tree(mapping: dict[str, Path], tree: Path = TREE) -> None:
    """A package whose subpackages are mapped elsewhere becomes a folder of per-entry links; any other, one link."""
    wanted: dict[Path, Path | None] = {}
    """tree path -> link target, or None for a real folder"""
    for package in sorted(mapping, key=lambda p: p.count(".")):
        target = tree.joinpath(*package.split("."))
        if target in wanted:
            raise SystemExit(f"typecheck: {package} is mapped to {mapping[package]} but {target} is already taken")
        if any(other.startswith(package + ".") for other in mapping):
            wanted[target] = None
            for entry in mapping[package].iterdir():
                if entry.name not in SKIP:
                    wanted[target / entry.name] = entry
        else:
            wanted[target] = mapping[package]
    for name in SCRIPTS:
        wanted[tree / name] = ROOT / name
    for path, link in sorted(wanted.items(), key=lambda item: len(item[0].parts)):
        if link is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            _link(path, link)
            continue
        if path.is_symlink() or path.is_file():
            path.unlink()
        path.mkdir(parents=True, exist_ok=True)
        for stale in path.iterdir():
            if stale not in wanted:
                _remove(stale)


LOCATION = re.compile(r"^(?P<path>[^:\s][^:]*\.pyi?)(?P<rest>:.*)$")


def repository_path(line: str, tree: Path = TREE) -> str:
    """`rover/operators/aoa/operator.py:3: error` -> `operators/aoa/operator.py:3: error`."""
    match = LOCATION.match(line)
    if match is None:
        return line
    real = Path(os.path.realpath(tree / match["path"]))
    if not real.is_relative_to(ROOT):
        return line
    return f"{real.relative_to(ROOT)}{match['rest']}"


def main(argv: list[str]) -> int:
    mapping = package_dirs()
    build_tree(mapping)
    roots = sorted({package.split(".")[0] for package in mapping})
    env = dict(os.environ, MYPYPATH=os.pathsep.join(str(TREE / name) for name in SCRIPTS))
    command = [sys.executable, "-m", "mypy", "--config-file", str(ROOT / "pyproject.toml")]
    command += roots + list(SCRIPTS) + argv
    proc = subprocess.run(command, cwd=TREE, env=env, capture_output=True, text=True, check=False)
    for line in proc.stdout.splitlines():
        print(repository_path(line))
    sys.stderr.write(proc.stderr)
    return proc.returncode


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
