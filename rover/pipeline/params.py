"""Typed operator parameters: a dataclass per operator, values checked and coerced before anything starts."""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal, Union, get_args, get_origin


class ParamTypeError(ValueError):
    """A parameter value that does not fit the declared type."""


def type_label(tp: Any) -> str:
    """A short human name for a type annotation (`float`, `list[float]`, `'max' | float`)."""
    origin = get_origin(tp)
    if origin is Literal:
        return " | ".join(repr(a) for a in get_args(tp))
    if origin in (Union, types.UnionType):
        return " | ".join(type_label(a) for a in get_args(tp))
    if origin in (list, tuple, dict):
        return f"{origin.__name__}[{', '.join(type_label(a) for a in get_args(tp) if a is not Ellipsis)}]"
    if tp is type(None):
        return "null"
    return getattr(tp, "__name__", str(tp))


def coerce(value: Any, tp: Any) -> Any:
    """Return `value` as type `tp` or raise ParamTypeError; ints widen to float, nothing else is guessed."""
    origin = get_origin(tp)
    if tp is Any:
        return value
    if origin is Literal:
        if value in get_args(tp):
            return value
        raise ParamTypeError(f"expected {type_label(tp)}, got {value!r}")
    if origin in (Union, types.UnionType):
        for arg in get_args(tp):
            try:
                return coerce(value, arg)
            except ParamTypeError:
                continue
        raise ParamTypeError(f"expected {type_label(tp)}, got {value!r}")
    if tp is type(None):
        if value is None:
            return None
        raise ParamTypeError(f"expected null, got {value!r}")
    if origin in (list, tuple):
        if not isinstance(value, list):
            raise ParamTypeError(f"expected {type_label(tp)}, got {value!r}")
        (item,) = [a for a in get_args(tp) if a is not Ellipsis][:1] or [Any]
        items = [coerce(v, item) for v in value]
        return tuple(items) if origin is tuple else items
    if origin is dict:
        key_t, val_t = get_args(tp) or (Any, Any)
        if not isinstance(value, dict):
            raise ParamTypeError(f"expected {type_label(tp)}, got {value!r}")
        return {coerce(k, key_t): coerce(v, val_t) for k, v in value.items()}
    if tp is bool:
        if isinstance(value, bool):
            return value
    elif tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
    elif tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif tp is str:
        if isinstance(value, str):
            return value
    elif isinstance(tp, type) and isinstance(value, tp):
        return value
    raise ParamTypeError(f"expected {type_label(tp)}, got {value!r}")


def fields(params_cls: type) -> dict[str, dataclasses.Field]:
    return {f.name: f for f in dataclasses.fields(params_cls)}


def resolved_types(params_cls: type) -> dict[str, Any]:
    return typing.get_type_hints(params_cls)


def has_default(field: dataclasses.Field) -> bool:
    return field.default is not dataclasses.MISSING or field.default_factory is not dataclasses.MISSING


@dataclass(frozen=True)
class Wording:
    """How `bind` words its problems for one kind of mapping (operator params, a scenario section)."""

    unknown: Callable[[str], str]
    """the message for an unknown key (a did-you-mean hint is appended)"""
    ill_typed: Callable[[str], str]
    """the prefix of a type error"""
    missing: Callable[[str, str], str]
    """the message for a required key, given the key and its type label"""
    known_list: bool = False
    """append the list of known keys to the unknown-key message"""


Report = Callable[[tuple, str, bool], None]
"""report(path below the mapping, message, at_key)"""


def bind(cls: type, values: dict[str, Any], wording: Wording, report: Report) -> Any | None:
    """Coerce a mapping into the dataclass `cls`, reporting every unknown key, ill-typed value and
    missing field; None when there was any problem."""
    from rover.pipeline.spec import did_you_mean

    known = fields(cls)
    hints = resolved_types(cls)
    out: dict[str, Any] = {}
    ok = True
    for key, value in values.items():
        if key not in known:
            listing = f" (params: {', '.join(known) or 'none'})" if wording.known_list else ""
            report((key,), f"{wording.unknown(key)}{did_you_mean(key, known)}{listing}", True)
            ok = False
            continue
        try:
            out[key] = coerce(value, hints[key])
        except ParamTypeError as exc:
            report((key,), f"{wording.ill_typed(key)}: {exc}", False)
            ok = False
    for key, field in known.items():
        if key not in values and not has_default(field):
            report((), wording.missing(key, type_label(hints[key])), True)
            ok = False
    if not ok:
        return None
    try:
        return cls(**out)
    except (TypeError, ValueError) as exc:
        report((), str(exc), False)
        return None
