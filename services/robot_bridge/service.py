"""robot_bridge: a ROS 2 robot as the plant -- odometry in, ``cmd_vel`` out, over Zenoh.

It publishes and consumes the same keys as plant_sim (``srl/<robot>/state``, ``srl/<robot>/action``)
and declares the same liveliness token (``srl/<robot>/alive/plant``, plus ``alive/robot_bridge``),
so the actor and the critic cannot tell which plant they talk to (docs/turtlebot.md).

A bridge is three parts: the logic (services/robot_bridge/bridge.py: goal frame, odometry checks,
the live actor session's actions, the watchdog), the ROS side (services/robot_bridge/ros_link.py:
keys, CDR, cmd_vel discovery, attachment format) and the run here: :func:`wire_robot` joins the first
two for one robot, :func:`attach` puts them on srl's bus, :func:`shut_down` is the way out, and
:func:`run` serves one robot with them (services/robot_bridge/host.py serves several). On the way
out every robot is commanded zero :data:`SHUTDOWN_ZEROS` times before anything is undeclared.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from common.config.settings import Settings
from common.contracts.keys import ACTION, STATE, liveliness_key
from common.contracts.messages import PlantState
from common.contracts.ros_wire import RosGraph
from common.contracts.summaries import BridgeSummary
from common.net.provenance import SourceGate
from common.net.security import SecurityError
from common.net.transport import Bus, bus_status, start_status_thread
from common.system.clock import Ticker
from services.robot_bridge.bridge import Counts, RobotBridge
from services.robot_bridge.robot_router import robot_session
from services.robot_bridge.ros_link import RosLink, undeclare

log = logging.getLogger(__name__)
# zero-velocity commands on the way out, 20 ms apart: one lost sample must not leave the robot
# driving (a TurtleBot3 holds its last command)
SHUTDOWN_ZEROS = 3


def wire_robot(
    settings: Settings,
    session: Any,
    publish_state: Callable[[PlantState], None],
    counts: Counts,
    entity_base: int = 0,
) -> tuple[RosLink, RobotBridge, SourceGate]:
    """One robot's bridge on ``session`` (its robot's router, or srl's): its ROS link, the logic
    the link feeds and that sends through it, and the gate of the actor sessions it follows."""
    link = RosLink(session, RosGraph.from_settings(settings.bridge), settings.bridge, counts, entity_base)
    actor_gate = SourceGate("actor")
    bridge = RobotBridge(settings, publish_state, link.send, counts, actor_gate)
    link.on_odometry = bridge.on_odometry
    link.on_localization = bridge.on_localization
    return link, bridge, actor_gate


def attach(bus: Bus, robot: str, link: RosLink, bridge: RobotBridge, actor_gate: SourceGate) -> None:
    """One robot's bridge on srl's bus: the actor is alive while one of its sessions' identity
    tokens is (common.net.provenance), its actions come in; then the ROS link starts."""
    bus.watch_identities(robot, "actor", actor_gate, bridge.on_actor_identity)
    bus.subscribe(
        ACTION,
        ACTION.key(robot),
        lambda message, source: bridge.on_action(message, time.monotonic(), source),
        with_source=True,
    )
    link.start()


def shut_down(
    robots: list[tuple[RosLink, RobotBridge]], tokens: list[Any], sessions: list[Any]
) -> list[dict[str, Any]]:
    """The way out of one bridge or a bridge host: each link's wire described, every robot
    commanded zero :data:`SHUTDOWN_ZEROS` times, srl's ``tokens`` undeclared, the links closed,
    then the robots' own ``sessions``. Returns each link's description, in order."""
    wires = [link.describe() for link, _ in robots]
    for _ in range(SHUTDOWN_ZEROS):  # on the way out: stop every robot
        for _, bridge in robots:
            bridge.stop()
        time.sleep(0.02)
    undeclare(tokens)
    for link, _ in robots:
        link.close()
    for session in sessions:
        session.close()
    return wires


def run(settings: Settings, bus: Bus, stop: threading.Event, duration: float | None) -> dict:
    if settings.transport.secure and not settings.bridge.robot_endpoint:
        # srl's access rules cover srl's keys: a robot's ROS 2 traffic on srl's secured router
        # would be refused, and the bridge would wait for odometry that never comes
        raise SecurityError(
            "robot_bridge: with transport.secure the robot must be on its own Zenoh router: set "
            "bridge.robot_endpoint (SRL_BRIDGE__ROBOT_ENDPOINT, --robot-endpoint)"
        )
    robot = settings.transport.robot
    own_session = bool(settings.bridge.robot_endpoint)
    session = robot_session(settings.bridge, settings.transport, stop) if own_session else bus.session
    link, bridge, actor_gate = wire_robot(settings, session, bus.publisher(STATE, robot), bus)
    graph = link.graph
    tokens: list[Any] = []
    try:
        # one plant per robot: never a second plant beside a live one
        bus.refuse_other_plant(robot)
        attach(bus, robot, link, bridge, actor_gate)
        bus.declare_sole_plant(robot)  # and a plant started at the same moment: one of the two yields
        tokens.append(bus.session.liveliness().declare_token(liveliness_key(robot, "robot_bridge")))
        own = bus_status(
            bus, lambda: {"seq": bridge.seq, "cmd_v": bridge.last_command[0], "cmd_omega": bridge.last_command[1]}
        )
        start_status_thread(bus, [(robot, own)], settings.transport.status_period, stop)
        log.info(
            "robot_bridge ready (robot %s, %s, goal %s in the odom frame)", robot, graph.profile, settings.bridge.goal
        )
        ticker = Ticker(settings.plant.sampling_time / 10.0, stop)
        end = None if duration is None else time.monotonic() + duration
        while (now := ticker.wait()) is not None and (end is None or now < end):
            link.tick(now)
            bridge.tick(now)
    finally:
        [wire] = shut_down([(link, bridge)], tokens, [session] if own_session else [])
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
            "localization": bridge.localization(),
            "max_abs_command": bridge.max_abs_command,
            "timing": bridge.timing(),
            "counters": counters,
        }
    )
