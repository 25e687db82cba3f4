"""The bridge host: one ``srl robot-bridge --robots ...`` process for several ROS 2 robots.

Each srl robot id is its robot's ROS namespace (common/math/fleet.py ``ros_fleet``): robot ``tb3_1``
reads ``/tb3_1/odom`` and commands ``/tb3_1/cmd_vel`` (rmw_zenoh keys ``<domain>/tb3_1/odom/...``,
ros2dds keys ``tb3_1/odom``), and its frames are ``tb3_1/odom``, ``tb3_1/base_footprint``.
Every robot keeps what one bridge keeps -- its own :class:`RobotBridge` (goal frame, heading,
odometry checks, the live actor session's actions in order, the watchdog) and its own
:class:`RosLink` (cmd_vel discovery, attachment format, publishers), its own counters and
summary -- on srl's keys of its own id (``srl/<id>/state``, ``action``, ``alive/plant``,
``alive/robot_bridge``, ``status/plant``), wired, attached and shut down as one bridge is
(services/robot_bridge/service.py). One srl session serves them all, and one client
session per distinct robot endpoint: robots that each run their own router (``rmw_zenohd`` on
the robot, ``--robot-endpoints``) get one session each, robots reached through one router
(``--robot-endpoint``) share one. Each is opened as one bridge opens its robot's
(services/robot_bridge/robot_router.py ``robot_session``): with the ``bridge.robot_*`` login and
TLS, waited for up to ``bridge.robot_connect_timeout``. A robot's commands can only go to its own
namespace's keys: its link builds every key from its namespace, and its bridge applies only
actions for its id.

Why a host and not one bridge per robot: a bridge process is a Python interpreter with Zenoh and
the ROS type store, and a host pays for one of them whatever its number of robots
(docs/fleets.md). One bridge per robot (``srl up --robots K --plant robot --layout process``)
isolates a crash to one robot; either way a real robot still needs its own command timeout
(docs/turtlebot.md).
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
from common.contracts.fleet_summary import FleetBridgeSummary
from common.contracts.keys import STATE, liveliness_key
from common.contracts.messages import Action
from common.contracts.ros_wire import RosGraph
from common.net.provenance import SourceGate
from common.net.security import SecurityError
from common.net.transport import Bus, start_status_thread
from common.process.counts import RobotCounts
from common.system.clock import Ticker
from services.robot_bridge.bridge import RobotBridge
from services.robot_bridge.robot_router import robot_session
from services.robot_bridge.ros_link import RosLink
from services.robot_bridge.service import attach, bridge_summary, shut_down, wire_robot

log = logging.getLogger(__name__)
# node and entity ids per robot in a shared session: robot i uses i * ENTITY_IDS ... (rmw_zenoh
# wants them unique per session; a link needs 2 + one per cmd_vel target)
ENTITY_IDS = 100


@dataclass
class BridgeUnit:
    """One robot of the host: its id (= namespace), endpoint, settings, bridge and link."""

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


def robot_settings(settings: Settings, robot: str, endpoint: str) -> Settings:
    """The settings of one robot of the host: its id, its namespace (the id), its endpoint."""
    return settings.model_copy(
        update={
            "transport": settings.transport.model_copy(update={"robot": robot}),
            "bridge": settings.bridge.model_copy(update={"namespace": robot, "robot_endpoint": endpoint}),
        }
    )


def open_unit(
    settings: Settings,
    robot: str,
    endpoint: str,
    index: int,
    session: Any,
    publish_state: Any,
) -> BridgeUnit:
    """Robot ``index`` of the host on ``session`` (its robot's router, or srl's): transport-free
    but for the session, so a test can hand it a fake one."""
    own = robot_settings(settings, robot, endpoint)
    counts = RobotCounts(robot, "robot_bridge")
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
    settings: Settings, bus: Bus, fleet: dict[str, str], stop: threading.Event, duration: float | None
) -> dict[str, Any]:
    """Serve every robot of ``fleet`` (robot id = namespace -> its endpoint, '' = srl's router)."""
    if settings.transport.secure and not all(fleet.values()):
        raise SecurityError(
            "robot_bridge: with transport.secure every robot must be on its own Zenoh router: "
            "give every robot an endpoint (--robot-endpoints, --robot-endpoint)"
        )
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
            units.append(open_unit(settings, robot, endpoint, index, session, bus.publisher(STATE, robot)))
        for unit in units:
            attach(bus, unit.robot, unit.link, unit.bridge, unit.actor_gate)
        bus.declare_sole_plants(robots)
        tokens = [bus.session.liveliness().declare_token(liveliness_key(r, "robot_bridge")) for r in robots]
        start_status_thread(
            bus, [(unit.robot, unit_status(unit)) for unit in units], settings.transport.status_period, stop
        )
        log.info(
            "bridge host ready: %d robots (%s), %s",
            len(robots),
            settings.bridge.profile,
            ", ".join(f"{u.robot} on {u.endpoint or 'srl router'}" for u in units),
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
    return FleetBridgeSummary(
        robots=robots,
        endpoints=dict(fleet),
        per_robot={
            unit.robot: bridge_summary(
                unit.graph, unit.settings, wires[unit.robot], unit.bridge, unit.counts.snapshot()
            )
            for unit in units
        },
        counters={k: float(v) for k, v in bus.counters.items()},
    ).to_json_dict()


def unit_status(unit: BridgeUnit) -> Callable[[], dict[str, float]]:
    """One robot's status counters (``srl/<id>/status/plant``), as one bridge's."""

    def counters() -> dict[str, float]:
        values = {k: float(v) for k, v in unit.counts.snapshot().items()}
        values.update(
            seq=float(unit.bridge.seq), cmd_v=unit.bridge.last_command[0], cmd_omega=unit.bridge.last_command[1]
        )
        return values

    return counters
