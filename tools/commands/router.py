"""``srl router``: a Zenoh router (Python, mode router): srl's one meeting point."""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading

from common.config.arguments import COMMAND_SETTINGS, UsageError, add_settings_arguments, settings_from_args
from common.contracts.summaries import RouterSummary
from common.process.runtime import own_resources, service_stop, zenoh_reason

NAME = "router"
HELP = "a Zenoh router (Python, mode router)"
ROUTER_CLOSE_SECONDS = 3.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, COMMAND_SETTINGS[NAME])
    parser.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help="also connect to this endpoint, e.g. another host's router tcp/192.168.1.20:7447; repeat for "
        "several (one router per host) (default: transport.connect, none in common/config/srl.toml)",
    )
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:

    import zenoh

    from common.net.transport import zenoh_config

    settings = settings_from_args(args, any_system=True)  # it routes whatever system the keys carry
    stop = service_stop()  # signals (bounded) and srl up's death
    try:
        session = zenoh.open(zenoh_config(settings.transport, router=True))
    except zenoh.ZError as error:
        raise UsageError(
            f"router: cannot listen on {settings.transport.router}: {zenoh_reason(error)} "
            "(another router on that port? choose one with --router)"
        ) from error
    # its one line of normal output, on stdout (not a warning): what it serves and how
    transport = settings.transport
    robots = transport.rule_robots
    whose = f"robot {robots[0]}" if len(robots) == 1 else f"{len(robots)} robots ({robots[0]}..{robots[-1]})"
    rules = f"; users and access rules of {whose} enforced" if transport.secure else ""
    # Zenoh keeps trying an unreachable router (a router's connect never gives up): it links when that one comes up
    links = f"; connecting to {', '.join(transport.connect)}" if transport.connect else ""
    print(
        f"srl router: router listening on {settings.transport.router} (multicast scouting "
        f"{'on' if settings.transport.multicast_scouting else 'off'}{rules}{links})",
        flush=True,
    )
    stop.wait()
    # A router holds no state, so its close is bounded: a close still waiting on its links after
    # ROUTER_CLOSE_SECONDS ends the process anyway (the summary says so), never a hang.
    closer = threading.Thread(target=session.close, name="router-close", daemon=True)
    closer.start()
    closer.join(ROUTER_CLOSE_SECONDS)
    summary = RouterSummary(
        endpoint=settings.transport.router, resources=own_resources(), close_timed_out=closer.is_alive()
    ).to_json_dict()
    if summary["close_timed_out"]:
        print(json.dumps(summary), flush=True)
        sys.stderr.flush()
        os._exit(0)  # the interpreter's exit would wait on the session's runtime
    print(json.dumps(summary), flush=True)
    return 0
