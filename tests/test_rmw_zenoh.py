"""The rmw_zenoh wire format (rmw_zenoh_cpp 0.2.4+, Jazzy) against the examples of its own documentation.

The expected strings are rmw_zenoh's docs/design.md examples (talker/listener, the `/robot1`
namespace) and the values of /tmp/rmw_zenoh_spec.md (the GID and attachment of the talker's token).
"""

from __future__ import annotations

import pytest
from rmw_bytes import legacy_attachment

from rover.drivers import rmw_zenoh as rz

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
IMU_HASH = "RIHS01_7d9a00ff131080897a5ec7e26e315954b8eae3353c3f995c55faf71574000b5b"
TWIST_HASH = "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"
TALKER_ZID = "8b20917502ee955ac4476e0266340d5c"
TALKER_MP = (
    f"@ros2_lv/0/{TALKER_ZID}/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,"
)
TALKER_GID = bytes.fromhex("eb85fa883b7846dc448a4501890ad062")
EXAMPLE_ATTACHMENT = bytes.fromhex(
    "0100000000000000" + "15cd853dfe9c9717" + "10" + "eb85fa883b7846dc448a4501890ad062"
)  # seq 1, 1700000000123456789 ns, the talker's GID
EXAMPLE_STAMP_NS = 1_700_000_000_123_456_789


def test_type_names_and_hashes():
    assert rz.dds_type_name("std_msgs/msg/String") == "std_msgs::msg::dds_::String_"
    assert rz.dds_type_name("sensor_msgs/msg/Imu") == "sensor_msgs::msg::dds_::Imu_"
    assert rz.ros_type_name("sensor_msgs::msg::dds_::Imu_") == "sensor_msgs/msg/Imu"
    assert rz.type_hash("std_msgs/msg/String") == STRING_HASH
    assert rz.type_hash("sensor_msgs/msg/Imu") == IMU_HASH
    assert rz.type_hash("geometry_msgs/msg/Twist") == TWIST_HASH
    assert rz.type_hash("rover_msgs/msg/Aoa").startswith("RIHS01_")
    with pytest.raises(ValueError):
        rz.dds_type_name("String")
    with pytest.raises(ValueError):
        rz.type_hash("nope_msgs/msg/Nope")


def test_layouts_that_differ_from_jazzy_are_found():
    assert rz.same_layout_as_jazzy("sensor_msgs/msg/Imu")
    assert rz.same_layout_as_jazzy("rover_msgs/msg/Aoa")
    assert rz.same_layout_as_jazzy("sensor_msgs/msg/NavSatStatus")  # constants differ, fields do not
    assert not rz.same_layout_as_jazzy("sensor_msgs/msg/Range")  # Jazzy added `variance`


def test_data_keys_of_the_design_document():
    assert rz.topic_key(0, "/chatter", "std_msgs/msg/String", STRING_HASH) == (
        f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    )
    assert rz.topic_key(0, "/robot1/chatter", "std_msgs/msg/String", STRING_HASH) == (
        f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    )
    assert rz.topic_key(3, "/imu/data", "sensor_msgs/msg/Imu", "*") == "3/imu/data/sensor_msgs::msg::dds_::Imu_/*"


def test_mangling():
    assert rz.mangle("/") == "%"
    assert rz.mangle("/robot1") == "%robot1"
    assert rz.mangle("/ns/a/b") == "%ns%a%b"
    assert rz.mangle("") == "%"


def test_tokens_of_the_design_document():
    listener = "@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    assert rz.node_token(0, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "/", "/", "listener") == listener
    talker = rz.entity_token(
        "MP", 0, TALKER_ZID, 0, 10, "/", "/", "talker", "/chatter", "std_msgs/msg/String", STRING_HASH, "::,7:,:,:,,"
    )
    assert talker == TALKER_MP
    sub = rz.entity_token(
        "MS", 0, "aac3178e146ba6f1fc6e6a4085e77f21", 0, 1, "/", "/", "listener", "/chatter", "std_msgs/msg/String",
        STRING_HASH, rz.qos_string(True, 10),
    )  # fmt: skip
    assert sub.endswith(f"/1/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/{STRING_HASH}/::,10:,:,:,,")
    in_ns = rz.entity_token(
        "MP", 0, TALKER_ZID, 0, 1, "/", "/robot1", "talker", "/robot1/chatter", "std_msgs/msg/String", STRING_HASH,
        "::,10:,:,:,,",
    )  # fmt: skip
    assert in_ns == (
        f"@ros2_lv/0/{TALKER_ZID}/0/1/MP/%/%robot1/talker/%robot1%chatter/std_msgs::msg::dds_::String_/"
        f"{STRING_HASH}/::,10:,:,:,,"
    )
    with pytest.raises(ValueError):
        rz.entity_token("NN", 0, TALKER_ZID, 0, 1, "/", "/", "n", "/t", "std_msgs/msg/String", STRING_HASH, "")


def test_tokens_parse_back():
    parsed = rz.parse_entity_token(TALKER_MP)
    assert parsed == rz.EntityToken(
        0, TALKER_ZID, 0, 10, "MP", "/", "/", "talker", "/chatter", "std_msgs/msg/String", STRING_HASH, "::,7:,:,:,,"
    )
    node = rz.parse_entity_token("@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%robot1/listener")
    assert (node.kind, node.namespace, node.node, node.topic) == ("NN", "/robot1", "listener", "")
    for bad in ("0/chatter/x/y", "@ros2_lv/0/z/0/0/XX/%/%/n", "@ros2_lv/0/z/0/0/NN/%//n", TALKER_MP.rsplit("/", 1)[0]):
        with pytest.raises(ValueError):
            rz.parse_entity_token(bad)


def test_rollings_optional_backends_chunk_is_read():
    """rmw_zenoh_cpp 0.12 (Rolling) appends `backends:NAME:META;...` to the token of a Buffer type,
    each field with `%`, `;`, `:` and `/` escaped as %XX; a 14th chunk of another kind is ignored."""
    with_backends = f"{TALKER_MP}/backends:cuda:dev%3A0%2Fstream%253B;cpu:"
    parsed = rz.parse_entity_token(with_backends)
    assert parsed.backends == (("cuda", "dev:0/stream%3B"), ("cpu", ""))
    assert parsed.topic == "/chatter" and parsed.qos == "::,7:,:,:,,"
    assert rz.parse_entity_token(f"{TALKER_MP}/future:thing").backends == ()
    with pytest.raises(ValueError, match="optional backends"):
        rz.parse_entity_token(f"{TALKER_MP}/backends:cpu:/extra")


@pytest.mark.parametrize(
    ("reliable", "depth", "transient_local", "expected"),
    [
        (True, 10, False, "::,10:,:,:,,"),  # rclcpp/rclpy QoS(10)
        (True, 7, False, "::,7:,:,:,,"),  # the design document's talker
        (True, 1, True, ":1:,1:,:,:,,"),
        (False, 5, False, "2::,5:,:,:,,"),  # sensor data
        (True, 42, False, "::,:,:,:,,"),  # rmw_zenoh's default depth is left out
    ],
)
def test_qos_strings(reliable, depth, transient_local, expected):
    assert rz.qos_string(reliable, depth, transient_local) == expected
    assert len(expected.split(":")) == 6  # what rmw_zenoh's parser requires


def test_qos_depth_must_be_positive():
    with pytest.raises(ValueError):
        rz.qos_string(True, 0)


def test_gid_of_the_talker_token():
    assert rz.gid(TALKER_MP) == TALKER_GID


def test_attachment_bytes():
    data = rz.attachment(1, EXAMPLE_STAMP_NS, TALKER_GID)
    assert data == EXAMPLE_ATTACHMENT
    assert data.hex(" ").startswith("01 00 00 00 00 00 00 00 15 cd 85 3d fe 9c 97 17 10 eb 85")
    assert rz.parse_attachment(data) == (1, EXAMPLE_STAMP_NS, TALKER_GID)
    with pytest.raises(ValueError):
        rz.attachment(1, 0, b"short")


def test_both_attachment_forms_parse():
    old = legacy_attachment(1, EXAMPLE_STAMP_NS, TALKER_GID)
    assert len(old) == 77
    assert old.startswith(b"\x0fsequence_number\x01" + bytes(7) + b"\x10source_timestamp\x15\xcd\x85")
    assert rz.parse_attachment(old) == (1, EXAMPLE_STAMP_NS, TALKER_GID)
    assert rz.parse_attachment(bytearray(EXAMPLE_ATTACHMENT)) == (1, EXAMPLE_STAMP_NS, TALKER_GID)


@pytest.mark.parametrize(
    "data",
    [
        None,
        b"",
        EXAMPLE_ATTACHMENT[:-1],
        EXAMPLE_ATTACHMENT + b"\x00",
        EXAMPLE_ATTACHMENT[:16] + b"\x08" + EXAMPLE_ATTACHMENT[17:],  # a GID length other than 16
        legacy_attachment(1, 2, TALKER_GID).replace(b"sequence_number", b"sequence_numbex"),
        legacy_attachment(1, 2, TALKER_GID)[:-1],
        bytes(77),
    ],
)
def test_other_attachments_are_rejected(data):
    with pytest.raises(ValueError):
        rz.parse_attachment(data)


def test_a_keep_all_qos_string_carries_the_history_kind():
    """rmw_zenoh writes KEEP_ALL's policy number (2) before the depth's comma."""
    assert rz.qos_string(True, 10, keep_all=True) == "::2,10:,:,:,,"
