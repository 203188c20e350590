"""Read-only messages: what the runtime hands an operator, so one decoded message can be shared.

The runtime decodes a message once per process and gives the same object to every operator of
the process that takes it; an edit by one would show in the others' inputs. `freeze` makes a
decoded message read-only in place, all the way down: each nested message's class becomes a
read-only subclass of its own (isinstance, attribute reads and serialization are unchanged),
sequences of messages or strings become `FrozenList`s (lists that refuse to change) and numpy
arrays are flagged read-only. An edit raises `ReadOnlyMessage` naming the field. `thaw` gives a
mutable deep copy; `copy.copy` and `dataclasses.replace` give a mutable shallow one.
"""

from __future__ import annotations

import copy
from functools import cache
from typing import Any, NoReturn, cast

import numpy as np
from rosbags.interfaces import Nodetype

from rover.messages import typestore

WRITABLE_HINT = (
    "input messages are read-only (one decoded message is shared by every operator of the process that "
    "takes it): edit a copy (rover.frozen.thaw(msg), dataclasses.replace(msg, ...)) or declare the port "
    "In(..., writable=True)"
)


class ReadOnlyMessage(AttributeError):
    """An edit of a read-only message (an operator's input). An AttributeError, as a frozen dataclass's."""


class FrozenList(list[Any]):
    """A list that refuses every change: a read-only message's sequence of messages or strings."""

    def _refuse(self, *_args: Any, **_kwargs: Any) -> NoReturn:
        raise ReadOnlyMessage(f"a sequence of a read-only message cannot change: {WRITABLE_HINT}")

    append = extend = insert = pop = remove = clear = sort = reverse = _refuse
    __setitem__ = __delitem__ = __iadd__ = __imul__ = _refuse

    def __copy__(self) -> list[Any]:
        return list(self)

    def __deepcopy__(self, memo: dict[int, Any]) -> list[Any]:
        return [thaw(item) for item in self]


_MESSAGE, _MESSAGES, _STRINGS, _ARRAY = range(4)


@cache
def _plan(typename: str) -> tuple[tuple[str, int], ...]:
    """What freezing does to each field of `typename` that can change (scalars and strings cannot)."""
    plan = []
    for name, (kind, spec) in typestore.fielddefs[typename][1]:
        if kind == Nodetype.NAME:
            plan.append((name, _MESSAGE))
        elif kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            (item_kind, item_spec), _length = cast(tuple[tuple[int, Any], int], spec)
            if item_kind == Nodetype.NAME:
                plan.append((name, _MESSAGES))
            elif item_spec[0] in ("string", "wstring"):
                plan.append((name, _STRINGS))
            else:
                plan.append((name, _ARRAY))
    return tuple(plan)


_FROZEN: dict[type[Any], type[Any]] = {}
"""each message class -> its read-only subclass"""
_ORIGINAL: dict[type[Any], type[Any]] = {}
"""each read-only message class -> the message class it was made from"""


def _frozen_class(cls: type[Any]) -> type[Any]:
    frozen = _FROZEN.get(cls)
    if frozen is None:
        frozen = _FROZEN[cls] = _read_only_subclass(cls)
        _ORIGINAL[frozen] = cls
    return frozen


def _read_only_subclass(cls: type[Any]) -> type[Any]:
    """The read-only subclass of a message class: same layout, so an instance's class can be swapped."""
    typename = cls.__msgtype__

    def refuse(self: Any, name: str, *_value: Any) -> NoReturn:
        raise ReadOnlyMessage(f"{typename}.{name}: {WRITABLE_HINT}")

    def new(_cls: type[Any], *args: Any, **kwargs: Any) -> Any:
        """Building one (dataclasses.replace does) gives a mutable message of the original class."""
        return cls(*args, **kwargs)

    def values(msg: Any) -> tuple[Any, ...]:
        return tuple(getattr(msg, name) for name, _ in typestore.fielddefs[typename][1])

    def equal(self: Any, other: Any) -> bool:
        """Equal to a message of the original class with equal fields, as the dataclass compares."""
        if not isinstance(other, cls):
            return NotImplemented
        return values(self) == values(other)

    def shallow(self: Any) -> Any:
        return cls(*values(self))

    def deep(self: Any, memo: dict[int, Any]) -> Any:
        return thaw(self)

    namespace = {
        "__slots__": (),
        "__setattr__": refuse,
        "__delattr__": refuse,
        "__new__": new,
        "__eq__": equal,
        "__hash__": None,
        "__copy__": shallow,
        "__deepcopy__": deep,
    }
    return type(cls.__name__, (cls,), namespace)


def is_frozen(msg: Any) -> bool:
    return type(msg) in _ORIGINAL


def freeze(msg: Any) -> Any:
    """Make a decoded message read-only in place, nested messages and arrays included; return it.
    A message already frozen is returned as it is."""
    if is_frozen(msg):
        return msg
    for name, how in _plan(msg.__msgtype__):
        value = getattr(msg, name)
        if how == _MESSAGE:
            freeze(value)
        elif how == _MESSAGES:
            object.__setattr__(msg, name, FrozenList(freeze(item) for item in value))
        elif how == _STRINGS:
            object.__setattr__(msg, name, FrozenList(value))
        elif isinstance(value, np.ndarray):
            value.flags.writeable = False
        else:  # a sequence given as a list (a message built by hand)
            object.__setattr__(msg, name, FrozenList(value))
    msg.__class__ = _frozen_class(type(msg))
    return msg


def thaw(msg: Any) -> Any:
    """A mutable deep copy of a message, frozen or not: nested messages, lists and arrays copied."""
    cls = _ORIGINAL.get(type(msg), type(msg))
    values = {}
    for name, _ in typestore.fielddefs[msg.__msgtype__][1]:
        value = getattr(msg, name)
        if hasattr(value, "__msgtype__"):
            value = thaw(value)
        elif isinstance(value, np.ndarray):
            value = value.copy()
        elif isinstance(value, list):
            value = [thaw(item) if hasattr(item, "__msgtype__") else copy.copy(item) for item in value]
        values[name] = value
    return cls(**values)
