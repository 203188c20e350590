"""Message types and CDR serialization through one rosbags typestore.

Standard ROS 2 types come from the Humble store; the project's own types are the `.msg`
files under `rover_msgs/msg/`, registered here at import so every module sees one schema.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from functools import cache
from importlib import resources
from typing import Any

import numpy as np
from rosbags.interfaces import Nodetype
from rosbags.interfaces.typing import Typesdict
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from rover.errors import BadInput

ANY = "*"
"""Port type that accepts every message type (recorders)."""

_CDR_LE = b"\x00\x01"
_STAMP = struct.Struct("<iI")


def _load_store() -> Typestore:
    store = get_typestore(Stores.ROS2_HUMBLE)
    types: Typesdict = {}
    for entry in sorted(resources.files("rover.rover_msgs").joinpath("msg").iterdir(), key=lambda p: p.name):
        if entry.name.endswith(".msg"):
            types.update(get_types_from_msg(entry.read_text(), f"rover_msgs/msg/{entry.name[:-4]}"))
    store.register(types)
    return store


typestore = _load_store()


@dataclass(frozen=True)
class Raw:
    """A message kept as its CDR bytes (pass-through ports: replay, recorders)."""

    typename: str
    payload: bytes


def known_type(typename: str) -> bool:
    return typename == ANY or typename in typestore.fielddefs


def type_names() -> list[str]:
    return sorted(typestore.fielddefs)


def message_class(typename: str) -> type[Any]:
    try:
        return typestore.types[typename]
    except KeyError:
        raise BadInput(f"unknown message type {typename!r}") from None


_NUMPY_DTYPES = {
    "bool": "bool",
    "int8": "int8",
    "uint8": "uint8",
    "byte": "uint8",
    "char": "uint8",
    "int16": "int16",
    "uint16": "uint16",
    "int32": "int32",
    "uint32": "uint32",
    "int64": "int64",
    "uint64": "uint64",
    "float32": "float32",
    "float64": "float64",
}


def _zero(kind: int, spec: Any) -> Any:
    if kind == Nodetype.BASE:
        name = spec[0]
        return (
            ""
            if name in ("string", "wstring")
            else (False if name == "bool" else 0 if "int" in name or name in ("byte", "char") else 0.0)
        )
    if kind == Nodetype.NAME:
        return make(spec)
    (item_kind, item_spec), length = spec
    numeric = item_kind == Nodetype.BASE and item_spec[0] in _NUMPY_DTYPES
    if kind == Nodetype.ARRAY:
        if numeric:
            return np.zeros(length, dtype=_NUMPY_DTYPES[item_spec[0]])
        return [_zero(item_kind, item_spec) for _ in range(length)]
    return np.zeros(0, dtype=_NUMPY_DTYPES[item_spec[0]]) if numeric else []


DEFAULTS: dict[str, dict[str, Any]] = {"geometry_msgs/msg/Quaternion": {"w": 1.0}}
"""The non-zero defaults of the standard interfaces' .msg files, which rosbags' definitions leave
out: a ROS 2 node's unset quaternion is the identity, not zero (common_interfaces' Quaternion.msg)."""


def make(typename: str, **fields: Any) -> Any:
    """A message of `typename` with the given fields and every other field zero, empty or its
    .msg default (`DEFAULTS`)."""
    if typename not in typestore.fielddefs:
        raise BadInput(f"unknown message type {typename!r}")
    _consts, defs = typestore.fielddefs[typename]
    fields = {**DEFAULTS.get(typename, {}), **fields}
    values = {name: fields.pop(name) if name in fields else _zero(kind, spec) for name, (kind, spec) in defs}
    if fields:
        raise TypeError(f"{typename} has no field(s) {', '.join(fields)}")
    return typestore.types[typename](**values)


def serialize(msg: Any, typename: str | None = None) -> bytes:
    if isinstance(msg, Raw):
        return msg.payload
    return bytes(typestore.serialize_cdr(msg, typename or msg.__msgtype__))


def deserialize(payload: bytes, typename: str) -> Any:
    return typestore.deserialize_cdr(payload, typename)


@cache
def has_header(typename: str) -> bool:
    """True when the type's first field is a std_msgs/Header (its stamp is then at a fixed offset)."""
    fields = typestore.fielddefs.get(typename)
    if not fields or not fields[1]:
        return False
    _name, (_kind, ref) = fields[1][0]
    return ref == "std_msgs/msg/Header"


def cdr_stamp_ns(payload: bytes) -> int:
    """Header stamp of a CDR message whose first field is a Header, without deserializing it."""
    if len(payload) < 12:
        raise ValueError("payload too short for a header stamp")
    sec, nsec = _STAMP.unpack_from(payload, 4) if payload[:2] == _CDR_LE else struct.unpack_from(">iI", payload, 4)
    return int(sec) * 1_000_000_000 + int(nsec)


def stamp_ns(msg: Any) -> int:
    """Event time of a decoded or raw message with a header."""
    if isinstance(msg, Raw):
        return cdr_stamp_ns(msg.payload)
    stamp = msg.header.stamp
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def header(stamp: int, frame_id: str = "") -> Any:
    """A std_msgs/Header for an event time in nanoseconds."""
    Time = typestore.types["builtin_interfaces/msg/Time"]
    Header = typestore.types["std_msgs/msg/Header"]
    return Header(stamp=Time(sec=stamp // 1_000_000_000, nanosec=stamp % 1_000_000_000), frame_id=frame_id)


@cache
def ros2_msgdef(typename: str) -> str:
    """The concatenated ROS 2 message definition, as MCAP `ros2msg` schemas carry it."""
    text, _ = typestore.generate_msgdef(typename, ros_version=2)
    return text
