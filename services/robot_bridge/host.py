"""robot_bridge: ROS 2 robots as the plant -- odometry in, ``cmd_vel`` out, over Zenoh.

It publishes and consumes the same keys as plant_sim (``srl/<robot>/state``, ``srl/<robot>/action``)
and declares the same liveliness token (``srl/<robot>/alive/plant``, plus ``alive/robot_bridge``),
so the actor and the critic cannot tell which plant they talk to (docs/turtlebot.md).

One process serves K robots (``srl robot-bridge``: K = 1, its robot id ``transport.robot`` and its
ROS namespace ``bridge.namespace``; ``--robots``: each robot's id is its ROS namespace,
common/math/fleet.py ``ros_fleet``: robot ``tb3_1`` reads ``/tb3_1/odom`` and commands
``/tb3_1/cmd_vel``, rmw_zenoh keys ``<domain>/tb3_1/odom/...``, ros2dds keys ``tb3_1/odom``, and its
frames are ``tb3_1/odom``, ``tb3_1/base_footprint``). One robot and many run the same code.

A robot's bridge is three parts: the logic (services/robot_bridge/bridge.py: goal frame, odometry
checks, the live actor session's actions, the watchdog), the ROS side
(services/robot_bridge/ros_link.py: keys, CDR, cmd_vel discovery, attachment format) and the run
here: :func:`wire_robot` joins the first two for one robot, :func:`attach` puts them on srl's bus,
:func:`shut_down` is the way out. Every robot keeps its own :class:`RobotBridge`, :class:`RosLink`,
counters and summary, on srl's keys of its own id (``srl/<id>/state``, ``action``, ``alive/plant``,
``alive/robot_bridge``, ``status/plant``). On the way out every robot is commanded zero
:data:`SHUTDOWN_ZEROS` times before anything is undeclared.

One srl session serves them all, and one client session per distinct robot endpoint: robots that
each run their own router (``rmw_zenohd`` on the robot, ``--robot-endpoints``) get one session
each, robots reached through one router (``--robot-endpoint``) share one. Each is opened by
services/robot_bridge/robot_router.py ``robot_session``: with the ``bridge.robot_*`` login and TLS,
waited for up to ``bridge.robot_connect_timeout``. A robot's commands can only go to its own
namespace's keys: its link builds every key from its namespace, and its bridge applies only
actions for its id.

Why one process for several robots and not one bridge per robot: a bridge process is a Python
interpreter with Zenoh and the ROS type store, and a host pays for one of them whatever its number
of robots (docs/fleets.md). One bridge per robot (``srl up --robots K --plant robot --layout
process``) isolates a crash to one robot; either way a real robot still needs its own command
timeout (docs/robot.md).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from common.config.arguments import UsageError
from common.config.settings import BridgeSettings, Settings, TransportSettings
from common.contracts.keys import ACTION, STATE, liveliness_key
from common.contracts.messages import Action, PlantState
from common.contracts.ros_wire import RosGraph
from common.contracts.summaries import BridgeSummary, FleetBridgeSummary
from common.net.provenance import SourceGate
from common.net.security import SecurityError
from common.net.transport import Bus, bus_status, start_status_thread
from common.process.counts import RobotCounts
from common.system.clock import Ticker
from services.robot_bridge.bridge import Counts, RobotBridge
from services.robot_bridge.robot_router import robot_session
from services.robot_bridge.ros_link import RosLink, undeclare

log = logging.getLogger(__name__)
# node and entity ids per robot in a shared session: robot i uses i * ENTITY_IDS ... (rmw_zenoh
# wants them unique per session; a link needs 2 + one per cmd_vel target)
ENTITY_IDS = 100
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


@dataclass
class BridgeUnit:
    """One robot of the host: its id, endpoint, settings (its ROS namespace), bridge and link."""

    robot: str
    endpoint: str
    settings: Settings
    graph: RosGraph
    counts: RobotCounts
    link: RosLink
    bridge: RobotBridge
    actor_gate: SourceGate

    def on_action(self, message: Action, source: str | None) -> None:
        self.bridge.on_action(message, time.monotonic(), source)


def robot_settings(settings: Settings, robot: str, endpoint: str, namespace: str | None = None) -> Settings:
    """The settings of one robot of the host: its id, its ROS namespace (default: the id), its endpoint."""
    ros_namespace = robot if namespace is None else namespace
    return settings.model_copy(
        update={
            "transport": settings.transport.model_copy(update={"robot": robot}),
            "bridge": settings.bridge.model_copy(update={"namespace": ros_namespace, "robot_endpoint": endpoint}),
        }
    )


def open_unit(
    settings: Settings,
    robot: str,
    endpoint: str,
    index: int,
    session: Any,
    publish_state: Any,
    namespace: str | None = None,
    forward: Callable[[str, str], None] | None = None,
) -> BridgeUnit:
    """Robot ``index`` of the host on ``session`` (its robot's router, or srl's): transport-free
    but for the session, so a test can hand it a fake one. ``namespace``: its ROS namespace
    (default: its id); ``forward``: where its refusals go too (the process's ``Bus.reject``)."""
    own = robot_settings(settings, robot, endpoint, namespace)
    counts = RobotCounts(robot, "robot_bridge", forward=forward)
    link, bridge, gate = wire_robot(own, session, publish_state, counts, entity_base=index * ENTITY_IDS)
    return BridgeUnit(robot, endpoint, own, link.graph, counts, link, bridge, gate)


def open_robot_sessions(
    settings: Settings,
    fleet: dict[str, str],
    stop: threading.Event,
    sessions: dict[str, Any],
    connect: Callable[[BridgeSettings, TransportSettings, threading.Event], Any] = robot_session,
) -> None:
    """One session per distinct robot endpoint of ``fleet`` into ``sessions``, each opened as one
    bridge opens its robot's (services/robot_bridge/robot_router.py ``robot_session``): the
    ``bridge.robot_user`` login and ``robot_tls_*`` on a ``tls/`` endpoint, waiting with one status
    line up to ``bridge.robot_connect_timeout`` for a robot that boots late, ``stop`` ending the
    wait, and under ``transport.secure`` one WARNING per robot router that lets in strangers. The
    timeout bounds the whole fleet, not each robot (``srl up`` waits that long for the host). A
    robot that never comes is one error line naming the robots behind that endpoint; the sessions
    already open stay in ``sessions`` for the caller to close."""
    deadline = time.monotonic() + settings.bridge.robot_connect_timeout
    for endpoint in sorted({e for e in fleet.values() if e}):
        left = max(0.0, deadline - time.monotonic())
        bridge = settings.bridge.model_copy(update={"robot_endpoint": endpoint, "robot_connect_timeout": left})
        try:
            sessions[endpoint] = connect(bridge, settings.transport, stop)
        except UsageError as error:
            on_it = ", ".join(r for r, e in fleet.items() if e == endpoint)
            raise UsageError(f"{error} (robot {on_it})") from None


def run_bridge_host(
    settings: Settings,
    bus: Bus,
    fleet: dict[str, str],
    stop: threading.Event,
    duration: float | None,
    namespaces: dict[str, str] | None = None,
) -> FleetBridgeSummary:
    """Serve every robot of ``fleet`` (robot id -> its endpoint, '' = srl's router) until ``stop``
    or ``duration``. ``namespaces``: each robot's ROS namespace (default: its id; one robot's
    ``srl robot-bridge``: ``bridge.namespace``, which may be none). The host's
    :class:`FleetBridgeSummary`, whatever the number of robots (one robot's own:
    common.contracts.summaries.robot_summary)."""
    if settings.transport.secure and not all(fleet.values()):
        # srl's access rules cover srl's keys: a robot's ROS 2 traffic on srl's secured router
        # would be refused, and the bridge would wait for odometry that never comes
        raise SecurityError(
            "robot_bridge: with transport.secure every robot must be on its own Zenoh router: give it an "
            "endpoint (bridge.robot_endpoint, SRL_BRIDGE__ROBOT_ENDPOINT, --robot-endpoint; with --robots "
            "also --robot-endpoints)"
        )
    own_namespace = namespaces or {}
    robots = list(fleet)
    sessions: dict[str, Any] = {}
    units: list[BridgeUnit] = []
    tokens: list[Any] = []
    try:
        for robot in robots:  # one plant per robot, before declaring anything
            bus.refuse_other_plant(robot)
        open_robot_sessions(settings, fleet, stop, sessions)
        for index, robot in enumerate(robots):
            endpoint = fleet[robot]
            session = sessions[endpoint] if endpoint else bus.session
            publish = bus.publisher(STATE, robot)
            namespace = own_namespace.get(robot)
            units.append(open_unit(settings, robot, endpoint, index, session, publish, namespace, bus.reject))
        for unit in units:
            attach(bus, unit.robot, unit.link, unit.bridge, unit.actor_gate)
        bus.declare_sole_plants(robots)
        tokens = [bus.session.liveliness().declare_token(liveliness_key(r, "robot_bridge")) for r in robots]
        rows = [(unit.robot, unit_status(unit)) for unit in units]
        if len(units) == 1:  # the process's counters are its one robot's (srl up's live line)
            rows = [(units[0].robot, bus_status(bus, rows[0][1]))]
        start_status_thread(bus, rows, settings.transport.status_period, stop)
        log.info(
            "robot_bridge ready: %d robots (%s, goal %s in each odom frame), %s",
            len(robots),
            settings.bridge.profile,
            settings.bridge.goal,
            ", ".join(
                f"{u.robot} (namespace {u.graph.namespace or '/'}) on {u.endpoint or 'srl router'}" for u in units
            ),
        )
        ticker = Ticker(settings.plant.sampling_time / 10.0, stop)
        end = None if duration is None else time.monotonic() + duration
        while (now := ticker.wait()) is not None and (end is None or now < end):
            for unit in units:
                unit.link.tick(now)
                unit.bridge.tick(now)
    finally:
        described = shut_down([(unit.link, unit.bridge) for unit in units], tokens, list(sessions.values()))
        wires = {unit.robot: wire for unit, wire in zip(units, described, strict=True)}
    process = {k: float(v) for k, v in bus.counters.items()}
    return FleetBridgeSummary(
        robots=robots,
        endpoints=dict(fleet),
        per_robot={
            unit.robot: bridge_summary(
                unit.graph, unit.settings, wires[unit.robot], unit.bridge, unit.counts.snapshot()
            )
            for unit in units
        },
        counters=process,
    )


def unit_status(unit: BridgeUnit) -> Callable[[], dict[str, float]]:
    """One robot's status counters (``srl/<id>/status/plant``), as one bridge's."""

    def counters() -> dict[str, float]:
        values = {k: float(v) for k, v in unit.counts.snapshot().items()}
        values.update(
            seq=float(unit.bridge.seq), cmd_v=unit.bridge.last_command[0], cmd_omega=unit.bridge.last_command[1]
        )
        return values

    return counters


def bridge_summary(
    graph: RosGraph, settings: Settings, wire: dict[str, Any], bridge: RobotBridge, counters: dict[str, Any]
) -> BridgeSummary:
    """One robot's bridge summary."""
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
