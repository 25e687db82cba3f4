"""``srl health SERVICE``: is this service ready? Exit 0 if yes, 1 if not (container healthchecks).

* ``router``: a Zenoh client session to the router opens (the router accepts connections).
* ``actor``, ``critic``, ``plant``, ``robot_bridge``, ...: the service's liveliness token
  ``srl/<robot>/alive/<service>`` is visible through the router. Every srl service declares it
  once it is ready (plant_sim and robot_bridge both as ``plant``; the bridge also as
  ``robot_bridge``), and it vanishes within milliseconds when the holder dies
  (docs/architecture.md).
* ``robot``: the ROS 2 robot (a real one, or the TurtleBot3 emulator) is visible through the
  router: a liveliness token of its graph, for the ``[bridge]`` settings' wire profile, domain
  and namespace (the pattern the bridge discovers the robot's ``cmd_vel`` subscription with).
* ``--key KEYEXPR``: any liveliness token matching KEYEXPR.

One line on stdout says what was found (Docker keeps it: ``docker inspect``, ``.State.Health``).
The session is a client of the router: explicit endpoint, multicast scouting as configured
(off by default), listening nowhere.

Why this module reads three transport settings itself: Docker runs a healthcheck every few
seconds in every container, and ``srl health`` imports the full settings stack (pydantic, numpy),
ten times the CPU of ``python -m tools.launch.health``: on a small machine, several containers'
checks would take most of a core. So
``transport_settings`` resolves ``router``, ``robot``, ``multicast_scouting`` and ``connect``
with the same precedence as :class:`common.config.settings.Settings` (flags > ``SRL_TRANSPORT__<NAME>``
> ``--config``/``SRL_CONFIG`` > the packaged ``common/config/srl.toml``) and ``ALIVE_KEY`` mirrors
:func:`common.contracts.keys.liveliness_key`; ``tests/test_health.py`` holds both equal to the originals.
``robot`` needs the ``[bridge]`` settings and takes the full path, and so does every check when
``transport.secure`` is on (the session must log in as ``transport.user``: ``zenoh_config``).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import time
import tomllib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import common

HEALTHY, UNHEALTHY, BAD_USAGE = 0, 1, 2
PACKAGED_CONFIG = Path(common.__file__).parent / "config" / "srl.toml"  # == common.config.settings.DEFAULT_CONFIG
ALIVE_KEY = "srl/{robot}/alive/{service}"  # == common.contracts.keys.liveliness_key (tested)
_CHUNK = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")
FIELDS = ("router", "robot", "multicast_scouting", "connect", "secure")  # of [transport]
_TRUE, _FALSE = {"1", "true", "yes", "on", "t", "y"}, {"0", "false", "no", "off", "f", "n"}


NAME = "health"
HELP = "exit 0 if a service is ready (router reachable, liveliness token seen)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``srl health``'s options (tools/cli.py) and ``python -m tools.launch.health``'s."""
    parser.add_argument(
        "service",
        nargs="?",
        default="router",
        help="router (default); robot (the ROS 2 robot's graph); or a service whose token "
        "srl/<robot>/alive/<service> to look for (actor, critic, plant, robot_bridge)",
    )
    parser.add_argument(
        "--key", help="instead: any liveliness token matching this key expression (default: the service's)"
    )
    parser.add_argument(
        "--config", type=Path, help="a TOML file overriding common/config/srl.toml (any subset) (default: none)"
    )
    parser.add_argument("--router", help="Zenoh router endpoint (default from config/environment)")
    parser.add_argument("--robot", help="robot id, the <robot> chunk of the key (default from config: tb3_0)")
    parser.add_argument("--timeout", type=float, default=2.0, help="[s] how long to wait for an answer (default: 2)")
    parser.set_defaults(func=main)


def transport_settings(
    config: Path | None = None, router: str | None = None, robot: str | None = None
) -> dict[str, Any]:
    """``router``, ``robot``, ``multicast_scouting``, ``connect``, ``secure`` as Settings resolves them."""
    files = [PACKAGED_CONFIG]
    user_file = config or os.environ.get("SRL_CONFIG")
    if user_file:
        if not Path(user_file).is_file():
            raise ValueError(f"config file {user_file} does not exist")
        files.append(Path(user_file))
    values: dict[str, Any] = {}
    for path in files:
        with open(path, "rb") as file:
            values.update(tomllib.load(file).get("transport", {}))
    environment = {name.upper(): value for name, value in os.environ.items()}
    for name in FIELDS:
        text = environment.get(f"SRL_TRANSPORT__{name.upper()}")
        if text is None:
            continue
        if name in ("multicast_scouting", "secure"):
            if text.strip().lower() not in _TRUE | _FALSE:
                raise ValueError(f"SRL_TRANSPORT__{name.upper()}={text!r} is not a boolean")
            values[name] = text.strip().lower() in _TRUE
        elif name == "connect":
            values[name] = json.loads(text)
        else:
            values[name] = text
    if router is not None:
        values["router"] = router
    if robot is not None:
        values["robot"] = robot
    if not isinstance(values.get("robot"), str) or not _CHUNK.match(values["robot"]):
        raise ValueError(f"robot id {values.get('robot')!r} must be 1-64 characters of A-Z a-z 0-9 _ -")
    return {name: values.get(name, False) if name == "secure" else values[name] for name in FIELDS}


def client_config(transport: dict[str, Any], config_file: Path | None = None) -> Any:
    """A client of the router (as ``common.net.transport.zenoh_config`` makes for clients); with
    ``secure`` on, ``zenoh_config`` itself (it adds this process's login)."""
    import zenoh

    if transport["secure"] or str(transport["router"]).startswith("tls/"):  # login or TLS: the full settings
        from common.config.settings import Settings
        from common.net.transport import zenoh_config

        settings = Settings.load(config_file, transport={"router": transport["router"], "robot": transport["robot"]})
        return zenoh_config(settings.transport)

    config = zenoh.Config()
    config.insert_json5("mode", json.dumps("client"))
    config.insert_json5("scouting/multicast/enabled", json.dumps(bool(transport["multicast_scouting"])))
    config.insert_json5("listen/endpoints", "[]")
    config.insert_json5("connect/endpoints", json.dumps([transport["router"], *transport["connect"]]))
    return config


def robot_graph_pattern(config: Path | None) -> str:
    """The liveliness pattern of the robot's ROS 2 graph, from the full ``[bridge]`` settings."""
    from common.config.settings import Settings
    from common.contracts.ros_wire import RosGraph

    bridge = Settings.load(config).bridge
    return str(RosGraph.from_settings(bridge).discovery_pattern(bridge.cmd_vel_topic))


def check(
    transport: dict[str, Any], service: str, key: str | None, timeout: float, config: Path | None = None
) -> tuple[bool, str]:
    """(ready, what was found). An unreachable router or a missing token is an answer, not an error."""
    import zenoh

    if key is None and service not in ("router", "robot") and not _CHUNK.match(service):
        raise ValueError(f"service {service!r} must be 1-64 characters of A-Z a-z 0-9 _ -")
    wanted = key
    if wanted is None and service == "robot":
        wanted = robot_graph_pattern(config)
    elif wanted is None and service != "router":
        wanted = ALIVE_KEY.format(robot=transport["robot"], service=service)
    endpoint = transport["router"]
    deadline = time.monotonic() + timeout
    while True:  # a client session fails at once when nothing listens: retry until the timeout
        try:
            session = zenoh.open(client_config(transport, config))
            break
        except zenoh.ZError as error:
            if time.monotonic() >= deadline:
                return False, f"router {endpoint} not reachable: {error}"
            time.sleep(0.1)
    try:
        if wanted is None:
            return True, f"router {endpoint} accepts sessions"
        remaining = max(0.1, deadline - time.monotonic())
        replies = session.liveliness().get(wanted, timeout=remaining)
        found = [str(reply.ok.key_expr) for reply in replies if reply.ok is not None]
    finally:
        session.close()
    if found:
        return True, f"alive: {found[0]}" + (f" (+{len(found) - 1} more)" if len(found) > 1 else "")
    return False, f"no liveliness token {wanted} seen through {endpoint} within {remaining:.1f} s"


def main(args: argparse.Namespace) -> int:
    """``srl health``: one line on stdout, the exit code says ready (0), not ready (1), bad usage (2)."""
    try:
        transport = transport_settings(args.config, args.router, args.robot)
        ready, what = check(transport, args.service, args.key, args.timeout, args.config)
    except (ValueError, OSError, tomllib.TOMLDecodeError) as error:  # bad settings or service name
        print(f"unhealthy: {error}", flush=True)
        return BAD_USAGE
    print(("healthy: " if ready else "unhealthy: ") + what, flush=True)
    return HEALTHY if ready else UNHEALTHY


def module_main(argv: Sequence[str] | None = None) -> int:
    """``python -m tools.launch.health``: the same as ``srl health``, without the ``srl`` imports."""
    parser = argparse.ArgumentParser(
        prog="python -m tools.launch.health", description=(__doc__ or "").split("\n", 1)[0]
    )
    add_arguments(parser)
    return main(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(module_main())
