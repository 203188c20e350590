"""The package as a user gets it: a wheel installed, not editable, into a fresh virtualenv.

The editable install of the development venv maps `rover.*` onto the repository's folders
whatever pyproject's `packages` says; a subpackage missing from that list, or a data file
missing from `package-data`, only shows in a real install. The wheel is built from a copy of
the files pyproject names (so a stale `build/` of the repository cannot hide a missing entry),
installed with `pip --python` into a venv made with `--without-pip`, and the dependencies are
lent by a `.pth` line naming the development venv's site-packages (a path line does not run
the `.pth` files inside that folder, so its editable finder stays off). Every command runs
from a folder outside the repository.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
SETUPTOOLS = PYPROJECT["tool"]["setuptools"]
PACKAGES: list[str] = SETUPTOOLS["packages"]
PACKAGE_DIR: dict[str, str] = SETUPTOOLS["package-dir"]
NOT_SHIPPED = {"rover_msgs/CMakeLists.txt"}
"""Files of the mapped folders that the wheel leaves out on purpose (the ROS build file of the messages)."""


def source_dir(package: str) -> Path:
    """The repository folder of a package, from pyproject's package-dir mapping."""
    parts = package.split(".")
    for n in range(len(parts), 0, -1):
        mapped = PACKAGE_DIR.get(".".join(parts[:n]))
        if mapped is not None:
            return ROOT / mapped / Path(*parts[n:])
    return ROOT / Path(*parts)


def run(args: list[str | Path], cwd: Path, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP")}
    env["PYTHONNOUSERSITE"] = "1"
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    return subprocess.run(
        [str(a) for a in args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout, check=False
    )


def ok(proc: subprocess.CompletedProcess[str]) -> str:
    assert proc.returncode == 0, f"{proc.args} exited {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    return proc.stdout


class Installed:
    def __init__(self, venv: Path, work: Path):
        self.venv = venv
        self.work = work
        self.python = venv / "bin" / "python"
        self.site = Path(ok(self.run("-c", "import sysconfig; print(sysconfig.get_path('purelib'))")).strip())

    def run(self, *args: str | Path) -> subprocess.CompletedProcess[str]:
        return run([self.python, *args], cwd=self.work)


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Installed:
    base = tmp_path_factory.mktemp("install")
    src = base / "src"
    src.mkdir()
    for name in ("pyproject.toml", PYPROJECT["project"]["readme"]):
        shutil.copy2(ROOT / name, src / name)
    for folder in sorted(set(PACKAGE_DIR.values())):
        shutil.copytree(ROOT / folder, src / folder, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    wheels = base / "wheels"
    pip = [sys.executable, "-m", "pip", "--quiet"]
    ok(run([*pip, "wheel", "--no-deps", "--no-build-isolation", "-w", wheels, "."], src))
    (wheel,) = wheels.glob("rover-*.whl")
    venv = base / "venv"
    ok(run([sys.executable, "-m", "venv", "--without-pip", venv], base))
    ok(run([*pip, "--python", venv / "bin" / "python", "install", "--no-deps", wheel], base))
    work = base / "elsewhere"
    work.mkdir()
    env = Installed(venv, work)
    (env.site / "_rover_test_dependencies.pth").write_text(sysconfig.get_path("purelib") + "\n")
    return env


def test_rover_is_imported_from_the_installed_wheel(installed: Installed) -> None:
    out = ok(
        installed.run(
            "-c",
            "import sys, rover, rover.operators; print(rover.__file__); print(rover.operators.__file__);"
            "print(any('editable' in type(f).__name__.lower() for f in sys.meta_path))",
        )
    )
    rover_file, operators_file, editable = out.splitlines()
    assert Path(rover_file) == installed.site / "rover" / "__init__.py"
    assert Path(operators_file) == installed.site / "rover" / "operators" / "__init__.py"
    assert editable == "False"


def test_every_listed_package_imports_from_the_wheel(installed: Installed) -> None:
    script = "import importlib, sys\nfor name in sys.argv[1:]: print(name, importlib.import_module(name).__file__)"
    out = ok(installed.run("-c", script, *PACKAGES))
    for line in out.splitlines():
        name, file = line.split(" ", 1)
        assert Path(file).is_relative_to(installed.site), f"{name} imported from {file}, not from the wheel"
    assert len(out.splitlines()) == len(PACKAGES)


def source_files(folder: Path) -> list[Path]:
    return sorted(
        p.relative_to(folder)
        for p in folder.rglob("*")
        if p.is_file()
        and p.suffix != ".pyc"
        and not any(part == "__pycache__" or part.startswith(".") for part in p.relative_to(folder).parts)
    )


def test_every_package_folder_is_listed() -> None:
    """A folder with an __init__.py under a mapped folder is a package: it must be in `packages` to ship."""
    found = {
        ".".join((package, *init.parent.relative_to(source_dir(package)).parts))
        for package in PACKAGE_DIR
        for init in source_dir(package).rglob("__init__.py")
        if "__pycache__" not in init.parts
    }
    assert not sorted(found - set(PACKAGES)), "add to [tool.setuptools] packages in pyproject.toml"


def test_every_source_file_is_in_the_wheel(installed: Installed) -> None:
    """Modules and data (pipeline.yaml, .msg files, scenarios) alike: a missing package or package-data entry."""
    missing = [
        f"{folder}/{rel}"
        for package, folder in PACKAGE_DIR.items()
        for rel in source_files(ROOT / folder)
        if f"{folder}/{rel}" not in NOT_SHIPPED and not (installed.site / Path(*package.split(".")) / rel).is_file()
    ]
    assert not missing, f"not in the wheel (see [tool.setuptools] packages and package-data): {missing}"


def test_the_command_line_runs(installed: Installed) -> None:
    rover = installed.venv / "bin" / "rover"
    pipeline = ok(installed.run("-c", "import importlib.resources as r; print(r.files('rover') / 'pipeline.yaml')"))
    pipeline = pipeline.strip()
    assert Path(pipeline).is_relative_to(installed.site)
    out = ok(run([rover, "check", pipeline], installed.work))
    assert "ok: pipeline" in out
    assert "--scenario" in ok(run([rover, "simulate", "--help"], installed.work))


def test_the_intel5300_driver_imports(installed: Installed) -> None:
    script = "import rover.drivers.intel5300\nfrom rover.drivers.intel5300 import read_dat, StreamDecoder"
    ok(installed.run("-c", script))
