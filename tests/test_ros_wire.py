"""The ROS 2 wire format against golden bytes and strings fixed here, not produced by the code under test.

Sources of the literals:
* CDR: the OMG CDR rules (little-endian encapsulation header ``00 01 00 00``, primitives aligned
  to their size counted from the end of that header, strings as uint32 length including the NUL,
  then the bytes and the NUL).
* RIHS01 hashes: published by ROS 2 itself and quoted in public code (``ros2 topic info -v``
  transcripts and golden-hash tables of independent ROS 2 client libraries give the same values
  for geometry_msgs/msg/Twist, TwistStamped and nav_msgs/msg/Odometry as below).
* Keys, tokens, attachment: rmw_zenoh_cpp 0.1.x (Humble) and 0.2.x (Jazzy) sources
  (liveliness_utils.cpp, rmw_publisher_data.cpp, attachment_helpers.cpp, qos.cpp); Humble's
  rmw_zenoh writes the literal ``TypeHashNotSupported`` where Jazzy writes the RIHS01 hash.
  The legacy attachment (Jazzy 0.2.0-0.2.3, Humble 0.1.0-0.1.1) is written out field by field
  from the zenoh-ext rules (string = LEB128 length + UTF-8, int64 = 8 bytes little endian).
* GIDs: XXH3-128 of the empty string is xxHash's published test value
  ``99aa06d3014798d86001c324468d497f`` (canonical, big endian); the token GIDs were computed
  by compiling rmw_zenoh's own ``src/detail/simplified_xxhash3.cpp`` (ros2/rmw_zenoh, rolling,
  2024-10) with a 10-line driver that copies ``low64`` then ``high64`` as ``Entity::Entity``
  in liveliness_utils.cpp does, and printing the 16 bytes.
"""

from __future__ import annotations

import contextlib
import math
import struct
from dataclasses import replace

import numpy as np
import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from common.contracts import ros_wire
from common.contracts.ros_wire import (
    ODOMETRY,
    TWIST,
    TWIST_STAMPED,
    Attachment,
    RosGraph,
    WireError,
)
from common.math.frames import (
    Pose2D,
    clamp_command,
    from_goal_frame,
    quaternion_from_yaw,
    to_goal_frame,
    wrap_angle,
    yaw_from_quaternion,
)
from common.math.turtlebot import firmware_velocity

TWIST_HASH = "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"
TWIST_STAMPED_HASH = "RIHS01_5f0fcd4f81d5d06ad9b4c4c63e3ea51b82d6ae4d0558f1d475229b1121db6f64"
ODOMETRY_HASH = "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0"

# Twist linear.x = 0.1, angular.z = 0.5: header, then six float64 (linear xyz, angular xyz).
TWIST_GOLDEN = "000100009a9999999999b93f" + "00" * 32 + "000000000000e03f"
# TwistStamped, stamp 1 s + 500000000 ns, frame_id "base_footprint", linear.x 0.1, angular.z 0.5:
TWIST_STAMPED_GOLDEN = (
    "00010000"  # encapsulation: CDR little endian, options 0
    "01000000"  # header.stamp.sec      int32  = 1            (offset 0)
    "0065cd1d"  # header.stamp.nanosec  uint32 = 500000000    (offset 4)
    "0f000000"  # header.frame_id length uint32 = 14 chars + NUL (offset 8)
    "626173655f666f6f747072696e7400"  # "base_footprint\0"                         (offsets 12-26)
    "0000000000"  # padding: the next float64 must start at a multiple of 8 (32)
    "9a9999999999b93f"
    "0000000000000000"
    "0000000000000000"  # twist.linear  x y z  (32-55)
    "0000000000000000"
    "0000000000000000"
    "000000000000e03f"  # twist.angular x y z  (56-79)
)


def test_twist_golden_bytes() -> None:
    for distro in ("humble", "jazzy"):
        payload = ros_wire.encode_command(distro, TWIST, 0.1, 0.5)
        assert len(payload) == 52
        assert payload.hex() == TWIST_GOLDEN
        assert ros_wire.decode_command(distro, TWIST, bytes.fromhex(TWIST_GOLDEN)) == (0.1, 0.5)


def test_twist_stamped_golden_bytes() -> None:
    for distro in ("humble", "jazzy"):
        payload = ros_wire.encode_command(
            distro, TWIST_STAMPED, 0.1, 0.5, stamp_ns=1_500_000_000, frame_id="base_footprint"
        )
        assert len(payload) == 4 + 80
        assert payload.hex() == TWIST_STAMPED_GOLDEN
        assert ros_wire.decode_command(distro, TWIST_STAMPED, bytes.fromhex(TWIST_STAMPED_GOLDEN)) == (0.1, 0.5)


def test_type_hashes_are_the_published_ones() -> None:
    assert ros_wire.type_hash("jazzy", TWIST) == TWIST_HASH
    assert ros_wire.type_hash("jazzy", TWIST_STAMPED) == TWIST_STAMPED_HASH
    assert ros_wire.type_hash("jazzy", ODOMETRY) == ODOMETRY_HASH
    # Humble has no type hashes: rmw_zenoh (humble branch) writes a constant instead
    assert ros_wire.type_hash("humble", TWIST) == "TypeHashNotSupported"


def test_rmw_zenoh_data_keys() -> None:
    humble = RosGraph("rmw_zenoh", "humble", 0, "")
    jazzy = RosGraph("rmw_zenoh", "jazzy", 0, "")
    assert humble.data_key("cmd_vel", TWIST) == "0/cmd_vel/geometry_msgs::msg::dds_::Twist_/TypeHashNotSupported"
    assert jazzy.data_key("cmd_vel", TWIST) == f"0/cmd_vel/geometry_msgs::msg::dds_::Twist_/{TWIST_HASH}"
    assert jazzy.data_key("cmd_vel", TWIST_STAMPED) == (
        "0/cmd_vel/geometry_msgs::msg::dds_::TwistStamped_/"
        "RIHS01_5f0fcd4f81d5d06ad9b4c4c63e3ea51b82d6ae4d0558f1d475229b1121db6f64"
    )
    assert jazzy.data_key("odom", ODOMETRY) == f"0/odom/nav_msgs::msg::dds_::Odometry_/{ODOMETRY_HASH}"
    # a namespaced robot on another domain: the namespace is part of the topic name
    assert RosGraph("rmw_zenoh", "jazzy", 7, "tb3_1").data_key("cmd_vel", TWIST) == (
        f"7/tb3_1/cmd_vel/geometry_msgs::msg::dds_::Twist_/{TWIST_HASH}"
    )
    assert jazzy.data_key("odom", ODOMETRY, "*") == "0/odom/nav_msgs::msg::dds_::Odometry_/*"


def test_ros2dds_keys_are_plain_topics() -> None:
    assert RosGraph("ros2dds", "jazzy", 0, "").data_key("cmd_vel", TWIST_STAMPED) == "cmd_vel"
    assert RosGraph("ros2dds", "humble", 3, "tb3_1").data_key("odom", ODOMETRY) == "tb3_1/odom"


def test_rmw_zenoh_liveliness_tokens() -> None:
    zid = "1f2e3d4c5b6a79880f1e2d3c4b5a6978"
    jazzy = RosGraph("rmw_zenoh", "jazzy", 0, "")
    assert jazzy.node_token(zid, 0, "turtlebot3_node") == f"@ros2_lv/0/{zid}/0/0/NN/%/%/turtlebot3_node"
    assert jazzy.endpoint_token(zid, 0, 10, "MS", "turtlebot3_node", "cmd_vel", TWIST_STAMPED) == (
        f"@ros2_lv/0/{zid}/0/10/MS/%/%/turtlebot3_node/%cmd_vel/geometry_msgs::msg::dds_::TwistStamped_/"
        f"{TWIST_STAMPED_HASH}/::,10:,:,:,,"
    )
    humble = RosGraph("rmw_zenoh", "humble", 0, "tb3_1")
    assert humble.node_token(zid, 20, "diff_drive_controller") == (
        f"@ros2_lv/0/{zid}/20/20/NN/%/%tb3_1/diff_drive_controller"
    )
    assert humble.endpoint_token(zid, 20, 21, "MP", "diff_drive_controller", "odom", ODOMETRY) == (
        f"@ros2_lv/0/{zid}/20/21/MP/%/%tb3_1/diff_drive_controller/%tb3_1%odom/nav_msgs::msg::dds_::Odometry_/"
        "TypeHashNotSupported/::,10:,:,:,,"
    )
    # the QoS chunk lists what differs from rmw_zenoh's default (depth 42)
    assert ros_wire.qos_chunk(42) == "::,:,:,:,,"


def test_discovery_parses_the_robot_subscription_only() -> None:
    zid = "aa"
    for graph in (
        RosGraph("rmw_zenoh", "jazzy", 0, ""),
        RosGraph("rmw_zenoh", "humble", 0, "tb3_1"),
        RosGraph("ros2dds", "jazzy", 0, ""),
        RosGraph("ros2dds", "humble", 0, "tb3_1"),
    ):
        for ros_type in (TWIST, TWIST_STAMPED):
            token = graph.endpoint_token(zid, 0, 10, "MS", "turtlebot3_node", "cmd_vel", ros_type)
            parsed = graph.parse_subscription(token, "cmd_vel")
            assert parsed is not None and parsed[0] == ros_type, (graph, token)
            assert graph.parse_subscription(token, "odom") is None
            publisher = graph.endpoint_token(zid, 0, 10, "MP", "turtlebot3_node", "cmd_vel", ros_type)
            assert graph.parse_subscription(publisher, "cmd_vel") is None
            # the liveliness key expression the bridge subscribes to matches the token, not the publisher's
            assert zenoh.KeyExpr(graph.discovery_pattern("cmd_vel")).intersects(zenoh.KeyExpr(token))
            assert not zenoh.KeyExpr(graph.discovery_pattern("cmd_vel")).intersects(zenoh.KeyExpr(publisher))
            assert not zenoh.KeyExpr(graph.discovery_pattern("odom")).intersects(zenoh.KeyExpr(token))
    other_domain = RosGraph("rmw_zenoh", "jazzy", 1, "").endpoint_token(zid, 0, 1, "MS", "n", "cmd_vel", TWIST)
    assert RosGraph("rmw_zenoh", "jazzy", 0, "").parse_subscription(other_domain, "cmd_vel") is None
    assert (
        RosGraph("ros2dds", "jazzy", 0, "")
        .ros2dds_token(zid, "MS", "cmd_vel", TWIST)
        .startswith(f"@/{zid}/@ros2_lv/MS/cmd_vel/geometry_msgs§msg§Twist/:1:0:0,10")
    )


def test_attachment_layout() -> None:
    gid = bytes(range(16))
    expected = (
        "0100000000000000"  # int64 LE sequence number 1
        "15cd853dfe9c9717"  # int64 LE source timestamp 1700000000123456789 ns
        "10"  # the GID as a sequence: LEB128 length 16
        "000102030405060708090a0b0c0d0e0f"  # the 16 GID bytes
    )
    raw = Attachment(1, 1_700_000_000_123_456_789, gid).encode()
    assert len(raw) == 33
    assert raw.hex() == expected
    assert Attachment.decode(bytes.fromhex(expected)) == Attachment(1, 1_700_000_000_123_456_789, gid)
    for bad in (raw[:-1], raw + b"\x00", raw[:16] + b"\x0f" + raw[17:], b""):
        with pytest.raises(WireError):
            Attachment.decode(bad)


LEGACY_GOLDEN = (
    "0f"
    "73657175656e63655f6e756d626572"  # "sequence_number": LEB128 length 15, UTF-8
    "0100000000000000"  # int64 LE 1
    "10"
    "736f757263655f74696d657374616d70"  # "source_timestamp": length 16
    "15cd853dfe9c9717"  # int64 LE 1700000000123456789
    "0a"
    "736f757263655f676964"  # "source_gid": length 10
    "10"
    "000102030405060708090a0b0c0d0e0f"  # the GID: LEB128 length 16, 16 bytes
)


def test_legacy_attachment_layout() -> None:
    gid = bytes(range(16))
    raw = Attachment(1, 1_700_000_000_123_456_789, gid, "legacy").encode()
    assert len(raw) == 77
    assert raw.hex() == LEGACY_GOLDEN
    decoded = Attachment.decode(bytes.fromhex(LEGACY_GOLDEN))
    assert decoded == Attachment(1, 1_700_000_000_123_456_789, gid, "legacy")
    # the compact golden bytes decode as compact: the format is read from the bytes
    compact = Attachment(1, 1_700_000_000_123_456_789, gid).encode()
    assert Attachment.decode(compact).format == "compact"
    renamed = raw.replace(b"source_gid", b"source_gix")
    for bad in (raw[:-1], raw + b"\x00", renamed, raw[:40], raw.replace(b"\x10\x00\x01", b"\x0f\x00\x01")):
        with pytest.raises(WireError):
            Attachment.decode(bad)


def test_huge_length_prefixes_are_wire_errors_not_panics() -> None:
    """zenoh.ext.z_deserialize panics (pyo3 PanicException, "capacity overflow") on these: the
    decoder must parse them itself and refuse them like any other bad attachment."""
    for bad in (
        bytes(16) + b"\xff" * 9 + b"\x01" + bytes(7),  # compact, 33 bytes
        bytes(16) + b"\xff\xff\xff\xff\x0f" + bytes(12),
        bytes.fromhex(LEGACY_GOLDEN)[:16] + b"\xff" * 9 + b"\x01" + bytes(60),
        b"\x0fsequence_number" + bytes(8) + b"\xff" * 12,
    ):
        with pytest.raises(WireError):
            Attachment.decode(bad)


# (token, GID bytes as rmw_zenoh's Entity stores them) -- see the module docstring
GID_GOLDEN = [
    ("", "7f498d4624c30160d8984701d306aa99"),  # = reversed 99aa06d3014798d86001c324468d497f
    ("a", "1f4e961eb632c6e63468f15a70af6fa9"),
    (
        "@ros2_lv/0/1f2e3d4c5b6a79880f1e2d3c4b5a6978/0/2/MP/%/%/srl_robot_bridge/%cmd_vel/"
        "geometry_msgs::msg::dds_::TwistStamped_/"
        "RIHS01_5f0fcd4f81d5d06ad9b4c4c63e3ea51b82d6ae4d0558f1d475229b1121db6f64/::,10:,:,:,,",
        "9a292280a901961f7f29611bd4126c6d",
    ),
    (
        "@ros2_lv/0/1f2e3d4c5b6a79880f1e2d3c4b5a6978/20/21/MP/%/%tb3_1/diff_drive_controller/%tb3_1%odom/"
        "nav_msgs::msg::dds_::Odometry_/TypeHashNotSupported/::,10:,:,:,,",
        "aa15e9768bae822ea3883b84252975a2",
    ),
]


@pytest.mark.parametrize(("token", "gid"), GID_GOLDEN)
def test_gid_is_rmw_zenohs_xxh3_128(token: str, gid: str) -> None:
    assert ros_wire.gid_for(token).hex() == gid


def test_gid_of_the_bridges_own_publisher_token() -> None:
    zid = "1f2e3d4c5b6a79880f1e2d3c4b5a6978"
    token = RosGraph("rmw_zenoh", "jazzy", 0, "").endpoint_token(
        zid, 0, 2, "MP", ros_wire.BRIDGE_NODE, "cmd_vel", TWIST_STAMPED
    )
    assert token == GID_GOLDEN[2][0]  # the token the bridge declares is the one hashed above
    assert ros_wire.gid_for(token).hex() == GID_GOLDEN[2][1]


def _cdr_string(text: str, offset: int) -> tuple[bytes, int]:
    """A CDR string at ``offset`` (counted after the 4-byte header): uint32 length with NUL, bytes."""
    pad = b"\x00" * (-offset % 4)
    body = struct.pack("<I", len(text) + 1) + text.encode() + b"\x00"
    return pad + body, offset + len(pad) + len(body)


def _hand_built_odometry(x: float, y: float, yaw: float, v: float, omega: float) -> bytes:
    """nav_msgs/msg/Odometry packed field by field with struct, as the CDR rules say (the oracle)."""
    out = b"\x00\x01\x00\x00" + struct.pack("<iI", 12, 345)  # header.stamp 12 s 345 ns
    offset = 8
    frame, offset = _cdr_string("odom", offset)
    child, offset = _cdr_string("base_footprint", offset)
    out += frame + child
    pad = b"\x00" * (-offset % 8)
    qz, qw = math.sin(yaw / 2), math.cos(yaw / 2)
    doubles = [x, y, 0.0, 0.0, 0.0, qz, qw, *[0.0] * 36, v, 0.0, 0.0, 0.0, 0.0, omega, *[0.0] * 36]
    return out + pad + struct.pack(f"<{len(doubles)}d", *doubles)


def test_odometry_decodes_a_hand_built_sample() -> None:
    raw = _hand_built_odometry(1.25, -0.5, 2.0, 0.2, -1.5)
    # header 4 | stamp 8 | "odom" 4+5, pad 3 | "base_footprint" 4+15, pad 1 | 85 float64
    assert len(raw) == 4 + 8 + (4 + 5) + 3 + (4 + 15) + 1 + (7 + 36 + 6 + 36) * 8
    for distro in ("humble", "jazzy"):
        odom = ros_wire.decode_odometry(distro, raw)
        assert odom.stamp_ns == 12_000_000_345
        assert (odom.frame_id, odom.child_frame_id) == ("odom", "base_footprint")
        assert (odom.x, odom.y, odom.v, odom.omega) == (1.25, -0.5, 0.2, -1.5)
        assert yaw_from_quaternion(*odom.orientation) == pytest.approx(2.0, abs=1e-12)
        # and the encoder writes exactly these bytes back
        assert ros_wire.encode_odometry(distro, odom) == raw


def test_wrong_type_and_garbage_are_wire_errors() -> None:
    twist = bytes.fromhex(TWIST_GOLDEN)
    stamped = bytes.fromhex(TWIST_STAMPED_GOLDEN)
    with pytest.raises(WireError):
        ros_wire.decode_command("jazzy", TWIST, stamped)  # 32 bytes too long for a Twist
    with pytest.raises(WireError):
        ros_wire.decode_command("jazzy", TWIST_STAMPED, twist)
    for garbage in (b"", b"\x00\x01", b"\x01\x00\x00\x00" + twist[4:], twist, b"\xff" * 1000):
        with pytest.raises(WireError):
            ros_wire.decode_odometry("jazzy", garbage)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=900))
def test_decoders_raise_only_wire_errors(data: bytes) -> None:
    for decode in (
        lambda b: ros_wire.decode_odometry("jazzy", b),
        lambda b: ros_wire.decode_command("humble", TWIST, b),
        lambda b: ros_wire.decode_command("jazzy", TWIST_STAMPED, b),
        Attachment.decode,
    ):
        with contextlib.suppress(WireError):  # anything else fails the test
            decode(data)


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 76), st.integers(0, 255), st.binary(max_size=80))
def test_corrupted_legacy_attachments_raise_only_wire_errors(index: int, value: int, tail: bytes) -> None:
    raw = bytearray.fromhex(LEGACY_GOLDEN)
    raw[index] = value
    for candidate in (bytes(raw), bytes.fromhex(LEGACY_GOLDEN)[:index] + tail):
        with contextlib.suppress(WireError):  # anything else fails the test
            Attachment.decode(candidate)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 900), st.integers(0, 255))
def test_corrupted_odometry_raises_only_wire_errors(index: int, value: int) -> None:
    raw = bytearray(_hand_built_odometry(0.5, 0.5, 0.3, 0.1, 0.1))
    raw[index % len(raw)] = value
    with contextlib.suppress(WireError):  # anything else fails the test
        ros_wire.decode_odometry("jazzy", bytes(raw))


def test_commands_refuse_nan() -> None:
    for value in (math.nan, math.inf):
        with pytest.raises(ValueError):
            ros_wire.encode_command("jazzy", TWIST, value, 0.0)
        with pytest.raises(ValueError):
            clamp_command(0.0, value, 0.22, 2.84)


# -- the planar math --------------------------------------------------------------------------
@settings(max_examples=200, deadline=None)
@given(st.floats(-10, 10), st.floats(-1.5, 1.5), st.floats(-1.5, 1.5), st.floats(0.5, 2.0))
def test_yaw_from_quaternion_matches_scipy(yaw: float, pitch: float, roll: float, scale: float) -> None:
    qx, qy, qz, qw = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_quat()
    expected = Rotation.from_quat([qx, qy, qz, qw]).as_euler("ZYX")[0]
    # a quaternion off unit length gives the same yaw
    got = yaw_from_quaternion(qx * scale, qy * scale, qz * scale, qw * scale)
    assert math.isclose(got, expected, abs_tol=1e-9) or abs(abs(got - expected) - 2 * math.pi) < 1e-9


def test_yaw_from_quaternion_cases() -> None:
    assert yaw_from_quaternion(0.0, 0.0, 0.0, 1.0) == 0.0
    assert yaw_from_quaternion(0.0, 0.0, 1.0, 0.0) == pytest.approx(math.pi)
    assert yaw_from_quaternion(*quaternion_from_yaw(-2.5)) == pytest.approx(-2.5)
    for bad in ((0.0, 0.0, 0.0, 0.0), (math.nan, 0.0, 0.0, 1.0), (0.0, 0.0, math.inf, 1.0)):
        with pytest.raises(ValueError):
            yaw_from_quaternion(*bad)


@settings(max_examples=200, deadline=None)
@given(
    st.tuples(st.floats(-5, 5), st.floats(-5, 5), st.floats(-7, 7)),
    st.tuples(st.floats(-5, 5), st.floats(-5, 5), st.floats(-7, 7)),
)
def test_goal_frame_transform_matches_homogeneous_matrices(pose: tuple, goal: tuple) -> None:
    def matrix(p: tuple) -> np.ndarray:
        c, s = math.cos(p[2]), math.sin(p[2])
        return np.array([[c, -s, p[0]], [s, c, p[1]], [0, 0, 1]])

    relative = np.linalg.inv(matrix(goal)) @ matrix(pose)  # the pose seen from the goal frame
    got = to_goal_frame(Pose2D(*pose), Pose2D(*goal))
    np.testing.assert_allclose([got.x, got.y], relative[:2, 2], atol=1e-9)
    assert got.theta == pytest.approx(pose[2] - goal[2])
    assert (
        wrap_angle(got.theta) == pytest.approx(wrap_angle(math.atan2(relative[1, 0], relative[0, 0])), abs=1e-9)
        or abs(abs(wrap_angle(got.theta)) - math.pi) < 1e-9
    )
    back = from_goal_frame(got, Pose2D(*goal))
    np.testing.assert_allclose(back, pose, atol=1e-9)


def test_goal_frame_example() -> None:
    # goal at (1, 1) facing +y: a robot at (1, 3) facing +y is 2 m ahead of it, heading 0
    state = to_goal_frame(Pose2D(1.0, 3.0, math.pi / 2), Pose2D(1.0, 1.0, math.pi / 2))
    np.testing.assert_allclose(state, (2.0, 0.0, 0.0), atol=1e-12)


def test_clamp_command() -> None:
    assert clamp_command(0.5, -5.0, 0.22, 2.84) == (0.22, -2.84)
    assert clamp_command(-0.1, 1.0, 0.22, 2.84) == (-0.1, 1.0)


# -- the TurtleBot3 firmware's velocity path ---------------------------------------------------
@pytest.mark.parametrize(
    ("command", "limit", "applied"),
    [
        (0.1, 0.22, 0.1),  # int32(10.000000000000002) = 10 -> 10 * 0.01f
        (0.219, 0.22, 0.21),  # truncated, not rounded
        (0.2199999, 0.22, 0.21),
        (0.009, 0.22, 0.0),  # below the 0.01 resolution: zero
        (-0.019, 0.22, -0.01),  # toward zero for negative values too
        (0.3, 0.22, 0.22),  # then constrained to the limit
        (-5.0, 2.84, -2.84),
        (2.849, 2.84, 2.84),
        (0.29, 2.84, 0.28),  # 0.29 * 100 = 28.999999999999996 in binary floating point
        (math.nan, 0.22, 0.0),  # ARM's float->int conversion: NaN -> 0
        (1e300, 0.22, 0.22),  # saturates at INT32_MAX, then the limit
    ],
)
def test_firmware_truncation(command: float, limit: float, applied: float) -> None:
    # applied within float32 resolution (the firmware multiplies in float32)
    assert firmware_velocity(command, limit) == pytest.approx(applied, abs=1e-7)
    if abs(applied) < limit:  # not limited: exactly the float32 count of 0.01 steps
        assert firmware_velocity(command, limit) == float(np.float32(round(applied * 100)) * np.float32(0.01))


@pytest.mark.parametrize("fmt", ["compact", "legacy"])
def test_attachment_encoding_is_zenoh_exts_serialization(fmt: str) -> None:
    """common/contracts/ros_wire.py writes the zenoh-ext serialization itself (common never imports zenoh
    outside common/net/transport.py): byte for byte what zenoh.ext.z_serialize writes."""
    import random

    import zenoh.ext

    from common.contracts.ros_wire import LEGACY_FIELDS

    rng = random.Random(7)
    for _ in range(100):
        attachment = Attachment(
            rng.randint(-(2**63), 2**63 - 1),
            rng.randint(-(2**63), 2**63 - 1),
            bytes(rng.randrange(256) for _ in range(16)),
            fmt,
        )
        seq, stamp = zenoh.ext.Int64(attachment.seq), zenoh.ext.Int64(attachment.stamp_ns)
        fields = (
            (LEGACY_FIELDS[0], seq, LEGACY_FIELDS[1], stamp, LEGACY_FIELDS[2], attachment.gid)
            if fmt == "legacy"
            else (seq, stamp, attachment.gid)
        )
        assert attachment.encode() == bytes(zenoh.ext.z_serialize(fields).to_bytes())
        assert Attachment.decode(attachment.encode()) == attachment


# -- localization messages (docs/turtlebot-localization.md) --------------------------------------
# RIHS01 hashes of the localization types as ROS 2 Jazzy publishes them (``ros2 topic info -v``
# transcripts of AMCL's /tf and golden-hash tables of independent ROS 2 client libraries agree).
POSE_WITH_COVARIANCE_HASH = "RIHS01_26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e"
POSE_STAMPED_HASH = "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8"
TF_MESSAGE_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"


def test_localization_type_hashes_are_the_published_ones() -> None:
    assert ros_wire.type_hash("jazzy", ros_wire.POSE_WITH_COVARIANCE) == POSE_WITH_COVARIANCE_HASH
    assert ros_wire.type_hash("jazzy", ros_wire.POSE_STAMPED) == POSE_STAMPED_HASH
    assert ros_wire.type_hash("jazzy", ros_wire.TF_MESSAGE) == TF_MESSAGE_HASH


def _hand_built_pose(x: float, y: float, yaw: float, covariance: list[float] | None) -> bytes:
    """PoseStamped (``covariance`` None) or PoseWithCovarianceStamped packed field by field with
    struct, as the CDR rules say: header (stamp 12 s 345 ns, frame "map"), position, orientation."""
    out = b"\x00\x01\x00\x00" + struct.pack("<iI", 12, 345)
    frame, offset = _cdr_string("map", 8)
    out += frame + b"\x00" * (-offset % 8)
    doubles = [x, y, 0.0, 0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2), *(covariance or [])]
    return out + struct.pack(f"<{len(doubles)}d", *doubles)


def test_pose_messages_golden_bytes() -> None:
    covariance = [0.0] * 36
    covariance[0], covariance[7], covariance[35] = 0.04, 0.09, 0.01
    fix = ros_wire.PoseFix(12_000_000_345, "map", "", 1.25, -0.5, quaternion_from_yaw(2.0), (0.04, 0.09, 0.01))
    for distro in ("humble", "jazzy"):
        for ros_type, cov in ((ros_wire.POSE_WITH_COVARIANCE, covariance), (ros_wire.POSE_STAMPED, None)):
            raw = _hand_built_pose(1.25, -0.5, 2.0, cov)
            # header 4 | stamp 8 | "map" 4+4 (ends at offset 16: aligned, no pad) | 7 (+ 36) float64
            assert len(raw) == 4 + 8 + (4 + 4) + (7 + (36 if cov else 0)) * 8
            assert ros_wire.encode_pose(distro, ros_type, fix if cov else replace(fix, variance=(0, 0, 0))) == raw
            [decoded] = ros_wire.decode_localization(distro, ros_type, raw)
            assert (decoded.stamp_ns, decoded.frame_id, decoded.x, decoded.y) == (12_000_000_345, "map", 1.25, -0.5)
            assert yaw_from_quaternion(*decoded.orientation) == pytest.approx(2.0, abs=1e-12)
            assert decoded.variance == ((0.04, 0.09, 0.01) if cov else (0.0, 0.0, 0.0))


def test_tf_message_golden_bytes() -> None:
    """tf2_msgs/msg/TFMessage with one map -> odom transform: sequence length, then a
    TransformStamped (header, child_frame_id, translation xyz, rotation xyzw)."""
    out = b"\x00\x01\x00\x00" + struct.pack("<I", 1) + struct.pack("<iI", 7, 5)  # 1 transform, stamp 7 s 5 ns
    frame, offset = _cdr_string("map", 12)
    child, offset = _cdr_string("odom", offset)
    out += frame + child + b"\x00" * (-offset % 8)
    raw = out + struct.pack("<7d", 0.5, -2.0, 0.0, 0.0, 0.0, math.sin(0.25), math.cos(0.25))
    transform = ros_wire.PoseFix(7_000_000_005, "map", "odom", 0.5, -2.0, quaternion_from_yaw(0.5))
    for distro in ("humble", "jazzy"):
        assert ros_wire.encode_tf(distro, [transform]) == raw
        assert ros_wire.decode_localization(distro, ros_wire.TF_MESSAGE, raw) == [transform]
    assert ros_wire.decode_localization("jazzy", ros_wire.TF_MESSAGE, ros_wire.encode_tf("jazzy", [])) == []


def test_amcl_pose_tokens_are_transient_local() -> None:
    """nav2_amcl's amcl_pose publisher (KeepLast(1), reliable, transient local): durability 1
    (RMW_QOS_POLICY_DURABILITY_TRANSIENT_LOCAL) and depth 1 in the QoS chunk; tf's listener KeepLast(100)."""
    zid = "1f2e3d4c5b6a79880f1e2d3c4b5a6978"
    jazzy = RosGraph("rmw_zenoh", "jazzy", 0, "")
    source = ros_wire.POSE_SOURCES["pose_with_covariance"]
    qos = ros_wire.qos_chunk(source.depth, source.transient_local)
    assert qos == ":1:,1:,:,:,,"
    assert jazzy.endpoint_token(zid, 30, 31, "MP", "amcl", "amcl_pose", source.ros_type, qos=qos) == (
        f"@ros2_lv/0/{zid}/30/31/MP/%/%/amcl/%amcl_pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/"
        f"{POSE_WITH_COVARIANCE_HASH}/:1:,1:,:,:,,"
    )
    assert ros_wire.qos_chunk(100) == "::,100:,:,:,,"
    assert jazzy.data_key("tf", ros_wire.TF_MESSAGE) == f"0/tf/tf2_msgs::msg::dds_::TFMessage_/{TF_MESSAGE_HASH}"


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=900))
def test_localization_decoders_raise_only_wire_errors(data: bytes) -> None:
    for ros_type in (ros_wire.POSE_WITH_COVARIANCE, ros_wire.POSE_STAMPED, ros_wire.TF_MESSAGE, ODOMETRY):
        with contextlib.suppress(WireError):  # anything else fails the test
            ros_wire.decode_localization("jazzy", ros_type, data)
