"""tb3_emulator: a TurtleBot3 Burger that speaks ROS 2 over Zenoh as the real robot does.

What it emulates, per wire profile (common/contracts/ros_wire.py has the formats):

* ``rmw_zenoh`` -- the robot's ``turtlebot3_node`` subscribes ``cmd_vel`` (Twist on Humble,
  TwistStamped on Jazzy: turtlebot3_bringup's ``enable_stamped_cmd_vel``; ``--cmd-type``
  overrides) with ``KeepLast(10)``; its ``diff_drive_controller`` publishes ``odom``. The
  emulator declares the liveliness tokens of both nodes, of the subscription and of the
  publisher, exactly as rmw_zenoh_cpp would, and, like rmw_zenoh's subscriber, drops a
  ``cmd_vel`` sample without the attachment (counted). Its own odometry carries one.
  ``--attachment legacy`` emulates rmw_zenoh_cpp Humble 0.1.0-0.1.1 / Jazzy 0.2.0-0.2.3 (the
  attachment with field names, ros_wire.py): its odometry carries that format, and a ``cmd_vel``
  attachment in the other format is counted under ``attachment_format_errors`` -- where that
  release's subscriber throws inside its Zenoh callback (the robot's process may abort).
* ``ros2dds`` -- a DDS robot behind zenoh-bridge-ros2dds: plain keys (``cmd_vel``, ``odom``,
  ``<namespace>/...``), raw CDR, no attachment; the bridge's ``@/<zid>/@ros2_lv/...`` tokens.

The command path is the real one: turtlebot3_node writes ``int32(v * 100)`` (C++
``static_cast<int32_t>``: truncation toward zero; on the robot's ARM CPU an out-of-range value
saturates and NaN becomes 0) to the OpenCR control table, whose firmware multiplies by ``0.01f``
(float32) and constrains to its limits. So velocities have a resolution of 0.01 m/s and
0.01 rad/s, and ``|v| < 0.01`` is zero. The limits default to the Burger's published 0.22 m/s
and 2.84 rad/s (the OpenCR ROS 2 firmware computes 0.2108 m/s and 2.635 rad/s from its 61 rpm
motors; pass ``--v-max``/``--omega-max`` to emulate that). Wheels reach the command at once (no
motor dynamics); the pose integrates the unicycle exactly (``common.math.dynamics.exact_step``),
piecewise at every command change. Odometry is published at 20 Hz (turtlebot3_node's 50 ms
sensor timer), frame ``odom``, child ``base_footprint`` (namespace-prefixed when namespaced),
with the applied velocity in its twist; optional seeded Gaussian noise on the reported pose and
a command latency.

**Localization** (``--localization``, docs/turtlebot-localization.md): the emulator also plays
the robot's localization, so the bridge's ``bridge.pose_source`` path is tested end to end. Then
its world frame is ``map``, its odometry starts at the origin of ``odom`` where the robot stands
at start (as a TurtleBot3's does at bringup), and it publishes the true pose in ``map`` with
seeded Gaussian noise (``--localization-noise``) by the source's rule (:class:`FixRule`):
``pose_with_covariance`` is AMCL's ``amcl_pose`` (a fix at start, then only after the robot
moved ``--localization-update`` 0.25 m or turned 0.2 rad, nav2_amcl's update_min_d/update_min_a
of turtlebot3_navigation2's burger.yaml; reliable, transient local, KeepLast(1), served to late
subscribers from a zenoh-ext AdvancedPublisher cache as rmw_zenoh_cpp does); ``tf`` is AMCL's
``map -> odom`` on ``/tf``, from the same sparse fixes, sent at ``--localization-rate``;
``odometry`` (an EKF's ``odometry/filtered``) and ``pose_stamped`` (motion capture) stream at
``--localization-rate`` (10 Hz).

A stock TurtleBot3 has no cmd_vel timeout: the OpenCR stops only when the heartbeat from
turtlebot3_node stops for 500 ms (``HEARTBEAT_TIMEOUT_MS``), and turtlebot3_node writes it every
100 ms whatever cmd_vel does -- it holds its last command forever. That is why the bridge has a
watchdog, and why a robot whose command path can break (its cmd_vel comes through a router that
may die) needs a timeout of its own, a node that publishes zero when its input falls silent
(docs/turtlebot-first-robot.md, the safety checklist: ``twist_mux`` alone only stops forwarding).
The emulator therefore times out by default (``--cmd-timeout``, 0.5 s,
the OpenCR's own heartbeat bound); ``--cmd-timeout 0`` emulates the stock robot that holds.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from collections import Counter, deque
from typing import Any

import numpy as np
import zenoh
import zenoh.ext

from common.contracts import ros_wire
from common.contracts.ros_wire import (
    ODOMETRY,
    POSE_SOURCES,
    Attachment,
    AttachmentFormat,
    Odometry,
    PoseFix,
    RosGraph,
    WireError,
    qos_chunk,
)
from common.math.frames import Pose2D, quaternion_from_yaw
from common.math.localization import compose, correction, inverse, motion
from common.math.physics import PhysicsParams
from common.math.plant_models import plant_model_row
from common.math.turtlebot import SimulatedRobot, TurtleBot, TurtleBotParams, cmd_vel_to_wheels
from common.system.clock import Ticker

log = logging.getLogger(__name__)


class Tb3Model:
    """The emulated robot in the odom frame, on a clock: the robot of plant model ``model``
    (common/math/plant_models.py; ``--model``), built from ``params`` (``[actuator]``, its speed
    limits replaced by ``v_max`` and ``omega_max``) and ``physics``. A model with no robot of its
    own (``ideal``) is the OpenCR command path in front of the exact unicycle, its odometry the
    truth. Commands reach the robot after ``latency``."""

    def __init__(
        self,
        pose: Pose2D,
        v_max: float,
        omega_max: float,
        latency: float,
        cmd_timeout: float,
        noise: tuple[float, float],
        seed: int,
        now: float,
        model: str = "ideal",
        params: TurtleBotParams | None = None,
        physics: PhysicsParams | None = None,
    ) -> None:
        start = np.array([pose.x, pose.y, pose.theta], dtype=float)
        build = plant_model_row(model).build
        self.ideal = build is None
        self.kind = model
        self.robot: SimulatedRobot
        if build is None:  # the firmware's conversion and limits, the wheels ideal
            self.robot = TurtleBot(dataclasses.replace(TurtleBotParams.ideal(v_max, omega_max), quantize=True), start)
        else:
            if params is None or physics is None:
                raise ValueError(f"the emulated {model!r} robot needs the [actuator] and [physics] settings")
            self.robot = build(dataclasses.replace(params, v_max=v_max, omega_max=omega_max), physics, start)
        self.latency, self.cmd_timeout = latency, cmd_timeout
        self.noise = noise
        self.rng = np.random.default_rng(seed)
        self.applied_at = now
        self.t = now
        self.pending: deque[tuple[float, float, float]] = deque()  # (due, v, omega) as received
        self.lock = threading.Lock()
        self.max_abs = [0.0, 0.0]
        self.timeouts = 0

    @property
    def state(self) -> np.ndarray:
        """The true pose (odom frame): where the emulated robot really is."""
        return self.robot.true_pose

    @property
    def odometry(self) -> np.ndarray:
        """The pose it reports (ideal: the true pose)."""
        return self.robot.odometry

    @property
    def applied(self) -> tuple[float, float]:
        return self.robot.applied

    def command(self, v: float, omega: float, now: float) -> tuple[float, float]:
        """A cmd_vel arrives: applied now or after the latency. Returns the (v, omega) the robot
        will apply (its conversion: common.math.turtlebot.cmd_vel_to_wheels)."""
        target = cmd_vel_to_wheels(self.robot.params, v, omega).applied
        with self.lock:
            self.pending.append((now + self.latency, v, omega))
            self._advance(now)
        return target

    def _advance(self, now: float) -> None:
        while self.pending and self.pending[0][0] <= now:
            due, v, omega = self.pending.popleft()
            self._integrate(max(due, self.t))
            applied = self.robot.command(v, omega)
            self.applied_at = due
            self.max_abs = [max(self.max_abs[0], abs(applied[0])), max(self.max_abs[1], abs(applied[1]))]
        if self.cmd_timeout > 0 and self.applied != (0.0, 0.0) and now - self.applied_at > self.cmd_timeout:
            self._integrate(self.applied_at + self.cmd_timeout)
            self.robot.command(0.0, 0.0)
            self.timeouts += 1
        self._integrate(now)

    def _integrate(self, until: float) -> None:
        if until > self.t:
            self.robot.advance(until - self.t)
            self.t = until

    def sample(self, now: float) -> tuple[np.ndarray, tuple[float, float]]:
        """Advance to ``now``; the reported pose (odometry, with noise) and velocity (ideal: the
        applied command; actuator: the encoders' velocity, as turtlebot3_node reports it)."""
        with self.lock:
            self._advance(now)
            pose = self.robot.odometry.copy()
            velocity = self.robot.applied if self.ideal else self.robot.velocity
        sigma_xy, sigma_theta = self.noise
        if sigma_xy > 0 or sigma_theta > 0:
            pose = pose + self.rng.normal(0.0, 1.0, 3) * np.array([sigma_xy, sigma_xy, sigma_theta])
        return pose, velocity


@dataclasses.dataclass(frozen=True)
class LocalizationConfig:
    """What localization the emulator publishes (``--localization`` and its options)."""

    source: str  # a key of ros_wire.POSE_SOURCES
    topic: str
    noise: tuple[float, float] = (0.0, 0.0)  # [m, rad] std. dev. on the published pose
    update: tuple[float, float] = (0.25, 0.2)  # [m, rad] AMCL: a fix after this much motion
    rate: float = 10.0  # [Hz] streaming sources, and /tf


class FixRule:
    """When a localization fix is due: for a source whose publisher updates after motion (its
    row's ``after_motion``: AMCL's ``pose_with_covariance`` and ``tf``) at the first call and then
    after the true pose moved ``update`` (distance or angle) since the last fix; else every
    ``1 / rate`` seconds."""

    def __init__(self, config: LocalizationConfig) -> None:
        self.sparse = ros_wire.POSE_SOURCES[config.source].after_motion
        self.update, self.period = config.update, 1.0 / config.rate
        self.last_pose: Pose2D | None = None
        self.last_at: float | None = None

    def due(self, truth: Pose2D, now: float) -> bool:
        if self.last_pose is None or self.last_at is None:
            ok = True
        elif self.sparse:
            distance, angle = motion(self.last_pose, truth)
            ok = distance >= self.update[0] or angle >= self.update[1]
        else:
            ok = now - self.last_at >= self.period - 1e-9
        if ok:
            self.last_pose, self.last_at = truth, now
        return ok


def run(
    session: zenoh.Session,
    graph: RosGraph,
    cmd_type: str,
    model: Tb3Model,
    stop: threading.Event,
    duration: float | None,
    odom_topic: str,
    cmd_topic: str,
    odom_rate: float,
    attachment: AttachmentFormat = "compact",
    localization: LocalizationConfig | None = None,
) -> dict[str, Any]:
    counters: Counter[str] = Counter()
    lock = threading.Lock()
    zid = str(session.info.zid())
    entities: list[Any] = []

    def count(name: str) -> None:
        with lock:
            counters[name] += 1

    def on_cmd(sample: zenoh.Sample) -> None:
        now = time.monotonic()
        count("cmd_received")
        if graph.profile == "rmw_zenoh":
            if sample.attachment is None:  # rmw_zenoh: "Unable to obtain attachment"
                count("rejected_no_attachment")
                return
            try:
                received = Attachment.decode(bytes(sample.attachment.to_bytes()))
            except WireError:
                count("rejected_bad_attachment")
                return
            if received.format != attachment:  # the robot's rmw_zenoh cannot read it
                count("rejected_bad_attachment")
                count("attachment_format_errors")
                log.error(
                    "tb3-emulator: cmd_vel with a %s attachment; this robot's rmw_zenoh reads %s only%s",
                    received.format,
                    attachment,
                    " (rmw_zenoh_cpp 0.2.0-0.2.3 throws here: the process may abort)" if attachment == "legacy" else "",
                )
                return
        try:
            v, omega = ros_wire.decode_command(graph.distro, cmd_type, bytes(sample.payload.to_bytes()))
        except WireError:
            count("rejected_cdr")
            return
        if not (math.isfinite(v) and math.isfinite(omega)):
            count("nonfinite_commands")  # the robot would apply 0 (ARM) -- a bridge must never send it
        model.command(v, omega, now)
        count("cmd_applied")

    ros_wire.typestore(graph.distro)  # load it now, not on the first sample
    cmd_key = graph.data_key(cmd_topic, cmd_type)
    odom_key = graph.data_key(odom_topic, ODOMETRY)
    entities.append(session.declare_subscriber(cmd_key, on_cmd))
    liveliness = session.liveliness()
    if graph.profile == "rmw_zenoh":
        tokens = [
            graph.node_token(zid, 0, ros_wire.TB3_CMD_NODE),
            graph.endpoint_token(zid, 0, 10, "MS", ros_wire.TB3_CMD_NODE, cmd_topic, cmd_type),
            graph.node_token(zid, 20, ros_wire.TB3_ODOM_NODE),
            graph.endpoint_token(zid, 20, 21, "MP", ros_wire.TB3_ODOM_NODE, odom_topic, ODOMETRY),
        ]
    else:
        tokens = [
            graph.ros2dds_plugin_token(zid),
            graph.ros2dds_token(zid, "MS", cmd_topic, cmd_type),
            graph.ros2dds_token(zid, "MP", odom_topic, ODOMETRY),
        ]
    entities.extend(liveliness.declare_token(token) for token in tokens)
    odom_gid = ros_wire.gid_for(tokens[-1])
    publisher = session.declare_publisher(odom_key)
    entities.append(publisher)
    frame, child = graph.frame_id(ros_wire.ODOM_FRAME), graph.frame_id(ros_wire.BASE_FRAME)
    log.info(
        "tb3-emulator ready: %s %s, cmd_vel %s on %s, odom on %s",
        graph.profile,
        graph.distro,
        cmd_type,
        cmd_key,
        odom_key,
    )

    localize = None if localization is None else _Localizer(session, graph, zid, localization, model, attachment)
    if localize is not None:
        entities.extend(localize.entities)
    # localized: the odom frame starts where the robot stands (REP 105), the world frame is map
    origin = Pose2D(*(float(c) for c in model.state)) if localize is not None else None
    seq = 0
    ticker = Ticker(1.0 / odom_rate, stop)
    end = None if duration is None else time.monotonic() + duration
    try:
        while (now := ticker.wait()) is not None and (end is None or now < end):
            pose, (v, omega) = model.sample(now)
            stamp = time.time_ns()
            if origin is not None:
                pose = np.array(compose(inverse(origin), Pose2D(*(float(c) for c in pose))))
            payload = ros_wire.encode_odometry(
                graph.distro,
                Odometry(
                    stamp_ns=stamp,
                    frame_id=frame,
                    child_frame_id=child,
                    x=float(pose[0]),
                    y=float(pose[1]),
                    orientation=quaternion_from_yaw(float(pose[2])),
                    v=v,
                    omega=omega,
                ),
            )
            seq += 1
            if graph.profile == "rmw_zenoh":
                publisher.put(payload, attachment=Attachment(seq, stamp, odom_gid, attachment).encode())
            else:
                publisher.put(payload)
            count("odom_published")
            if localize is not None:
                for name in localize.publish(Pose2D(*(float(c) for c in pose)), stamp, now):
                    count(name)
    finally:
        for entity in reversed(entities):
            try:
                entity.undeclare()
            except zenoh.ZError as error:
                log.debug("undeclare: %s", error)
    _, applied = model.sample(time.monotonic())
    reported = Pose2D(*(float(c) for c in model.odometry))
    if origin is not None:  # localized: odometry in its own odom frame
        reported = compose(inverse(origin), reported)
    return {
        "service": "tb3_emulator",
        "profile": graph.profile,
        "ros_distro": graph.distro,
        "cmd_type": cmd_type,
        "attachment": attachment if graph.profile == "rmw_zenoh" else None,
        "cmd_key": cmd_key,
        "odom_key": odom_key,
        "localization": None if localization is None else localization.source,
        "model": model.kind,
        "final_pose": [float(c) for c in model.state],  # the truth (odom frame)
        "final_odometry": [float(c) for c in reported],  # what it reported
        "saturated_commands": model.robot.saturated_commands,
        "applied": list(applied),
        "max_abs_applied": model.max_abs,
        "cmd_timeouts": model.timeouts,
        "counters": dict(counters),
        "missed_ticks": ticker.missed,
    }


class _Localizer:
    """The emulated robot's localization publisher (:class:`LocalizationConfig`, :class:`FixRule`)."""

    def __init__(
        self,
        session: zenoh.Session,
        graph: RosGraph,
        zid: str,
        config: LocalizationConfig,
        model: Tb3Model,
        attachment: AttachmentFormat,
    ) -> None:
        self.graph, self.config, self.model, self.attachment = graph, config, model, attachment
        self.source = POSE_SOURCES[config.source]
        self.rule = FixRule(config)
        self.rng = np.random.default_rng(model.rng.integers(2**32))  # its own stream, seeded by --seed
        self.key = graph.data_key(config.topic, self.source.ros_type)
        node = ros_wire.POSE_SOURCES[config.source].node
        if graph.profile == "rmw_zenoh":
            tokens = [
                graph.node_token(zid, 30, node),
                graph.endpoint_token(
                    zid,
                    30,
                    31,
                    "MP",
                    node,
                    config.topic,
                    self.source.ros_type,
                    qos=qos_chunk(self.source.depth, self.source.transient_local),
                ),
            ]
        else:
            tokens = [graph.ros2dds_token(zid, "MP", config.topic, self.source.ros_type)]
        self.gid = ros_wire.gid_for(tokens[-1])
        self.entities: list[Any] = [session.liveliness().declare_token(token) for token in tokens]
        if self.source.transient_local:
            # rmw_zenoh_cpp's transient-local publisher (rmw_publisher_data.cpp): an AdvancedPublisher
            # with a cache of ``depth`` samples, detectable by late subscribers
            self.publisher: Any = zenoh.ext.declare_advanced_publisher(
                session,
                self.key,
                cache=zenoh.ext.CacheConfig(max_samples=self.source.depth),
                publisher_detection=True,
            )
        else:
            self.publisher = session.declare_publisher(self.key)
        self.entities.append(self.publisher)
        self.seq = 0
        self.frames = (graph.frame_id(ros_wire.MAP_FRAME), graph.frame_id(ros_wire.ODOM_FRAME))
        self.child = graph.frame_id(ros_wire.BASE_FRAME)
        self.map_to_odom: Pose2D | None = None
        self.tf_at: float | None = None
        log.info("tb3-emulator: localization %s on %s", config.source, self.key)

    def publish(self, odom: Pose2D, stamp: int, now: float) -> list[str]:
        """Publish what is due at ``now`` (``odom``: the odometry just published); the counter names."""
        truth = Pose2D(*(float(c) for c in self.model.state))
        published: list[str] = []
        if self.rule.due(truth, now):
            sigma_xy, sigma_theta = self.config.noise
            noise = self.rng.normal(0.0, 1.0, 3) * np.array([sigma_xy, sigma_xy, sigma_theta])
            fix = Pose2D(truth.x + noise[0], truth.y + noise[1], truth.theta + noise[2])
            if self.source.map_to_odom:  # /tf: the map -> odom transform, not a pose
                self.map_to_odom = correction(fix, odom)  # AMCL's map -> odom from its estimate
            else:
                message = PoseFix(
                    stamp,
                    self.frames[0],
                    self.child,
                    fix.x,
                    fix.y,
                    quaternion_from_yaw(fix.theta),
                    (sigma_xy**2, sigma_xy**2, sigma_theta**2),
                )
                if self.source.ros_type == ODOMETRY:
                    payload = ros_wire.encode_odometry(
                        self.graph.distro,
                        Odometry(stamp, message.frame_id, self.child, fix.x, fix.y, message.orientation, 0.0, 0.0),
                    )
                else:
                    payload = ros_wire.encode_pose(self.graph.distro, self.source.ros_type, message)
                self._put(payload, stamp)
                published.append("localization_published")
        if (
            self.source.map_to_odom
            and self.map_to_odom is not None
            and (self.tf_at is None or now - self.tf_at >= 1.0 / self.config.rate - 1e-9)
        ):
            self.tf_at = now
            c = self.map_to_odom
            transform = PoseFix(stamp, self.frames[0], self.frames[1], c.x, c.y, quaternion_from_yaw(c.theta))
            self._put(ros_wire.encode_tf(self.graph.distro, [transform]), stamp)
            published.append("tf_published")
        return published

    def _put(self, payload: bytes, stamp: int) -> None:
        self.seq += 1
        if self.graph.profile == "rmw_zenoh":
            self.publisher.put(payload, attachment=Attachment(self.seq, stamp, self.gid, self.attachment).encode())
        else:
            self.publisher.put(payload)
