"""Safe YAML loading that remembers where every key and value came from, for compiler-style messages.

Every YAML Rover reads from users (pipeline, setup and scenario files, `--set` values, YAML kept
in a dataset's metadata) is held to three limits, so a hostile or broken input is one clean
`SpecError` line instead of a MemoryError, a RecursionError or minutes of parsing.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, Protocol

import yaml

from rover.errors import Diagnostic, SpecError

Path = tuple[Any, ...]

MAX_YAML_BYTES = 1_048_576
"""bytes (1 MiB) of one YAML text. The shipped pipeline is 2.7 kB, a scenario 3 kB, a setup file
less; a 1,500-operator pipeline is about 100 kB. `read_yaml_text` refuses a larger file from its size."""
MAX_YAML_DEPTH = 64
"""open mappings and sequences around a value, after alias expansion. Real files nest at most 5
deep (operators > NAME > params > topics > value). PyYAML's composer and Rover's own walks recurse
once per level, and Python's stack of 1,000 frames gives out after a few hundred levels."""
MAX_YAML_NODES = 100_000
"""keys, values and items, as parsed and again as expanded, where each alias counts the whole
node it repeats: the bound that stops an alias bomb (9 levels of 9 aliases make 9**9 = 387 million
nodes) before it is expanded, and a file's parse time (pure-Python PyYAML parses some 20,000 nodes
a second). The shipped pipeline has 200 nodes, about 20 per operator (50 for the busiest,
`record`): a 1,500-operator pipeline needs about 30,000, a chain of 1,500 one-input operators
12,000. A scenario's waypoint costs 3 nodes."""


class YamlLimitError(SpecError):
    """YAML input over MAX_YAML_BYTES, MAX_YAML_DEPTH or MAX_YAML_NODES."""


def _mib(size: int) -> str:
    return f"{size / 2**20:g} MiB"


def size_error(file: str, size: int | None) -> YamlLimitError:
    """The error for a text of `size` bytes (None: more than MAX_YAML_BYTES, exact size unknown)."""
    what = f"{size:,} bytes" if size is not None else f"more than {MAX_YAML_BYTES:,} bytes"
    message = f"{what}: larger than the {_mib(MAX_YAML_BYTES)} a YAML input may be"
    return YamlLimitError([Diagnostic(file, 0, 0, message)])


def _check_size(text: str, file: str) -> None:
    if len(text) * 4 <= MAX_YAML_BYTES:  # UTF-8 takes at most 4 bytes a character
        return
    size = len(text.encode("utf-8", "surrogatepass"))
    if size > MAX_YAML_BYTES:
        raise size_error(file, size)


class _Mark(Protocol):
    """A position in the text: PyYAML's Mark (0-based)."""

    @property
    def line(self) -> int: ...

    @property
    def column(self) -> int: ...


def _limit(file: str, mark: _Mark | None, message: str) -> YamlLimitError:
    line, col = (mark.line + 1, mark.column + 1) if mark else (0, 0)
    return YamlLimitError([Diagnostic(file, line, col, message)])


def _too_deep(file: str, mark: _Mark | None, through_aliases: bool) -> YamlLimitError:
    how = " (through aliases)" if through_aliases else ""
    return _limit(file, mark, f"YAML nested deeper than {MAX_YAML_DEPTH} levels{how}")


def _too_many(file: str, mark: _Mark | None, aliases: bool) -> YamlLimitError:
    if aliases:
        return _limit(file, mark, f"YAML aliases expand to more than {MAX_YAML_NODES:,} nodes (an alias bomb?)")
    return _limit(file, mark, f"YAML has more than {MAX_YAML_NODES:,} nodes (keys, values and items)")


class _LimitedLoader(yaml.SafeLoader):
    """SafeLoader that counts nodes and open collections on the parser's events as they reach the composer.

    The scanner and parser are state machines (no recursion); the composer recurses once per
    level, so stopping at the event that opens level MAX_YAML_DEPTH + 1 keeps it far from the
    stack's end. Counting on the event stream the composer reads costs next to nothing, where a
    separate first pass would parse everything twice.
    """

    def __init__(self, text: str, file: str):
        super().__init__(text)
        self.file = file
        self.depth = 0
        self.nodes = 0
        self.aliases = False

    def fetch_flow_collection_start(self, TokenClass: type[yaml.Token]) -> None:  # noqa: N803 - PyYAML's name
        """Stop at the `[` or `{` that opens flow level MAX_YAML_DEPTH + 1, as it is scanned: the
        scanner looks up to 1,024 characters ahead, in time quadratic in the flow level."""
        if self.flow_level >= MAX_YAML_DEPTH:
            raise _too_deep(self.file, self.get_mark(), False)
        super().fetch_flow_collection_start(TokenClass)

    def get_event(self) -> yaml.Event:
        event: yaml.Event = super().get_event()  # type: ignore[no-untyped-call]  # untyped in types-PyYAML
        if isinstance(event, yaml.NodeEvent):
            self.nodes += 1
            if self.nodes > MAX_YAML_NODES:
                raise _too_many(self.file, event.start_mark, False)
        if isinstance(event, yaml.CollectionStartEvent):
            self.depth += 1
            if self.depth > MAX_YAML_DEPTH:
                raise _too_deep(self.file, event.start_mark, False)
        elif isinstance(event, yaml.CollectionEndEvent):
            self.depth -= 1
        elif isinstance(event, yaml.AliasEvent):
            self.aliases = True
        return event


def _children(node: yaml.Node) -> Iterator[yaml.Node]:
    if isinstance(node, yaml.MappingNode):
        for key, value in node.value:
            yield key
            yield value
    elif isinstance(node, yaml.SequenceNode):
        yield from node.value


def _check_expansion(root: yaml.Node, file: str, aliases: bool) -> None:
    """Walk the node graph as a loader would expand it, without recursion, up to the limits.

    Aliases make one node reachable many times (and `&a [*a]` makes a cycle); each visit counts.
    """
    count = 1
    stack: list[Iterator[yaml.Node]] = [_children(root)]
    while stack:
        child = next(stack[-1], None)
        if child is None:
            stack.pop()
            continue
        count += 1
        if count > MAX_YAML_NODES:
            raise _too_many(file, child.start_mark, aliases)
        if isinstance(child, yaml.CollectionNode):
            if len(stack) + 1 > MAX_YAML_DEPTH:
                raise _too_deep(file, child.start_mark, True)
            stack.append(_children(child))


def _problem(exc: yaml.YAMLError) -> str:
    """PyYAML's complaint on one line (its str() adds lines that quote the input)."""
    text = str(exc.problem or exc.context) if isinstance(exc, yaml.MarkedYAMLError) else str(exc)
    return " ".join(text.split())


def _yaml_error(file: str, exc: yaml.YAMLError, what: str) -> SpecError:
    mark = (exc.problem_mark or exc.context_mark) if isinstance(exc, yaml.MarkedYAMLError) else None
    line, col = (mark.line + 1, mark.column + 1) if mark else (0, 0)
    return SpecError([Diagnostic(file, line, col, f"{what}: {_problem(exc)}")])


EXPONENT_FLOAT = re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9][0-9_]*)[eE][-+]?[0-9]+$")
"""floats with an exponent that YAML 1.1 leaves as strings (`1e9`, `1.5E-3`: it wants a dot and a signed
exponent), read as floats, as YAML 1.2 and Python do"""
_LimitedLoader.add_implicit_resolver("tag:yaml.org,2002:float", EXPONENT_FLOAT, list("-+0123456789."))


def _compose(text: str, file: str) -> tuple[_LimitedLoader, yaml.Node | None]:
    """The single document's node graph, within the limits; raise SpecError for syntax errors."""
    _check_size(text, file)
    try:
        loader = _LimitedLoader(text, file)
    except yaml.reader.ReaderError as exc:  # raised up front, for the whole text
        line = text.count("\n", 0, exc.position) + 1
        col = exc.position - text.rfind("\n", 0, exc.position)
        message = f"YAML syntax error: unacceptable character #x{exc.character:04x}: {exc.reason}"
        raise SpecError([Diagnostic(file, line, col, message)]) from None
    try:
        root = loader.get_single_node()
        if root is not None:
            _check_expansion(root, file, loader.aliases)
    except yaml.YAMLError as exc:
        raise _yaml_error(file, exc, "YAML syntax error") from None
    finally:
        loader.dispose()
    return loader, root


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


_NOT_A_KEY = object()
_CONSTRUCT_ERRORS = (yaml.YAMLError, ValueError, TypeError, KeyError, IndexError, AttributeError, OverflowError)
"""what PyYAML's safe constructors raise on a bad scalar: `!!float ;` (ValueError), `!!float` with
no value (IndexError), `!!bool x` (KeyError), `!!timestamp x` (AttributeError), `2024-13-01` or an
int of 5,000 digits (ValueError)"""


def _bad_value(node: yaml.Node, exc: Exception) -> str:
    if isinstance(exc, yaml.YAMLError):
        return f"bad value: {_problem(exc)}"
    value = str(node.value)
    shown = value if len(value) <= 40 else value[:40] + "..."
    why = f" ({' '.join(str(exc).split())})" if isinstance(exc, ValueError) else ""
    return f"bad value: {shown!r} is not a valid {node.tag.rsplit(':', 1)[-1]}{why}"


def _scalar_key(loader: yaml.SafeLoader, node: yaml.Node) -> Any:
    """The key a scalar node makes, else _NOT_A_KEY; a collection is never constructed (it may be an alias bomb)."""
    if not isinstance(node, yaml.ScalarNode):
        return _NOT_A_KEY
    try:
        key = loader.construct_object(node)
        hash(key)
    except _CONSTRUCT_ERRORS:
        return _NOT_A_KEY
    return key


def load(text: str, file: str) -> Located:
    """Parse one YAML document with the safe loader; raise SpecError for syntax errors, duplicate
    keys and input over the limits (YamlLimitError)."""
    loader, root = _compose(text, file)
    problems: list[Diagnostic] = []
    doc = Located(file, None)
    if root is None:
        doc.data = {}
        return doc

    def walk(node: yaml.Node, path: Path) -> Any:
        doc.values[path] = _pos(node)
        if isinstance(node, yaml.MappingNode):
            out: dict[Any, Any] = {}
            for key_node, value_node in node.value:
                key = _scalar_key(loader, key_node)
                if key is _NOT_A_KEY:
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
            return loader.construct_object(node)
        except _CONSTRUCT_ERRORS as exc:
            problems.append(Diagnostic(file, *_pos(node), _bad_value(node, exc)))
            return None

    doc.data = walk(root, ())
    if problems:
        raise SpecError(problems)
    return doc


def safe_load_limited(text: str, source: str) -> Any:
    """`yaml.safe_load` held to the limits, for YAML that needs no positions (a dataset's metadata).

    Raise SpecError naming `source` for syntax errors and bad values, YamlLimitError over a limit.
    """
    loader, root = _compose(text, source)
    if root is None:
        return None
    try:
        return loader.construct_document(root)
    except yaml.YAMLError as exc:
        raise _yaml_error(source, exc, "bad value") from None
    except _CONSTRUCT_ERRORS as exc:
        why = " ".join(str(exc).split())
        raise SpecError([Diagnostic(source, 0, 0, f"bad value: {type(exc).__name__}: {why}")]) from None


def parse_scalar(text: str, source: str = "--set") -> Any:
    """Type a command-line value the way YAML would (`30` -> 30, `max` -> 'max', `` -> '').

    Text that is not one YAML value stays a string; text over the limits is YamlLimitError naming
    `source` (e.g. `--set slam.window`).
    """
    if text == "":
        return ""
    try:
        value = safe_load_limited(text, source)
    except YamlLimitError as exc:
        raise YamlLimitError([Diagnostic(source, 0, 0, d.message) for d in exc.diagnostics]) from None
    except SpecError:
        return text
    return text if isinstance(value, dict) or value is None else value
