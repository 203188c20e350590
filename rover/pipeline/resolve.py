"""Finding operator classes: short names through a table the caller gives, user classes by dotted path."""

from __future__ import annotations

import importlib
from collections.abc import Mapping

from rover.errors import OperatorDefinitionError
from rover.operator import Operator


class UnknownOperator(LookupError):
    """`uses:` names neither a built-in nor an importable Operator class."""


def resolve(uses: str, builtins: Mapping[str, str]) -> type[Operator]:
    """The Operator class for a `uses:` value; raise UnknownOperator with the reason.

    `builtins` maps short names to `module:Class`; modules are imported only when a pipeline uses them.
    """
    if uses in builtins:
        module_name, _, attr = builtins[uses].partition(":")
    elif "." in uses:
        module_name, _, attr = uses.rpartition(".")
    else:
        raise UnknownOperator(f"unknown operator {uses!r}")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise UnknownOperator(f"cannot import {module_name!r} for operator {uses!r}: {exc}") from None
    cls = getattr(module, attr, None)
    if not (isinstance(cls, type) and issubclass(cls, Operator)):
        raise UnknownOperator(f"{uses!r} is not an Operator class")
    try:
        cls.check_definition()
    except OperatorDefinitionError as exc:
        raise UnknownOperator(f"operator {uses!r} is badly declared: {exc}") from None
    return cls
