"""``srl actor`` / ``python -m services.actor``: the delta-periodic actor loop."""

from __future__ import annotations

import argparse

from common.arguments import COMMAND_SETTINGS, add_settings_arguments, settings_from_args
from common.runtime import add_lifetime_arguments, add_mode_argument, add_robots_argument, fleet_robots, serve

NAME = "actor"
HELP = "the delta-periodic actor loop"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, COMMAND_SETTINGS[NAME])
    add_mode_argument(parser)
    add_lifetime_arguments(
        parser, "stop after this long (default: until signalled; a lockstep actor stops after one episode)"
    )
    parser.add_argument(
        "--sync-critic", action="store_true", help="lockstep: wait for the weights trained on the previous step"
    )
    add_robots_argument(parser, "serve every robot of the list in this one process (real time): ")
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from services.actor.service import run

    robots = fleet_robots(args)
    if robots is not None:
        from services.actor.host import run_host

        return serve(
            settings_from_args(args),
            "actor",
            args.connect_timeout,
            lambda settings, bus, stop: run_host(settings, bus, robots, stop, args.run_seconds),
        )
    return serve(
        settings_from_args(args),
        "actor",
        args.connect_timeout,
        lambda settings, bus, stop: run(settings, bus, args.mode, stop, args.run_seconds, args.sync_critic),
    )
