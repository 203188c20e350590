"""The import direction between layers: the core never imports the method, the drivers, the datasets or the CLI."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
from helpers import ROOT

FOLDERS = {
    "rover": ROOT / "rover",
    "transport": ROOT / "transport",
    "operators": ROOT / "operators",
    "drivers": ROOT / "drivers",
    "datasets": ROOT / "datasets",
    "cli": ROOT / "cli",
}
"""each layer's folder; the package installs them as rover, rover.operators, rover.drivers, ..."""

FORBIDDEN = {
    "rover": ("rover.operators", "rover.drivers", "rover.datasets", "rover.cli"),
    "transport": (
        "rover.operators",
        "rover.drivers",
        "rover.datasets",
        "rover.cli",
        "rover.pipeline",
        "rover.security",
    ),
    "operators": ("rover.drivers", "rover.datasets", "rover.cli"),
    "drivers": ("rover.datasets", "rover.cli"),
    "datasets": ("rover.drivers", "rover.cli"),
    "cli": (),
}
"""what each layer may not import; the CLI on top may import anything. The transport moves bytes for the
core's runtime: it knows the errors and the status query's model, not the pipeline or the method."""


def imported_modules(path: Path) -> list[tuple[int, str]]:
    """Every module (or module.name) an `import` or `from ... import` in the file names, with its line."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, f"{path}:{node.lineno}: use absolute imports (rover.…)"
            found += [(node.lineno, node.module or "")]
            found += [(node.lineno, f"{node.module}.{alias.name}") for alias in node.names]
    return found


def violations(layer: str) -> list[str]:
    bad = []
    for path in sorted(FOLDERS[layer].rglob("*.py")):
        for line, module in imported_modules(path):
            if any(module == f or module.startswith(f + ".") for f in FORBIDDEN[layer]):
                bad.append(f"{path.relative_to(FOLDERS[layer].parent)}:{line}: imports {module}")
    return bad


@pytest.mark.parametrize("layer", sorted(FORBIDDEN))
def test_layers_import_only_downwards(layer):
    assert violations(layer) == []


def test_the_check_finds_a_violation(tmp_path, monkeypatch):
    core = tmp_path / "rover"
    core.mkdir()
    (core / "bad.py").write_text("import json\nfrom rover.operators.slam import operator\n")
    monkeypatch.setitem(FOLDERS, "rover", core)
    assert violations("rover") == [
        "rover/bad.py:2: imports rover.operators.slam",
        "rover/bad.py:2: imports rover.operators.slam.operator",
    ]
