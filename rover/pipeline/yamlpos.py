"""Safe YAML loading that remembers where every key and value came from, for compiler-style messages."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import yaml

from rover.errors import Diagnostic, SpecError

Path = tuple[Any, ...]


@dataclass
class Located:
    """A loaded YAML document and the 1-based (line, column) of each value and mapping key by path."""

    file: str
    data: Any
    values: dict[Path, tuple[int, int]] = field(default_factory=dict)
    keys: dict[Path, tuple[int, int]] = field(default_factory=dict)

    def at(self, *path: Any) -> tuple[int, int]:
        """Position of the value at `path`, else of the nearest enclosing value that has one."""
        for cut in range(len(path), -1, -1):
            if path[:cut] in self.values:
                return self.values[path[:cut]]
        return (1, 1)

    def key_at(self, *path: Any) -> tuple[int, int]:
        """Position of the mapping key that names `path` (falls back to the value)."""
        return self.keys.get(path) or self.at(*path)

    def diag(self, path: Path, message: str, *, key: bool = False) -> Diagnostic:
        line, col = self.key_at(*path) if key else self.at(*path)
        return Diagnostic(self.file, line, col, message)


def _pos(node: yaml.Node) -> tuple[int, int]:
    return node.start_mark.line + 1, node.start_mark.column + 1


def load(text: str, file: str) -> Located:
    """Parse one YAML document with the safe loader; raise SpecError for syntax errors and duplicate keys."""
    loader = yaml.SafeLoader(text)
    problems: list[Diagnostic] = []
    try:
        root = loader.get_single_node()
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line, col = (mark.line + 1, mark.column + 1) if mark else (0, 0)
        raise SpecError([Diagnostic(file, line, col, f"YAML syntax error: {exc.problem or exc.context}")]) from None
    except yaml.YAMLError as exc:
        raise SpecError([Diagnostic(file, 0, 0, f"YAML error: {exc}")]) from None
    finally:
        loader.dispose()
    doc = Located(file, None)
    if root is None:
        doc.data = {}
        return doc

    def walk(node: yaml.Node, path: Path) -> Any:
        doc.values[path] = _pos(node)
        if isinstance(node, yaml.MappingNode):
            out: dict[Any, Any] = {}
            for key_node, value_node in node.value:
                try:
                    key = loader.construct_object(key_node, deep=True)
                    hash(key)
                except (yaml.YAMLError, TypeError):
                    problems.append(Diagnostic(file, *_pos(key_node), "mapping keys must be plain scalars"))
                    continue
                if key in out:
                    problems.append(Diagnostic(file, *_pos(key_node), f"duplicate key {key!r}"))
                    continue
                doc.keys[path + (key,)] = _pos(key_node)
                out[key] = walk(value_node, path + (key,))
            return out
        if isinstance(node, yaml.SequenceNode):
            return [walk(item, path + (i,)) for i, item in enumerate(node.value)]
        try:
            return loader.construct_object(node, deep=True)
        except yaml.YAMLError as exc:
            problems.append(Diagnostic(file, *_pos(node), f"bad value: {exc}"))
            return None

    doc.data = walk(root, ())
    if problems:
        raise SpecError(problems)
    return doc


def parse_scalar(text: str) -> Any:
    """Type a command-line value the way YAML would (`30` -> 30, `max` -> 'max', `` -> '')."""
    if text == "":
        return ""
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        return text
    return text if isinstance(value, dict) or value is None else value
