"""The robot's own Zenoh router (services/robot_bridge/robot_router.py, docs/security.md): secured,
it lets no one without its credentials drive the robot; the bridge logs in there with TLS, waits
for a robot that boots late, and gives up after its timeout with one line.

The secured router is ``srl tb3-emulator --listen tls/...`` with the credentials ``srl up
--plant robot --secure`` makes for it (:class:`RobotLogins`); "the robot moved" is read from the
emulator's own report of its true pose (the ideal model: odometry is the truth).
"""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path
from typing import Any

import pytest
import zenoh

from common.config.settings import BridgeSettings, Settings
from common.contracts import ros_wire
from common.contracts.ros_wire import ODOMETRY, TWIST_STAMPED, Attachment, Odometry, RosGraph
from common.net.certs import write_tls_material
from common.net.security import Rule
from common.net.transport import plain_config
from services.robot_bridge.robot_router import (
    BRIDGE_USER,
    ROBOT_USER,
    RobotLogins,
    robot_acl,
    robot_client_config,
    robot_router_open,
    robot_rules,
    warn_if_open,
)
from tests.harness import ROOT, Proc, cluster, free_port, srl, wait_until

GRAPH = RosGraph("rmw_zenoh", "jazzy", 0, "")
START = (-1.0, 0.0, 0.0)
FORGED = 100  # cmd_vel samples each intruder pushes, if it gets a session


def _settings() -> Settings:
    return Settings.load()


def _cmd_vel(seq: int, v: float) -> tuple[str, bytes, bytes]:
    """(key, payload, attachment) of one Jazzy TurtleBot3 cmd_vel, as rmw_zenoh sends it."""
    stamp = time.time_ns()
    key = GRAPH.data_key("cmd_vel", TWIST_STAMPED)
    payload = ros_wire.encode_command("jazzy", TWIST_STAMPED, v, 0.0, stamp_ns=stamp)
    return key, payload, Attachment(seq, stamp, bytes(16), "compact").encode()


class OdomWatch:
    """The robot's odometry as a logged-in ROS tool sees it."""

    def __init__(self, session: zenoh.Session) -> None:
        self.odom: list[Odometry] = []
        self.subscriber = session.declare_subscriber(
            GRAPH.data_key("odom", ODOMETRY, "*"),
            lambda s: self.odom.append(ros_wire.decode_odometry("jazzy", bytes(s.payload.to_bytes()))),
        )

    def pose(self) -> tuple[float, float]:
        return (self.odom[-1].x, self.odom[-1].y) if self.odom else (math.nan, math.nan)


def _secured_emulator(tmp_path: Path) -> tuple[Proc, str, RobotLogins, BridgeSettings]:
    logins = RobotLogins.create(tmp_path / "robot")
    endpoint = f"tls/127.0.0.1:{free_port()}"
    emulator = Proc(
        "emulator",
        ["tb3-emulator", "--listen", endpoint, f"--initial-pose={','.join(map(str, START))}"],
        logins.emulator_environment,
    )
    return emulator, endpoint, logins, logins.bridge(_settings().bridge, endpoint)


def _open_or_none(config: zenoh.Config) -> zenoh.Session | None:
    try:
        return zenoh.open(config)
    except zenoh.ZError:
        return None


# -- the rules, without a router ---------------------------------------------------------------------
def _granted(rules: list[Rule], flow: str, message: str) -> set[str]:
    return {key for rule in rules if rule.flow == flow and message in rule.messages for key in rule.keys}


def test_robot_acl_lets_the_bridge_drive_and_read_its_topics_only() -> None:
    settings = _settings().bridge
    acl = robot_acl(GRAPH, settings)
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert {s["id"] for s in acl["subjects"]} == {ROBOT_USER, BRIDGE_USER}
    bridge = robot_rules(GRAPH, settings)[BRIDGE_USER]
    assert _granted(bridge, "ingress", "put") == {"0/cmd_vel/*/*"}
    assert _granted(bridge, "egress", "put") == {"0/odom/*/*"}
    assert not any("query" in rule.messages or "declare_queryable" in rule.messages for rule in bridge)
    # AMCL's transient-local pose: read, and its publisher's cache queried (rmw_zenoh's advanced publisher)
    amcl = robot_rules(GRAPH, settings.model_copy(update={"pose_source": "pose_with_covariance"}))[BRIDGE_USER]
    assert _granted(amcl, "egress", "put") == {"0/odom/*/*", "0/amcl_pose/*/*", "0/amcl_pose/*/*/@adv/**"}
    assert _granted(amcl, "ingress", "query") == {"0/amcl_pose/*/*/@adv/**"}
    assert _granted(amcl, "ingress", "put") == {"0/cmd_vel/*/*"}
    namespaced = robot_rules(
        RosGraph("ros2dds", "humble", 0, "tb3_1"), settings.model_copy(update={"pose_source": "tf"})
    )[BRIDGE_USER]
    assert _granted(namespaced, "ingress", "put") == {"tb3_1/cmd_vel"}
    assert _granted(namespaced, "egress", "put") == {"tb3_1/odom", "tb3_1/tf"}


def test_the_documented_robot_router_config_grants_what_the_emulator_grants() -> None:
    """docs/security.md's rmw_zenohd configuration: login, mutual TLS, and exactly robot_rules."""
    page = (ROOT / "docs" / "security.md").read_text()
    config = json.loads(page.split("<!-- robot-router-config -->\n```json5\n", 1)[1].split("\n```", 1)[0])
    acl = config["access_control"]
    rules = {rule["id"]: rule for rule in acl["rules"]}
    usernames = {subject["id"]: subject["usernames"] for subject in acl["subjects"]}
    documented: dict[str, set[tuple[str, str, str]]] = {}
    for policy in acl["policies"]:
        granted = {
            (flow, message, key)
            for rule_id in policy["rules"]
            if rules[rule_id]["permission"] == "allow"
            for flow in rules[rule_id]["flows"]
            for message in rules[rule_id]["messages"]
            for key in rules[rule_id]["key_exprs"]
        }
        for subject in policy["subjects"]:
            for user in usernames[subject]:
                documented.setdefault(user, set()).update(granted)
    expected = {
        user: {(rule.flow, message, key) for rule in granted for message in rule.messages for key in rule.keys}
        for user, granted in robot_rules(GRAPH, _settings().bridge).items()
    }
    assert documented == expected
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert config["transport"]["auth"]["usrpwd"]["dictionary_file"]
    assert config["transport"]["link"]["tls"]["enable_mtls"] is True
    assert [e for e in config["listen"]["endpoints"] if not e.startswith("tcp/127.0.0.1:")] == ["tls/0.0.0.0:7448"]


@pytest.mark.integration
def test_secure_warns_once_against_an_open_robot_router(caplog: pytest.LogCaptureFixture) -> None:
    """A robot router that takes anyone (rmw_zenohd as it ships): one WARNING under --secure."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = _settings()
    router = zenoh.open(plain_config(settings.transport, endpoint, router=True))
    try:
        bridge = settings.bridge.model_copy(update={"robot_endpoint": endpoint})
        with caplog.at_level(logging.WARNING):
            assert warn_if_open(bridge, settings.transport)
    finally:
        router.close()
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "lets in sessions without login or certificate" in warnings[0].getMessage()


# -- the secured robot router ---------------------------------------------------------------------------
@pytest.mark.integration
def test_without_the_robot_routers_credentials_the_robot_moves_0_000_m(tmp_path: Path) -> None:
    emulator, endpoint, _logins, bridge = _secured_emulator(tmp_path)
    settings = _settings()
    transport = settings.transport
    wrong = tmp_path / "wrong.password"
    wrong.write_text("not-the-password\n")
    wrong.chmod(0o600)
    stranger = write_tls_material(tmp_path / "stranger", (BRIDGE_USER,))
    intruders: dict[str, BridgeSettings] = {
        "no login, no certificate": bridge.model_copy(
            update={"robot_user": "", "robot_tls_cert": "", "robot_tls_key": ""}
        ),
        "certificate, no login": bridge.model_copy(update={"robot_user": ""}),
        "certificate, wrong password": bridge.model_copy(update={"robot_password_file": str(wrong)}),
        "another CA's certificate, no login": bridge.model_copy(
            update={
                "robot_user": "",
                "robot_tls_cert": str(stranger.cert(BRIDGE_USER)),
                "robot_tls_key": str(stranger.key(BRIDGE_USER)),
            }
        ),
    }
    legit: zenoh.Session | None = None
    opened: list[str] = []
    try:
        legit = _open_or_none(robot_client_config(bridge, transport))
        deadline = time.monotonic() + 30
        while legit is None and time.monotonic() < deadline and emulator.process.poll() is None:
            time.sleep(0.1)
            legit = _open_or_none(robot_client_config(bridge, transport))
        assert legit is not None, emulator.stderr[-10:]
        watch = OdomWatch(legit)
        wait_until(lambda: len(watch.odom) >= 2, 10, "the robot's odometry")
        before = watch.pose()
        started = time.monotonic()
        attempts = [
            _open_or_none(plain_config(transport, endpoint.replace("tls/", "tcp/"))),  # no TLS at all
            *(_open_or_none(robot_client_config(intruder, transport)) for intruder in intruders.values()),
        ]
        refusing = time.monotonic() - started
        for name, session in zip(["plain tcp", *intruders], attempts, strict=True):
            if session is not None:  # it got in: may it drive?
                opened.append(name)
                for seq in range(FORGED):
                    key, payload, attachment = _cmd_vel(seq + 1, 0.22)
                    session.put(key, payload, attachment=attachment)
                    time.sleep(0.005)
                session.close()
        assert not robot_router_open(bridge, transport)  # what srl up --secure's bridge probes
        time.sleep(0.5)  # a forged command would have moved the robot by now (0.22 m/s)
        after = watch.pose()
        moved = math.dist(before, after)
        # the control: the bridge's own login drives the robot on the same path
        publisher = legit.declare_publisher(GRAPH.data_key("cmd_vel", TWIST_STAMPED))
        for seq in range(10):
            key, payload, attachment = _cmd_vel(seq + 1, 0.2)
            publisher.put(payload, attachment=attachment)
            time.sleep(0.05)
        wait_until(lambda: watch.pose()[0] > before[0] + 0.05, 5, "the legitimate commands to move the robot")
    finally:
        if legit is not None:
            legit.close()
        code = emulator.stop()
    summary = emulator.summary()
    print(
        f"\nfigures: secured robot router: {len(attempts)} intruders ({refusing:.2f} s to refuse them all), "
        f"sessions opened {opened}, robot moved {moved:.3f} m; cmd_vel received by the robot "
        f"{summary['counters'].get('cmd_received', 0)} (the bridge's 10)"
    )
    assert code == 0
    assert opened == []
    assert moved == 0.0 and before == (START[0], START[1])
    assert summary["counters"]["cmd_received"] == 10  # only the legitimate ones reached the robot


# -- the bridge waits for the robot's router --------------------------------------------------------
@pytest.mark.integration
def test_a_bridge_started_before_the_robot_connects_when_it_comes_and_gives_up_at_its_timeout(
    tmp_path: Path,
) -> None:
    """The bridge (TLS and login at the robot) starts first, says it waits, and connects when the
    robot's router comes up 3 s later. A second bridge whose robot never comes ends after its
    2 s timeout with one error line and exit code 2."""
    logins = RobotLogins.create(tmp_path / "robot")
    endpoint = f"tls/127.0.0.1:{free_port()}"
    never = f"tcp/127.0.0.1:{free_port()}"
    with cluster(robot="rr_wait") as c:
        assert c.session is not None
        states: list[bytes] = []
        c.session.declare_subscriber("srl/rr_wait/state", lambda s: states.append(bytes(s.payload.to_bytes())))
        bridge = c.start(
            "bridge",
            "robot-bridge",
            f"--robot-endpoint={endpoint}",
            env={**logins.bridge_environment, "SRL_BRIDGE__ROBOT_CONNECT_TIMEOUT": "30"},
        )
        lost = c.start(
            "lost",
            "robot-bridge",
            "--robot=rr_never",
            f"--robot-endpoint={never}",
            env={"SRL_BRIDGE__ROBOT_CONNECT_TIMEOUT": "2"},
        )
        wait_until(lambda: any("waiting for the robot's Zenoh router" in line for line in bridge.stderr), 30, "status")
        time.sleep(3.0)  # the robot boots after the workstation
        assert bridge.process.poll() is None and not states
        came = time.monotonic()
        c.start(
            "emulator",
            "tb3-emulator",
            "--listen",
            endpoint,
            f"--initial-pose={','.join(map(str, START))}",
            env=logins.emulator_environment,
        )
        wait_until(lambda: len(states) >= 3, 30, "srl state from the late robot")
        connected_after = time.monotonic() - came
        wait_until(lambda: lost.process.poll() is not None, 30, "the bridge whose robot never comes to give up")
        assert bridge.stop() == 0
        summary: dict[str, Any] = bridge.summary()
    waiting = [line for line in bridge.stderr if "waiting for the robot's Zenoh router" in line]
    errors = [line for line in lost.stderr if line.startswith("srl: error:")]
    print(
        f"\nfigures: bridge started before the robot: connected {connected_after:.1f} s after the robot's "
        f"router started; status: {waiting[0].split(': ', 2)[-1]!r}; no robot: {errors}"
    )
    assert len(waiting) == 1 and endpoint in waiting[0] and "(up to 30 s)" in waiting[0]
    assert summary["counters"]["odom_received"] >= 3
    assert lost.process.returncode == 2 and "Traceback" not in "\n".join(lost.stderr)
    assert errors == [
        f"srl: error: robot_bridge: cannot reach the robot's Zenoh router at {never} after 2 s "
        "(is the robot up and its rmw_zenohd running? see --robot-endpoint, bridge.robot_connect_timeout) "
        "(robot rr_never)"  # the robot behind that endpoint, as a bridge of several names them
    ]


@pytest.mark.integration
@pytest.mark.slow
def test_srl_up_secure_secures_the_emulated_robots_router_and_drives_through_it(tmp_path: Path) -> None:
    """``srl up --plant robot --secure``: the emulator's router demands TLS and the bridge's login,
    the bridge has them and drives the robot, no warning of an open robot router, nothing left."""
    temp = tmp_path / "tmp"
    temp.mkdir()
    done = srl(
        "up",
        "--plant",
        "robot",
        "--secure",
        "--router",
        f"tcp/127.0.0.1:{free_port()}",
        "--robot",
        "rr_up",
        "--start=1.5,1",
        "--duration",
        "4",
        "--json",
        env={"TMPDIR": str(temp)},
        timeout=180,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    emulator = summary["emulator"]
    print(
        f"\nfigures: srl up --plant robot --secure: {summary['steps']} steps, the robot applied "
        f"{emulator['counters'].get('cmd_applied', 0)} cmd_vel through its secured router"
    )
    assert "robot router   the emulated robot's own: mutual TLS" in done.stdout
    assert "lets in sessions without login" not in done.stderr
    assert summary["secure"] is True and emulator["counters"]["cmd_applied"] >= 20
    assert list(temp.iterdir()) == [], "srl up left the robot's credentials behind"
