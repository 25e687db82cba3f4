"""Who may do what on the bus: srl's roles, their Zenoh access-control rules, their credentials.

With ``transport.secure`` (``srl up --secure``) the router runs Zenoh's own user/password
authentication (``transport/auth/usrpwd``: a session with an unknown user or a wrong password
is refused when it connects) and Zenoh's access control (``access_control``, default deny):
every process logs in as the user of its role, and the router lets each role publish, read,
serve, query and announce only its own keys. This module is pure: it builds dicts and writes
credential files, and never imports zenoh; :func:`common.net.transport.zenoh_config` inserts
:func:`zenoh_entries` into a session's config.

How Zenoh applies the rules (zenoh 1.10, ``zenoh/src/net/routing/interceptor/``): the router
checks every message on the transport of an authenticated user in two flows, ``ingress`` (from
that user into the router) and ``egress`` (from the router out to that user), and a rule's key
expression must INCLUDE the message's key expression. In srl's terms:

* publish K: ingress ``put`` on K.
* read K: ingress ``declare_subscriber`` on K and egress ``put`` on K (a sample reaches a
  subscriber only if its user may read the key, whoever subscribed).
* query K: ingress ``query`` on K, egress ``reply`` on K. serve K: ingress ``declare_queryable``
  and ``reply`` on K.
* token K: ingress ``liveliness_token`` on K. watch K: ingress ``liveliness_query`` and
  ``declare_liveliness_subscriber`` on K, egress ``liveliness_token`` on K.
* discovery: a client's publisher sends only once the router has told it of a matching
  subscriber (write-side filtering: without it nothing is delivered), and the same
  holds for queriers and queryables. So every role receives subscriber and queryable
  declarations and queries anywhere in srl's key space (:data:`DISCOVERY`). They carry no data
  it may not see: a query reaches a session only through a queryable it was allowed to declare.

Zenoh-ext's advanced publishers (the actor's transition cache, the critic's weights cache) and
advanced subscribers (the critic's recovery of transitions, the actor's of weights) use
``<key>/@adv/...`` for their cache queryable, heartbeats and liveliness tokens, and the cache
answers with replies on ``<key>`` itself: :func:`advanced_publish` and :func:`advanced_read`
grant exactly that.
"""

from __future__ import annotations

import ipaddress
import logging
import secrets
import stat
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from common.config.settings import TransportSettings
from common.contracts.keys import (
    ACTION,
    ACTION_BATCH,
    ALIVE,
    ALL_KEYS,
    BATCH_CHUNK,
    PLANT_RESET,
    PLANT_STEP,
    STATE,
    STATE_BATCH,
    STATUS,
    TRANSITION,
    TRANSITION_BATCH,
    WEIGHTS,
    WEIGHTS_BATCH,
    advanced_pattern,
    check_chunk,
)
from common.system.checkpoint import write_private

log = logging.getLogger(__name__)

ROLES = ("actor", "critic", "plant", "monitor")
"""Zenoh users. plant_sim and robot_bridge share ``plant`` (same keys, docs/architecture.md);
``monitor`` is the read-only observer: ``srl up``'s readiness probes, ``srl health``, dashboards."""

PASSWORD_BYTES = 32  # secrets.token_urlsafe(32): 256 random bits, 43 URL-safe characters
Flow = Literal["ingress", "egress"]


class SecurityError(ValueError):
    """A secure configuration that cannot work (no user, no password, no users file)."""


@dataclass(frozen=True)
class Rule:
    """One allow rule: ``messages`` in ``flow`` on ``keys``; ``what`` names it in srl's terms."""

    what: str
    flow: Flow
    messages: tuple[str, ...]
    keys: tuple[str, ...]

    def as_zenoh(self, rule_id: str) -> dict[str, Any]:
        return {
            "id": rule_id,
            "messages": list(self.messages),
            "flows": [self.flow],
            "permission": "allow",
            "key_exprs": list(self.keys),
        }


def publish(*keys: str) -> list[Rule]:
    return [Rule("publish", "ingress", ("put",), keys)]


def read(*keys: str) -> list[Rule]:
    return [Rule("read", "ingress", ("declare_subscriber",), keys), Rule("read", "egress", ("put",), keys)]


def query(*keys: str) -> list[Rule]:
    return [Rule("query", "ingress", ("query",), keys), Rule("query", "egress", ("reply",), keys)]


def serve(*keys: str) -> list[Rule]:
    return [Rule("serve", "ingress", ("declare_queryable", "reply"), keys)]


def token(*keys: str) -> list[Rule]:
    return [Rule("token", "ingress", ("liveliness_token",), keys)]


def watch(*keys: str) -> list[Rule]:
    return [
        Rule("watch", "ingress", ("liveliness_query", "declare_liveliness_subscriber"), keys),
        Rule("watch", "egress", ("liveliness_token",), keys),
    ]


def advanced_publish(key: str) -> list[Rule]:
    """A zenoh-ext advanced publisher with a cache and heartbeats (common.net.transport.Bus.publisher)."""
    adv = advanced_pattern(key)
    return [*publish(key, adv), *serve(adv), Rule("serve history", "ingress", ("reply",), (key,)), *token(adv)]


def advanced_read(key: str) -> list[Rule]:
    """A zenoh-ext advanced subscriber with history and recovery (Bus.subscribe(recover=True))."""
    adv = advanced_pattern(key)
    return [*read(key, adv), *query(adv), Rule("query history", "egress", ("reply",), (key,)), *watch(adv)]


# the batch keys' verbatim chunk (srl/@batch/...) is outside srl/**: named here, or no publisher of
# a batch would hear of its subscribers (common.contracts.keys.Batch)
DISCOVERY = Rule(
    "discover",
    "egress",
    ("declare_subscriber", "declare_queryable", "query"),
    (ALL_KEYS, advanced_pattern(ALL_KEYS), f"srl/{BATCH_CHUNK}/**", advanced_pattern(f"srl/{BATCH_CHUNK}/**")),
)


def role_rules(robots: str | Sequence[str], *, lockstep: bool) -> dict[str, list[Rule]]:
    """Every role's rules for ``robots`` (one id, or a fleet's ids; besides :data:`DISCOVERY`,
    which all roles get).

    ``lockstep`` (``transport.plant_queries``): the actor may query ``plant/step`` and
    ``plant/reset`` and the plant may serve them. In real time nobody may: a real-time plant
    declares no queryable, and a step or reset would move the robot behind the actor's back.

    A fleet (several ids): each rule grants its keys for every robot of the fleet (one host
    process serves many robots under one login), and the monitor -- the read-only observer whose
    readiness probes and status lines cover the whole fleet (tools/launch/up.py) -- may also watch
    every robot's liveliness and read every robot's status and state (``srl/*/alive/...``,
    ``srl/*/status/*``, ``srl/*/state``)."""
    ids = [robots] if isinstance(robots, str) else list(robots)
    if not ids:
        raise ValueError("role rules for no robot")
    each = [_robot_rules(robot, lockstep=lockstep) for robot in ids]
    if len(each) == 1:
        return each[0]
    merged: dict[str, list[Rule]] = {}
    for role, rules in each[0].items():  # every robot's list has the same rules in the same order
        merged[role] = [
            Rule(
                rule.what, rule.flow, rule.messages, tuple(dict.fromkeys(k for one in each for k in one[role][i].keys))
            )
            for i, rule in enumerate(rules)
        ]
    alive = ALIVE.format(robot="*", service="*")
    merged["monitor"] += [
        *read(STATUS.pattern.format(robot="*", service="*"), STATE.pattern.format(robot="*")),
        *watch(alive, alive + "/*"),
    ]
    return merged


def _robot_rules(robot: str, *, lockstep: bool) -> dict[str, list[Rule]]:
    """Every role's rules for the one robot ``robot`` (:func:`role_rules`)."""
    check_chunk(robot, "robot id")

    def key(pattern: str, service: str = "*", robot: str = robot) -> str:
        return pattern.format(robot=robot, service=service)

    # every role may see which services are alive (srl/<robot>/alive/*) and which sessions they
    # are (identity tokens srl/<robot>/alive/<service>/<zid>, common.net.provenance)
    alive = (key(ALIVE), key(ALIVE) + "/*")

    def own(service: str) -> tuple[str, str]:  # a service's liveliness and identity tokens
        return key(ALIVE, service), key(ALIVE, service) + "/*"

    return {
        "actor": [
            *publish(key(ACTION.pattern), ACTION_BATCH.pattern, key(STATUS.pattern, "actor")),
            *advanced_publish(key(TRANSITION.pattern)),
            *advanced_publish(TRANSITION_BATCH.pattern),  # an actor host's (a host of many robots)
            # states and weights come on the robot's key or in batches (common.contracts.keys.Batch)
            *read(key(STATE.pattern), STATE_BATCH.pattern),
            # weights with recovery from the critic's cache (services.actor.ports.wire_weights)
            *advanced_read(key(WEIGHTS.pattern)),
            *advanced_read(WEIGHTS_BATCH.pattern),
            *(query(key(PLANT_STEP.pattern), key(PLANT_RESET.pattern)) if lockstep else []),
            *token(*own("actor")),
            *watch(*alive),
        ],
        "critic": [
            *publish(key(STATUS.pattern, "critic")),
            *advanced_publish(key(WEIGHTS.pattern)),
            *advanced_publish(WEIGHTS_BATCH.pattern),  # a critic of a robot list's
            # the critic subscribes to every robot's transitions (srl/*/transition): the rule
            # must include that wildcard; it still publishes weights for this robot only
            *advanced_read(key(TRANSITION.pattern, robot="*")),
            *advanced_read(TRANSITION_BATCH.pattern),
            *token(*own("critic")),
            *watch(*alive),
        ],
        "plant": [
            *publish(key(STATE.pattern), STATE_BATCH.pattern, key(STATUS.pattern, "plant")),
            *read(key(ACTION.pattern), ACTION_BATCH.pattern),
            *(serve(key(PLANT_STEP.pattern), key(PLANT_RESET.pattern)) if lockstep else []),
            *token(*own("plant"), key(ALIVE, "robot_bridge")),
            *watch(*alive),
        ],
        "monitor": [
            *read(key(STATUS.pattern), key(STATE.pattern), STATE_BATCH.pattern),
            *watch(*alive),
        ],
    }


def acl_config(robots: str | Sequence[str], *, lockstep: bool) -> dict[str, Any]:
    """The router's ``access_control`` section for ``robots`` (one id or a fleet's): default deny,
    one subject and policy per role (``lockstep``: the plant queries are allowed, see
    :func:`role_rules`)."""
    rules: list[dict[str, Any]] = [DISCOVERY.as_zenoh("discover")]
    policies: list[dict[str, Any]] = []
    for role, granted in role_rules(robots, lockstep=lockstep).items():
        ids = []
        for i, rule in enumerate(granted):
            rule_id = f"{role}-{i}-{rule.what.replace(' ', '-')}-{rule.flow}"
            rules.append(rule.as_zenoh(rule_id))
            ids.append(rule_id)
        policies.append({"id": role, "rules": ["discover", *ids], "subjects": [role]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": [{"id": role, "usernames": [role]} for role in ROLES],
        "policies": policies,
    }


# -- credentials -------------------------------------------------------------------------------
@dataclass(frozen=True)
class Credentials:
    """Fresh credentials of one run: the router's users file and one password file per role."""

    directory: Path
    users_file: Path
    password_files: dict[str, Path]

    def router_environment(self, *, lockstep: bool = False) -> dict[str, str]:
        """Environment (SRL_<SECTION>__<NAME> settings) of the secure router; ``lockstep`` lets the
        actor query (and the plant serve) plant/step and plant/reset (``transport.plant_queries``)."""
        return {
            "SRL_TRANSPORT__SECURE": "true",
            "SRL_TRANSPORT__USERS_FILE": str(self.users_file),
            "SRL_TRANSPORT__PLANT_QUERIES": "true" if lockstep else "false",
        }

    def role_environment(self, role: str) -> dict[str, str]:
        """Environment of a process that logs in as ``role``."""
        return {
            "SRL_TRANSPORT__SECURE": "true",
            "SRL_TRANSPORT__USER": role,
            "SRL_TRANSPORT__PASSWORD_FILE": str(self.password_files[role]),
        }

    def transport(self, transport: TransportSettings, role: str) -> TransportSettings:
        """``transport`` as seen by a process in this process that logs in as ``role``."""
        return transport.model_copy(
            update={"secure": True, "user": role, "password_file": str(self.password_files[role])}
        )


def write_credentials(directory: Path, roles: Iterable[str] = ROLES) -> Credentials:
    """A random password per role (``secrets.token_urlsafe``), written into ``directory``
    (created 0700): ``users.txt`` (``user:password`` lines, Zenoh's usrpwd dictionary) and
    ``<role>.password``, all 0600. Nothing is ever written into the repository."""
    directory.mkdir(mode=0o700, parents=True, exist_ok=True)
    directory.chmod(0o700)
    passwords = {role: secrets.token_urlsafe(PASSWORD_BYTES) for role in roles}
    users_file = directory / "users.txt"
    write_private(users_file, "".join(f"{role}:{password}\n" for role, password in passwords.items()).encode())
    files = {}
    for role, password in passwords.items():
        files[role] = directory / f"{role}.password"
        write_private(files[role], (password + "\n").encode())
    return Credentials(directory, users_file, files)


_WARNED: set[tuple[Path, int]] = set()


def _read_secret_file(path_text: str, what: str) -> str:
    path = Path(path_text).expanduser()
    try:
        mode = path.stat().st_mode
        text = path.read_text()
    except OSError as error:
        raise SecurityError(f"{what} {path}: {error.strerror}") from error
    if mode & (stat.S_IRWXG | stat.S_IRWXO) and (path, mode) not in _WARNED:
        # once per file and mode: a client retrying its login every 200 ms must not repeat it
        _WARNED.add((path, mode))
        log.warning("%s %s is readable by others (mode %o): chmod 600 it", what, path, stat.S_IMODE(mode))
    return text


def client_credentials(transport: TransportSettings) -> tuple[str, str]:
    """(user, password) of this process: ``transport.user`` and ``transport.password``
    (``SRL_TRANSPORT__PASSWORD``) or else the first line of ``transport.password_file``."""
    if not transport.user:
        raise SecurityError("transport.secure needs transport.user (SRL_TRANSPORT__USER): one of " + ", ".join(ROLES))
    password = transport.password.get_secret_value()
    if not password and transport.password_file:
        lines = _read_secret_file(transport.password_file, "password file").splitlines()
        password = lines[0].strip() if lines else ""
    if not password:
        raise SecurityError(
            f"transport.secure: no password for user {transport.user!r}: set "
            "transport.password_file or SRL_TRANSPORT__PASSWORD"
        )
    return transport.user, password


def zenoh_entries(transport: TransportSettings, *, router: bool) -> dict[str, Any]:
    """Config entries (path -> JSON value) that secure a session: the router checks users
    against ``transport.users_file`` and enforces :func:`acl_config`; a client logs in."""
    if router:
        if not transport.users_file:
            raise SecurityError(
                "a secure router needs transport.users_file (SRL_TRANSPORT__USERS_FILE): 'user:password' lines"
            )
        users_file = Path(transport.users_file).expanduser()
        _read_secret_file(str(users_file), "users file")  # fail here with a clear message
        return {
            "transport/auth/usrpwd/dictionary_file": str(users_file),
            "access_control": acl_config(transport.rule_robots, lockstep=transport.plant_queries),
        }
    user, password = client_credentials(transport)
    return {"transport/auth/usrpwd/user": user, "transport/auth/usrpwd/password": password}


# -- TLS and network exposure -----------------------------------------------------------------
LOOPBACK_NAMES = ("localhost",)


def endpoint_host(endpoint: str) -> tuple[str, str]:
    """``(protocol, host)`` of a Zenoh endpoint such as ``tls/[::1]:7447#iface=lo`` or ``tcp/router:7447``."""
    protocol, _, rest = endpoint.partition("/")
    address = rest.split("#", 1)[0].split("?", 1)[0]
    if address.startswith("["):  # [v6]:port
        return protocol, address[1 : address.find("]")]
    return protocol, address.rsplit(":", 1)[0] if ":" in address else address


def is_loopback(endpoint: str) -> bool:
    """True for an endpoint bound to loopback only: 127.0.0.0/8, ::1, localhost (and unix sockets)."""
    protocol, host = endpoint_host(endpoint)
    if protocol in ("unixsock-stream", "unixpipe"):
        return True
    if host.lower() in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a host name or 0.0.0.0 / [::]: reachable from elsewhere


def check_network_exposure(transport: TransportSettings, listen: list[str]) -> None:
    """A router that listens off loopback must be secure (login + role rules) and TLS on every
    such endpoint, unless ``transport.allow_insecure_network`` (a private container network)."""
    exposed = [endpoint for endpoint in listen if not is_loopback(endpoint)]
    if not exposed or transport.allow_insecure_network:
        if exposed:
            log.warning(
                "router listens on %s without the secure-network checks (allow_insecure_network): "
                "only safe inside a private container network",
                ", ".join(exposed),
            )
        return
    problems = []
    if not transport.secure:
        problems.append("transport.secure is off (no login, no access rules)")
    plain = [endpoint for endpoint in exposed if endpoint_host(endpoint)[0] != "tls"]
    if plain:
        problems.append(f"{', '.join(plain)} is not a tls/ endpoint")
    if not (transport.tls_ca and transport.tls_cert and transport.tls_key):
        problems.append("transport.tls_ca, tls_cert and tls_key are not all set (srl certs --out DIR)")
    if problems:
        raise SecurityError(
            f"refusing to run a router on {', '.join(exposed)}, reachable from the network: "
            + "; ".join(problems)
            + ". Use a loopback endpoint, or secure = true with a tls/ endpoint and "
            "certificates (docs/security.md), or allow_insecure_network = true ONLY inside a private "
            "container network"
        )


def tls_entries(transport: TransportSettings, *, router: bool) -> dict[str, Any]:
    """Config entries (path -> JSON value) of Zenoh's TLS links (zenoh 1.10 ``transport/link/tls``):
    the CA every side verifies the other against, this process's certificate and key (the
    router's as listener and for its own outgoing links, a client's as its mTLS identity)."""
    for name in ("tls_ca", "tls_cert", "tls_key"):
        path = getattr(transport, name)
        if path and not Path(path).expanduser().is_file():
            raise SecurityError(f"transport.{name}: {path} is not a file")
    if not transport.tls_ca:
        raise SecurityError(
            "a tls/ endpoint needs transport.tls_ca (SRL_TRANSPORT__TLS_CA): the CA certificate "
            "(srl certs --out DIR writes ca.pem)"
        )
    if transport.tls_key:
        _read_secret_file(transport.tls_key, "TLS private key")  # warns if others may read it
    entries: dict[str, Any] = {"transport/link/tls/root_ca_certificate": str(Path(transport.tls_ca).expanduser())}
    cert = str(Path(transport.tls_cert).expanduser()) if transport.tls_cert else ""
    key = str(Path(transport.tls_key).expanduser()) if transport.tls_key else ""
    if router:
        if not (cert and key):
            raise SecurityError(
                "a router on a tls/ endpoint needs transport.tls_cert and tls_key "
                "(srl certs writes router.pem and router.key)"
            )
        entries.update(
            {
                "transport/link/tls/listen_certificate": cert,
                "transport/link/tls/listen_private_key": key,
                "transport/link/tls/enable_mtls": transport.tls_mtls,
            }
        )
    elif transport.tls_mtls and not (cert and key):
        raise SecurityError(
            "mutual TLS (transport.tls_mtls) needs this process's transport.tls_cert and tls_key "
            "(srl certs writes <role>.pem and <role>.key)"
        )
    if cert and key:  # outgoing links: a client's identity, a router's links to other routers
        entries.update(
            {
                "transport/link/tls/connect_certificate": cert,
                "transport/link/tls/connect_private_key": key,
                "transport/link/tls/enable_mtls": transport.tls_mtls,
            }
        )
    return entries
