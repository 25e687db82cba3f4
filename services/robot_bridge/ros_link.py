"""The robot's side of the bridge: the ROS 2 graph over Zenoh (rmw_zenoh or zenoh-bridge-ros2dds).

:class:`RosLink` subscribes the robot's odometry, decodes it (CDR, common/contracts/ros_wire.py)
and hands it to the bridge's logic (services/robot_bridge/bridge.py); it finds the robot's
``cmd_vel`` subscriptions and puts every command on them. Its rules (docs/robot.md):

* **Odometry** is refused (counted) when it does not decode as nav_msgs/msg/Odometry, carries a
  foreign type hash, or has no rmw_zenoh attachment (the profile requires one).
* **cmd_vel type.** ``bridge.cmd_type`` twist / twist_stamped forces it; ``auto`` reads it from the
  robot's subscription tokens (rmw_zenoh ``MS`` tokens carry type and hash; zenoh-bridge-ros2dds
  announces ``MS`` with the ROS type) and publishes to every subscription found. With no token
  after ``bridge.discovery_timeout`` it falls back to the distro's TurtleBot3 default (Humble
  Twist, Jazzy TwistStamped) and says so. On rmw_zenoh, a Humble robot's ``TypeHashNotSupported``
  subscription is served even when the bridge is configured for Jazzy (the CDR of Twist,
  TwistStamped and Odometry is the same), an unknown RIHS01 hash is refused.
* **rmw_zenoh attachment format.** rmw_zenoh_cpp changed its attachment format in Jazzy 0.2.4 /
  Humble 0.1.2 (ros_wire.py); an older robot's subscriber throws (and may abort) on the new
  one. The link reads the format from the robot's odometry and writes every ``cmd_vel`` in
  it; until the first valid odometry sample it sends nothing on ``cmd_vel`` (counted under
  ``commands_format_unknown``; the actor cannot act before a state anyway). Odometry in neither
  format is refused with one error naming the supported releases.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh
import zenoh.ext

from common.config.settings import BridgeSettings
from common.contracts import ros_wire
from common.contracts.ros_wire import (
    ODOMETRY,
    ODOMETRY_ONLY,
    POSE_SOURCES,
    TWIST,
    TWIST_STAMPED,
    Attachment,
    AttachmentFormat,
    CmdEndpoint,
    Odometry,
    PoseFix,
    RosGraph,
    WireError,
    pose_topic,
    qos_chunk,
)
from services.robot_bridge.bridge import Counts

log = logging.getLogger(__name__)
FALLBACK = "fallback"  # the source of a cmd_vel target guessed from the distro, not discovered
MAX_TRANSFORMS = 64  # of one /tf sample looked at (a robot's tree has a few dozen frames)
LOCALIZATION_EID = 50  # the entity id of the localization subscription (after odom and cmd_vel's)


class _Target:
    """One cmd_vel subscription of the robot, with our publisher (and rmw_zenoh identity) for it."""

    def __init__(self, endpoint: CmdEndpoint, publisher: Any, token: Any, gid: bytes) -> None:
        self.endpoint, self.publisher, self.token, self.gid = endpoint, publisher, token, gid
        self.seq = 0
        self.sources: set[str] = set()  # liveliness tokens that announced it ("" = configured)


class RosLink:
    """The robot's side of the bridge: Zenoh keys, tokens and CDR of one wire profile."""

    def __init__(
        self, session: zenoh.Session, graph: RosGraph, bridge: BridgeSettings, counts: Counts, entity_base: int = 0
    ) -> None:
        self.session, self.graph, self.bridge, self.counts = session, graph, bridge, counts
        # rmw_zenoh numbers the nodes and entities of one session uniquely: a bridge host's links
        # that share a session to one router take disjoint ranges (services/robot_bridge/host.py)
        self.entity_base = entity_base
        self.on_odometry: Callable[[Odometry, float], object] = lambda odom, received: None
        self.on_localization: Callable[[PoseFix, float], object] = lambda fix, received: None
        self.lock = threading.Lock()
        self.targets: dict[str, _Target] = {}
        self.entities: list[Any] = []
        self.zid = str(session.info.zid())
        self.started = time.monotonic()
        self.fallback = False
        self.discovered: list[str] = []
        self.dropped = 0
        # the robot's rmw_zenoh attachment format, from its odometry (None: not seen yet)
        self.attachment_format: AttachmentFormat | None = None
        self.format_warned = False

    # -- setup ----------------------------------------------------------------------------
    def start(self) -> None:
        ros_wire.typestore(self.graph.distro)  # load it now, not on the first odometry sample
        odom_key = self.graph.data_key(self.bridge.odom_topic, ODOMETRY, "*")
        self.entities.append(self.session.declare_subscriber(odom_key, self._on_odom_sample))
        if self.graph.profile == "rmw_zenoh":
            liveliness = self.session.liveliness()
            nid = self.entity_base
            self.entities.append(liveliness.declare_token(self.graph.node_token(self.zid, nid, ros_wire.BRIDGE_NODE)))
            self.entities.append(
                liveliness.declare_token(
                    self.graph.endpoint_token(
                        self.zid, nid, nid + 1, "MS", ros_wire.BRIDGE_NODE, self.bridge.odom_topic, ODOMETRY
                    )
                )
            )
        if self.bridge.pose_source != ODOMETRY_ONLY:
            self._subscribe_localization()
        if self.bridge.cmd_type == "auto":
            pattern = self.graph.discovery_pattern(self.bridge.cmd_vel_topic)
            self.entities.append(self.session.liveliness().declare_subscriber(pattern, self._on_token, history=True))
        else:
            self._add_target(
                self.graph.cmd_endpoint(self.bridge.cmd_vel_topic, ros_wire.CMD_TYPES[self.bridge.cmd_type]), ""
            )
        log.info(
            "robot_bridge: %s (%s), odometry on %s, cmd_vel type %s",
            self.graph.profile,
            self.graph.distro,
            odom_key,
            self.bridge.cmd_type,
        )

    def _subscribe_localization(self) -> None:
        """The localization topic, with the QoS its publisher uses (ros_wire.POSE_SOURCES).

        Transient local (AMCL's ``amcl_pose``): rmw_zenoh_cpp (Jazzy >= 0.2.2, "Introduce the
        advanced publisher and subscriber", ros2/rmw_zenoh#469) publishes it with a zenoh-ext
        AdvancedPublisher that caches the last ``depth`` samples and announces itself, and
        subscribes with an AdvancedSubscriber whose history detects late publishers and queries
        their caches (rmw_subscription_data.cpp). The link does the same (under ros2dds too: a
        cache the robot's side keeps in zenoh-ext's form answers it), so the fix AMCL made before
        the bridge started arrives at once."""
        source = POSE_SOURCES[self.bridge.pose_source]
        topic = pose_topic(self.bridge)
        key = self.graph.data_key(topic, source.ros_type, "*")
        self.localization_key = key
        if source.transient_local:
            history = zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=source.depth)
            self.entities.append(
                zenoh.ext.declare_advanced_subscriber(
                    self.session, key, self._on_pose_sample, history=history, subscriber_detection=True
                )
            )
        else:
            self.entities.append(self.session.declare_subscriber(key, self._on_pose_sample))
        if self.graph.profile == "rmw_zenoh":
            nid = self.entity_base
            token = self.graph.endpoint_token(
                self.zid,
                nid,
                nid + LOCALIZATION_EID,
                "MS",
                ros_wire.BRIDGE_NODE,
                topic,
                source.ros_type,
                qos=qos_chunk(source.depth, source.transient_local),
            )
            self.entities.append(self.session.liveliness().declare_token(token))
        log.info("robot_bridge: localization %s on %s", self.bridge.pose_source, key)

    def close(self) -> None:
        with self.lock:
            targets = list(self.targets.values())
            self.targets.clear()
        undeclare([*(t.publisher for t in targets), *(t.token for t in targets if t.token), *self.entities])
        self.entities.clear()

    # -- odometry in ----------------------------------------------------------------------
    def _rmw_attachment(self, sample: zenoh.Sample, what: str, ros_type: str) -> Attachment | None:
        """rmw_zenoh: the sample's attachment, after its key's type hash is checked; None (counted)
        when either is not rmw_zenoh's."""
        key = str(sample.key_expr)
        if sample.attachment is None:
            self.counts.reject(what, f"{key}: no rmw_zenoh attachment")
            return None
        try:
            attachment = Attachment.decode(bytes(sample.attachment.to_bytes()))
        except WireError as error:
            self.counts.reject(what, f"{key}: {error}; srl speaks {ros_wire.SUPPORTED_RMW_ZENOH}")
            return None
        chunk = self.graph.hash_chunk_of(key)
        if not self.graph.accepts_hash(ros_type, chunk):
            self.counts.reject(what, f"{key}: type hash {chunk} is not {ros_type}'s")
            return None
        return attachment

    def _on_odom_sample(self, sample: zenoh.Sample) -> None:
        received = time.monotonic()
        attachment = None
        if self.graph.profile == "rmw_zenoh":
            attachment = self._rmw_attachment(sample, "odom", ODOMETRY)
            if attachment is None:
                return
        try:
            odom = ros_wire.decode_odometry(self.graph.distro, bytes(sample.payload.to_bytes()))
        except WireError as error:
            self.counts.reject("odom", str(error))
            return
        if attachment is not None:
            self._learn_format(attachment.format)
        self.counts.count("odom_received")
        try:
            self.on_odometry(odom, received)
        except Exception:  # a handler bug must not kill zenoh's callback thread silently
            self.counts.count("handler_errors.odom")
            log.exception("robot_bridge: odometry handler failed")

    # -- localization in ---------------------------------------------------------------------
    def _on_pose_sample(self, sample: zenoh.Sample) -> None:
        received = time.monotonic()
        ros_type = POSE_SOURCES[self.bridge.pose_source].ros_type
        if self.graph.profile == "rmw_zenoh" and self._rmw_attachment(sample, "localization", ros_type) is None:
            return
        try:
            fixes = ros_wire.decode_localization(self.graph.distro, ros_type, bytes(sample.payload.to_bytes()))
        except WireError as error:
            self.counts.reject("localization", str(error))
            return
        self.counts.count("localization_received")
        for fix in fixes[:MAX_TRANSFORMS]:
            try:
                self.on_localization(fix, received)
            except Exception:  # a handler bug must not kill zenoh's callback thread silently
                self.counts.count("handler_errors.localization")
                log.exception("robot_bridge: localization handler failed")

    def _learn_format(self, found: AttachmentFormat) -> None:
        """The robot's attachment format, from a valid odometry sample: cmd_vel follows it."""
        with self.lock:
            previous, self.attachment_format = self.attachment_format, found
        if previous == found:
            return
        if previous is None:
            log.info(
                "robot_bridge: the robot's rmw_zenoh attachments are %s%s: cmd_vel in that format",
                found,
                " (rmw_zenoh_cpp Humble 0.1.0-0.1.1 / Jazzy 0.2.0-0.2.3)" if found == "legacy" else "",
            )
        else:
            log.warning(
                "robot_bridge: the robot's rmw_zenoh attachment format changed from %s to %s (robot "
                "software changed?): cmd_vel follows",
                previous,
                found,
            )
            self.counts.count("attachment_format_changes")
        self.counts.count(f"attachment_format.{found}")

    # -- cmd_vel type discovery ------------------------------------------------------------
    def _on_token(self, sample: zenoh.Sample) -> None:
        token = str(sample.key_expr)
        parsed = self.graph.parse_subscription(token, self.bridge.cmd_vel_topic)
        if parsed is None:
            return
        ros_type, chunk = parsed
        if ros_type not in (TWIST, TWIST_STAMPED):
            self.counts.reject("cmd_vel_discovery", f"robot subscribes {ros_type}, not a velocity command")
            return
        if self.graph.profile == "rmw_zenoh" and not self.graph.accepts_hash(ros_type, chunk):
            self.counts.reject("cmd_vel_discovery", f"{ros_type} with unknown type hash {chunk}")
            return
        endpoint = self.graph.cmd_endpoint(self.bridge.cmd_vel_topic, ros_type, chunk or None)
        if sample.kind == zenoh.SampleKind.DELETE:
            self._remove_source(endpoint, token)
            return
        if self.graph.profile == "rmw_zenoh" and chunk != ros_wire.type_hash(self.graph.distro, ros_type):
            log.warning(
                "robot_bridge: the robot's %s subscription has type hash %s (configured distro %s): serving it",
                ros_type,
                chunk,
                self.graph.distro,
            )
        self.discovered.append(ros_type)
        self.counts.count("cmd_vel_discovered")
        log.info("robot_bridge: the robot subscribes %s on %s", ros_type, endpoint.key)
        self._add_target(endpoint, token)

    def _add_target(self, endpoint: CmdEndpoint, source: str) -> None:
        with self.lock:
            if source not in ("", FALLBACK) and self.fallback:  # the robot has spoken: forget the guess
                for guessed in list(self.targets.values()):
                    guessed.sources.discard(FALLBACK)
                self._prune()
                self.fallback = False
            target: _Target | None = self.targets.get(endpoint.key + "|" + endpoint.ros_type)
            if target is None:
                taken = any(t.endpoint.key == endpoint.key for t in self.targets.values())
                if self.graph.profile == "ros2dds" and taken:
                    log.warning(
                        "robot_bridge: %s is also announced as %s; the plain ros2dds key cannot carry "
                        "both, keeping the first",
                        endpoint.key,
                        endpoint.ros_type,
                    )
                    return
                publisher = self.session.declare_publisher(endpoint.key, express=True)
                token = gid_token = None
                if self.graph.profile == "rmw_zenoh":
                    gid_token = self.graph.endpoint_token(
                        self.zid,
                        self.entity_base,
                        self.entity_base + 2 + len(self.targets),
                        "MP",
                        ros_wire.BRIDGE_NODE,
                        self.bridge.cmd_vel_topic,
                        endpoint.ros_type,
                        endpoint.type_hash,
                    )
                    token = self.session.liveliness().declare_token(gid_token)
                gid = ros_wire.gid_for(gid_token or endpoint.key)
                target = _Target(endpoint, publisher, token, gid)
                self.targets[endpoint.key + "|" + endpoint.ros_type] = target
            target.sources.add(source)

    def _remove_source(self, endpoint: CmdEndpoint, source: str) -> None:
        with self.lock:
            target = self.targets.get(endpoint.key + "|" + endpoint.ros_type)
            if target is not None:
                target.sources.discard(source)
                self._prune()

    def _prune(self) -> None:
        for name, target in list(self.targets.items()):
            if not target.sources:
                del self.targets[name]
                target.publisher.undeclare()
                if target.token is not None:
                    target.token.undeclare()

    def tick(self, now: float) -> None:
        """Fall back to the distro's default type when discovery found nothing in time."""
        if (
            self.bridge.cmd_type != "auto"
            or self.fallback
            or self.discovered
            or now - self.started < self.bridge.discovery_timeout
        ):
            return  # once the robot has announced its subscription, never guess (it may be restarting)
        with self.lock:
            if self.targets:
                return
            self.fallback = True
        ros_type = ros_wire.DEFAULT_CMD_TYPE[self.graph.distro]
        log.warning(
            "robot_bridge: no cmd_vel subscription of the robot seen in %.1f s: sending %s (the TurtleBot3 %s default)",
            self.bridge.discovery_timeout,
            ros_type,
            self.graph.distro,
        )
        self.counts.count("cmd_vel_fallback")
        self._add_target(self.graph.cmd_endpoint(self.bridge.cmd_vel_topic, ros_type), FALLBACK)

    # -- commands out ----------------------------------------------------------------------
    def send(self, v: float, omega: float) -> None:
        with self.lock:
            targets = list(self.targets.values())
        if not targets:
            self.dropped += 1
            self.counts.count("commands_without_subscriber")
            return
        with self.lock:
            attachment_format = self.attachment_format
        if self.graph.profile == "rmw_zenoh" and attachment_format is None:
            # a wrong attachment can abort the robot's process (ros_wire.py): say nothing yet
            self.counts.count("commands_format_unknown")
            if not self.format_warned:
                self.format_warned = True
                log.warning(
                    "robot_bridge: no cmd_vel until the robot's odometry shows its rmw_zenoh attachment "
                    "format (srl speaks %s)",
                    ros_wire.SUPPORTED_RMW_ZENOH,
                )
            return
        stamp = time.time_ns()  # ROS time is the system clock
        for target in targets:
            payload = ros_wire.encode_command(
                self.graph.distro,
                target.endpoint.ros_type,
                v,
                omega,
                stamp_ns=stamp,
                frame_id=self.graph.frame_id(ros_wire.BASE_FRAME),
            )
            try:
                if self.graph.profile == "rmw_zenoh":
                    target.seq += 1
                    attachment = Attachment(target.seq, stamp, target.gid, attachment_format or "compact")
                    target.publisher.put(payload, attachment=attachment.encode())
                else:
                    target.publisher.put(payload)
            except zenoh.ZError as error:  # the robot's subscription vanished while we sent
                self.counts.reject("cmd_vel", f"{target.endpoint.key}: {error}")
        self.counts.count("commands_sent")

    def describe(self) -> dict[str, Any]:
        with self.lock:
            return {
                "cmd_vel": [{"type": t.endpoint.ros_type, "key": t.endpoint.key} for t in self.targets.values()],
                "fallback": self.fallback,
                "discovered": sorted(set(self.discovered)),
                "attachment_format": self.attachment_format,
            }


def undeclare(entities: list[Any]) -> None:
    """Undeclare each of ``entities`` (publishers, subscribers, tokens) in order; one already gone
    with its session is skipped."""
    for entity in entities:
        try:
            entity.undeclare()
        except zenoh.ZError as error:
            log.debug("undeclare: %s", error)
