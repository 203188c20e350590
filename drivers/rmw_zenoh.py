"""The rmw_zenoh wire format: key expressions, liveliness tokens, QoS strings and attachments.

Pure functions, no sessions: `rover.drivers.ros2` uses them to talk to ROS 2 nodes that run
`rmw_zenoh_cpp` directly, without a bridge.

Supported: rmw_zenoh_cpp 0.2.4 and later as released for ROS 2 Jazzy (ros2-gbp/rmw_zenoh-release,
tags release/jazzy/rmw_zenoh_cpp/0.2.4-1 to 0.2.10-1), and Humble's 0.1.x publishers (no type
hash). Older Jazzy releases (0.2.0-0.2.3) wrote a 77-byte labelled attachment: `parse_attachment`
still reads it, and `ros2_subscribe` names such a publisher's node once. Kilted (0.6.x) writes the
same tokens as Jazzy; Rolling (0.12) adds an optional 14th token chunk, `backends:NAME:META;...`,
for Buffer message types, which `parse_entity_token` reads (`EntityToken.backends`). Tested against
an independent implementation (zenoh-ros2-sdk, tests/test_ros2_interop.py), not a ROS 2 install.
"""

from __future__ import annotations

import dataclasses
import re
import struct
from dataclasses import dataclass
from functools import cache
from typing import Any

import xxhash
from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from rover.messages import typestore

LIVELINESS_PREFIX = "@ros2_lv"
"""first chunk of every liveliness token: hermetic, so `*` and `**` never match it"""
HUMBLE_HASH = "TypeHashNotSupported"
"""what rmw_zenoh_cpp 0.1.x (Humble) writes in place of a type hash"""
ANY_HASH = "*"
"""the hash chunk of a subscription that accepts any publisher's type hash (Humble's included)"""
NODE = "NN"
PUBLISHER = "MP"
SUBSCRIPTION = "MS"
ENTITY_KINDS = (NODE, PUBLISHER, SUBSCRIPTION, "SS", "SC")
"""node, message publisher, message subscription, service server, service client"""
DEFAULT_DEPTH = 42
"""the history depth rmw_zenoh leaves out of a QoS string (src/detail/qos.cpp)"""
RELIABILITY_BEST_EFFORT = 2
DURABILITY_TRANSIENT_LOCAL = 1
HISTORY_KEEP_ALL = 2
GID_BYTES = 16

_ATTACHMENT = struct.Struct("<qqB16s")
"""sequence number, source timestamp (ns since the Unix epoch), GID length (16), GID (0.2.4 and later)"""
ATTACHMENT_BYTES = _ATTACHMENT.size  # 33
_LABELS = (b"sequence_number", b"source_timestamp", b"source_gid")
LEGACY_ATTACHMENT_BYTES = sum(1 + len(label) for label in _LABELS) + 8 + 8 + 1 + GID_BYTES  # 77
_DDS_TYPE = re.compile(r"^([A-Za-z0-9_]+)::(msg|srv|action)::dds_::([A-Za-z0-9_]+)_$")


def dds_type_name(typename: str) -> str:
    """`pkg/msg/Name` -> `pkg::msg::dds_::Name_`, the type name rmw_zenoh puts in keys and tokens."""
    parts = typename.split("/")
    if len(parts) != 3 or not all(parts):
        raise ValueError(f"not a ROS 2 type name (pkg/msg/Name): {typename!r}")
    pkg, kind, name = parts
    return f"{pkg}::{kind}::dds_::{name}_"


def ros_type_name(dds_name: str) -> str:
    """The inverse of `dds_type_name`; a name of another form is returned as it is."""
    match = _DDS_TYPE.match(dds_name)
    return f"{match[1]}/{match[2]}/{match[3]}" if match else dds_name


@cache
def _jazzy() -> Typestore:
    return get_typestore(Stores.ROS2_JAZZY)


def _rosidl_base(base: Any) -> Any:
    """A base type as rosidl hashes it: `char` is `uint8` (rosidl_parser maps it before the type
    description is made; rosbags hashes it as `char`, type id 13)."""
    name, size = base
    return ("uint8", size) if name == "char" else base


def _rosidl_field(desc: Any) -> Any:
    kind, spec = desc
    if kind == Nodetype.BASE:
        return kind, _rosidl_base(spec)
    if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        (item_kind, item), count = spec
        return kind, ((item_kind, _rosidl_base(item) if item_kind == Nodetype.BASE else item), count)
    return desc


@cache
def _hashing_store(jazzy: bool) -> Typestore:
    """Jazzy's types (or Rover's own) as rosidl sees them when it hashes them."""
    source = _jazzy() if jazzy else typestore
    view = get_typestore(Stores.EMPTY)
    view.register(
        {
            name: (consts, [(field, _rosidl_field(desc)) for field, desc in fields])
            for name, (consts, fields) in source.fielddefs.items()
        }
    )
    return view


def type_hash(typename: str) -> str:
    """The RIHS01 type hash a Jazzy node computes: from Jazzy's definition for standard types, from
    Rover's own for the types only it has (rover_msgs), with `char` hashed as rosidl does."""
    jazzy = typename in _jazzy().fielddefs
    if not jazzy and typename not in typestore.fielddefs:
        raise ValueError(f"unknown message type {typename!r}")
    return _hashing_store(jazzy).hash_rihs01(typename)


def _references(fields: Any) -> list[str]:
    """The message types a type's fields name, directly or as array/sequence items."""
    found = []
    for _name, (kind, spec) in fields:
        if kind == Nodetype.NAME:
            found.append(spec)
        elif kind in (Nodetype.ARRAY, Nodetype.SEQUENCE) and spec[0][0] == Nodetype.NAME:
            found.append(spec[0][1])
    return found


NOT_AS_IN_JAZZY = frozenset({"rosbag2_interfaces/msg/ReadSplitEvent", "rosbag2_interfaces/msg/WriteSplitEvent"})
"""Types whose definition in rosbags' Jazzy store is not Jazzy's own (rosbag2 0.26.0 added
`node_name` to both): neither their layout nor their hash can be trusted"""


@cache
def same_layout_as_jazzy(typename: str) -> bool:
    """Whether Rover's definition of a type (Humble's, for standard types) has the same fields as
    Jazzy's, nested types included: only then is its CDR what a Jazzy node reads and writes.
    Constants may differ (they change the hash, which is taken from Jazzy's definition)."""
    if typename in NOT_AS_IN_JAZZY:
        return False
    pending, seen = [typename], set()
    while pending:
        name = pending.pop()
        if name in seen:
            continue
        seen.add(name)
        ours = typestore.fielddefs.get(name)
        if ours is None:
            return False
        theirs = _jazzy().fielddefs.get(name)
        if theirs is not None and theirs[1] != ours[1]:
            return False
        pending.extend(_references(ours[1]))
    return True


def _strip_slashes(name: str) -> str:
    """rmw_zenoh's `strip_slashes`: one leading and one trailing `/` removed, inner ones kept."""
    if name.startswith("/"):
        name = name[1:]
    if name.endswith("/"):
        name = name[:-1]
    return name


def topic_key(domain_id: int, topic: str, typename: str, hash: str) -> str:
    """The data key `<domain>/<topic>/<dds type>/<hash>` (rmw_zenoh `TopicInfo`); `hash` may be `*`."""
    return f"{domain_id}/{_strip_slashes(topic)}/{dds_type_name(typename)}/{hash}"


def mangle(name: str) -> str:
    """A name as one key chunk: every `/` becomes `%`, and an empty name is `%` (chunks are never empty)."""
    return name.replace("/", "%") or "%"


def demangle(chunk: str) -> str:
    return chunk.replace("%", "/")


def qos_string(reliable: bool, depth: int, transient_local: bool = False, keep_all: bool = False) -> str:
    """The QoS chunk of a token for a KEEP_LAST(depth) (or KEEP_ALL) endpoint with automatic
    liveliness and no deadline, lifespan or lease, in rmw_zenoh's compact form (0.2.3 and later):
    each field is left empty when it equals rmw_zenoh's default (reliable, volatile, keep last,
    depth 42)."""
    if depth < 1:
        raise ValueError(f"QoS depth must be >= 1, got {depth}")
    rel = "" if reliable else str(RELIABILITY_BEST_EFFORT)
    dur = str(DURABILITY_TRANSIENT_LOCAL) if transient_local else ""
    hist = str(HISTORY_KEEP_ALL) if keep_all else ""
    dep = "" if depth == DEFAULT_DEPTH else str(depth)
    return f"{rel}:{dur}:{hist},{dep}:,:,:,,"


def node_token(domain_id: int, zid: str, nid: int, enclave: str, namespace: str, node: str) -> str:
    """A node's liveliness token: `@ros2_lv/<domain>/<zid>/<nid>/<nid>/NN/<enclave>/<namespace>/<node>`."""
    chunks = [LIVELINESS_PREFIX, str(domain_id), zid, str(nid), str(nid), NODE]
    return "/".join([*chunks, mangle(enclave), mangle(namespace), mangle(node)])


def entity_token(
    kind: str,
    domain_id: int,
    zid: str,
    nid: int,
    eid: int,
    enclave: str,
    namespace: str,
    node: str,
    topic: str,
    typename: str,
    hash: str,
    qos: str,
) -> str:
    """A publisher's (`MP`) or subscription's (`MS`) liveliness token; `typename` is the ROS name
    (`std_msgs/msg/String`), written in its DDS form; the QoS chunk is not mangled."""
    if kind not in (PUBLISHER, SUBSCRIPTION):
        raise ValueError(f"entity kind must be {PUBLISHER} or {SUBSCRIPTION}, got {kind!r}")
    chunks = [LIVELINESS_PREFIX, str(domain_id), zid, str(nid), str(eid), kind]
    chunks += [mangle(enclave), mangle(namespace), mangle(node), mangle(topic), mangle(dds_type_name(typename))]
    chunks += [mangle(hash), qos]
    return "/".join(chunks)


@dataclass(frozen=True)
class EntityToken:
    """A parsed liveliness token; the names demangled (`/chatter`, `std_msgs/msg/String`), and the
    topic fields empty for a node (`NN`)."""

    domain_id: int
    zid: str
    nid: int
    eid: int
    kind: str
    enclave: str
    namespace: str
    node: str
    topic: str = ""
    typename: str = ""
    type_hash: str = ""
    qos: str = ""
    backends: tuple[tuple[str, str], ...] = ()
    """Rolling's optional 14th chunk (Buffer types): (backend, metadata) pairs, in the token's order"""


def parse_entity_token(key: str) -> EntityToken:
    """Read a node or entity token (`node_token`, `entity_token`, or one of a ROS 2 node); ValueError
    on anything else. The QoS chunk is kept as a string."""
    chunks = str(key).split("/")
    if len(chunks) < 9 or chunks[0] != LIVELINESS_PREFIX:
        raise ValueError(f"not an rmw_zenoh liveliness token: {key!r}")
    if any(not c for c in chunks):
        raise ValueError(f"liveliness token with an empty chunk: {key!r}")
    _prefix, domain, zid, nid, eid, kind, enclave, namespace, node, *rest = chunks
    if kind not in ENTITY_KINDS:
        raise ValueError(f"unknown entity kind {kind!r} in {key!r}")
    if not (domain.isdigit() and nid.isdigit() and eid.isdigit()):
        raise ValueError(f"liveliness token with a non-numeric domain or id: {key!r}")
    node_entity = EntityToken(
        int(domain), zid, int(nid), int(eid), kind, demangle(enclave), demangle(namespace), demangle(node)
    )
    if kind == NODE:
        if rest:
            raise ValueError(f"node token with extra chunks: {key!r}")
        return node_entity
    if len(rest) not in (4, 5):
        raise ValueError(f"entity token needs topic, type, hash and QoS chunks (and optional backends): {key!r}")
    topic, dds_type, hash_chunk, qos = rest[:4]
    return dataclasses.replace(
        node_entity,
        topic=demangle(topic),
        typename=ros_type_name(demangle(dds_type)),
        type_hash=demangle(hash_chunk),
        qos=qos,
        backends=parse_backends(rest[4]) if len(rest) == 5 else (),
    )


BACKENDS = "backends:"
_ESCAPED = re.compile(r"%([0-9A-Fa-f]{2})")


def parse_backends(chunk: str) -> tuple[tuple[str, str], ...]:
    """Rolling's backends chunk, `backends:NAME:META;NAME:META`, each field with `%`, `;`, `:` and
    `/` escaped as %XX; another optional chunk (a later release's) is ignored, as rmw_zenoh does."""
    if not chunk.startswith(BACKENDS):
        return ()
    pairs = []
    for entry in chunk[len(BACKENDS) :].split(";"):
        if entry:
            name, _, meta = entry.partition(":")
            pairs.append((_unescape(name), _unescape(meta)))
    return tuple(pairs)


def _unescape(field: str) -> str:
    return _ESCAPED.sub(lambda m: chr(int(m[1], 16)), field)


def gid(token: str) -> bytes:
    """An entity's GID, as rmw_zenoh derives it: XXH3-128 of its liveliness token, low 64 bits then
    high 64 bits, each little-endian (what `ros2 topic info -v` shows and attachments carry)."""
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(GID_BYTES, "little")


def attachment(seq: int, stamp_ns: int, gid: bytes) -> bytes:
    """The 33-byte attachment of every sample (rmw_zenoh_cpp 0.2.4+): int64 LE sequence number,
    int64 LE source timestamp in ns, the GID's length (16) as one LEB128 byte, the GID."""
    if len(gid) != GID_BYTES:
        raise ValueError(f"a GID has {GID_BYTES} bytes, got {len(gid)}")
    return _ATTACHMENT.pack(seq, stamp_ns, GID_BYTES, gid)


def _legacy(data: bytes) -> tuple[int, int, bytes]:
    """The labelled 77-byte form of rmw_zenoh_cpp 0.2.0-0.2.3: each value follows its name as a
    LEB128-length string."""
    at = 0
    values: list[Any] = []
    for label, size in zip(_LABELS, (8, 8, 1 + GID_BYTES), strict=True):
        if data[at] != len(label) or data[at + 1 : at + 1 + len(label)] != label:
            raise ValueError(f"legacy attachment without the {label.decode()!r} label")
        at += 1 + len(label)
        values.append(data[at : at + size])
        at += size
    seq, stamp = struct.unpack("<q", values[0])[0], struct.unpack("<q", values[1])[0]
    if values[2][0] != GID_BYTES:
        raise ValueError(f"attachment GID of length {values[2][0]}, not {GID_BYTES}")
    return seq, stamp, bytes(values[2][1:])


def is_legacy_attachment(data: bytes | bytearray | None) -> bool:
    """Whether an attachment has the labelled form of rmw_zenoh_cpp 0.2.0-0.2.3."""
    return data is not None and len(data) == LEGACY_ATTACHMENT_BYTES


def parse_attachment(data: bytes | bytearray | None) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp in ns, GID) of a sample's attachment, in the 33-byte form
    (0.2.4+) or the labelled 77-byte one (0.2.0-0.2.3); ValueError for anything else."""
    if data is None:
        raise ValueError("no attachment")
    data = bytes(data)
    if len(data) == ATTACHMENT_BYTES:
        seq, stamp, length, gid_bytes = _ATTACHMENT.unpack(data)
        if length != GID_BYTES:
            raise ValueError(f"attachment GID of length {length}, not {GID_BYTES}")
        return seq, stamp, gid_bytes
    if len(data) == LEGACY_ATTACHMENT_BYTES:
        return _legacy(data)
    raise ValueError(
        f"attachment of {len(data)} bytes: rmw_zenoh's has {ATTACHMENT_BYTES} (or {LEGACY_ATTACHMENT_BYTES}, labelled)"
    )
