"""Access control: only the actor commands, only the critic trains, only the plant reports.

Unit tests check every role's Zenoh access rules (common/net/security.py) against an independent
oracle: a decision function over the generated ``access_control`` dict that uses Zenoh's own
key-expression inclusion (``zenoh.KeyExpr.includes``), as the router does. Process tests run
the real services through a secured router with credentials generated at test time, and show
that strangers cannot connect and wrong roles can neither publish nor read what is not theirs:
legitimate observers and the services' own counters never see a rogue sample.
"""

from __future__ import annotations

import itertools
import json
import os
import socket
import stat
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import zenoh
from pydantic import ValidationError

from common.config.settings import Settings
from common.contracts.messages import CriticWeights
from common.net.provenance import QUIET_REFUSALS
from common.net.security import (
    ROLES,
    Credentials,
    SecurityError,
    acl_config,
    client_credentials,
    role_rules,
    write_credentials,
    zenoh_entries,
)
from common.net.transport import plain_config, zenoh_config
from tests.harness import ROOT, Cluster, client_config, free_port, wait_until

ROBOT = "t0"


# -- the oracle: Zenoh's decision over the generated config ------------------------------------
def allowed(acl: dict[str, Any], user: str, message: str, flow: str, key: str) -> bool:
    """May ``user`` send/receive ``message`` on ``key`` in ``flow``? Default deny; a rule
    applies when one of its key expressions includes ``key`` (zenoh's policy decision point)."""
    subjects = {s["id"] for s in acl["subjects"] if user in s.get("usernames", [])}
    rule_ids = {r for p in acl["policies"] if subjects & set(p["subjects"]) for r in p["rules"]}
    for rule in acl["rules"]:
        if (
            rule["id"] in rule_ids
            and message in rule["messages"]
            and flow in rule["flows"]
            and any(zenoh.KeyExpr(k).includes(zenoh.KeyExpr(key)) for k in rule["key_exprs"])
        ):
            assert rule["permission"] == "allow"
            return True
    return False


def who(acl: dict[str, Any], message: str, flow: str, key: str) -> set[str]:
    return {user for user in (*ROLES, "stranger") if allowed(acl, user, message, flow, key)}


ACL = acl_config(ROBOT, lockstep=False)  # real time (the default): nobody steps or resets the plant
ACL_LOCKSTEP = acl_config(ROBOT, lockstep=True)
HEARTBEAT = "srl/t0/transition/@adv/pub/1234abcd/1/uhlc"  # an advanced publisher's own key


@pytest.mark.parametrize(
    ("key", "writers"),
    [
        ("srl/t0/action", {"actor"}),
        ("srl/t0/transition", {"actor"}),
        (HEARTBEAT, {"actor"}),
        ("srl/t0/critic/weights", {"critic"}),
        ("srl/@batch/critic/weights", {"critic"}),  # a round of weights (common.contracts.keys.Batch)
        ("srl/@batch/state", {"plant"}),  # a plant host's states of one state tick
        ("srl/@batch/action", {"actor"}),  # an actor host's actions of one tick group
        ("srl/@batch/transition", {"actor"}),  # an actor host's transitions of one tick group
        ("srl/@batch/transition/@adv/pub/z1/e1/tok", {"actor"}),  # its cache's heartbeats
        ("srl/@batch/status/actor", set()),  # no other batch key is anyone's
        ("srl/t0/state", {"plant"}),
        ("srl/t0/status/actor", {"actor"}),
        ("srl/t0/status/critic", {"critic"}),
        ("srl/t0/status/plant", {"plant"}),
        ("srl/t1/action", set()),  # another robot's keys: no role of this robot
        ("srl/t1/critic/weights", set()),
        ("srl/t0/plant/step", set()),
        ("other/key", set()),
    ],
)
def test_only_the_owner_role_may_publish_a_key(key: str, writers: set[str]) -> None:
    assert who(ACL, "put", "ingress", key) == writers
    assert who(ACL, "delete", "ingress", key) == set()


@pytest.mark.parametrize(
    ("key", "readers"),
    [
        ("srl/t0/state", {"actor", "monitor"}),
        ("srl/t0/action", {"plant"}),
        ("srl/t0/critic/weights", {"actor"}),
        ("srl/@batch/critic/weights", {"actor"}),
        ("srl/@batch/state", {"actor", "monitor"}),
        ("srl/@batch/action", {"plant"}),
        ("srl/t0/transition", {"critic"}),
        ("srl/*/transition", {"critic"}),  # the critic's own (wildcard) subscription
        ("srl/@batch/transition", {"critic"}),
        ("srl/@batch/transition/@adv/pub/z1/e1/tok", {"critic"}),
        (HEARTBEAT, {"critic"}),
        ("srl/t0/status/*", {"monitor"}),
        ("srl/**", set()),
        ("**", set()),
    ],
)
def test_only_roles_with_business_may_read_a_key(key: str, readers: set[str]) -> None:
    assert who(ACL, "declare_subscriber", "ingress", key) == readers
    if "*" not in key:  # samples are published on concrete keys
        assert who(ACL, "put", "egress", key) == readers


@pytest.mark.parametrize(
    ("acl", "server", "client"),
    [(ACL_LOCKSTEP, {"plant"}, {"actor"}), (ACL, set(), set())],
    ids=["lockstep", "realtime"],
)
def test_plant_queries_only_in_lockstep(acl: dict[str, Any], server: set[str], client: set[str]) -> None:
    for service in ("srl/t0/plant/step", "srl/t0/plant/reset"):
        assert who(acl, "declare_queryable", "ingress", service) == server
        assert who(acl, "query", "ingress", service) == client
        assert who(acl, "reply", "ingress", service) == server
        assert who(acl, "reply", "egress", service) == client
    # everything else is the same in both modes
    others = {
        k: [r for r in v if "plant/step" not in str(r.keys) and "plant/reset" not in str(r.keys)]
        for k, v in role_rules(ROBOT, lockstep=True).items()
    }
    assert others == role_rules(ROBOT, lockstep=False)


def test_queries_queryables_and_liveliness_per_role() -> None:
    # the transition cache: the actor serves it, the critic queries it (history, recovery)
    history_query = "srl/*/transition/@adv/*/1234abcd/1/**"
    assert who(ACL, "declare_queryable", "ingress", "srl/t0/transition/@adv/pub/1234abcd/1/uhlc") == {"actor"}
    assert who(ACL, "query", "ingress", history_query) == {"critic"}
    assert who(ACL, "reply", "ingress", "srl/t0/transition") == {"actor"}
    assert who(ACL, "reply", "egress", "srl/t0/transition") == {"critic"}
    assert who(ACL, "declare_liveliness_subscriber", "ingress", "srl/*/transition/@adv/pub/**") == {"critic"}
    # liveliness: each role announces only its own services; every role may see who is alive
    for service, owner in (("actor", "actor"), ("critic", "critic"), ("plant", "plant"), ("robot_bridge", "plant")):
        assert who(ACL, "liveliness_token", "ingress", f"srl/t0/alive/{service}") == {owner}
        assert who(ACL, "liveliness_token", "egress", f"srl/t0/alive/{service}") == set(ROLES)
    assert who(ACL, "liveliness_token", "ingress", "srl/t0/alive/monitor") == set()
    assert who(ACL, "liveliness_query", "ingress", "srl/t0/alive/*") == set(ROLES)
    # identity tokens (common.net.provenance): a role announces the sessions of its own services only
    zid = "0123456789abcdef0123456789abcdef"
    for service, owner in (("actor", "actor"), ("critic", "critic"), ("plant", "plant")):
        assert who(ACL, "liveliness_token", "ingress", f"srl/t0/alive/{service}/{zid}") == {owner}
        assert who(ACL, "liveliness_token", "egress", f"srl/t0/alive/{service}/{zid}") == set(ROLES)
        assert who(ACL, "declare_liveliness_subscriber", "ingress", f"srl/t0/alive/{service}/*") == set(ROLES)
    assert who(ACL, "liveliness_token", "ingress", f"srl/t1/alive/plant/{zid}") == set()
    # discovery (declarations, queries to one's own queryables) carries no samples: every role
    assert who(ACL, "declare_subscriber", "egress", "srl/*/transition") == set(ROLES)


@pytest.mark.parametrize("acl", [ACL, ACL_LOCKSTEP], ids=["realtime", "lockstep"])
def test_acl_config_is_well_formed(acl: dict[str, Any]) -> None:
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    ids = [rule["id"] for rule in acl["rules"]]
    assert len(ids) == len(set(ids))
    assert {s["id"] for s in acl["subjects"]} == set(ROLES) == {p["id"] for p in acl["policies"]}
    for policy in acl["policies"]:
        assert set(policy["rules"]) <= set(ids) and policy["subjects"] == [policy["id"]]
    for rule in acl["rules"]:
        assert rule["permission"] == "allow" and rule["flows"] in (["ingress"], ["egress"])
        assert rule["messages"] and rule["key_exprs"]
        for key in rule["key_exprs"]:
            zenoh.KeyExpr(key)  # a valid key expression (raises otherwise)
    assert set(role_rules(ROBOT, lockstep=False)) == set(ROLES)
    json.dumps(acl)  # insertable as JSON5
    with pytest.raises(ValueError, match="robot id"):
        acl_config("a/b", lockstep=False)


def test_a_fleet_acl_grants_each_role_its_keys_of_every_robot_of_the_fleet_only() -> None:
    """``srl up --robots K --secure`` (transport.acl_robots): one login per role serves many
    robots, so each rule carries every robot's key; a robot outside the fleet gets nothing, and the
    monitor (the fleet's probes and status lines) may watch and read status across robots.
    Negative control: the one-robot ACL grants neither another robot nor the monitor's wildcards."""
    fleet = acl_config(["t0", "t1"], lockstep=False)
    for robot in ("t0", "t1"):
        assert who(fleet, "put", "ingress", f"srl/{robot}/action") == {"actor"}
        assert who(fleet, "put", "egress", f"srl/{robot}/action") == {"plant"}
        assert who(fleet, "put", "ingress", f"srl/{robot}/critic/weights") == {"critic"}
        assert who(fleet, "put", "ingress", f"srl/{robot}/state") == {"plant"}
        assert who(fleet, "liveliness_token", "ingress", f"srl/{robot}/alive/actor") == {"actor"}
        assert who(fleet, "declare_queryable", "ingress", f"srl/{robot}/transition/@adv/pub/1234abcd/1/uhlc") == {
            "actor"
        }
    for key in ("srl/t2/action", "srl/t2/critic/weights", "srl/t2/state"):
        assert who(fleet, "put", "ingress", key) == set()  # not a robot of the fleet
    # the critic's rounds: one key for the fleet (each item still goes only to its own robot's
    # subscriptions, from a live critic of that robot: common.net.transport, common.net.provenance)
    assert who(fleet, "put", "ingress", "srl/@batch/critic/weights") == {"critic"}
    assert who(fleet, "put", "egress", "srl/@batch/critic/weights") == {"actor"}
    assert who(fleet, "liveliness_query", "ingress", "srl/*/alive/actor") == {"monitor"}
    assert who(fleet, "declare_subscriber", "ingress", "srl/*/status/actor") == {"monitor"}
    assert who(fleet, "declare_subscriber", "ingress", "srl/*/state") == {"monitor"}
    assert who(fleet, "declare_subscriber", "ingress", "srl/**") == set()
    assert who(fleet, "put", "ingress", "srl/t2/status/actor") == set()  # reading all is not writing any
    assert who(ACL, "put", "ingress", "srl/t1/action") == set()
    assert who(ACL, "liveliness_query", "ingress", "srl/*/alive/actor") == set()
    assert who(ACL, "declare_subscriber", "ingress", "srl/*/status/actor") == set()
    assert len(fleet["rules"]) == len(acl_config(["t0", "t1", "t2", "t3"], lockstep=False)["rules"])  # not per robot
    with pytest.raises(ValueError, match="no robot"):
        acl_config([], lockstep=False)


def test_the_router_takes_its_fleet_from_acl_robots() -> None:
    base = Settings.load().transport
    assert base.rule_robots == [base.robot]
    fleet = base.model_copy(update={"acl_robots": "t0,t1"})
    assert fleet.rule_robots == ["t0", "t1"]
    with pytest.raises(ValueError, match="acl_robots"):
        Settings.load(transport={"acl_robots": "t0,,t1"})


# -- credentials and settings -------------------------------------------------------------------
def test_credentials_are_random_private_and_read_back(tmp_path: Path) -> None:
    first = write_credentials(tmp_path / "one")
    second = write_credentials(tmp_path / "two")
    assert stat.S_IMODE(first.directory.stat().st_mode) == 0o700
    files = [first.users_file, *first.password_files.values()]
    assert all(stat.S_IMODE(f.stat().st_mode) == 0o600 for f in files)
    users = dict(line.split(":", 1) for line in first.users_file.read_text().splitlines())
    assert set(users) == set(ROLES)
    assert len(set(users.values())) == len(ROLES) and all(len(p) >= 43 for p in users.values())
    assert all(first.password_files[r].read_text().strip() == users[r] for r in ROLES)
    assert not set(users.values()) & {p.read_text().strip() for p in second.password_files.values()}

    base = Settings.load().transport
    transport = first.transport(base, "critic")
    assert client_credentials(transport) == ("critic", users["critic"])
    entries = zenoh_entries(transport, router=False)
    assert entries == {"transport/auth/usrpwd/user": "critic", "transport/auth/usrpwd/password": users["critic"]}
    router = zenoh_entries(base.model_copy(update={"secure": True, "users_file": str(first.users_file)}), router=True)
    assert router["transport/auth/usrpwd/dictionary_file"] == str(first.users_file)
    assert router["access_control"] == acl_config(base.robot, lockstep=False)  # real time unless asked
    lockstep = zenoh_entries(
        base.model_copy(update={"secure": True, "users_file": str(first.users_file), "plant_queries": True}),
        router=True,
    )
    assert lockstep["access_control"] == acl_config(base.robot, lockstep=True) != router["access_control"]
    env = first.role_environment("plant")
    assert env["SRL_TRANSPORT__USER"] == "plant" and users["plant"] not in json.dumps(env)


def test_secure_settings_refuse_what_cannot_work(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    base = Settings.load().transport.model_copy(update={"secure": True})
    with pytest.raises(SecurityError, match=r"transport\.user"):
        zenoh_entries(base, router=False)
    with pytest.raises(SecurityError, match="no password"):
        zenoh_entries(base.model_copy(update={"user": "actor"}), router=False)
    with pytest.raises(SecurityError, match="password file"):
        zenoh_entries(base.model_copy(update={"user": "actor", "password_file": str(tmp_path / "nope")}), router=False)
    with pytest.raises(SecurityError, match="users_file"):
        zenoh_entries(base, router=True)
    with pytest.raises(ValidationError, match="client"):
        Settings.load(transport={"secure": True, "mode": "peer"})
    # the password comes from the environment; it never appears in the printed settings
    monkeypatch.setenv("SRL_TRANSPORT__PASSWORD", "not-a-real-secret-0123")
    monkeypatch.setenv("SRL_TRANSPORT__USER", "monitor")
    monkeypatch.setenv("SRL_TRANSPORT__SECURE", "true")
    settings = Settings.load()
    assert client_credentials(settings.transport) == ("monitor", "not-a-real-secret-0123")
    assert "not-a-real-secret-0123" not in json.dumps(settings.as_dict())


@pytest.mark.integration
def test_no_secret_is_committed() -> None:
    transport = Settings.load(ROOT / "common" / "config" / "srl.toml").transport
    assert (
        transport.secure,
        transport.user,
        transport.password.get_secret_value(),
        transport.password_file,
        transport.users_file,
    ) == (False, "", "", "", "")
    if not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    tracked = subprocess.run(
        ["git", "ls-files", "--cached", "--others", "--exclude-standard"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    suspicious = [f for f in tracked if f.endswith((".password", ".pem", ".key")) or Path(f).name == "users.txt"]
    assert suspicious == []


# -- processes: a secured router with the real services -------------------------------------------
def session_as(
    endpoint: str, user: str | None, password: str | None = None, tls: tuple[Path, Path, Path] | None = None
) -> zenoh.Session:
    """A client session logged in as ``user``; ``tls`` = (CA, certificate, key) for a mutual-TLS link."""
    if tls is None:
        config = client_config(endpoint)
    else:  # the TLS material goes in through the settings, as every srl process gives it
        ca, cert, key = (str(path) for path in tls)
        transport = Settings.load().transport.model_copy(
            update={"tls_ca": ca, "tls_cert": cert, "tls_key": key, "tls_mtls": True}
        )
        config = plain_config(transport, endpoint)
    if user is not None:
        config.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
    if password is not None:
        config.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    return zenoh.open(config)


def password_of(credentials: Credentials, role: str) -> str:
    return credentials.password_files[role].read_text().strip()


class Logins:
    """Sessions to a secured router, one per call, all closed at the end."""

    def __init__(self, endpoint: str, credentials: Credentials) -> None:
        self.endpoint, self.credentials = endpoint, credentials
        self.sessions: list[zenoh.Session] = []

    def __call__(self, role: str) -> zenoh.Session:
        session = session_as(self.endpoint, role, password_of(self.credentials, role))
        self.sessions.append(session)
        return session

    def close(self) -> None:
        for session in self.sessions:
            session.close()


@contextmanager
def secured_cluster(robot: str, credentials: Credentials) -> Iterator[tuple[Cluster, Logins]]:
    """A secured router (services started on demand); the cluster's own session is a monitor."""
    c = Cluster(robot)
    login = Logins(c.endpoint, credentials)
    try:
        c.start("router", "router", env=credentials.router_environment())

        def opened() -> bool:
            try:
                c.session = session_as(c.endpoint, "monitor", password_of(credentials, "monitor"))
            except zenoh.ZError:
                return False
            return True

        wait_until(opened, 30, "the secured router")
        yield c, login
    finally:
        login.close()
        c.close()  # closes the monitor session, stops every process by its pid


class Recorder:
    def __init__(self) -> None:
        self.payloads: list[bytes] = []

    def __call__(self, sample: zenoh.Sample) -> None:
        self.payloads.append(sample.payload.to_bytes())

    def rogue(self) -> list[bytes]:
        return [p for p in self.payloads if p.startswith(b"ROGUE")]


# (user, key) a wrong role tries to publish on; the legitimate reader of each key watches
ROGUE_PUTS = [
    ("critic", "action"),
    ("plant", "action"),
    ("monitor", "action"),
    ("plant", "critic/weights"),
    ("actor", "critic/weights"),
    ("monitor", "critic/weights"),
    ("actor", "state"),
    ("critic", "state"),
    ("monitor", "state"),
    ("plant", "transition"),
    ("critic", "transition"),
    ("critic", "status/actor"),
    ("plant", "status/critic"),
]
LEGIT_READER = {
    "action": "plant",
    "critic/weights": "actor",
    "state": "monitor",
    "transition": "critic",
    "status/actor": "monitor",
    "status/critic": "monitor",
}
# (user, key) a wrong role tries to read
ROGUE_READS = [
    ("plant", "critic/weights"),
    ("plant", "transition"),
    ("critic", "action"),
    ("critic", "state"),
    ("monitor", "action"),
    ("monitor", "critic/weights"),
    ("monitor", "transition"),
    ("actor", "transition"),
    ("actor", "action"),
    ("critic", "**"),
    ("monitor", "**"),
]


@pytest.mark.timing
@pytest.mark.integration
@pytest.mark.slow
def test_secured_services_run_and_wrong_roles_can_neither_publish_nor_read(tmp_path: Path) -> None:
    credentials = write_credentials(tmp_path / "credentials")
    robot = "sec"
    with secured_cluster(robot, credentials) as (c, login):
        # observers, rogue writers and rogue readers are separate sessions: a session delivers its
        # own puts to its own subscribers locally, without the router
        observers = {role: login(role) for role in ROLES}
        rogues = {role: login(role) for role in ROLES}
        thieves = {role: login(role) for role in ROLES}
        legit: dict[str, Recorder] = {}
        for key, role in LEGIT_READER.items():
            legit[key] = Recorder()
            observers[role].declare_subscriber(f"srl/{robot}/{key}", legit[key])
        versions: list[int] = []
        observers["actor"].declare_subscriber(
            f"srl/{robot}/critic/weights",
            lambda s: versions.append(CriticWeights.model_validate_json(s.payload.to_bytes()).version),
        )
        stolen: dict[tuple[str, str], Recorder] = {}
        for user, key in ROGUE_READS:
            stolen[user, key] = Recorder()
            thieves[user].declare_subscriber(key if key == "**" else f"srl/{robot}/{key}", stolen[user, key])

        c.start("plant", "plant-sim", "--mode", "realtime", env=credentials.role_environment("plant"))
        c.wait_alive("plant")
        actor = c.start(
            "actor", "actor", "--mode", "realtime", "--run-seconds", "8", env=credentials.role_environment("actor")
        )
        c.wait_alive("actor")
        # the critic comes late: it must recover the transitions published before it through
        # the advanced subscriber's history query, which the rules must let through
        wait_until(lambda: len(legit["transition"].payloads) >= 10, 30, "transitions before the critic starts")
        c.start("critic", "critic", env=credentials.role_environment("critic"))
        c.wait_alive("critic")
        wait_until(lambda: len(versions) >= 5, 30, "weights from the secured critic")

        # wrong roles publish garbage (which the services would count as rejected if it arrived)
        publishers = [(user, key, rogues[user].declare_publisher(f"srl/{robot}/{key}")) for user, key in ROGUE_PUTS]
        for i in range(10):
            for user, key, publisher in publishers:
                publisher.put(f"ROGUE {user} {key} {i}".encode())
                rogues[user].put(f"srl/{robot}/{key}", f"ROGUE {user} {key} session-put {i}".encode())
            time.sleep(0.05)
        # wrong roles query the plant and announce a service that is not theirs
        rogue_replies = [
            r
            for user in ("critic", "monitor")
            for r in rogues[user].get(f"srl/{robot}/plant/reset", payload=b"ROGUE", timeout=1.0)
        ]
        # real time: even the actor may not reset the plant (the router refuses; plant_sim serves none)
        actor_replies = list(observers["actor"].get(f"srl/{robot}/plant/reset", payload=b"{", timeout=2.0))
        impostor = rogues["critic"].liveliness().declare_token(f"srl/{robot}/alive/robot_bridge")
        time.sleep(0.5)
        impersonated = c.alive("robot_bridge")
        impostor.undeclare()
        genuine = observers["plant"].liveliness().declare_token(f"srl/{robot}/alive/robot_bridge")
        wait_until(lambda: c.alive("robot_bridge"), 5, "a token the plant role may declare")
        genuine.undeclare()

        assert actor.process.wait(timeout=60) == 0, actor.stderr[-10:]
        time.sleep(1.0)  # the last transitions reach the critic
        summaries = {}
        for name in ("critic", "plant"):
            assert c.procs[name].stop() == 0, c.procs[name].stderr[-10:]
            summaries[name] = c.procs[name].summary()
        summaries["actor"] = actor.summary()

    # the legitimate readers saw the system run, and never a rogue sample
    assert all(legit[key].payloads for key in ("action", "critic/weights", "state", "transition")), {
        key: len(r.payloads) for key, r in legit.items()
    }
    assert {key: r.rogue() for key, r in legit.items()} == {key: [] for key in legit}
    # the wrong readers got nothing at all, while the same keys carried hundreds of samples
    assert {k: len(r.payloads) for k, r in stolen.items()} == {k: 0 for k in stolen}
    assert rogue_replies == []
    assert actor_replies == []
    assert not impersonated, "a critic announced the robot bridge"
    actor_summary, critic_summary, plant_summary = summaries["actor"], summaries["critic"], summaries["plant"]
    # the services never saw a rogue payload or query: nothing was rejected, except what normal
    # operation refuses (QUIET_REFUSALS: the stopping actor's last action, still in flight when its
    # token vanished, is ``action.late``; a CI run saw one), of which a stop leaves at most a few
    quiet = {f"rejected.{what}" for what in QUIET_REFUSALS}
    rejected = {
        name: {k: v for k, v in s["counters"].items() if k.startswith("rejected.") and k not in quiet}
        for name, s in summaries.items()
    }
    assert rejected == {"actor": {}, "critic": {}, "plant": {}}, rejected
    late = {name: s["counters"].get("rejected.action.late", 0) for name, s in summaries.items()}
    assert late["actor"] == late["critic"] == 0 and late["plant"] <= 3, late
    # the system ran normally through the secured router
    steps = actor_summary["steps"]
    assert steps >= 70 and actor_summary["loop"]["missed_deadlines"] == 0
    assert critic_summary["seen_steps"][robot] == actor_summary["transition_steps"]  # late critic recovered all
    assert critic_summary["transitions_received"] >= steps
    assert actor_summary["weights_version"] in versions and all(b > a for a, b in itertools.pairwise(versions))
    assert plant_summary["counters"]["received.action"] >= steps
    print(
        f"\nfigures: secured run: {steps} steps, latency median {actor_summary['latency_ms']['median']:.2f} ms "
        f"p99 {actor_summary['latency_ms']['p99']:.2f} ms, {len(versions)} weight versions, late critic "
        f"recovered {critic_summary['seen_steps'][robot]}; rogue: {len(ROGUE_PUTS) * 20} puts by wrong roles, "
        f"{len(ROGUE_READS)} wrong subscriptions, 3 plant/reset queries (actor's included), 1 impostor token: "
        "0 got through"
    )


@pytest.mark.integration
@pytest.mark.slow
def test_strangers_and_wrong_passwords_cannot_connect(tmp_path: Path) -> None:
    credentials = write_credentials(tmp_path / "credentials")
    other = write_credentials(tmp_path / "other")  # valid-looking passwords of another deployment
    with secured_cluster("gate", credentials) as (c, _):
        attempts: list[tuple[str | None, str | None]] = [
            (None, None),  # no credentials at all
            ("stranger", "whatever"),  # unknown user
            ("actor", password_of(other, "actor")),  # right user, wrong password
            ("actor", password_of(credentials, "critic")),  # another role's password
            ("actor", ""),
        ]
        for user, password in attempts:
            started = time.monotonic()
            with pytest.raises(zenoh.ZError):
                session_as(c.endpoint, user, password).close()
            assert time.monotonic() - started < 5.0
        # a peer-mode session opens even when its connection fails (peers keep retrying in the
        # background): without credentials it never gets a link to the router
        config = client_config(c.endpoint)
        config.insert_json5("mode", '"peer"')
        peer = zenoh.open(config)
        try:
            time.sleep(1.0)
            assert list(peer.info.routers_zid()) == [] and list(peer.info.peers_zid()) == []
        finally:
            peer.close()
        # the services' own code path (zenoh_config from settings) logs in; the router is unharmed
        transport = credentials.transport(Settings.load().transport, "plant").model_copy(
            update={"router": c.endpoint, "robot": "gate"}
        )
        zenoh.open(zenoh_config(transport)).close()
        assert c.session is not None and c.session.info.routers_zid()


def _plant_alive(session: zenoh.Session, robot: str) -> bool:
    return any(r.ok is not None for r in session.liveliness().get(f"srl/{robot}/alive/plant", timeout=0.5))


def _tcp_open(endpoint: str) -> bool:
    host, port = endpoint.removeprefix("tcp/").rsplit(":", 1)
    with socket.socket() as sock:
        sock.settimeout(0.2)
        return sock.connect_ex((host, int(port))) == 0


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.parametrize("mode", ["realtime", "lockstep"])
def test_srl_up_secure_runs_and_removes_its_credentials(tmp_path: Path, mode: str) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    temp = tmp_path / "tmp"
    temp.mkdir()
    up = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "tools.cli",
            "up",
            "--secure",
            "--mode",
            mode,
            "--router",
            endpoint,
            "--robot",
            "su",
            "--duration",
            "5",
            "--json",
        ],
        cwd=ROOT,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,
        env={**os.environ, "TMPDIR": str(temp)},
    )
    refused = 0
    try:
        wait_until(lambda: _tcp_open(endpoint) or up.poll() is not None, 60, "the router of srl up --secure")
        credential_dirs = list(temp.iterdir())
        # the router accepts TCP connections, but no Zenoh session without credentials
        for _ in range(3):
            with pytest.raises(zenoh.ZError):
                session_as(endpoint, None).close()
            refused += 1
        # the actor's own login may query plant/reset in lockstep only (a malformed request: the
        # plant answers with an error and changes nothing); in real time the router refuses it
        actor_password = (credential_dirs[0] / "actor.password").read_text().strip()
        # srl up --secure serves its tcp/ address over mutual TLS: log in with the actor's certificate
        tls = credential_dirs[0] / "tls"
        wait_until(lambda: (tls / "actor.key").is_file() or up.poll() is not None, 30, "the TLS material")
        actor = session_as(
            endpoint.replace("tcp/", "tls/", 1),
            "actor",
            actor_password,
            tls=(tls / "ca.pem", tls / "actor.pem", tls / "actor.key"),
        )
        try:
            wait_until(lambda: _plant_alive(actor, "su") or up.poll() is not None, 60, "the plant of srl up --secure")
            reset_replies = list(actor.get("srl/su/plant/reset", payload=b"{", timeout=2.0))
        finally:
            actor.close()
        out, err = up.communicate(timeout=180)
    finally:
        if up.poll() is None:
            os.killpg(up.pid, 9)
            up.wait()
    assert up.returncode == 0, err[-3000:]
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["secure"] is True and set(summary["services"]) == {"router", "plant", "critic", "actor"}
    assert summary["steps"] >= (45 if mode == "realtime" else 50)
    assert summary["critic"]["transitions_received"] >= summary["steps"]
    assert summary["weights_version"] > 0 and summary["critic"]["weights_published"] >= summary["steps"] - 1
    if mode == "lockstep":  # the synchronous critic's weights came through every step
        assert summary["critic_timeouts"] == 0 and summary["staleness_steps"]["max"] == 0
    assert [d.name.startswith("srl-secure-") for d in credential_dirs] == [True]
    assert list(temp.iterdir()) == [], "srl up left its credentials behind"
    assert refused == 3
    if mode == "lockstep":
        assert len(reset_replies) == 1 and reset_replies[0].err is not None
    else:
        assert reset_replies == [], "real time: the router let the actor role reset the plant"
    print(
        f"\nfigures: srl up --secure --mode {mode}: {summary['steps']} steps, weights version "
        f"{summary['weights_version']}, {summary['critic']['transitions_received']} transitions at the critic; "
        f"the actor role's plant/reset query got {len(reset_replies)} replies"
    )


@pytest.mark.parametrize(
    ("key", "accepted"),
    [
        ("srl/tb3_0/transition", True),
        ("srl/tb3_1/transition", False),  # another robot's key: a robot's login may publish there in a fleet
        ("srl/tb3_0x/transition", False),
        ("other/tb3_0/transition", False),
    ],
)
def test_a_sample_about_one_robot_on_another_robots_key_is_refused(key: str, accepted: bool) -> None:
    # common.net.transport.decode_sample, what every subscription, newest-sample take and history
    # reply decodes with: the key's robot chunk and the message's robot field must agree, or a
    # critic (a wildcard on srl/*/transition) would file one robot's transition under another's.
    from common.contracts.keys import TRANSITION, robot_of
    from common.contracts.messages import MessageError, Transition
    from common.net.transport import decode_sample

    sample = Transition(robot="tb3_0", episode=1, step=3, state=(0.1, 0.2, 0.3), action=(0.0, 0.0), cost=0.01).encode()
    if accepted:
        assert decode_sample(TRANSITION, key, sample).robot == "tb3_0" == robot_of(key)
    else:
        with pytest.raises(MessageError, match=f"robot 'tb3_0' on the key {key}, which names another robot"):
            decode_sample(TRANSITION, key, sample)
