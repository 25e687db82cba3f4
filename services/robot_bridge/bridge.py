"""The robot bridge's logic, transport-free: odometry -> PlantState, Action -> command, the watchdog.

:class:`RobotBridge` is given its ports (``publish_state``, ``send_command``, counters, the actor's
:class:`~common.net.provenance.SourceGate`) and knows nothing of Zenoh or ROS keys; the ROS side is
services/robot_bridge/ros_link.py, the process services/robot_bridge/host.py. Its rules
(docs/robot.md):

* **Goal frame.** The goal is a configured pose ``bridge.goal`` in the robot's odom frame, default
  ``(0, 0, 0)``: the odom origin, where the robot's odometry started (TurtleBot3: at bringup or
  after ``reset_odometry``). Not "the pose at bridge start-up": a bridge restart would then move
  the target to wherever the robot stands, silently. The state is ``common.math.frames.to_goal_frame``
  of the odometry pose, its heading unwrapped (continuous) from sample to sample.
* **Localization** (``bridge.pose_source``, docs/turtlebot-localization.md). ``odom``: the state is
  the odometry pose. Otherwise the state is the odometry pose corrected by the ``map -> odom``
  transform (common/math/localization.py): taken from ``/tf`` as it is, or computed from each fix
  of AMCL's ``PoseWithCovarianceStamped``, an EKF's ``Odometry`` or a motion-capture
  ``PoseStamped`` and the odometry at the fix's stamp; a new correction is blended in over
  ``bridge.pose_blend_time`` (no jump in the state), and the goal is in the localization's frame.
  The localization is **stale** once odometry has moved ``bridge.pose_stale_distance`` or turned
  ``bridge.pose_stale_angle`` since its last fix (AMCL updates only after motion, so age alone
  says nothing while the robot stands), or, for a streaming source (tf, odometry, pose_stamped),
  when its last fix is older than ``bridge.pose_timeout``. Stale: the robot is commanded zero at
  once, no state is published and no action applied until a fresh fix (one warning line, counted
  under ``localization_stale_stops``); before the first fix no state is published (one warning
  after ``bridge.pose_timeout``).
* **Odometry** is refused (counted, never published) when it has a non-finite pose or a zero
  quaternion, is beyond the schema's physical bounds, or is not newer than the last sample by its
  header stamp (out of order), or is stamped far ahead of the robot's clock. After
  :data:`CLOCK_RESET_AFTER` refused stale (or far-ahead) samples in a row the robot's clock is taken
  to have been reset (or to have jumped) and the new time base is accepted. (What does not decode,
  carries a foreign type hash or lacks the rmw_zenoh attachment is refused by the link first.)
* **Commands.** An action is applied only if it is for this robot, newer (episode, step) than the
  last one, from the live actor session, and the actor's liveliness token is present. It is
  clamped to ``plant.v_max``, ``plant.omega_max`` and the TurtleBot3 Burger's 0.22 m/s, 2.84 rad/s;
  a non-finite value can never reach ``cmd_vel`` (the schema refuses it, and the last guard before
  the wire sends zero).
* **Watchdog.** Every ``delta / 10`` the bridge checks that the last applied action is younger than
  ``bridge.watchdog_timeout_steps * delta`` and that the actor is alive; otherwise it commands zero
  velocity at once and keeps commanding zero every ``delta / 2`` until a fresh action arrives (a
  TurtleBot3 holds its last command forever, so the zero must come from here). The actor's token
  vanishing stops the robot at once (from the liveliness callback).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any, Protocol

from pydantic import ValidationError

from common.config.settings import Settings
from common.contracts import ros_wire
from common.contracts.messages import MAX_POSITION, Action, PlantState
from common.contracts.ros_wire import ODOM_FRAME, POSE_SOURCES, Odometry, PoseFix, pose_topic
from common.math.dynamics import unwrap_heading
from common.math.frames import Pose2D, clamp_command, to_goal_frame, wrap_angle, yaw_from_quaternion
from common.math.localization import CorrectionBlend, OdomHistory, correction, motion
from common.math.stats import Window
from common.net.provenance import (
    MAX_ACTION_EPISODE_JUMP,
    MAX_ACTION_STEP_JUMP,
    RESYNC_AFTER,
    ActionGate,
    ActionOrder,
    SourceGate,
)

log = logging.getLogger(__name__)
CLOCK_RESET_AFTER = 20  # consecutive out-of-order odometry samples taken as a robot clock reset
# An odometry stamp more than this ahead of where the robot's clock should be (the last stamp
# plus the time elapsed here) is refused WITHOUT becoming the reference: one sample stamped an
# hour ahead must not make the next real samples "old". CLOCK_RESET_AFTER such samples in a row
# are taken as the robot's clock having jumped forward.
FUTURE_STAMP_TOLERANCE_NS = 5_000_000_000
# A localization fix farther than this from its frame's origin is refused: the state schema's bound.
LOCALIZATION_BOUND = MAX_POSITION


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
        # provenance: with a gate, actions only from the live actor session (common.net.provenance)
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
        # localization (bridge.pose_source): the map -> odom correction and when it is stale
        bridge = settings.bridge
        self.pose_source = bridge.pose_source
        # its row (common/contracts/ros_wire.py POSE_SOURCES); None: odometry alone (odom)
        self.source = POSE_SOURCES.get(bridge.pose_source)
        self.localized = self.source is not None
        self.pose_topic = pose_topic(bridge)
        self.odom_frame = f"{bridge.namespace}/{ODOM_FRAME}" if bridge.namespace else ODOM_FRAME
        self.pose_timeout = bridge.pose_timeout
        self.stale_distance, self.stale_angle = bridge.pose_stale_distance, bridge.pose_stale_angle
        self.streaming = self.source is None or self.source.streams  # AMCL's pose: only after motion
        self.blend = CorrectionBlend(bridge.pose_blend_time)
        self.correction: Pose2D | None = None  # the map -> odom correction of the newest localized state
        self.history = OdomHistory()
        self.fix_at: float | None = None  # when (our monotonic clock) the last fix came
        self.fix_odom: Pose2D | None = None  # the odometry pose at the last fix
        self.fix_stamp_ns: int | None = None
        self.fix_frame: str | None = None
        self.pending_fix: tuple[int, Pose2D, float] | None = None  # a fix that came before any odometry
        self.localization_stale: str | None = None  # why the localization is stale (None: fresh)
        self.missing_warned = False
        self.started_at = time.monotonic()
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
            raw = Pose2D(odom.x, odom.y, yaw)
            if self.localized:
                located = self._localize(odom.stamp_ns, raw, received)
                if located is None:  # no fresh localization: no state (the actor stops on its own)
                    self.stale_run = self.future_run = 0
                    self.last_stamp_ns, self.last_stamp_at = odom.stamp_ns, received
                    self.counts.count("states_withheld")
                    return None
                raw = located
            correction = self.correction if self.localized else None
            pose = to_goal_frame(raw, self.goal)
            alpha = wrap_angle(pose.theta) if self.alpha is None else unwrap_heading(self.alpha, pose.theta)
            try:
                state = PlantState(
                    robot=self.robot,
                    episode=0,
                    seq=self.seq + 1,
                    stamp_ns=time.monotonic_ns(),
                    state=(pose.x, pose.y, alpha),
                    source="robot",
                    map_to_odom=None if correction is None else (correction.x, correction.y, correction.theta),
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

    # -- localization ---------------------------------------------------------------------
    def on_localization(self, fix: PoseFix, received: float) -> None:
        """A fix of the localization source: the ``map -> odom`` correction it implies."""
        if self.source is None:  # odometry alone: not localized
            return
        if self.source.map_to_odom and fix.child_frame_id.lstrip("/") != self.odom_frame:
            return  # /tf carries every transform of the robot: only map -> odom is ours
        try:
            yaw = yaw_from_quaternion(*fix.orientation)
            if not (math.isfinite(fix.x) and math.isfinite(fix.y)):
                raise ValueError(f"position ({fix.x}, {fix.y}) is not finite")
            if max(abs(fix.x), abs(fix.y)) > LOCALIZATION_BOUND:
                raise ValueError(f"position ({fix.x}, {fix.y}) beyond {LOCALIZATION_BOUND:g} m")
        except ValueError as error:
            self.counts.reject("localization", str(error))
            return
        with self.lock:
            if self.fix_stamp_ns is not None and fix.stamp_ns <= self.fix_stamp_ns:
                # transient-local history and the live sample may both bring one fix
                self.counts.reject("localization", f"stamp {fix.stamp_ns} not newer than {self.fix_stamp_ns}")
                return
            self.fix_stamp_ns = fix.stamp_ns
            if self.fix_frame != fix.frame_id:
                self.fix_frame = fix.frame_id
                log.info(
                    "robot_bridge: localized by %s on %s in frame %s", self.pose_source, self.pose_topic, fix.frame_id
                )
            pose = Pose2D(fix.x, fix.y, yaw)
            if not self.source.map_to_odom and self.history.latest() is None:
                # a fix before any odometry (AMCL's transient-local pose comes at once): fused with
                # the first odometry sample
                self.pending_fix = (fix.stamp_ns, pose, received)
                return
            self._take_fix(fix.stamp_ns, pose, received)

    def _take_fix(self, stamp_ns: int, pose: Pose2D, received: float) -> None:
        """A fix's correction (lock held): ``/tf``'s map -> odom as it is, else the fix composed
        with the odometry at its stamp."""
        self.pending_fix = None
        if self.source is not None and self.source.map_to_odom:
            target, at = pose, self.history.latest()
        else:
            at = self.history.at(stamp_ns)
            if at is None:
                return
            target = correction(pose, at)
        # after a stale spell (the robot stopped, no state published) or at the first fix the
        # correction is taken at once; otherwise blended in: no jump in the actor's state
        self.blend.set(target, received, snap=self.localization_stale is not None or self.fix_at is None)
        self.fix_at, self.fix_odom = received, at
        self.counts.count("localization_fixes")
        if self.localization_stale is not None:
            log.warning("robot_bridge: localization on %s is back: states resume", self.pose_topic)
            self.localization_stale = None

    def _localize(self, stamp_ns: int, odom: Pose2D, now: float) -> Pose2D | None:
        """The localized pose of an odometry sample (lock held); None while the localization is
        missing or stale (then the robot is stopped once, with one warning)."""
        self.history.add(stamp_ns, odom)
        if self.pending_fix is not None:
            self._take_fix(*self.pending_fix)
        reason = self._stale_reason(odom, now)
        if reason is not None:
            self._localization_lost(reason, now)
            return None
        self.correction = self.blend.value(now)
        return self.blend.apply(odom, now)

    def _stale_reason(self, odom: Pose2D | None, now: float) -> str | None:
        if self.fix_at is None:
            return "missing"
        if odom is not None and self.fix_odom is not None:
            distance, angle = motion(self.fix_odom, odom)
            if distance > self.stale_distance or angle > self.stale_angle:
                return (
                    f"odometry moved {distance:.2f} m and turned {angle:.2f} rad since the last fix on "
                    f"{self.pose_topic} (limits {self.stale_distance:g} m, {self.stale_angle:g} rad)"
                )
        if self.streaming and now - self.fix_at > self.pose_timeout:
            return f"no fix on {self.pose_topic} for {now - self.fix_at:.2f} s (limit {self.pose_timeout:g} s)"
        return None

    def _localization_lost(self, reason: str, now: float) -> None:
        """No usable localization (lock held): say so once, stop the robot if it was localized."""
        if reason == "missing":
            if not self.missing_warned and now - self.started_at > self.pose_timeout:
                self.missing_warned = True
                self.counts.count("localization_missing")
                log.warning(
                    "robot_bridge: no localization on %s (pose_source %s) in %.1f s: no state until a fix comes",
                    self.pose_topic,
                    self.pose_source,
                    self.pose_timeout,
                )
            return
        if self.localization_stale is None:
            self.localization_stale = reason
            self.counts.count("localization_stale_stops")
            log.warning("robot_bridge: localization stale (%s): stopping the robot, no state until a fresh fix", reason)
            self.driving = False
            self.last_action_at = None
            self._zero(now)

    def localization(self) -> str:
        """What the state's pose is, for the summary."""
        if not self.localized:
            return "odometry only"
        return f"{self.pose_source} on {self.pose_topic} (frame {self.fix_frame or 'none seen'})"

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
            if self.localized and (self.fix_at is None or self.localization_stale is not None):
                self.counts.reject("action", "no fresh localization")
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
                self._actor_lost()
                self.actor_alive = live  # counted once: the stop above is the actor's loss
                return
        self.set_actor_alive(live)

    def set_actor_alive(self, alive: bool) -> None:
        with self.lock:
            if self.actor_alive and not alive:
                log.warning("robot_bridge: the actor's liveliness token vanished: stopping the robot")
                self._actor_lost()
            self.actor_alive = alive

    def _actor_lost(self) -> None:
        """The actor is gone (lock held): zero velocity at once, no action applied until a fresh one."""
        self.counts.count("actor_lost_stops")
        self.driving = False
        self.last_action_at = None
        self._zero(time.monotonic())

    def tick(self, now: float) -> None:
        """The watchdog: zero velocity, repeated, while no fresh action from a live actor."""
        with self.lock:
            if self.localized and self.localization_stale is None and self.fix_at is not None:
                reason = self._stale_reason(self.history.latest(), now)  # a streaming source fell silent
                if reason is not None:
                    self._localization_lost(reason, now)
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
