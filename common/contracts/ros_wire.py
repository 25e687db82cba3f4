"""The ROS 2 wire over Zenoh: every ROS key expression and token of srl, and the only place one is written.

srl's own keys live in ``common/contracts/keys.py``; this module holds what a ROS 2 robot sees. Two wire
profiles (docs/robot.md):

``rmw_zenoh`` -- a robot running ``RMW_IMPLEMENTATION=rmw_zenoh_cpp`` (read from the
rmw_zenoh_cpp sources, 0.1.x for Humble and 0.2.x for Jazzy, ``src/detail/liveliness_utils.cpp``,
``rmw_publisher_data.cpp``, ``rmw_subscription_data.cpp``, ``attachment_helpers.cpp``):

* data key ``<domain>/<topic without leading slash>/<dds type>/<type hash>``, e.g.
  ``0/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_9c45...8d2a`` (namespace included in the
  topic: ``0/tb3_1/cmd_vel/...``). The dds type is ``<pkg>::msg::dds_::<Name>_``.
* type hash: Jazzy writes the RIHS01 hash of the type description; **Humble has no type hashes
  and rmw_zenoh writes the constant ``TypeHashNotSupported``** in the key and the tokens.
* every sample carries an attachment, zenoh-ext serialized, in one of two formats
  (``attachment_helpers.cpp``, ``AttachmentData``):

  - ``compact`` (33 bytes; rmw_zenoh_cpp Jazzy >= 0.2.4, Humble >= 0.1.2, Kilted, Lyrical and
    Rolling >= 0.6.0: "Change serialization format in attachment_helpers.cpp", ros2/rmw_zenoh#601,
    backported as #605 to Jazzy and #606 to Humble): int64 sequence number (from 1), int64
    source timestamp (system clock, ns), the 16-byte GID as a sequence (one LEB128 length byte
    ``0x10``, then 16 bytes);
  - ``legacy`` (77 bytes; Jazzy 0.2.0-0.2.3, Humble 0.1.0-0.1.1): each field preceded by its
    name as a zenoh-ext string (LEB128 length, UTF-8): ``"sequence_number"``, int64,
    ``"source_timestamp"``, int64, ``"source_gid"``, the GID as above. The deserializer of that
    release throws ``std::runtime_error`` when a name does not match, inside the Zenoh callback
    and uncaught: a compact attachment can abort a legacy robot's process, and a legacy one
    is garbage to a compact reader. So the bridge speaks the format the robot's own odometry
    carries and sends nothing on ``cmd_vel`` before it knows it (services/robot_bridge/ros_link.py).

  A subscriber drops samples without an attachment ("Unable to obtain attachment").
* the GID of an entity (``Entity::Entity`` in ``liveliness_utils.cpp``) is XXH3-128 (seed 0,
  ``simplified_xxhash3.cpp``, the reference algorithm without its speed-ups) of the entity's
  full liveliness token, stored as the low 64 bits then the high 64 bits, each in the host's
  byte order (little endian on x86-64 and ARM64): :func:`gid_for`.
* liveliness tokens, the ROS graph (the same shape on Humble and Jazzy):
  ``@ros2_lv/<domain>/<zid>/<nid>/<eid>/<NN|MP|MS|SS|SC>/<enclave>/<namespace>/<node>``
  and, for publishers and subscriptions, ``/<topic>/<dds type>/<type hash>/<qos>``. Names are
  mangled ``/`` -> ``%`` (root namespace ``/`` -> ``%``). The QoS chunk lists only what differs
  from rmw_zenoh's default (reliable, volatile, keep last 42, infinite deadline, lifespan and
  lease): ``<rel>:<dur>:<hist>,<depth>:<dl s>,<dl ns>:<ls s>,<ls ns>:<lv>,<lease s>,<lease ns>``,
  so the TurtleBot3's ``KeepLast(10)`` is ``::,10:,:,:,,``.

``ros2dds`` -- a DDS robot behind ``zenoh-bridge-ros2dds``: the key is the topic itself
(``cmd_vel``, or ``<namespace>/cmd_vel``), raw CDR, no attachment. The bridge announces the
robot's endpoints as ``@/<bridge zid>/@ros2_lv/<MP|MS>/<key, / -> §>/<ROS type, / -> §>/<qos>``.

CDR and RIHS01 hashes come from ``rosbags`` (its typestores for Humble and Jazzy), never from
hand-written packing.
"""

from __future__ import annotations

import functools
import math
import re
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import xxhash
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_typestore

from common.contracts.pose_sources import (  # the localization sources' table and the types it names
    ODOMETRY as ODOMETRY,
)
from common.contracts.pose_sources import (
    ODOMETRY_ONLY as ODOMETRY_ONLY,
)
from common.contracts.pose_sources import (
    POSE_SOURCES as POSE_SOURCES,
)
from common.contracts.pose_sources import (
    POSE_STAMPED as POSE_STAMPED,
)
from common.contracts.pose_sources import (
    POSE_WITH_COVARIANCE as POSE_WITH_COVARIANCE,
)
from common.contracts.pose_sources import (
    QOS_DEPTH as QOS_DEPTH,
)
from common.contracts.pose_sources import (
    TF_MESSAGE as TF_MESSAGE,
)
from common.contracts.pose_sources import (
    PoseSource as PoseSource,
)

Distro = Literal["humble", "jazzy"]
Profile = Literal["rmw_zenoh", "ros2dds"]

TWIST = "geometry_msgs/msg/Twist"
TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"
CMD_TYPES = {"twist": TWIST, "twist_stamped": TWIST_STAMPED}
# What a TurtleBot3 subscribes to by default: turtlebot3_bringup's burger.yaml sets
# enable_stamped_cmd_vel false on Humble and true on Jazzy.
DEFAULT_CMD_TYPE: dict[str, str] = {"humble": TWIST, "jazzy": TWIST_STAMPED}
HASH_NOT_SUPPORTED = "TypeHashNotSupported"

# TurtleBot3 Burger (ROBOTIS e-Manual); the bridge never commands more.
TB3_BURGER_V_MAX = 0.22
TB3_BURGER_OMEGA_MAX = 2.84
TB3_CMD_NODE = "turtlebot3_node"  # subscribes cmd_vel
TB3_ODOM_NODE = "diff_drive_controller"  # publishes odom
ODOM_FRAME = "odom"
BASE_FRAME = "base_footprint"
BRIDGE_NODE = "srl_robot_bridge"

ATTACHMENT_SIZE = 33  # the compact format
GID_SIZE = 16
AttachmentFormat = Literal["compact", "legacy"]
ATTACHMENT_FORMATS: tuple[AttachmentFormat, ...] = ("compact", "legacy")
LEGACY_FIELDS = ("sequence_number", "source_timestamp", "source_gid")
# What the docs (docs/robot.md) and every refusal name: the rmw_zenoh_cpp releases whose wire srl speaks.
SUPPORTED_RMW_ZENOH = (
    "rmw_zenoh_cpp Humble 0.1.0-0.1.1 and Jazzy 0.2.0-0.2.3 (legacy attachment), "
    "Humble >= 0.1.2, Jazzy >= 0.2.4, Kilted, Lyrical and Rolling >= 0.6.0 (compact attachment)"
)
ADMIN = "@ros2_lv"
_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*$")
_STORES = {"humble": Stores.ROS2_HUMBLE, "jazzy": Stores.ROS2_JAZZY}
DECODE_ERRORS = (SerdeError, ValueError, IndexError, TypeError, UnicodeDecodeError)

MAP_FRAME = "map"


def pose_topic(bridge: Any) -> str:
    """The localization topic of ``bridge`` settings: ``pose_topic``, or the source's usual one."""
    if bridge.pose_source == ODOMETRY_ONLY:
        return str(bridge.odom_topic)
    return str(bridge.pose_topic or POSE_SOURCES[bridge.pose_source].topic)


class WireError(ValueError):
    """A sample that is not a valid message of the expected ROS type (or attachment)."""


# -- types and hashes -------------------------------------------------------------------------
@functools.cache
def typestore(distro: str) -> Any:
    return get_typestore(_STORES[distro])


@functools.cache  # rosbags computes the hash from the type description: ~1 ms per call
def type_hash(distro: str, ros_type: str) -> str:
    """The hash chunk rmw_zenoh writes: ``TypeHashNotSupported`` on Humble, RIHS01 on Jazzy."""
    if distro == "humble":
        return HASH_NOT_SUPPORTED
    return str(typestore(distro).hash_rihs01(ros_type))


def dds_type_name(ros_type: str) -> str:
    """``geometry_msgs/msg/Twist`` -> ``geometry_msgs::msg::dds_::Twist_`` (rmw_zenoh's type name)."""
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def ros_type_from_dds(name: str) -> str | None:
    match = re.fullmatch(r"([A-Za-z0-9_]+)::(msg|srv|action)::dds_::([A-Za-z0-9_]+)_", name)
    return f"{match[1]}/{match[2]}/{match[3]}" if match else None


def mangle(name: str) -> str:
    """rmw_zenoh's token mangling: every ``/`` becomes ``%``."""
    return name.replace("/", "%")


def escape_ros2dds(name: str) -> str:
    """zenoh-bridge-ros2dds's token escaping: every ``/`` becomes ``§``."""
    return name.replace("/", "§")


def qos_chunk(depth: int = QOS_DEPTH, transient_local: bool = False) -> str:
    """rmw_zenoh QoS chunk of a reliable, keep-last ``depth`` endpoint, volatile or transient local
    (``qos_to_keyexpr`` in liveliness_utils.cpp writes the rmw enum values that differ from the
    default; RMW_QOS_POLICY_DURABILITY_TRANSIENT_LOCAL is 1)."""
    return f":{'1' if transient_local else ''}:,{'' if depth == 42 else depth}:,:,:,,"


@dataclass(frozen=True)
class CmdEndpoint:
    """Where commands must go: the ROS type the robot subscribes and the Zenoh key to put to."""

    ros_type: str
    key: str
    type_hash: str


@dataclass(frozen=True)
class RosGraph:
    """One robot's ROS 2 graph as seen through one wire profile."""

    profile: str
    distro: str
    domain_id: int
    namespace: str  # "" or "tb3_1" (no leading slash)

    def __post_init__(self) -> None:
        if self.profile not in ("rmw_zenoh", "ros2dds") or self.distro not in _STORES:
            raise ValueError(f"unknown profile {self.profile!r} or distro {self.distro!r}")
        if self.namespace and not _NAME.match(self.namespace):
            raise ValueError(f"namespace {self.namespace!r} is not a ROS name")

    @classmethod
    def from_settings(cls, bridge: Any, distro: str | None = None) -> RosGraph:
        return cls(bridge.profile, distro or bridge.ros_distro, bridge.domain_id, bridge.namespace)

    # -- names ------------------------------------------------------------------------------
    def topic_name(self, topic: str) -> str:
        """Fully qualified ROS name: ``/cmd_vel`` or ``/tb3_1/cmd_vel``."""
        if not _NAME.match(topic):
            raise ValueError(f"topic {topic!r} is not a relative ROS name")
        return f"/{self.namespace}/{topic}" if self.namespace else f"/{topic}"

    def node_namespace(self) -> str:
        return f"/{self.namespace}" if self.namespace else "/"

    def frame_id(self, frame: str) -> str:
        """TurtleBot3 prefixes its frame ids with the namespace (``tb3_1/odom``)."""
        return f"{self.namespace}/{frame}" if self.namespace else frame

    # -- data keys --------------------------------------------------------------------------
    def data_key(self, topic: str, ros_type: str, hash_chunk: str | None = None) -> str:
        """The key samples of ``topic`` travel on (``hash_chunk`` '*' for a subscription to any)."""
        name = self.topic_name(topic)[1:]
        if self.profile == "ros2dds":
            return name
        chunk = type_hash(self.distro, ros_type) if hash_chunk is None else hash_chunk
        return f"{self.domain_id}/{name}/{dds_type_name(ros_type)}/{chunk}"

    def cmd_endpoint(self, topic: str, ros_type: str, hash_chunk: str | None = None) -> CmdEndpoint:
        chunk = type_hash(self.distro, ros_type) if hash_chunk is None else hash_chunk
        return CmdEndpoint(ros_type, self.data_key(topic, ros_type, chunk), chunk)

    def hash_chunk_of(self, key: str) -> str:
        """The type-hash chunk of an rmw_zenoh data key ('' under ros2dds)."""
        return key.rsplit("/", 1)[-1] if self.profile == "rmw_zenoh" else ""

    def accepts_hash(self, ros_type: str, chunk: str) -> bool:
        """A sample of ``ros_type`` from a Humble or Jazzy robot (identical CDR for our types)."""
        return chunk in (HASH_NOT_SUPPORTED, type_hash("jazzy", ros_type))

    # -- liveliness tokens ------------------------------------------------------------------
    def node_token(self, zid: str, nid: int, node: str) -> str:
        return f"{ADMIN}/{self.domain_id}/{zid}/{nid}/{nid}/NN/%/{mangle(self.node_namespace())}/{node}"

    def endpoint_token(
        self,
        zid: str,
        nid: int,
        eid: int,
        kind: Literal["MP", "MS"],
        node: str,
        topic: str,
        ros_type: str,
        hash_chunk: str | None = None,
        qos: str | None = None,
    ) -> str:
        """rmw_zenoh token of a publisher (MP) or subscription (MS) of ``node`` (``qos``: its
        :func:`qos_chunk`, default the TurtleBot3's KeepLast(10), reliable, volatile)."""
        if self.profile == "ros2dds":
            return self.ros2dds_token(zid, kind, topic, ros_type)
        chunk = type_hash(self.distro, ros_type) if hash_chunk is None else hash_chunk
        return (
            f"{ADMIN}/{self.domain_id}/{zid}/{nid}/{eid}/{kind}/%/{mangle(self.node_namespace())}/{node}/"
            f"{mangle(self.topic_name(topic))}/{dds_type_name(ros_type)}/{chunk}/{qos or qos_chunk()}"
        )

    def ros2dds_token(self, zid: str, kind: Literal["MP", "MS"], topic: str, ros_type: str) -> str:
        """What zenoh-bridge-ros2dds declares for a DDS endpoint it routes (keyless, reliable,
        volatile, keep last 10; since Iron the DDS user data with the type hash follows)."""
        qos = f":1:0:0,{QOS_DEPTH}"
        if self.distro != "humble":
            qos += f":typehash={type_hash(self.distro, ros_type)};"
        return f"@/{zid}/{ADMIN}/{kind}/{escape_ros2dds(self.topic_name(topic)[1:])}/{escape_ros2dds(ros_type)}/{qos}"

    def ros2dds_plugin_token(self, zid: str) -> str:
        return f"@/{zid}/{ADMIN}"

    def discovery_pattern(self, topic: str) -> str:
        """Liveliness key expression that matches the robot's subscriptions of ``topic``."""
        if self.profile == "ros2dds":
            return f"@/*/{ADMIN}/MS/{escape_ros2dds(self.topic_name(topic)[1:])}/**"
        # <zid>/<nid>/<eid>/MS/<enclave>/<namespace>/<node>/<topic>/<type>/<hash>/<qos>
        return f"{ADMIN}/{self.domain_id}/*/*/*/MS/*/*/*/{mangle(self.topic_name(topic))}/**"

    def parse_subscription(self, token: str, topic: str) -> tuple[str, str] | None:
        """``(ROS type, hash chunk)`` of a subscription token of ``topic``; None for any other token."""
        parts = token.split("/")
        if self.profile == "ros2dds":
            want = escape_ros2dds(self.topic_name(topic)[1:])
            if len(parts) < 7 or parts[0] != "@" or parts[2] != ADMIN or parts[3] != "MS" or parts[4] != want:
                return None
            return parts[5].replace("§", "/"), ""
        if len(parts) != 13 or parts[0] != ADMIN or parts[1] != str(self.domain_id) or parts[5] != "MS":
            return None
        if parts[9] != mangle(self.topic_name(topic)):
            return None
        ros_type = ros_type_from_dds(parts[10])
        return (ros_type, parts[11]) if ros_type else None


def gid_for(token: str) -> bytes:
    """The 16-byte GID rmw_zenoh gives the entity of liveliness token ``token``.

    rmw_zenoh_cpp ``src/detail/liveliness_utils.cpp``, ``Entity::Entity``: ``simplified_XXH3_128bits``
    of the whole token string, then ``memcpy(gid_, &low64, 8)``, ``memcpy(gid_ + 8, &high64, 8)``
    (host order, little endian). That is the 128-bit value in little-endian byte order: the
    reverse of xxHash's canonical (big-endian) digest. So ``ros2 topic info -v`` and a subscriber's
    ``publisher_gid`` show the same GID for the bridge's publisher."""
    return xxhash.xxh3_128(token.encode()).intdigest().to_bytes(GID_SIZE, "little")


# -- the rmw_zenoh attachment -----------------------------------------------------------------
# zenoh-ext serialization, written here (no zenoh import in common/ but common/net/transport.py):
# an int64 is its 8 little-endian bytes; a string or a byte sequence is its length as LEB128
# then its bytes; a tuple is its fields one after the other (tests/test_ros_wire.py holds these
# bytes equal to zenoh.ext.z_serialize's and to golden attachments).
def _int64(value: int) -> bytes:
    return int(value).to_bytes(8, "little", signed=True)


def _sequence(data: bytes) -> bytes:
    length, prefix = len(data), bytearray()
    while True:
        byte, length = length & 0x7F, length >> 7
        prefix.append(byte | (0x80 if length else 0))
        if not length:
            return bytes(prefix) + data


@dataclass(frozen=True)
class Attachment:
    seq: int
    stamp_ns: int
    gid: bytes
    format: AttachmentFormat = "compact"

    def encode(self) -> bytes:
        """zenoh-ext serialization, the same serializer rmw_zenoh uses (zenoh::ext::Serializer)."""
        if len(self.gid) != GID_SIZE:
            raise ValueError(f"a GID has {GID_SIZE} bytes, not {len(self.gid)}")
        seq, stamp = _int64(self.seq), _int64(self.stamp_ns)
        if self.format == "legacy":
            names = [_sequence(name.encode()) for name in LEGACY_FIELDS]
            fields: tuple[bytes, ...] = (names[0], seq, names[1], stamp, names[2], _sequence(self.gid))
        elif self.format == "compact":
            fields = (seq, stamp, _sequence(self.gid))
        else:
            raise ValueError(f"unknown attachment format {self.format!r}")
        return b"".join(fields)

    @classmethod
    def decode(cls, raw: bytes) -> Attachment:
        """Either format (recorded in ``format``); WireError for anything else.

        Parsed here, by the zenoh-ext rules, not by ``zenoh.ext.z_deserialize``: that one panics
        (``pyo3_runtime.PanicException``, not an Exception: "capacity overflow", and it can
        abort the process) on a length prefix of 10 bytes."""
        reader = _Reader(raw)
        if (
            raw[:1] == bytes([len(LEGACY_FIELDS[0])])
            and raw[1 : 1 + len(LEGACY_FIELDS[0])] == LEGACY_FIELDS[0].encode()
        ):
            names, values = [], []
            for _ in range(2):
                names.append(reader.string())
                values.append(reader.int64())
            names.append(reader.string())
            if tuple(names) != LEGACY_FIELDS:
                raise WireError(f"legacy attachment with fields {tuple(names)}, expected {LEGACY_FIELDS}")
            attachment_format: AttachmentFormat = "legacy"
        else:
            if len(raw) != ATTACHMENT_SIZE:
                raise WireError(
                    f"attachment of {len(raw)} bytes, expected {ATTACHMENT_SIZE} (compact) or the legacy named fields"
                )
            values = [reader.int64(), reader.int64()]
            attachment_format = "compact"
        gid = reader.sequence()
        if len(gid) != GID_SIZE:
            raise WireError(f"attachment GID of {len(gid)} bytes")
        if reader.pos != len(raw):
            raise WireError(f"attachment of {len(raw)} bytes has {len(raw) - reader.pos} trailing bytes")
        return cls(values[0], values[1], gid, attachment_format)


class _Reader:
    """zenoh-ext's wire rules for what attachments hold: int64 = 8 bytes little endian; a
    sequence (bytes, string) = LEB128 length then the bytes. Every read is bounded by the input."""

    MAX_LENGTH_BYTES = 5  # LEB128 of a length below 2**35: far more than any attachment

    def __init__(self, raw: bytes) -> None:
        self.raw, self.pos = raw, 0

    def take(self, n: int) -> bytes:
        if n < 0 or self.pos + n > len(self.raw):
            raise WireError(f"attachment truncated: {n} bytes wanted at offset {self.pos} of {len(self.raw)}")
        chunk = self.raw[self.pos : self.pos + n]
        self.pos += n
        return bytes(chunk)

    def int64(self) -> int:
        return int.from_bytes(self.take(8), "little", signed=True)

    def sequence(self) -> bytes:
        length, shift = 0, 0
        for _ in range(self.MAX_LENGTH_BYTES):
            byte = self.take(1)[0]
            length |= (byte & 0x7F) << shift
            shift += 7
            if not byte & 0x80:
                return self.take(length)
        raise WireError(f"attachment length prefix longer than {self.MAX_LENGTH_BYTES} bytes")

    def string(self) -> str:
        try:
            return self.sequence().decode("utf-8")
        except UnicodeDecodeError as error:
            raise WireError(f"attachment field name is not UTF-8: {error}") from None


# -- CDR ------------------------------------------------------------------------------------
def _stamp(store: Any, stamp_ns: int) -> Any:
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return store.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)


def _vector3(store: Any, x: float, y: float, z: float) -> Any:
    return store.types["geometry_msgs/msg/Vector3"](x=float(x), y=float(y), z=float(z))


def encode_command(
    distro: str, ros_type: str, v: float, omega: float, *, stamp_ns: int = 0, frame_id: str = BASE_FRAME
) -> bytes:
    """CDR (little endian) of a Twist or TwistStamped with ``linear.x = v``, ``angular.z = omega``."""
    if not (math.isfinite(v) and math.isfinite(omega)):
        raise ValueError(f"command ({v}, {omega}) is not finite")
    store = typestore(distro)
    twist = store.types[TWIST](linear=_vector3(store, v, 0.0, 0.0), angular=_vector3(store, 0.0, 0.0, omega))
    if ros_type == TWIST:
        message = twist
    elif ros_type == TWIST_STAMPED:
        header = store.types["std_msgs/msg/Header"](stamp=_stamp(store, stamp_ns), frame_id=frame_id)
        message = store.types[TWIST_STAMPED](header=header, twist=twist)
    else:
        raise ValueError(f"{ros_type} is not a velocity command type")
    return bytes(store.serialize_cdr(message, ros_type, little_endian=True))


def decode_command(distro: str, ros_type: str, payload: bytes) -> tuple[float, float]:
    """``(linear.x, angular.z)`` of a Twist/TwistStamped sample; WireError if it is not one."""
    try:
        message = typestore(distro).deserialize_cdr(payload, ros_type)
    except DECODE_ERRORS as error:
        raise WireError(f"not a {ros_type}: {error}") from None
    twist = message.twist if ros_type == TWIST_STAMPED else message
    return float(twist.linear.x), float(twist.angular.z)


@dataclass(frozen=True)
class Odometry:
    """The fields of nav_msgs/msg/Odometry the bridge and the emulator use (covariances zero)."""

    stamp_ns: int
    frame_id: str
    child_frame_id: str
    x: float
    y: float
    orientation: tuple[float, float, float, float]  # (x, y, z, w)
    v: float  # twist.linear.x [m/s], body frame
    omega: float  # twist.angular.z [rad/s]


def encode_odometry(distro: str, odom: Odometry) -> bytes:
    store = typestore(distro)
    t = store.types
    qx, qy, qz, qw = odom.orientation
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=float(odom.x), y=float(odom.y), z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](x=float(qx), y=float(qy), z=float(qz), w=float(qw)),
    )
    twist = t[TWIST](linear=_vector3(store, odom.v, 0.0, 0.0), angular=_vector3(store, 0.0, 0.0, odom.omega))
    message = t[ODOMETRY](
        header=t["std_msgs/msg/Header"](stamp=_stamp(store, odom.stamp_ns), frame_id=odom.frame_id),
        child_frame_id=odom.child_frame_id,
        pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
    )
    return bytes(store.serialize_cdr(message, ODOMETRY, little_endian=True))


def decode_odometry(distro: str, payload: bytes) -> Odometry:
    """Decode a nav_msgs/msg/Odometry sample; WireError if it is not one (values not checked)."""
    try:
        message = typestore(distro).deserialize_cdr(payload, ODOMETRY)
    except DECODE_ERRORS as error:
        raise WireError(f"not a {ODOMETRY}: {error}") from None
    stamp = message.header.stamp
    q = message.pose.pose.orientation
    return Odometry(
        stamp_ns=int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec),
        frame_id=str(message.header.frame_id),
        child_frame_id=str(message.child_frame_id),
        x=float(message.pose.pose.position.x),
        y=float(message.pose.pose.position.y),
        orientation=(float(q.x), float(q.y), float(q.z), float(q.w)),
        v=float(message.twist.twist.linear.x),
        omega=float(message.twist.twist.angular.z),
    )


@dataclass(frozen=True)
class PoseFix:
    """A localization sample: the pose of ``child_frame_id`` in ``frame_id`` (``map`` -> ``odom`` of a
    ``/tf`` transform, or the robot's pose in ``map`` of AMCL, an EKF or motion capture).
    ``variance`` is the covariance diagonal of x, y and yaw (zero where the message has none)."""

    stamp_ns: int
    frame_id: str
    child_frame_id: str
    x: float
    y: float
    orientation: tuple[float, float, float, float]  # (x, y, z, w)
    variance: tuple[float, float, float] = (0.0, 0.0, 0.0)


def _header(store: Any, stamp_ns: int, frame_id: str) -> Any:
    return store.types["std_msgs/msg/Header"](stamp=_stamp(store, stamp_ns), frame_id=frame_id)


def _pose(store: Any, fix: PoseFix) -> Any:
    t = store.types
    qx, qy, qz, qw = fix.orientation
    return t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=float(fix.x), y=float(fix.y), z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](x=float(qx), y=float(qy), z=float(qz), w=float(qw)),
    )


def encode_pose(distro: str, ros_type: str, fix: PoseFix) -> bytes:
    """CDR of a PoseWithCovarianceStamped (``variance`` on the x, y, yaw diagonal) or a PoseStamped."""
    store = typestore(distro)
    t = store.types
    header = _header(store, fix.stamp_ns, fix.frame_id)
    if ros_type == POSE_WITH_COVARIANCE:
        covariance = np.zeros(36)
        covariance[[0, 7, 35]] = fix.variance
        message = t[ros_type](
            header=header, pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=_pose(store, fix), covariance=covariance)
        )
    elif ros_type == POSE_STAMPED:
        message = t[ros_type](header=header, pose=_pose(store, fix))
    else:
        raise ValueError(f"{ros_type} is not a pose type")
    return bytes(store.serialize_cdr(message, ros_type, little_endian=True))


def encode_tf(distro: str, transforms: list[PoseFix]) -> bytes:
    """CDR of a tf2_msgs/msg/TFMessage: each fix a ``frame_id -> child_frame_id`` transform (z 0)."""
    store = typestore(distro)
    t = store.types
    stamped = []
    for fix in transforms:
        qx, qy, qz, qw = fix.orientation
        transform = t["geometry_msgs/msg/Transform"](
            translation=_vector3(store, fix.x, fix.y, 0.0),
            rotation=t["geometry_msgs/msg/Quaternion"](x=float(qx), y=float(qy), z=float(qz), w=float(qw)),
        )
        stamped.append(
            t["geometry_msgs/msg/TransformStamped"](
                header=_header(store, fix.stamp_ns, fix.frame_id),
                child_frame_id=fix.child_frame_id,
                transform=transform,
            )
        )
    return bytes(store.serialize_cdr(t[TF_MESSAGE](transforms=stamped), TF_MESSAGE, little_endian=True))


def _stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _quaternion(q: Any) -> tuple[float, float, float, float]:
    return (float(q.x), float(q.y), float(q.z), float(q.w))


def decode_localization(distro: str, ros_type: str, payload: bytes) -> list[PoseFix]:
    """The fixes of a localization sample of ``ros_type`` (a TFMessage may hold several, the others
    one); WireError if it is not one (values not checked)."""
    if ros_type == ODOMETRY:
        odom = decode_odometry(distro, payload)
        return [PoseFix(odom.stamp_ns, odom.frame_id, odom.child_frame_id, odom.x, odom.y, odom.orientation)]
    if ros_type not in (POSE_WITH_COVARIANCE, POSE_STAMPED, TF_MESSAGE):
        raise ValueError(f"{ros_type} is not a localization type")
    try:
        message = typestore(distro).deserialize_cdr(payload, ros_type)
    except DECODE_ERRORS as error:
        raise WireError(f"not a {ros_type}: {error}") from None
    if ros_type == TF_MESSAGE:
        return [
            PoseFix(
                _stamp_ns(tf.header),
                str(tf.header.frame_id),
                str(tf.child_frame_id),
                float(tf.transform.translation.x),
                float(tf.transform.translation.y),
                _quaternion(tf.transform.rotation),
            )
            for tf in message.transforms
        ]
    pose = message.pose.pose if ros_type == POSE_WITH_COVARIANCE else message.pose
    variance = (0.0, 0.0, 0.0)
    if ros_type == POSE_WITH_COVARIANCE:
        c = message.pose.covariance
        variance = (float(c[0]), float(c[7]), float(c[35]))
    return [
        PoseFix(
            _stamp_ns(message.header),
            str(message.header.frame_id),
            "",
            float(pose.position.x),
            float(pose.position.y),
            _quaternion(pose.orientation),
            variance,
        )
    ]
