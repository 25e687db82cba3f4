"""robot_bridge: a ROS 2 robot as the plant -- odometry in, ``cmd_vel`` out, over Zenoh.

It publishes and consumes the same keys as plant_sim (``srl/<robot>/state``, ``srl/<robot>/action``)
and declares the same liveliness token (``srl/<robot>/alive/plant``, plus ``alive/robot_bridge``),
so the actor and the critic cannot tell which plant they talk to.

Decisions (README, "Robot bridge"):

* **Goal frame.** The goal is a configured pose ``bridge.goal`` in the robot's odom frame, default
  ``(0, 0, 0)``: the odom origin, where the robot's odometry started (TurtleBot3: at bringup or
  after ``reset_odometry``). Not "the pose at bridge start-up": a bridge restart would then move
  the target to wherever the robot stands, silently. The state is ``common.math.frames.to_goal_frame``
  of the odometry pose, its heading unwrapped (continuous) from sample to sample.
* **Odometry** is refused (counted, never published) when it does not decode as
  nav_msgs/msg/Odometry, carries a foreign type hash, has no rmw_zenoh attachment (the profile
  requires one), has a non-finite pose or a zero quaternion, or is not newer than the last sample
  by its header stamp (out of order). After 20 refused stale samples in a row the robot's clock
  is taken to have been reset and the new time base is accepted.
* **Commands.** An action is applied only if it is for this robot, newer (episode, step) than the
  last one, and the actor's liveliness token is present. It is clamped to ``plant.v_max``,
  ``plant.omega_max`` and the TurtleBot3 Burger's 0.22 m/s, 2.84 rad/s; a non-finite value can
  never reach ``cmd_vel`` (the schema refuses it, and the last guard before the wire sends zero).
* **Watchdog.** Every ``delta / 10`` the bridge checks that the last applied action is younger than
  ``bridge.watchdog_timeout_steps * delta`` and that the actor is alive; otherwise it commands zero
  velocity at once and keeps commanding zero every ``delta / 2`` until a fresh action arrives (a
  TurtleBot3 holds its last command forever, so the zero must come from here). The actor's token
  vanishing stops the robot at once (from the liveliness callback). On shutdown: zero, three times.
* **cmd_vel type.** ``bridge.cmd_type`` twist / twist_stamped forces it; ``auto`` reads it from the
  robot's subscription tokens (rmw_zenoh ``MS`` tokens carry type and hash; zenoh-bridge-ros2dds
  announces ``MS`` with the ROS type) and publishes to every subscription found. With no token
  after ``bridge.discovery_timeout`` it falls back to the distro's TurtleBot3 default (Humble
  Twist, Jazzy TwistStamped) and says so. On rmw_zenoh, a Humble robot's ``TypeHashNotSupported``
  subscription is served even when the bridge is configured for Jazzy (the CDR of Twist,
  TwistStamped and Odometry is the same), an unknown RIHS01 hash is refused.
* **rmw_zenoh attachment format.** rmw_zenoh_cpp changed its attachment format in Jazzy 0.2.4 /
  Humble 0.1.2 (ros_wire.py); an older robot's subscriber throws (and may abort) on the new
  one. The bridge reads the format from the robot's odometry and writes every ``cmd_vel`` in
  it; until the first valid odometry sample it sends nothing on ``cmd_vel`` (counted under
  ``commands_format_unknown``; the actor cannot act before a state anyway). Odometry in neither
  format is refused with one error naming the supported releases.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any, Protocol

import zenoh
from pydantic import ValidationError

from common.config.settings import BridgeSettings, Settings
from common.contracts import ros_wire
from common.contracts.keys import ACTION, STATE, liveliness_key
from common.contracts.messages import Action, PlantState
from common.contracts.ros_wire import (
    ODOMETRY,
    TWIST,
    TWIST_STAMPED,
    Attachment,
    AttachmentFormat,
    CmdEndpoint,
    Odometry,
    RosGraph,
    WireError,
)
from common.contracts.summaries import BridgeSummary
from common.math.dynamics import unwrap_heading
from common.math.frames import Pose2D, clamp_command, to_goal_frame, wrap_angle, yaw_from_quaternion
from common.math.stats import Window
from common.net.provenance import (
    MAX_ACTION_EPISODE_JUMP,
    MAX_ACTION_STEP_JUMP,
    RESYNC_AFTER,
    ActionGate,
    ActionOrder,
    SourceGate,
)
from common.net.security import SecurityError
from common.net.transport import Bus, plain_config, start_status_thread
from common.system.clock import Ticker

log = logging.getLogger(__name__)
CLOCK_RESET_AFTER = 20  # consecutive out-of-order odometry samples taken as a robot clock reset
# An odometry stamp more than this ahead of where the robot's clock should be (the last stamp
# plus the time elapsed here) is refused WITHOUT becoming the reference: one sample stamped an
# hour ahead must not make the next real samples "old" (issue 13). CLOCK_RESET_AFTER such
# samples in a row are taken as the robot's clock having jumped forward.
FUTURE_STAMP_TOLERANCE_NS = 5_000_000_000
SHUTDOWN_ZEROS = 3
FALLBACK = "fallback"  # the source of a cmd_vel target guessed from the distro, not discovered


class Counts(Protocol):
    def count(self, name: str, amount: int = 1) -> None: ...

    def reject(self, what: str, reason: str) -> None: ...


class RobotBridge:
    """Transport-free logic: odometry -> PlantState, Action -> command, the watchdog.

    ``send_command(v, omega)`` puts one command on the wire; it is called with the bridge's
    lock held so that commands leave in the order they were decided.
    """

    def __init__(
        self,
        settings: Settings,
        publish_state: Callable[[PlantState], None],
        send_command: Callable[[float, float], None],
        counts: Counts,
        actor_gate: SourceGate | None = None,
    ) -> None:
        self.robot = settings.transport.robot
        # provenance (issue 13): with a gate, actions only from the live actor session
        self.actor_gate = actor_gate
        self.goal = Pose2D(*settings.bridge.goal)
        self.v_max = min(settings.plant.v_max, ros_wire.TB3_BURGER_V_MAX)
        self.omega_max = min(settings.plant.omega_max, ros_wire.TB3_BURGER_OMEGA_MAX)
        self.timeout = settings.bridge.watchdog_timeout_steps * settings.plant.sampling_time
        self.zero_repeat = settings.plant.sampling_time / 2.0
        self.last_zero_at: float | None = None
        self.publish_state = publish_state
        self.send_command = send_command
        self.counts = counts
        self.lock = threading.Lock()
        # odometry
        self.seq = 0
        self.last_stamp_ns: int | None = None
        self.last_stamp_at: float | None = None  # when (our monotonic clock) last_stamp_ns came
        self.stale_run = 0
        self.future_run = 0
        self.alpha: float | None = None
        self.last_state: tuple[float, float, float] | None = None
        self.frames: tuple[str, str] | None = None
        # commands
        self.actor_alive = False
        # (episode, step) of the followed actor session, bounded both ways (common.net.provenance)
        self.order = ActionOrder(MAX_ACTION_STEP_JUMP, MAX_ACTION_EPISODE_JUMP)
        # whose actions are applied: the live actor session's, in its order (common.net.provenance)
        self.actions = None if actor_gate is None else ActionGate(actor_gate, self.order)
        self.resyncs_seen = 0
        self.last_action_at: float | None = None
        self.driving = False
        self.last_command = (0.0, 0.0)
        self.max_abs_command = [0.0, 0.0]
        # timing (seconds)
        self.state_sent_at: OrderedDict[int, float] = OrderedDict()
        # latencies in fixed-size windows (common.math.stats.Window): a bridge runs for days
        self.odom_to_state = Window()
        self.action_to_cmd = Window()
        self.state_to_cmd = Window()

    # -- odometry -------------------------------------------------------------------------
    def on_odometry(self, odom: Odometry, received: float) -> PlantState | None:
        try:
            yaw = yaw_from_quaternion(*odom.orientation)
            if not (math.isfinite(odom.x) and math.isfinite(odom.y)):
                raise ValueError(f"position ({odom.x}, {odom.y}) is not finite")
        except ValueError as error:
            self.counts.reject("odom", str(error))
            return None
        with self.lock:
            if self.last_stamp_ns is not None and self.last_stamp_at is not None:
                expected = self.last_stamp_ns + int((received - self.last_stamp_at) * 1e9)
                if odom.stamp_ns > expected + FUTURE_STAMP_TOLERANCE_NS:
                    self.future_run += 1
                    if self.future_run < CLOCK_RESET_AFTER:
                        self.counts.reject(
                            "odom",
                            f"stamp {odom.stamp_ns} is {(odom.stamp_ns - expected) / 1e9:.1f} s "
                            "ahead of the robot's clock",
                        )
                        return None
                    log.warning(
                        "robot_bridge: %d odometry samples ahead of the robot's clock: taking it as a clock jump",
                        self.future_run,
                    )
                    self.counts.count("odom_clock_jumps")
            if self.last_stamp_ns is not None and odom.stamp_ns <= self.last_stamp_ns:
                self.stale_run += 1
                if self.stale_run < CLOCK_RESET_AFTER:
                    self.counts.reject("odom", f"stamp {odom.stamp_ns} not newer than {self.last_stamp_ns}")
                    return None
                log.warning(
                    "robot_bridge: %d odometry samples older than the last: taking it as a robot clock reset",
                    self.stale_run,
                )
                self.counts.count("odom_clock_resets")
            pose = to_goal_frame(Pose2D(odom.x, odom.y, yaw), self.goal)
            alpha = wrap_angle(pose.theta) if self.alpha is None else unwrap_heading(self.alpha, pose.theta)
            try:
                state = PlantState(
                    robot=self.robot,
                    episode=0,
                    seq=self.seq + 1,
                    stamp_ns=time.monotonic_ns(),
                    state=(pose.x, pose.y, alpha),
                    source="robot",
                )
            except ValidationError as error:  # beyond the schema's physical bounds (1e4 m)
                self.counts.reject("odom", f"state {pose} out of range: {error.errors()[0]['msg']}")
                return None
            self.stale_run = 0
            self.future_run = 0
            self.last_stamp_ns = odom.stamp_ns
            self.last_stamp_at = received
            self.alpha = alpha
            self.seq += 1
            if self.frames != (odom.frame_id, odom.child_frame_id):
                self.frames = (odom.frame_id, odom.child_frame_id)
                log.info("robot_bridge: odometry of %s in frame %s", odom.child_frame_id, odom.frame_id)
            self.publish_state(state)
            now = time.monotonic()
            self.state_sent_at[self.seq] = now
            if len(self.state_sent_at) > 200:
                self.state_sent_at.popitem(last=False)
            self.odom_to_state.append(now - received)
            self.last_state = state.state
            self.counts.count("states_published")
            return state

    # -- commands -------------------------------------------------------------------------
    def on_action(self, message: Action, received: float, source: str | None = None) -> None:
        with self.lock:
            if message.robot != self.robot:
                self.counts.reject("action", f"for robot {message.robot!r}, this is {self.robot!r}")
                return
            if not self.actor_alive:  # an action in flight when its actor left is late (ActionGate)
                late = self.actions.late_refusal(source, received) if self.actions is not None else None
                self.counts.reject(*(late or ("action", "the actor's liveliness token is absent")))
                return
            try:  # the value first: a refused one never moves the order
                v, omega = clamp_command(message.action[0], message.action[1], self.v_max, self.omega_max)
            except ValueError as error:
                self.counts.reject("action", str(error))
                return
            if self.actions is None:  # no provenance (unit tests of the order alone)
                reason = self.order.check(message.episode, message.step, received)
                refusal = None if reason is None else ("action", reason)
            else:
                refusal = self.actions.admit(message.episode, message.step, source, received)
            if refusal is not None:
                self.counts.reject(*refusal)
                return
            if self.order.resyncs != self.resyncs_seen:
                self.resyncs_seen = self.order.resyncs
                self.counts.count("action_resyncs")
                log.warning(
                    "robot_bridge: %d actions of the followed session refused in a row: following its "
                    "stream again from (episode, step) %s",
                    RESYNC_AFTER,
                    self.order.last,
                )
            self.last_action_at = received
            self.driving = True
            self._command(v, omega)
            now = time.monotonic()
            self.action_to_cmd.append(now - received)
            sent = self.state_sent_at.get(message.state_seq)
            if sent is not None:
                self.state_to_cmd.append(now - sent)
            self.counts.count("actions_applied")

    def on_actor_identity(self, zid: str, alive: bool) -> None:
        """An actor session's identity token came or went: the actor is alive while one is; the
        robot stops at once when the session whose actions it follows is gone (a stray or forged
        ``alive/actor`` token of another session cannot hide that death)."""
        if self.actor_gate is None:
            return
        live = bool(self.actor_gate.sources())
        with self.lock:
            if not alive and self.actions is not None and self.actor_alive and self.actions.lost(zid, time.monotonic()):
                log.warning("robot_bridge: the actor session %s is gone: stopping the robot", zid)
                self.counts.count("actor_lost_stops")
                self.driving = False
                self.last_action_at = None
                self._zero(time.monotonic())
                self.actor_alive = live  # counted once: the stop above is the actor's loss
                return
        self.set_actor_alive(live)

    def set_actor_alive(self, alive: bool) -> None:
        with self.lock:
            if self.actor_alive and not alive:
                log.warning("robot_bridge: the actor's liveliness token vanished: stopping the robot")
                self.counts.count("actor_lost_stops")
                self.driving = False
                self.last_action_at = None
                self._zero(time.monotonic())
            self.actor_alive = alive

    def tick(self, now: float) -> None:
        """The watchdog: zero velocity, repeated, while no fresh action from a live actor."""
        with self.lock:
            fresh = self.actor_alive and self.last_action_at is not None and now - self.last_action_at <= self.timeout
            if fresh:
                return
            if self.driving:
                self.driving = False
                self.counts.count("watchdog_stops")
                log.warning("robot_bridge: no fresh action for %.2f s: commanding zero velocity", self.timeout)
                self._zero(now)
            elif self.last_zero_at is None or now - self.last_zero_at >= self.zero_repeat:
                self._zero(now)

    def _zero(self, now: float) -> None:
        self.last_zero_at = now
        self._command(0.0, 0.0)

    def stop(self) -> None:
        with self.lock:
            self.driving = False
            self.last_action_at = None
            self._command(0.0, 0.0)

    def _command(self, v: float, omega: float) -> None:
        # The last guard before the wire: nothing non-finite or out of bounds ever leaves.
        if not (math.isfinite(v) and math.isfinite(omega)):
            v, omega = 0.0, 0.0
            self.counts.count("nonfinite_commands_zeroed")
        v = min(max(v, -self.v_max), self.v_max)
        omega = min(max(omega, -self.omega_max), self.omega_max)
        self.last_command = (v, omega)
        self.max_abs_command = [max(self.max_abs_command[0], abs(v)), max(self.max_abs_command[1], abs(omega))]
        self.send_command(v, omega)

    def timing(self) -> dict[str, Any]:
        return {
            "odom_to_state_ms": self.odom_to_state.summary(1e3),
            "action_to_cmd_ms": self.action_to_cmd.summary(1e3),
            "state_to_cmd_ms": self.state_to_cmd.summary(1e3),
        }


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

    def close(self) -> None:
        with self.lock:
            targets = list(self.targets.values())
            self.targets.clear()
        for entity in [*(t.publisher for t in targets), *(t.token for t in targets if t.token), *self.entities]:
            try:
                entity.undeclare()
            except zenoh.ZError as error:
                log.debug("undeclare: %s", error)
        self.entities.clear()

    # -- odometry in ----------------------------------------------------------------------
    def _on_odom_sample(self, sample: zenoh.Sample) -> None:
        received = time.monotonic()
        key = str(sample.key_expr)
        if self.graph.profile == "rmw_zenoh":
            if sample.attachment is None:
                self.counts.reject("odom", f"{key}: no rmw_zenoh attachment")
                return
            try:
                attachment = Attachment.decode(bytes(sample.attachment.to_bytes()))
            except WireError as error:
                self.counts.reject("odom", f"{key}: {error}; srl speaks {ros_wire.SUPPORTED_RMW_ZENOH}")
                return
            chunk = self.graph.hash_chunk_of(key)
            if not self.graph.accepts_hash(ODOMETRY, chunk):
                self.counts.reject("odom", f"{key}: type hash {chunk} is not {ODOMETRY}'s")
                return
        try:
            odom = ros_wire.decode_odometry(self.graph.distro, bytes(sample.payload.to_bytes()))
        except WireError as error:
            self.counts.reject("odom", str(error))
            return
        if self.graph.profile == "rmw_zenoh":
            self._learn_format(attachment.format)
        self.counts.count("odom_received")
        try:
            self.on_odometry(odom, received)
        except Exception:  # a handler bug must not kill zenoh's callback thread silently
            self.counts.count("handler_errors.odom")
            log.exception("robot_bridge: odometry handler failed")

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


def robot_session(bridge: BridgeSettings, transport: Any) -> zenoh.Session:
    """A client session to the robot's own Zenoh router (multicast scouting off)."""
    return zenoh.open(plain_config(transport, bridge.robot_endpoint))


def run(settings: Settings, bus: Bus, stop: threading.Event, duration: float | None) -> dict:
    if settings.transport.secure and not settings.bridge.robot_endpoint:
        # srl's access rules cover srl's keys: a robot's ROS 2 traffic on srl's secured router
        # would be refused, and the bridge would wait for odometry that never comes
        raise SecurityError(
            "robot_bridge: with transport.secure the robot must be on its own Zenoh router: set "
            "bridge.robot_endpoint (SRL_BRIDGE__ROBOT_ENDPOINT, --robot-endpoint)"
        )
    robot = settings.transport.robot
    graph = RosGraph.from_settings(settings.bridge)
    own_session = bool(settings.bridge.robot_endpoint)
    session = robot_session(settings.bridge, settings.transport) if own_session else bus.session
    link = RosLink(session, graph, settings.bridge, bus)
    actor_gate = SourceGate("actor")
    bridge = RobotBridge(settings, bus.publisher(STATE, robot), link.send, bus, actor_gate)
    link.on_odometry = bridge.on_odometry
    entities: list[Any] = []
    try:
        # one plant per robot (issue 13): never a second plant beside a live one
        bus.refuse_other_plant(robot)
        # the actor is alive while one of its sessions' identity tokens is (common.net.provenance)
        bus.watch_identities(robot, "actor", actor_gate, bridge.on_actor_identity)
        bus.subscribe(
            ACTION,
            ACTION.key(robot),
            lambda message, source: bridge.on_action(message, time.monotonic(), source),
            with_source=True,
        )
        link.start()
        bus.declare_sole_plant(robot)  # and a plant started at the same moment: one of the two yields
        entities.append(bus.session.liveliness().declare_token(liveliness_key(robot, "robot_bridge")))
        start_status_thread(
            bus,
            robot,
            settings.transport.status_period,
            stop,
            lambda: {"seq": bridge.seq, "cmd_v": bridge.last_command[0], "cmd_omega": bridge.last_command[1]},
        )
        log.info(
            "robot_bridge ready (robot %s, %s, goal %s in the odom frame)", robot, graph.profile, settings.bridge.goal
        )
        ticker = Ticker(settings.plant.sampling_time / 10.0, stop)
        end = None if duration is None else time.monotonic() + duration
        while (now := ticker.wait()) is not None and (end is None or now < end):
            link.tick(now)
            bridge.tick(now)
    finally:
        wire = link.describe()
        for _ in range(SHUTDOWN_ZEROS):  # on the way out: stop the robot
            bridge.stop()
            time.sleep(0.02)
        for entity in entities:
            try:
                entity.undeclare()
            except zenoh.ZError as error:
                log.debug("undeclare: %s", error)
        link.close()
        if own_session:
            session.close()
    return bridge_summary(graph, settings, wire, bridge, dict(bus.counters)).to_json_dict()


def bridge_summary(
    graph: RosGraph, settings: Settings, wire: dict[str, Any], bridge: RobotBridge, counters: dict[str, int]
) -> BridgeSummary:
    """One robot's bridge summary (a bridge process, or one robot of a bridge host)."""
    return BridgeSummary.model_validate(
        {
            "profile": graph.profile,
            "ros_distro": graph.distro,
            "namespace": graph.namespace,
            "goal": list(settings.bridge.goal),
            **wire,
            "final_state": None if bridge.last_state is None else list(bridge.last_state),
            "max_abs_command": bridge.max_abs_command,
            "timing": bridge.timing(),
            "counters": counters,
        }
    )
