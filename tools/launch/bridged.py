"""``srl up --plant robot``: ROS 2 robots behind robot bridges (docs/robot.md, docs/fleets.md).

The robot of the settings (``srl up --plant robot``) is named, placed and reached as its settings
say (``bridge.namespace``, ``episode.start``, ``bridge.robot_endpoint``). In a fleet each robot's
srl id is its ROS namespace (common/math/fleet.py ``ros_fleet``; ``--robots K`` names them
``tb3_1`` .. ``tb3_K``). Without endpoints, the robots are emulated TurtleBot3s, each under its
namespace and as its own Zenoh router on a free loopback port (as a real robot runs ``rmw_zenohd``;
under ``--secure`` secured, :func:`spawn_robot_plants`), a fleet's from distinct starts on its
circle. With ``--robot-endpoints`` / ``--robot-endpoint`` no emulator is started: the bridges talk
to the real robots there.
Layout ``host``: one bridge host for every robot (services/robot_bridge/host.py); ``process``:
one ``srl robot-bridge`` per robot. tools/launch/up.py starts the rest (router, critic, actors)
exactly as for simulated robots.
"""

from __future__ import annotations

import functools
import logging
import math
import threading
import time
from pathlib import Path
from typing import Any

import zenoh
from pydantic import TypeAdapter

from common.config.settings import Settings
from common.contracts.keys import STATE
from common.contracts.messages import PlantState
from common.contracts.summaries import BridgeSummary, EmulatorSummary, FleetBridgeSummary
from common.math.frames import Pose2D, to_goal_frame
from common.net.transport import zenoh_config
from services.robot_bridge.robot_router import RobotLogins, robot_router_reachable
from tools.launch.supervisor import Supervisor, free_loopback_endpoint, tls_endpoint

log = logging.getLogger(__name__)

EMULATOR_READY_S = 30.0  # [s] an emulator's router answers (as srl up --plant robot waits)
ODOMETRY_READY_S = 60.0  # [s] every robot's first state through its bridge


def spawn_robot_plants(
    supervisor: Supervisor,
    settings: Settings,
    common: list[str],
    robots: list[str],
    starts: list[tuple[float, float, float]] | None,
    endpoints: dict[str, str],
    bridge_args: list[str],
    layout: str,
    login: dict[str, str] | None = None,
    robot_secrets: Path | None = None,
) -> dict[str, str]:
    """The emulated robots (for robots without an endpoint) and the bridge(s) (children named
    ``robot_bridge``...: stopped first); robot -> endpoint. ``starts`` None: the robot of the settings, its
    namespace, start and endpoint (``bridge.robot_endpoint``) the settings' (``srl up --plant robot``);
    else a fleet, each robot's namespace its id, emulated from its start. ``login``: the bridges'
    login environment (the plant role's, ``--secure``). ``robot_secrets`` (``--secure``): a directory
    for the emulated robots' router credentials; each emulated robot's own router is then secured
    (docs/security.md, "The robot's own router"): ``tls/``, a login and the robot's access rules
    for its namespace, from ONE set of credentials (services/robot_bridge/robot_router.py
    ``RobotLogins``), since one bridge host logs in to every robot with one ``bridge.robot_*``. Real
    robots' routers are as their owners configured them."""
    own = starts is None  # the robot of the settings: named by the user's flags, not the fleet's
    fleet = dict(endpoints)
    if own and settings.bridge.robot_endpoint:
        fleet[robots[0]] = settings.bridge.robot_endpoint
    emulated = [robot for robot in robots if not fleet.get(robot)]
    robot_logins = RobotLogins.create(robot_secrets) if robot_secrets is not None and emulated else None
    emulator_env = None if robot_logins is None else robot_logins.emulator_environment
    if robot_logins is not None:  # the robot's credentials go to the bridges only
        login = {**(login or {}), **robot_logins.bridge_environment}
    for i, robot in enumerate(robots):
        if fleet.get(robot):
            continue  # a real robot: it is where it is
        endpoint = free_loopback_endpoint()
        fleet[robot] = endpoint = endpoint if robot_logins is None else tls_endpoint(endpoint) or endpoint
        where = [] if starts is None else [f"--namespace={robot}", "--start=" + ",".join(repr(c) for c in starts[i])]
        supervisor.spawn(
            "tb3_emulator" if own else f"tb3_emulator-{robot}",
            ["tb3-emulator", *common, *bridge_args, *where, f"--listen={endpoint}"],
            emulator_env,
        )
        log.info("the emulated robot's Zenoh router: %s (robot %s)", endpoint, robot)
    for robot in emulated:  # reachable as its bridge reaches it (with the login, if any)
        probe = (
            settings.bridge.model_copy(update={"robot_endpoint": fleet[robot]})
            if robot_logins is None
            else robot_logins.bridge(settings.bridge, fleet[robot])
        )
        supervisor.wait_for(
            f"the emulated robot {robot}'s router ({fleet[robot]})",
            functools.partial(robot_router_reachable, probe, settings.transport),
            timeout=EMULATOR_READY_S,
        )
    if own:
        (robot,) = robots
        supervisor.spawn(
            "robot_bridge", ["robot-bridge", *common, *bridge_args, f"--robot-endpoint={fleet[robot]}"], login
        )
    elif layout == "host":
        spec = ",".join(f"{robot}={fleet[robot]}" for robot in robots)
        supervisor.spawn(
            "robot_bridge",
            ["robot-bridge", *common, *bridge_args, f"--robots={','.join(robots)}", f"--robot-endpoints={spec}"],
            login,
        )
    else:
        for robot in robots:
            supervisor.spawn(
                f"robot_bridge-{robot}",
                [
                    "robot-bridge",
                    *common,
                    *bridge_args,
                    f"--robot={robot}",
                    f"--namespace={robot}",
                    f"--robot-endpoint={fleet[robot]}",
                ],
                login,
            )
    return fleet


def wait_odometry(supervisor: Supervisor, settings: Settings, fleet: dict[str, str]) -> None:
    """Until every robot's state came through its bridge; the robots still silent are named."""
    seen: set[str] = set()
    lock = threading.Lock()

    def on_state(sample: Any) -> None:
        try:
            robot = PlantState.model_validate_json(sample.payload.to_bytes()).robot
        except ValueError:
            return
        with lock:
            seen.add(robot)

    session = zenoh.open(zenoh_config(settings.transport))
    # one robot's own key: a secured router grants the monitor role that robot's keys, not srl/*
    robot = next(iter(fleet)) if len(fleet) == 1 else "*"
    subscriber = session.declare_subscriber(STATE.pattern.format(robot=robot), on_state)
    try:
        deadline = time.monotonic() + ODOMETRY_READY_S
        while time.monotonic() < deadline:
            supervisor.check()
            with lock:
                if set(fleet) <= seen:
                    return
            time.sleep(0.05)
        silent = [f"{r} (namespace /{r}, {fleet[r]})" for r in fleet if r not in seen]
        raise TimeoutError(
            f"no odometry after {ODOMETRY_READY_S:.0f} s from {', '.join(silent)} "
            f"({settings.bridge.profile}, {settings.bridge.ros_distro}, domain {settings.bridge.domain_id})"
        )
    finally:
        subscriber.undeclare()
        session.close()


def robot_fleet_summary(supervisor: Supervisor, settings: Settings, robots: list[str], layout: str) -> dict[str, Any]:
    """Per robot: its namespace, endpoint, what its bridge applied and sent, and (emulated) where
    the robot truly ended and which cmd_vel key it listened on."""
    if layout == "host":
        host = FleetBridgeSummary.model_validate(supervisor.children["robot_bridge"].summary())
        bridges, endpoints = host.per_robot, host.endpoints
    else:
        bridges = {
            r: TypeAdapter(BridgeSummary).validate_python(supervisor.children[f"robot_bridge-{r}"].summary())
            for r in robots
        }
        endpoints = {}
    goal = Pose2D(*settings.bridge.goal)
    rows: dict[str, Any] = {}
    for robot in robots:
        bridge = bridges[robot]
        row: dict[str, Any] = {
            "namespace": bridge.namespace,
            "endpoint": endpoints.get(robot),
            "cmd_vel": [target.key for target in bridge.cmd_vel],
            "actions_applied": bridge.counters.get("actions_applied", 0),
            # refused for whatever reason (rejected.action, rejected.action.unknown, ...)
            "actions_refused": sum(n for k, n in bridge.counters.items() if k.split(".")[:2] == ["rejected", "action"]),
            "commands_sent": bridge.counters.get("commands_sent", 0),  # every cmd_vel put: actions and zeros
            "states_published": bridge.counters.get("states_published", 0),
            "localization": bridge.localization,  # "odometry only", or the source its pose came from
            "emulator": None,
        }
        child = supervisor.children.get(f"tb3_emulator-{robot}")
        raw = None if child is None else child.summary()
        if raw is not None:
            emulator = EmulatorSummary.model_validate(raw)
            true = to_goal_frame(Pose2D(*emulator.final_pose), goal)
            row["emulator"] = {
                "cmd_key": emulator.cmd_key,
                "odom_key": emulator.odom_key,
                "cmd_received": emulator.counters.get("cmd_received", 0),
                "cmd_applied": emulator.counters.get("cmd_applied", 0),
                "initial_pose": emulator.initial_pose,
                "true_final_state": [true.x, true.y, true.theta],
                "true_final_distance_m": math.hypot(true.x, true.y),
                "applied_at_end": emulator.applied,
            }
        rows[robot] = row
    return rows


def format_robot_lines(rows: dict[str, Any]) -> list[str]:
    lines = []
    for robot, row in rows.items():
        emulator = row["emulator"]
        where = "real robot" if emulator is None else f"emulated, true final {emulator['true_final_distance_m']:.3f} m"
        lines.append(
            f"  {robot:<12} namespace /{row['namespace']}: actions applied {row['actions_applied']}, "
            f"refused {row['actions_refused']}, {where}, pose: {row.get('localization', 'odometry only')}"
        )
    return lines


def robot_router_line(rows: dict[str, Any]) -> str:
    """What ``--secure`` covers on the robots' side: the emulated robots' own routers are secured
    (:func:`spawn_robot_plants`); real robots' routers are as configured there (docs/security.md)."""
    if any(row["emulator"] is not None for row in rows.values()):
        return (
            "  robot routers  each emulated robot's own: mutual TLS, the bridge's login and the robot's "
            "access rules (services/robot_bridge/robot_router.py)"
        )
    return (
        "  robot routers  the robots' own, as configured there: the bridge logs in with bridge.robot_* and "
        "warns if one lets in sessions without credentials (docs/security.md)"
    )
