"""What travels with each Zenoh sample: CDR payload, the type name in the encoding, and a small
attachment with the sample kind (data, watermark, end of stream, stream cut short), its event time, and the
producer's watermark (nothing it sends later on this key is stamped earlier)."""

from __future__ import annotations

import struct
from enum import IntEnum

import zenoh

_ATTACHMENT = struct.Struct("<4sBqq")
_MAGIC = b"RVR1"


class Kind(IntEnum):
    DATA = 0
    WATERMARK = 1
    END = 2
    """end of stream: the producer went through all its input"""
    CUT = 3
    """end of stream before the end: the producer (or a host upstream of it) was stopped or lost"""


class CodecError(ValueError):
    """A sample that is not a Rover message (foreign or damaged bytes)."""


def encoding(typename: str) -> zenoh.Encoding:
    """`application/cdr;<type>`: the type name travels with every sample."""
    return zenoh.Encoding.APPLICATION_CDR.with_schema(typename)


def control_encoding() -> zenoh.Encoding:
    return zenoh.Encoding.ZENOH_BYTES.with_schema("rover/control")


def attachment(kind: Kind, stamp_ns: int, watermark_ns: int) -> bytes:
    return _ATTACHMENT.pack(_MAGIC, kind, stamp_ns, watermark_ns)


def read_attachment(raw: bytes | None) -> tuple[Kind, int, int]:
    """(kind, stamp, watermark) of a sample, or CodecError when it is not a Rover sample."""
    if raw is None or len(raw) != _ATTACHMENT.size:
        raise CodecError("missing or malformed Rover attachment")
    magic, kind, stamp, mark = _ATTACHMENT.unpack(raw)
    if magic != _MAGIC or kind > Kind.CUT:
        raise CodecError("not a Rover sample")
    return Kind(kind), stamp, mark


def is_control(raw: bytes | None) -> bool:
    """Whether an attachment is a Rover watermark or end of stream (cheap: no full parse)."""
    return raw is not None and len(raw) == _ATTACHMENT.size and raw[:4] == _MAGIC and raw[4] != Kind.DATA


def schema_of(encoding_text: str) -> str:
    """The type name of an `application/cdr;<type>` encoding string ('' when absent)."""
    _, _, schema = encoding_text.partition(";")
    return schema
