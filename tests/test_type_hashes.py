"""Every type Rover can publish or subscribe over ROS 2 has the RIHS01 hash a Jazzy node computes,
checked against ros2-pyterfaces (an independent RIHS01 implementation with its own copy of the
standard interfaces, tested against ROS 2 itself): the standard types from its definitions; Rover's
own types from their .msg files, read here by a small parser of the ROS 2 interface grammar; the
few standard types it lacks are written here from their ROS 2 definitions or listed as unchecked.

rosbags, where Rover's definitions come from, hashes `char` as type id 13 where rosidl first maps it
to `uint8`: `std_msgs/msg/Char` is the case a Jazzy node would never receive.
"""

from __future__ import annotations

import importlib
import pkgutil
import re
from pathlib import Path
from typing import Any

import pytest
import ros2_pyterfaces

ros2_pyterfaces.DISTRO = ros2_pyterfaces.Distro.JAZZY  # before its schemas load: Jazzy's (Range has variance)

from ros2_pyterfaces import core  # noqa: E402
from ros2_pyterfaces.core import Array, BoundedString, CoreSchema, SchemaEntry, Sequence, hash_rihs01  # noqa: E402

from rover.drivers.rmw_zenoh import type_hash  # noqa: E402
from rover.drivers.ros2 import parse_topics  # noqa: E402
from rover.messages import typestore  # noqa: E402

MSG_DIR = Path(__file__).parents[1] / "rover_msgs" / "msg"
VENDORED = Path(__file__).parent / "ros2_interop" / "msgs"
"""the standard interfaces' own .msg files (tests/ros2_interop/README.md says from where)"""
FIELD = re.compile(r"^(?P<type>[A-Za-z0-9_/]+)(?P<bound><=\d+)?(?P<array>\[(?:<=)?\d*\])?\s+(?P<name>\w+)(?P<rest>.*)$")
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
REFUSED = {"rosbag2_interfaces/msg/ReadSplitEvent", "rosbag2_interfaces/msg/WriteSplitEvent"}
"""Rover's definitions are not Jazzy's (rosbag2 0.26 added node_name): ros2_publish/subscribe refuse them"""


def standard_schemas() -> dict[str, CoreSchema]:
    """ros2-pyterfaces' own definitions of the standard messages, by type name."""
    found = {}
    for module in pkgutil.iter_modules(core.__path__):
        try:
            msg = importlib.import_module(f"ros2_pyterfaces.core.{module.name}.msg")
        except ImportError:
            continue
        found.update({v["__typename"]: v for v in vars(msg).values() if isinstance(v, dict) and "__typename" in v})
    return found


STANDARD = standard_schemas()


def entry(text: str, bound: str | None, array: str | None, package: str) -> SchemaEntry:
    """A field's type in ros2-pyterfaces' form, from its text in a .msg file."""
    if "/" in text:
        pkg, name = text.split("/")
        item: SchemaEntry = schema_of(f"{pkg}/msg/{name}")
    elif text == "char":  # rosidl's IDL maps char to uint8 (as ros2-pyterfaces' own std_msgs/Char says)
        item = "uint8"
    elif text in core.PRIMITIVES:
        item = BoundedString(int(bound[2:])) if bound else text  # type: ignore[assignment]  # a primitive
    else:  # a type of the same package
        item = schema_of(f"{package}/msg/{text}")
    if array is None:
        return item
    inner = array[1:-1]
    if inner == "":
        return Sequence(item)
    if inner.startswith("<="):
        return Sequence(item, int(inner[2:]))
    return Array(item, int(inner))


def schema_of(typename: str) -> CoreSchema:
    """ros2-pyterfaces' definition, else one read from the type's .msg file (Rover's or vendored)."""
    if typename in STANDARD:
        return STANDARD[typename]
    package, _, name = typename.split("/")
    schema: dict[str, Any] = {"__typename": typename}
    folder = MSG_DIR if package == "rover_msgs" else VENDORED / package / "msg"
    for line in (folder / f"{name}.msg").read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        match = FIELD.match(line)
        assert match, f"{name}.msg: cannot read {line!r}"
        if match["rest"].strip().startswith("="):
            continue  # a constant: not part of the type description
        schema[match["name"]] = entry(match["type"], match["bound"], match["array"], package)
    return schema


def test_rover_hashes_every_standard_type_as_ros2_pyterfaces_does():
    compared = sorted(name for name in typestore.fielddefs if name in STANDARD)
    assert len(compared) > 100 and "std_msgs/msg/Char" in compared
    wrong = {name: (type_hash(name), hash_rihs01(STANDARD[name])) for name in compared}
    wrong = {name: pair for name, pair in wrong.items() if pair[0] != pair[1]}
    assert not wrong, f"hashes that differ (Rover's, ros2-pyterfaces'): {wrong}"


def test_char_is_hashed_as_rosidl_does():
    """The hash rosidl generates for std_msgs/msg/Char (its .json type description), as three
    independent implementations give it."""
    assert type_hash("std_msgs/msg/Char") == "RIHS01_3ad2d04dd29ba19d04b16659afa3ccaedd691914b02a64e82e252f2fa6a586a9"


@pytest.mark.parametrize("name", sorted(path.stem for path in MSG_DIR.glob("*.msg")))
def test_rover_msgs_hash_as_their_msg_files_say(name):
    typename = f"rover_msgs/msg/{name}"
    assert type_hash(typename) == hash_rihs01(schema_of(typename))


@pytest.mark.parametrize(
    "typename",
    sorted(n for n in typestore.fielddefs if "/msg/" in n and n not in STANDARD and not n.startswith("rover_msgs/")),
)
def test_the_types_ros2_pyterfaces_lacks_hash_as_their_msg_files_say(typename):
    """Read from the standard interfaces' own .msg files (vendored), as rosidl hashes them."""
    if typename in REFUSED:
        with pytest.raises(ValueError, match="other fields in ROS 2 Jazzy"):
            parse_topics({"x": {"topic": "/x", "type": typename}})
        return
    assert type_hash(typename) == hash_rihs01(schema_of(typename))


def test_tf_message_hashes_as_its_definition_says():
    """tf2_msgs/msg/TFMessage (`geometry_msgs/TransformStamped[] transforms`), which ros2-pyterfaces lacks."""
    schema: dict[str, Any] = {
        "__typename": TF_MESSAGE,
        "transforms": Sequence(STANDARD["geometry_msgs/msg/TransformStamped"]),
    }
    assert type_hash(TF_MESSAGE) == hash_rihs01(schema)


def test_every_type_rover_can_send_has_a_definition_to_check_against():
    ours = {name for name in typestore.fielddefs if "/msg/" in name}
    vendored = {f"{p.parent.parent.name}/msg/{p.stem}" for p in VENDORED.glob("*/msg/*.msg")}
    unchecked = ours - set(STANDARD) - vendored - {n for n in ours if n.startswith("rover_msgs/")}
    assert unchecked == set(), unchecked
