"""Read-only messages: every way of editing one is refused, copies are mutable, bytes unchanged."""

from __future__ import annotations

import copy
import dataclasses
from typing import Any

import numpy as np
import pytest

from rover.frozen import FrozenList, ReadOnlyMessage, freeze, is_frozen, thaw
from rover.messages import deserialize, header, make, serialize

TAGS = "rover_msgs/msg/TagArray"


def tag_array() -> Any:
    tags = [make("rover_msgs/msg/Tag", id=i, covariance_xy=np.array([1.0, 0, 0, 1.0])) for i in range(3)]
    return make(TAGS, header=header(5, "world"), tags=tags)


def frozen_tags() -> Any:
    return freeze(deserialize(serialize(tag_array()), TAGS))


@pytest.mark.parametrize(
    "edit",
    [
        lambda m: setattr(m, "header", None),
        lambda m: delattr(m, "header"),
        lambda m: setattr(m.header.stamp, "sec", 1),
        lambda m: setattr(m.tags[0].position, "x", 1.0),
        lambda m: m.tags.append(m.tags[0]),
        lambda m: m.tags.__setitem__(0, None),
        lambda m: m.tags.sort(key=id),
        lambda m: m.tags.__iadd__([]),
    ],
)
def test_every_edit_of_a_frozen_message_is_refused(edit):
    msg = frozen_tags()
    with pytest.raises(ReadOnlyMessage, match="read-only"):
        edit(msg)
    assert serialize(msg) == serialize(tag_array())


def test_arrays_of_a_frozen_message_are_read_only():
    msg = freeze(tag_array())  # built by hand: its arrays were writable
    with pytest.raises(ValueError, match="read-only"):
        msg.tags[1].covariance_xy[0] = 2.0


def test_a_frozen_message_reads_serializes_and_compares_as_the_original():
    original = tag_array()
    msg = frozen_tags()
    assert isinstance(msg, type(original)) and is_frozen(msg) and is_frozen(msg.tags[2])
    assert isinstance(msg.tags, FrozenList) and msg.tags == list(msg.tags)
    assert [t.id for t in msg.tags] == [0, 1, 2] and msg.header.frame_id == "world"
    assert serialize(msg) == serialize(original)
    pose = make("geometry_msgs/msg/PoseStamped", header=header(7))
    frozen_pose = freeze(deserialize(serialize(pose), "geometry_msgs/msg/PoseStamped"))
    assert frozen_pose == pose and pose == frozen_pose
    frozen_pose_moved = freeze(thaw(frozen_pose))
    assert frozen_pose_moved == frozen_pose and freeze(frozen_pose) is frozen_pose


def test_copies_are_mutable_and_leave_the_frozen_message_as_it_was():
    msg = frozen_tags()
    deep = thaw(msg)
    deep.tags[0].position.x = 3.0
    deep.tags.append(make("rover_msgs/msg/Tag", id=9))
    deep.tags[1].covariance_xy[0] = 5.0
    assert not is_frozen(deep) and not is_frozen(deep.tags[0])
    assert not is_frozen(copy.deepcopy(msg)) and serialize(copy.deepcopy(msg)) == serialize(msg)
    shallow = copy.copy(msg)
    shallow.tags = []
    replaced = dataclasses.replace(msg, tags=[])
    replaced.header = header(1)
    assert not is_frozen(shallow) and not is_frozen(replaced)
    assert len(msg.tags) == 3 and msg.tags[0].position.x == 0.0 and msg.tags[1].covariance_xy[0] == 1.0
    assert serialize(msg) == serialize(tag_array())
