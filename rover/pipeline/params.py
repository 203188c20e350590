"""Typed operator parameters: a dataclass per operator, values checked and coerced before anything starts."""

from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated, Any, Literal, Protocol, Union, get_args, get_origin


class ParamTypeError(ValueError):
    """A parameter value that does not fit the declared type or its constraints."""


class ParamValueError(ValueError):
    """A constructed params object whose field `name` breaks its declared constraint."""

    def __init__(self, name: str, message: str):
        super().__init__(f"{name}: {message}")
        self.name = name
        self.message = message


class Constraint(Protocol):
    """A rule on a value, declared on a field with `typing.Annotated[TYPE, constraint]`."""

    def check(self, value: Any) -> None:
        """Raise ParamTypeError saying what is wrong with `value`."""

    def label(self) -> str:
        """The rule in words, shown after the type (`> 0`)."""


@dataclass(frozen=True)
class Range:
    """Bounds on a number: `dwell_s: Annotated[float, Range(gt=0)]`."""

    gt: float | None = None
    ge: float | None = None
    lt: float | None = None
    le: float | None = None

    def label(self) -> str:
        parts = [
            f"{op} {bound:g}"
            for op, bound in ((">", self.gt), (">=", self.ge), ("<", self.lt), ("<=", self.le))
            if bound is not None
        ]
        return " and ".join(parts)

    def check(self, value: Any) -> None:
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            return
        ok = (
            (self.gt is None or value > self.gt)
            and (self.ge is None or value >= self.ge)
            and (self.lt is None or value < self.lt)
            and (self.le is None or value <= self.le)
        )
        if not ok:
            raise ParamTypeError(f"must be {self.label()}, got {value!r}")


@dataclass(frozen=True)
class Matches:
    """A string that fully matches a pattern: `Annotated[str, Matches(r"...", "an endpoint like ...")]`."""

    pattern: str
    what: str

    def label(self) -> str:
        return self.what

    def check(self, value: Any) -> None:
        if isinstance(value, str) and not re.fullmatch(self.pattern, value):
            raise ParamTypeError(f"expected {self.what}, got {value!r}")


PositiveFloat = Annotated[float, Range(gt=0)]
NonNegativeFloat = Annotated[float, Range(ge=0)]
Fraction = Annotated[float, Range(ge=0, le=1)]
PositiveInt = Annotated[int, Range(gt=0)]
NonNegativeInt = Annotated[int, Range(ge=0)]


def _constraints(tp: Any) -> tuple[Any, list[Constraint]]:
    """The base type of an annotation and the constraints declared on it."""
    if get_origin(tp) is Annotated:
        base, *meta = get_args(tp)
        return base, [m for m in meta if hasattr(m, "check") and hasattr(m, "label")]
    return tp, []


def type_label(tp: Any) -> str:
    """A short human name for a type annotation (`float`, `list[float]`, `'max' | float`, `float > 0`)."""
    base, rules = _constraints(tp)
    if rules:
        return " ".join([type_label(base), *(r.label() for r in rules)])
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


NON_FINITE = ("inf", "infinity", "nan", ".inf", ".nan")
"""the words Python's float() (and YAML) read as infinite or not a number"""


def coerce(value: Any, tp: Any) -> Any:
    """Return `value` as type `tp` or raise ParamTypeError; ints widen to float, nothing else is guessed.

    Floats must be finite; constraints declared with `Annotated` are checked."""
    base, rules = _constraints(tp)
    if rules or base is not tp:
        value = coerce(value, base)
        for rule in rules:
            rule.check(value)
        return value
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
        args = get_args(tp)
        if origin is tuple and args and Ellipsis not in args:
            if len(value) != len(args):
                raise ParamTypeError(f"expected {type_label(tp)} ({len(args)} values), got {value!r}")
            return tuple(coerce(v, a) for v, a in zip(value, args, strict=True))
        (item,) = [a for a in args if a is not Ellipsis][:1] or [Any]
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
            if not math.isfinite(value):
                raise ParamTypeError(f"expected a finite number, got {value!r}")
            return float(value)
        if isinstance(value, str) and value.strip().lower().lstrip("+-") in NON_FINITE:
            raise ParamTypeError(f"expected a finite number, got {value!r}")
    elif tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif tp is str:
        if isinstance(value, str):
            return value
    elif isinstance(tp, type) and isinstance(value, tp):
        return value
    raise ParamTypeError(f"expected {type_label(tp)}, got {value!r}")


def fields(params_cls: type) -> dict[str, dataclasses.Field[Any]]:
    return {f.name: f for f in dataclasses.fields(params_cls)}


def resolved_types(params_cls: type) -> dict[str, Any]:
    return typing.get_type_hints(params_cls, include_extras=True)


def _check_value(value: Any, tp: Any) -> None:
    """The constraint part of `coerce` for a value already of its type (tuples stay tuples)."""
    base, rules = _constraints(tp)
    if get_origin(base) in (Union, types.UnionType):
        for arg in get_args(base):
            arg_base = _constraints(arg)[0]
            if (value is None and arg_base is type(None)) or (
                isinstance(arg_base, type) and isinstance(value, arg_base) and not isinstance(value, bool)
            ):
                _check_value(value, arg)
                return
        return
    if isinstance(value, float) and not math.isfinite(value):
        raise ParamTypeError(f"expected a finite number, got {value!r}")
    for rule in rules:
        rule.check(value)


def check_fields(obj: Any) -> None:
    """Check a dataclass instance against the constraints of its fields (ParamValueError).

    Call it from `__post_init__` so an object built in code obeys the same rules as one read from a file."""
    hints = resolved_types(type(obj))
    for f in dataclasses.fields(obj):
        try:
            _check_value(getattr(obj, f.name), hints[f.name])
        except ParamTypeError as exc:
            raise ParamValueError(f.name, str(exc)) from None


class Checked:
    """A params dataclass whose fields are checked when it is built (see `check_fields`)."""

    def __post_init__(self) -> None:
        check_fields(self)


def has_default(field: dataclasses.Field[Any]) -> bool:
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


Report = Callable[[tuple[Any, ...], str, bool], None]
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
    except ParamValueError as exc:
        report((exc.name,) if exc.name in values else (), f"{wording.ill_typed(exc.name)}: {exc.message}", False)
        return None
    except (TypeError, ValueError) as exc:
        report((), str(exc), False)
        return None
