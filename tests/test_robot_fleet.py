"""Several ROS 2 robots (docs/fleets.md): each srl robot id is its robot's ROS namespace.

First the mapping (common/math/fleet.py ``ros_fleet``) and the bridge host's per-robot units against an
in-memory Zenoh (every unit on ONE session, as robots reached through one router: only the
namespaces keep them apart); then ``srl up --robots 3 --plant robot`` with three emulated
TurtleBot3s, and a fleet on one shared robot router beside a robot the fleet does not map.
"""

from __future__ import annotations

import json
import logging
import math
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from common.config.arguments import UsageError
from common.config.settings import BridgeSettings, Settings, TransportSettings
from common.contracts import ros_wire
from common.contracts.messages import Action, PlantState
from common.contracts.ros_wire import ODOMETRY, TWIST_STAMPED, Attachment, Odometry, RosGraph
from common.math.fleet import FleetError, circle_starts, ros_fleet
from common.math.frames import quaternion_from_yaw
from services.robot_bridge.host import BridgeUnit, open_robot_sessions, open_unit
from tests.harness import ROOT, free_port, open_session, srl

ROBOTS = ["tb3_1", "tb3_2", "tb3_3"]
EMULATOR = [sys.executable, "-m", "tools.cli", "tb3-emulator"]

# -- the mapping --------------------------------------------------------------------------------


def test_each_robot_id_is_its_namespace_and_gets_its_endpoint() -> None:
    assert ros_fleet(ROBOTS, None, "") == dict.fromkeys(ROBOTS, "")  # none: emulate them
    shared = "tcp/10.0.0.10:7447"
    assert ros_fleet(ROBOTS, None, shared) == dict.fromkeys(ROBOTS, shared)  # one router for all
    own = "tb3_1=tcp/10.0.0.11:7447, tb3_2=tcp/10.0.0.12:7447,tb3_3=tcp/10.0.0.13:7447"
    assert ros_fleet(ROBOTS, own, "") == {
        "tb3_1": "tcp/10.0.0.11:7447",
        "tb3_2": "tcp/10.0.0.12:7447",
        "tb3_3": "tcp/10.0.0.13:7447",
    }
    # one robot on its own router, the rest through the shared one
    assert ros_fleet(ROBOTS, "tb3_2=tcp/10.0.0.12:7447", shared)["tb3_2"] == "tcp/10.0.0.12:7447"
    assert ros_fleet(ROBOTS, "tb3_2=tcp/10.0.0.12:7447", shared)["tb3_3"] == shared


@pytest.mark.parametrize(
    ("robots", "endpoints", "shared", "says"),
    [
        (["tb3_1", "robot-2"], None, "", "robot id 'robot-2' is not a ROS namespace"),
        (["1tb3"], None, "", "robot id '1tb3' is not a ROS namespace"),
        (ROBOTS, "tb3_9=tcp/10.0.0.19:7447", "", "namespace 'tb3_9' is not mapped to a robot of the fleet"),
        (ROBOTS, "tb3_1=tcp/a:1,tb3_1=tcp/b:1", "", "namespace 'tb3_1' is given twice"),
        (ROBOTS, "tb3_1", "", "is not NAMESPACE=ENDPOINT"),
        (ROBOTS, "tb3_1=10.0.0.11:7447", "", "is not NAMESPACE=ENDPOINT"),
        (ROBOTS, "tb3_1=tcp/10.0.0.11:7447", "", "no endpoint for tb3_2, tb3_3"),
        (ROBOTS, None, "10.0.0.10", "is not a Zenoh endpoint"),
    ],
)
def test_a_bad_mapping_is_refused_in_one_line(robots: list[str], endpoints: str | None, shared: str, says: str) -> None:
    with pytest.raises(FleetError) as refused:
        ros_fleet(robots, endpoints, shared)
    assert says in str(refused.value) and "\n" not in str(refused.value)


# -- the bridge host's units, against an in-memory Zenoh --------------------------------------


class _Bytes:
    def __init__(self, data: bytes) -> None:
        self.data = data

    def to_bytes(self) -> bytes:
        return self.data


@dataclass
class _Sample:
    key_expr: str
    payload: _Bytes
    attachment: _Bytes | None
    kind: Any = field(default_factory=lambda: zenoh.SampleKind.PUT)


class _Handle:
    def undeclare(self) -> None:
        pass


@dataclass
class FakeNetwork:
    """One router in memory: a put reaches every subscriber whose key expression intersects."""

    subscribers: list[tuple[zenoh.KeyExpr, Callable[[Any], None]]] = field(default_factory=list)
    puts: list[tuple[str, bytes, bytes | None]] = field(default_factory=list)
    tokens: list[str] = field(default_factory=list)

    def put(self, key: str, payload: bytes, attachment: bytes | None = None) -> None:
        self.puts.append((key, payload, attachment))
        sample = _Sample(key, _Bytes(payload), None if attachment is None else _Bytes(attachment))
        for expr, callback in list(self.subscribers):
            if expr.intersects(zenoh.KeyExpr(key)):
                callback(sample)


class FakeSession:
    """The part of zenoh.Session a RosLink uses."""

    def __init__(self, network: FakeNetwork) -> None:
        self.network = network
        self.info = type("Info", (), {"zid": staticmethod(lambda: "a1b2c3")})()

    def declare_subscriber(self, key: str, callback: Callable[[Any], None], **_: Any) -> _Handle:
        self.network.subscribers.append((zenoh.KeyExpr(key), callback))
        return _Handle()

    def declare_publisher(self, key: str, **_: Any) -> Any:
        network = self.network

        class _Publisher(_Handle):
            def put(self, payload: bytes, attachment: bytes | None = None) -> None:
                network.put(key, payload, attachment)

        return _Publisher()

    def liveliness(self) -> Any:
        session = self

        class _Liveliness:
            def declare_token(self, key: str) -> _Handle:
                session.network.tokens.append(key)
                return _Handle()

            def declare_subscriber(self, key: str, callback: Callable[[Any], None], **_: Any) -> _Handle:
                return session.declare_subscriber(key, callback)

        return _Liveliness()


ACTOR_ZID = "ac7"


def _units(network: FakeNetwork) -> tuple[dict[str, BridgeUnit], dict[str, list[PlantState]]]:
    settings = Settings.load(bridge={"cmd_type": "twist_stamped"})  # no discovery: the fake has no tokens
    session = FakeSession(network)
    states: dict[str, list[PlantState]] = {robot: [] for robot in ROBOTS}
    units = {}
    for index, robot in enumerate(ROBOTS):
        unit = open_unit(settings, robot, "", index, session, states[robot].append)
        unit.link.start()
        unit.actor_gate.update(ACTOR_ZID, True)  # each robot's actor is live
        unit.bridge.on_actor_identity(ACTOR_ZID, True)
        units[robot] = unit
    return units, states


def _odometry(network: FakeNetwork, namespace: str, stamp: int, x: float) -> None:
    """The robot of ``namespace`` publishes its odometry, as rmw_zenoh does (compact attachment)."""
    graph = RosGraph("rmw_zenoh", "jazzy", 0, namespace)
    odom = Odometry(stamp, f"{namespace}/odom", f"{namespace}/base_footprint", x, 0.0, quaternion_from_yaw(0.0), 0, 0)
    payload = ros_wire.encode_odometry("jazzy", odom)
    network.put(graph.data_key("odom", ODOMETRY), payload, Attachment(stamp, time.time_ns(), bytes(16)).encode())


def _action(robot: str, step: int, v: float) -> Action:
    return Action(robot=robot, episode=1, step=step, stamp_ns=0, action=(v, 0.0), state_seq=-1)


def _commands(network: FakeNetwork, namespace: str) -> list[float]:
    """The linear velocities put on ``namespace``'s cmd_vel."""
    prefix = f"0/{namespace}/cmd_vel/"
    return [
        ros_wire.decode_command("jazzy", TWIST_STAMPED, payload)[0]
        for key, payload, _ in network.puts
        if key.startswith(prefix)
    ]


def test_each_namespace_odometry_drives_only_its_own_robot_id() -> None:
    network = FakeNetwork()
    units, states = _units(network)
    for k, robot in enumerate(ROBOTS):
        _odometry(network, robot, 10, x=1.0 + k)
    _odometry(network, "tb3_9", 10, x=9.0)  # a robot on the same router that the fleet does not map
    _odometry(network, "", 10, x=8.0)  # and an un-namespaced one
    for k, robot in enumerate(ROBOTS):
        assert [(s.robot, s.state[0]) for s in states[robot]] == [(robot, 1.0 + k)]
        assert units[robot].counts.counters["odom_received"] == 1


def test_a_robot_never_receives_another_namespace_cmd_vel() -> None:
    network = FakeNetwork()
    units, _ = _units(network)
    for robot in ROBOTS:  # the attachment format comes from each robot's own odometry
        _odometry(network, robot, 10, x=1.0)
    received: dict[str, list[str]] = {robot: [] for robot in [*ROBOTS, "tb3_9"]}
    for namespace in received:  # each robot's turtlebot3_node subscribes its own cmd_vel
        key = RosGraph("rmw_zenoh", "jazzy", 0, namespace).data_key("cmd_vel", TWIST_STAMPED, "*")
        network.subscribers.append((zenoh.KeyExpr(key), lambda s, ns=namespace: received[ns].append(str(s.key_expr))))
    network.puts.clear()
    speeds = {"tb3_1": 0.05, "tb3_2": 0.10, "tb3_3": 0.15}
    for step in range(1, 4):
        for robot, v in speeds.items():
            units[robot].on_action(_action(robot, step, v), ACTOR_ZID)
    for robot, v in speeds.items():
        assert _commands(network, robot) == [v, v, v]  # its own actions, nobody else's
        assert received[robot] and all(key.startswith(f"0/{robot}/cmd_vel/") for key in received[robot])
        assert len(received[robot]) == 3
    assert received["tb3_9"] == []  # a namespace the fleet does not map hears nothing
    # negative control: tb3_2's action handed to tb3_1's bridge is refused, nothing reaches any robot
    before = len(network.puts)
    units["tb3_1"].on_action(_action("tb3_2", 4, 0.2), ACTOR_ZID)
    assert len(network.puts) == before
    assert units["tb3_1"].counts.counters["rejected.action"] == 1
    # and the watchdog of one robot stops that robot only
    units["tb3_2"].bridge.tick(time.monotonic() + 10.0)
    assert _commands(network, "tb3_2")[-1] == 0.0
    assert _commands(network, "tb3_1") == [0.05] * 3 and _commands(network, "tb3_3") == [0.15] * 3


def test_robots_on_one_session_have_distinct_rmw_zenoh_entities() -> None:
    """rmw_zenoh numbers a session's nodes and entities uniquely: three robots' links on one
    session declare three nodes and no (node id, entity id) twice."""
    network = FakeNetwork()
    units, _ = _units(network)
    # @ros2_lv/<domain>/<zid>/<nid>/<eid>/<kind>/...
    entities = [tuple(token.split("/")[3:5]) for token in network.tokens]
    nodes = [token for token in network.tokens if token.split("/")[5] == "NN"]
    assert len(nodes) == len(ROBOTS) and len(set(entities)) == len(entities), network.tokens
    assert len({t.split("/")[3] for t in nodes}) == len(ROBOTS)  # one node id per robot
    gids = {robot: next(iter(unit.link.targets.values())).gid for robot, unit in units.items()}
    assert len(set(gids.values())) == len(ROBOTS)
    keys = {robot: next(iter(unit.link.targets.values())).endpoint.key for robot, unit in units.items()}
    assert all(keys[robot].startswith(f"0/{robot}/cmd_vel/") for robot in ROBOTS)


# -- the host's sessions to the robots' own routers --------------------------------------------


def test_the_host_opens_each_robot_router_once_with_the_bridges_login_under_one_deadline() -> None:
    """Robots on one router share a session; each router gets the bridge's login and TLS
    (bridge.robot_*), the run's stop event, and what is left of ONE connect timeout."""
    settings = Settings.load(
        bridge={
            "robot_user": "srl_bridge",
            "robot_password_file": "/secrets/srl_bridge.password",
            "robot_tls_ca": "/secrets/ca.pem",
            "robot_connect_timeout": 7.0,
        }
    )
    shared, own = "tls/127.0.0.1:7001", "tls/127.0.0.1:7000"
    fleet = {"tb3_1": shared, "tb3_2": shared, "tb3_3": own}
    stop = threading.Event()
    calls: list[BridgeSettings] = []

    def connect(bridge: BridgeSettings, transport: TransportSettings, given: threading.Event) -> str:
        assert given is stop and transport == settings.transport
        calls.append(bridge)
        time.sleep(0.05)  # a robot that takes a while: the next one gets less time
        return f"session to {bridge.robot_endpoint}"

    sessions: dict[str, Any] = {}
    open_robot_sessions(settings, fleet, stop, sessions, connect)
    assert sessions == {own: f"session to {own}", shared: f"session to {shared}"}
    assert [c.robot_endpoint for c in calls] == [own, shared]
    for call in calls:
        assert (call.robot_user, call.robot_password_file, call.robot_tls_ca) == (
            "srl_bridge",
            "/secrets/srl_bridge.password",
            "/secrets/ca.pem",
        )
    assert 6.9 < calls[0].robot_connect_timeout <= 7.0
    assert calls[1].robot_connect_timeout <= calls[0].robot_connect_timeout - 0.05


def test_a_robot_router_that_never_comes_is_one_line_naming_its_robots() -> None:
    settings = Settings.load()
    fleet = {"tb3_1": "tcp/127.0.0.1:7000", "tb3_2": "tcp/127.0.0.1:7001", "tb3_3": "tcp/127.0.0.1:7001"}

    def connect(bridge: BridgeSettings, _transport: TransportSettings, _stop: threading.Event) -> str:
        if bridge.robot_endpoint.endswith(":7001"):
            raise UsageError(f"robot_bridge: cannot reach the robot's Zenoh router at {bridge.robot_endpoint}")
        return "opened"

    sessions: dict[str, Any] = {}
    with pytest.raises(UsageError) as refused:
        open_robot_sessions(settings, fleet, threading.Event(), sessions, connect)
    assert str(refused.value) == (
        "robot_bridge: cannot reach the robot's Zenoh router at tcp/127.0.0.1:7001 (robot tb3_2, tb3_3)"
    )
    assert sessions == {"tcp/127.0.0.1:7000": "opened"}  # left for the host to close


@pytest.mark.integration
def test_the_host_waits_for_a_late_robot_with_one_status_line_and_gives_up_at_its_timeout(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The real session (services/robot_bridge/robot_router.py robot_session), no robot there."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = Settings.load(bridge={"robot_connect_timeout": 1.0})
    started = time.monotonic()
    with caplog.at_level(logging.WARNING), pytest.raises(UsageError) as refused:
        open_robot_sessions(settings, {"tb3_1": endpoint}, threading.Event(), {})
    waited = time.monotonic() - started
    waiting = [r.getMessage() for r in caplog.records if "waiting for" in r.getMessage()]
    assert waiting == [f"robot_bridge: waiting for the robot's Zenoh router at {endpoint} (up to 1 s)"]
    assert 1.0 <= waited < 5.0
    assert str(refused.value).startswith(f"robot_bridge: cannot reach the robot's Zenoh router at {endpoint}")
    assert str(refused.value).endswith("(robot tb3_1)")


# -- the command line: a bad mapping is one line, nothing starts ------------------------------


def _srl(*argv: str, timeout: float = 60, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return srl(*argv, timeout=timeout, env=env)


@pytest.mark.integration
@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (("robot-bridge", "--robots", "tb3_1,tb3_2", "--robot-endpoints", "tb3_3=tcp/127.0.0.1:7447"), "not mapped"),
        (("robot-bridge", "--robots", "2", "--namespace", "tb3_1"), "each robot's ROS namespace is its robot id"),
        (("robot-bridge", "--robot-endpoints", "tb3_1=tcp/127.0.0.1:7447"), "--robot-endpoints needs --robots"),
        (("up", "--robots", "robot-1,robot-2", "--plant", "robot"), "is not a ROS namespace"),
        (("up", "--robots", "2", "--plant", "robot", "--robot-endpoints", "tb3_3=tcp/127.0.0.1:1"), "not mapped"),
        (("up", "--robots", "2", "--robot-endpoints", "tb3_1=tcp/127.0.0.1:1"), "is for --plant robot"),
    ],
)
def test_the_command_line_refuses_an_unmapped_namespace_in_one_line(argv: tuple[str, ...], says: str) -> None:
    done = _srl(*argv, "--router", f"tcp/127.0.0.1:{free_port()}")
    assert done.returncode == 2, done.stderr
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and says in lines[0], done.stderr


# -- integration: srl up --robots 3 --plant robot ---------------------------------------------


def _up_run(
    summary_dir: Path, *argv: str, timeout: float = 240, env: dict[str, str] | None = None
) -> tuple[dict[str, Any], str, str]:
    """``srl up ... --json``: its summary, stdout and stderr."""
    router = f"tcp/127.0.0.1:{free_port()}"
    done = _srl("up", *argv, "--router", router, "--json", "--summary-dir", str(summary_dir), timeout=timeout, env=env)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1]), done.stdout, done.stderr


def _up(summary_dir: Path, *argv: str, timeout: float = 240) -> dict[str, Any]:
    return _up_run(summary_dir, *argv, timeout=timeout)[0]


def _actor_summaries(summary: dict[str, Any], layout: str = "host") -> dict[str, Any]:
    """Each robot's actor summary, from the actor host's or from each robot's actor."""
    directory = Path(summary["summary_dir"])
    if layout == "host":
        return json.loads((directory / "actor.json").read_text())["per_robot"]
    return {robot: json.loads((directory / f"actor-{robot}.json").read_text()) for robot in summary["robots"]}


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.parametrize(("layout", "secure"), [("host", True), ("process", False)])
def test_up_three_emulated_turtlebots(tmp_path: Path, layout: str, secure: bool) -> None:
    """Three emulated TurtleBot3s (tb3_1..tb3_3, each its own router), one bridge host and one actor
    host (or one bridge and one actor per robot), the critic: each robot's odometry drives its own
    actor, every robot approaches the target. ``--secure`` (host layout): srl's router wants every
    role's login, and each emulated robot's own router TLS, the bridge's login and the robot's
    access rules, which the bridge host presents (services/robot_bridge/host.py)."""
    temp = tmp_path / "tmp"
    temp.mkdir()
    summary, out, err = _up_run(
        tmp_path,
        "--robots",
        "3",
        "--plant",
        "robot",
        "--layout",
        layout,
        "--agent",
        "mpc",
        "--duration",
        "12",
        *(["--secure"] if secure else []),
        env={"TMPDIR": str(temp)},
    )
    assert list(temp.iterdir()) == [], "srl up left credentials or scratch behind"
    assert summary["robots"] == ROBOTS and summary["plant"] == "robot" and summary["secure"] is secure
    if secure:  # every robot's router is tls/, and none lets in a session without credentials
        assert all(summary["robot_plant"][r]["endpoint"].startswith("tls/127.0.0.1:") for r in ROBOTS)
        assert "robot routers  each emulated robot's own: mutual TLS, the bridge's login" in out
        assert "lets in sessions without login" not in err
    for robot in ROBOTS:  # no localization source: each robot's pose is its odometry, and the table says so
        assert summary["robot_plant"][robot]["localization"] == "odometry only"
        assert any(line.startswith(f"  {robot} ") and line.endswith("pose: odometry only") for line in out.splitlines())
    per_robot = (
        ["robot_bridge", "actor"]
        if layout == "host"
        else [f"{s}-{r}" for s in ("robot_bridge", "actor") for r in ROBOTS]
    )
    assert set(summary["services"]) == {"router", "critic", *per_robot, *(f"tb3_emulator-{r}" for r in ROBOTS)}
    assert all(code == 0 for code in summary["exit_codes"].values()), summary["exit_codes"]
    actors = _actor_summaries(summary, layout)
    rows = {row["robot"]: row for row in summary["fleet"]["rows"]}
    for robot, start in zip(ROBOTS, circle_starts(3, 1.5), strict=True):
        plant = summary["robot_plant"][robot]
        emulator = plant["emulator"]
        # its actor saw ITS robot: the first state is where that robot's emulator started
        np.testing.assert_allclose(actors[robot]["start_state"], start, atol=1e-6)
        np.testing.assert_allclose(emulator["initial_pose"], start, atol=1e-9)
        assert emulator["cmd_key"].startswith(f"0/{robot}/cmd_vel/")
        assert emulator["odom_key"].startswith(f"0/{robot}/odom/")
        assert plant["cmd_vel"] == [emulator["cmd_key"]]
        # every robot approached the target: from 1.5 m to within 0.25 m (truly, not just by odometry)
        assert emulator["true_final_distance_m"] < 0.25, (robot, emulator)
        assert rows[robot]["final_distance_m"] < 0.25
        assert emulator["applied_at_end"] == [0.0, 0.0]  # stopped when the run ended
        steps = rows[robot]["steps"]
        assert steps >= 80
        # at most the actor's first action before its identity token was seen and its last one
        # after the token went (the provenance gate, common/net/provenance.py)
        assert plant["actions_applied"] >= steps - 2 and plant["actions_refused"] <= 2
        # its commands came from its own bridge only: it received no more than that bridge sent
        assert 0 < emulator["cmd_received"] <= plant["commands_sent"]
    assert summary["critic"]["transitions_received"] == summary["fleet"]["steps"]


@pytest.mark.integration
@pytest.mark.slow
def test_fleet_on_one_shared_robot_router_keeps_robots_apart(tmp_path: Path) -> None:
    """Two robots reached through ONE router (``--robot-endpoint``): only the namespaces keep them
    apart; a third on its own router (``--robot-endpoints tb9=...``, as a robot running rmw_zenohd).
    A fourth TurtleBot3 (tb3_9) on the shared router is not in the fleet: it must hear no command."""
    shared, own = f"tcp/127.0.0.1:{free_port()}", f"tcp/127.0.0.1:{free_port()}"
    robots = ["tb3_1", "tb3_2", "tb9"]  # any ROS namespaces will do
    starts = {"tb3_1": "1.2,0.3,0.2", "tb3_2": "-0.9,-0.9,-2.3", "tb9": "0.2,-1.3,-1.4", "tb3_9": "0.8,0.8,0.8"}
    procs: dict[str, subprocess.Popen[str]] = {}
    try:
        procs["router"] = subprocess.Popen(
            [sys.executable, "-m", "tools.cli", "router", "--router", shared],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
        )
        open_session(shared, 30, "the shared robot router").close()
        for namespace, start in starts.items():
            where = ["--listen", own] if namespace == "tb9" else ["--router", shared]
            procs[namespace] = subprocess.Popen(
                [*EMULATOR, *where, "--namespace", namespace, f"--initial-pose={start}"],
                cwd=ROOT,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
                start_new_session=True,
            )
        open_session(own, 30, "tb9's own router").close()
        summary = _up(
            tmp_path,
            "--robots",
            ",".join(robots),
            "--plant",
            "robot",
            "--robot-endpoint",
            shared,
            "--robot-endpoints",
            f"tb9={own}",
            "--agent",
            "mpc",
            "--duration",
            "10",
        )
    finally:
        results = {}
        for name, proc in reversed(list(procs.items())):
            proc.send_signal(2)
            out, _ = proc.communicate(timeout=20)
            if name != "router":
                results[name] = json.loads(out.strip().splitlines()[-1])
    assert "tb3_emulator-tb3_1" not in summary["services"]  # real robots: none started
    assert {r: summary["robot_plant"][r]["endpoint"] for r in robots} == {"tb3_1": shared, "tb3_2": shared, "tb9": own}
    actors = _actor_summaries(summary)
    for robot in robots:
        x, y, _ = (float(c) for c in starts[robot].split(","))
        np.testing.assert_allclose(actors[robot]["start_state"][:2], (x, y), atol=0.05)  # its own robot
        emulator, plant = results[robot], summary["robot_plant"][robot]
        assert emulator["cmd_key"].startswith(f"0/{robot}/cmd_vel/")
        # each robot heard only its own bridge's commands (actions and the watchdog's zeros): on one
        # router, another robot's commands would make it receive more than its bridge sent
        assert 0 < emulator["counters"]["cmd_received"] <= plant["commands_sent"], (robot, emulator, plant)
        assert math.hypot(*emulator["final_pose"][:2]) < math.hypot(x, y) - 0.5  # it drove toward the target
    assert results["tb3_9"]["counters"].get("cmd_received", 0) == 0  # not in the fleet: never commanded
    assert results["tb3_9"]["final_pose"] == pytest.approx([0.8, 0.8, 0.8])


@pytest.mark.integration
@pytest.mark.slow
def test_one_robot_of_a_simulated_fleet_swapped_for_a_robot_behind_a_bridge(tmp_path: Path) -> None:
    """A fleet's robot m3 is a TurtleBot3 (emulated) behind a robot bridge, its robots m1 and m2 in
    a plant host: one actor host and one critic serve all three, unchanged. The bridge takes m3's
    actions out of the actor host's batches and publishes its states on m3's own keys; the plant
    host takes only its own robots' actions and refuses none for m3. Every robot approaches."""
    from tests.harness import Proc, wait_until

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = ["--router", endpoint]
    started: list[Proc] = []

    def start(name: str, *argv: str) -> Proc:
        started.append(Proc(name, list(argv)))
        return started[-1]

    def alive(session: zenoh.Session, key: str) -> bool:
        if any(p.process.poll() is not None for p in started):
            failed = next(p for p in started if p.process.poll() is not None)
            raise AssertionError(f"{failed.name} exited: {failed.stderr[-10:]}")
        return any(r.ok is not None for r in session.liveliness().get(key, timeout=0.5))

    try:
        start("router", "router", *router)
        session = open_session(endpoint, 30, "the router")
        try:
            plant = start("plant", "plant-sim", *router, "--mode", "realtime", "--robots=m1,m2")
            emulator = start("emulator", "tb3-emulator", *router, "--robot=m3", "--start=1.0,-1.0")
            bridge = start("bridge", "robot-bridge", *router, "--robot=m3")
            critic = start("critic", "critic", *router, "--robots=m1,m2,m3")
            for robot in ("m1", "m2", "m3"):
                wait_until(lambda r=robot: alive(session, f"srl/{r}/alive/plant"), 60, f"{robot}'s plant")
            wait_until(lambda: alive(session, "srl/m1/alive/critic"), 60, "the critic")
            actor = start(
                "actor",
                "actor",
                *router,
                "--mode",
                "realtime",
                "--robots=m1,m2,m3",
                "--agent",
                "mpc",
                "--run-seconds",
                "12",
            )
            actor.process.wait(timeout=180)
        finally:
            session.close()
        assert actor.process.returncode == 0, actor.stderr[-10:]
        for proc in (plant, bridge, emulator, critic):
            assert proc.stop() == 0, (proc.name, proc.stderr[-10:])
    finally:
        for proc in reversed(started):
            proc.stop()
    actors = actor.summary()["per_robot"]
    np.testing.assert_allclose(actors["m3"]["start_state"][:2], [1.0, -1.0], atol=0.02)  # its actor saw ITS robot
    for robot in ("m1", "m2", "m3"):
        start_distance = math.hypot(*actors[robot]["start_state"][:2])
        assert actors[robot]["steps"] >= 80 and actors[robot]["final_distance"] < start_distance - 0.8, actors[robot]
    emulated = emulator.summary()
    truly = math.hypot(*emulated["final_pose"][:2])  # where the emulated robot truly is
    print(
        "\nfigures: final distances "
        + ", ".join(f"{r} {actors[r]['final_distance']:.3f} m" for r in actors)
        + f"; m3 truly {truly:.3f} m"
    )
    assert truly < math.hypot(1.0, -1.0) - 0.8 and emulated["applied"] == [0.0, 0.0], emulated
    counters = bridge.summary()["counters"]
    assert counters["actions_applied"] >= actors["m3"]["steps"] - 2, counters
    hosted = plant.summary()
    assert sorted(hosted["per_robot"]) == ["m1", "m2"]
    for robot in ("m1", "m2"):
        row = hosted["per_robot"][robot]["counters"]
        assert row["actions_applied"] >= actors[robot]["steps"] - 2 and row["actions_refused"] == 0, row
    assert not any(name.startswith("rejected.") for name in hosted["counters"]), hosted["counters"]
    assert critic.summary()["transitions_received"] >= sum(actors[r]["steps"] for r in actors) - 6
