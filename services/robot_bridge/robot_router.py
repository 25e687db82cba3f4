"""The robot's own Zenoh router (``rmw_zenohd`` on the robot): the bridge's session to it, that
router's login, TLS and access rules (docs/security.md, "The robot's own router").

Whoever opens a session to a robot's router drives the robot: its ``cmd_vel`` subscription
takes every sample. rmw_zenoh's router takes Zenoh's own configuration (rmw_zenoh_cpp's
``DEFAULT_RMW_ZENOH_ROUTER_CONFIG.json5``), so it can require what srl's router requires
(common/net/security.py): a user/password login (``transport/auth/usrpwd``), TLS on a ``tls/``
endpoint, mutual unless turned off, and access rules with default deny (``access_control``).

* :func:`robot_session`: the bridge's client session, with ``bridge.robot_user`` /
  ``robot_password_file`` and, on a ``tls/`` endpoint, ``bridge.robot_tls_*``. A robot that boots
  after the workstation is normal: it waits (one status line) up to ``bridge.robot_connect_timeout``
  (common.process.runtime.connect_with_retry), then one error line. Under ``transport.secure`` it
  warns once when the robot's router also lets in a session without credentials.
* :func:`robot_acl`: the rules of a secured robot router: the robot's own nodes (:data:`ROBOT_USER`)
  may do anything; the bridge (:data:`BRIDGE_USER`) may publish ``cmd_vel``, read ``odom`` and
  announce and watch ROS graph tokens, nothing else.
* :func:`robot_router_config`: that router as ``srl tb3-emulator --listen`` runs it, secured by
  the ``[transport]`` settings as ``srl router`` is (``secure``, ``users_file``, ``tls_*``).
"""

from __future__ import annotations

import json
import logging
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh
from pydantic import SecretStr

from common.config.settings import BridgeSettings, Settings, TransportSettings
from common.contracts.keys import advanced_pattern
from common.contracts.ros_wire import ADMIN, ODOMETRY_ONLY, POSE_SOURCES, RosGraph, pose_topic
from common.net.certs import write_tls_material
from common.net.security import (
    Rule,
    SecurityError,
    advanced_read,
    client_credentials,
    publish,
    query,
    read,
    token,
    watch,
    write_credentials,
    zenoh_entries,
)
from common.net.transport import plain_config
from common.process.runtime import RouterWait, connect_with_retry

log = logging.getLogger(__name__)

ROBOT_USER = "robot"  # the robot's own ROS 2 nodes (their rmw_zenoh sessions log in as this user)
BRIDGE_USER = "srl_bridge"  # srl's robot bridge
# Zenoh 1.10's access-control message kinds (zenoh/src/net/routing/interceptor/access_control.rs)
ALL_MESSAGES = (
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "liveliness_query",
    "declare_liveliness_subscriber",
)


def robot_transport(
    bridge: BridgeSettings, transport: TransportSettings, *, identity: bool = True
) -> TransportSettings:
    """``transport`` with the robot router's TLS files in place of srl's (a ``tls/`` robot endpoint);
    ``identity`` False: without the bridge's own certificate (a probe that presents no credential)."""
    cert, key = (bridge.robot_tls_cert, bridge.robot_tls_key) if identity else ("", "")
    return transport.model_copy(
        update={"tls_ca": bridge.robot_tls_ca, "tls_cert": cert, "tls_key": key, "tls_mtls": bool(cert and key)}
    )


def robot_login(bridge: BridgeSettings, transport: TransportSettings) -> tuple[str, str] | None:
    """(user, password) of the bridge at the robot's router, or None (``bridge.robot_user`` empty)."""
    if not bridge.robot_user:
        return None
    if not bridge.robot_password_file:
        raise SecurityError(
            f"bridge.robot_user {bridge.robot_user!r} needs bridge.robot_password_file "
            "(SRL_BRIDGE__ROBOT_PASSWORD_FILE): the file whose first line is its password"
        )
    login = transport.model_copy(
        update={"user": bridge.robot_user, "password": SecretStr(""), "password_file": bridge.robot_password_file}
    )
    return client_credentials(login)


def robot_client_config(bridge: BridgeSettings, transport: TransportSettings, *, login: bool = True) -> zenoh.Config:
    """A client of the robot's router at ``bridge.robot_endpoint``: TLS with ``bridge.robot_tls_*``
    on a ``tls/`` endpoint, the login ``bridge.robot_user`` (``login`` False: no login, no
    certificate: what a stranger who reaches the robot can present)."""
    config = plain_config(robot_transport(bridge, transport, identity=login), bridge.robot_endpoint)
    credentials = robot_login(bridge, transport) if login else None
    if credentials is not None:
        user, password = credentials
        config.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
        config.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    return config


def robot_router_wait(bridge: BridgeSettings) -> RouterWait:
    """The robot's router as the bridge's waiting and error lines name it."""
    return RouterWait(
        bridge.robot_endpoint,
        "the robot's Zenoh router",
        bridge.robot_user or None,
        "bridge.robot_user",
        "check bridge.robot_password_file against the robot router's users file, docs/security.md",
        "is the robot up and its rmw_zenohd running? see --robot-endpoint, bridge.robot_connect_timeout",
    )


def robot_session(
    bridge: BridgeSettings, transport: TransportSettings, stop: threading.Event | None = None
) -> zenoh.Session:
    """A client session to the robot's own Zenoh router (multicast scouting off), once it accepts
    one: retried every 0.2 s for ``bridge.robot_connect_timeout`` s, one status line while it
    waits, one error line (:class:`common.config.arguments.UsageError`) at the end or on ``stop``.
    Under ``transport.secure``, one WARNING if the router also takes a session without credentials."""
    robot_client_config(bridge, transport)  # a missing password or TLS file: one line now, no waiting
    session = connect_with_retry(
        lambda: zenoh.open(robot_client_config(bridge, transport)),
        None,
        "robot_bridge",
        bridge.robot_connect_timeout,
        stop or threading.Event(),
        robot_router_wait(bridge),
    )
    if transport.secure:
        warn_if_open(bridge, transport)
    return session


def robot_router_open(bridge: BridgeSettings, transport: TransportSettings) -> bool:
    """Whether the robot's router lets in a session that presents no login and no certificate
    (it only checks the router's certificate against ``bridge.robot_tls_ca`` on a ``tls/``
    endpoint, as anyone who has the CA certificate can)."""
    try:
        config = robot_client_config(bridge, transport, login=False)
    except SecurityError:  # a tls/ endpoint and no CA to check it against: nothing to probe with
        return False
    try:
        session = zenoh.open(config)
    except zenoh.ZError:
        return False
    session.close()
    return True


def warn_if_open(bridge: BridgeSettings, transport: TransportSettings) -> bool:
    """One WARNING line when the robot's router takes a session without credentials: whoever
    reaches it drives the robot, whatever srl's own router refuses."""
    if not robot_router_open(bridge, transport):
        return False
    log.warning(
        "robot_bridge: the robot's Zenoh router at %s lets in sessions without login or certificate: "
        "anyone who reaches it drives the robot (srl's --secure covers srl's router only); secure it "
        "(docs/security.md, the robot's own router)",
        bridge.robot_endpoint,
    )
    return True


def robot_router_reachable(bridge: BridgeSettings, transport: TransportSettings) -> bool:
    """Can the bridge open its session to the robot's router now (with its login, if any)?"""
    try:
        session = zenoh.open(robot_client_config(bridge, transport))
    except zenoh.ZError:
        return False
    session.close()
    return True


# -- the robot router's side ------------------------------------------------------------------------
def robot_rules(graph: RosGraph, bridge: BridgeSettings) -> dict[str, list[Rule]]:
    """The users of a robot's router and what each may do (rules in common/net/security.py's terms):
    the bridge publishes ``bridge.cmd_vel_topic`` and reads ``bridge.odom_topic`` and its
    localization topic (``bridge.pose_source``), as services/robot_bridge/ros_link.py does.

    rmw_zenoh keys are ``<domain>/<topic>/<type>/<hash>`` and its graph tokens ``@ros2_lv/<domain>/...``
    (common/contracts/ros_wire.py); behind zenoh-bridge-ros2dds the keys are the topic names and
    the tokens ``@/<zid>/@ros2_lv/...``. A ``@`` chunk is verbatim in Zenoh: ``**`` never matches
    it, so the robot's own user is granted those prefixes by name. A transient-local localization
    (AMCL's pose) comes from a zenoh-ext advanced publisher under rmw_zenoh, whose cache, heartbeats
    and tokens live at ``<key>/@adv/**`` (common.contracts.keys.advanced_pattern), and from the
    cache of zenoh-bridge-ros2dds, asked by one query, under ros2dds."""

    def topic_keys(topic: str) -> str:
        name = graph.topic_name(topic)[1:]
        return name if graph.profile == "ros2dds" else f"{graph.domain_id}/{name}/*/*"

    cmd_vel, odom = topic_keys(bridge.cmd_vel_topic), topic_keys(bridge.odom_topic)
    graph_tokens = f"@/*/{ADMIN}/**" if graph.profile == "ros2dds" else f"{ADMIN}/{graph.domain_id}/**"
    everything = ("**", f"{ADMIN}/**", "@/**")
    localization: list[Rule] = []
    if bridge.pose_source != ODOMETRY_ONLY:
        located = topic_keys(pose_topic(bridge))
        localization = read(located)
        if POSE_SOURCES[bridge.pose_source].transient_local:
            if graph.profile == "rmw_zenoh":
                cache = advanced_pattern(located)
                localization = [
                    *advanced_read(located),
                    *token(cache),  # the subscriber announces itself (subscriber_detection)
                    Rule("discover history", "egress", ("declare_queryable",), (cache,)),
                ]
            else:
                localization += [
                    *query(located),
                    Rule("discover history", "egress", ("declare_queryable",), (located,)),
                ]
    return {
        ROBOT_USER: [Rule("anything", flow, ALL_MESSAGES, everything) for flow in ("ingress", "egress")],
        BRIDGE_USER: [
            *publish(cmd_vel),
            # a publisher sends only once the router has told it of a matching subscriber
            Rule("discover", "egress", ("declare_subscriber",), (cmd_vel,)),
            *read(odom),
            *localization,
            # the bridge's own node and endpoint tokens (rmw_zenoh; a ros2dds robot takes none)
            *(token(graph_tokens) if graph.profile == "rmw_zenoh" else []),
            *watch(graph_tokens),
        ],
    }


def robot_acl(graph: RosGraph, bridge: BridgeSettings) -> dict[str, Any]:
    """The ``access_control`` section of a secured robot router: default deny, :func:`robot_rules`."""
    rules: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for user, granted in robot_rules(graph, bridge).items():
        ids = []
        for i, rule in enumerate(granted):
            rule_id = f"{user}-{i}-{rule.what.replace(' ', '-')}-{rule.flow}"
            rules.append(rule.as_zenoh(rule_id))
            ids.append(rule_id)
        policies.append({"id": user, "rules": ids, "subjects": [user]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": [{"id": user, "usernames": [user]} for user in (ROBOT_USER, BRIDGE_USER)],
        "policies": policies,
    }


def robot_router_config(settings: Settings, endpoint: str) -> zenoh.Config:
    """The robot's own router listening on ``endpoint``, as ``srl tb3-emulator --listen`` runs it.
    Open by default (as ``rmw_zenohd`` ships); with ``transport.secure`` it checks logins against
    ``transport.users_file`` and enforces :func:`robot_acl`; on a ``tls/`` endpoint TLS with
    ``transport.tls_*`` (mutual with ``tls_mtls``), as ``srl router`` does."""
    transport, bridge = settings.transport, settings.bridge
    config = plain_config(transport, endpoint, router=True)
    if transport.secure:
        entries = zenoh_entries(transport, router=True)  # the users file, checked as srl's router checks it
        entries["access_control"] = robot_acl(RosGraph.from_settings(bridge), bridge)
        for path, value in entries.items():
            config.insert_json5(path, json.dumps(value))
    return config


@dataclass(frozen=True)
class RobotLogins:
    """Fresh credentials of an emulated robot's secured router (``srl up --plant robot --secure``):
    the emulator's environment (its router's users file and TLS) and the bridge's (its login and
    certificate), all in ``directory`` (0700, files 0600; the caller removes it)."""

    directory: Path
    emulator_environment: dict[str, str]
    bridge_environment: dict[str, str]

    @classmethod
    def create(cls, directory: Path) -> RobotLogins:
        credentials = write_credentials(directory, (BRIDGE_USER,))
        tls = write_tls_material(directory / "tls", (BRIDGE_USER,))
        emulator = {
            "SRL_TRANSPORT__SECURE": "true",
            "SRL_TRANSPORT__USERS_FILE": str(credentials.users_file),
            **tls.environment("router"),
        }
        bridge = {
            "SRL_BRIDGE__ROBOT_USER": BRIDGE_USER,
            "SRL_BRIDGE__ROBOT_PASSWORD_FILE": str(credentials.password_files[BRIDGE_USER]),
            "SRL_BRIDGE__ROBOT_TLS_CA": str(tls.ca),
            "SRL_BRIDGE__ROBOT_TLS_CERT": str(tls.cert(BRIDGE_USER)),
            "SRL_BRIDGE__ROBOT_TLS_KEY": str(tls.key(BRIDGE_USER)),
        }
        return cls(directory, emulator, bridge)

    def bridge(self, bridge: BridgeSettings, endpoint: str) -> BridgeSettings:
        """``bridge`` as the bridge sees it with these credentials, its robot at ``endpoint``."""
        return bridge.model_copy(
            update={
                "robot_endpoint": endpoint,
                "robot_user": BRIDGE_USER,
                "robot_password_file": self.bridge_environment["SRL_BRIDGE__ROBOT_PASSWORD_FILE"],
                "robot_tls_ca": self.bridge_environment["SRL_BRIDGE__ROBOT_TLS_CA"],
                "robot_tls_cert": self.bridge_environment["SRL_BRIDGE__ROBOT_TLS_CERT"],
                "robot_tls_key": self.bridge_environment["SRL_BRIDGE__ROBOT_TLS_KEY"],
            }
        )
