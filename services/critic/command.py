"""``srl critic`` / ``python -m services.critic``: the off-board critic learner (TD least squares)."""

from __future__ import annotations

import argparse

from common.config.arguments import (
    COMMAND_SETTINGS,
    add_lifetime_arguments,
    add_robots_argument,
    add_settings_arguments,
    fleet_robots,
    settings_from_args,
)
from common.process.runtime import serve

NAME = "critic"
HELP = "the off-board critic learner (TD least squares)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, COMMAND_SETTINGS[NAME])
    add_lifetime_arguments(
        parser, "[s] learn this long, then stop (default: until signalled; srl up stops it after the actor)"
    )
    add_robots_argument(
        parser, "learn from these robots only and declare this critic alive for each (a fleet, or its shard): "
    )
    parser.add_argument(
        "--pooled",
        action="store_true",
        help="one learner for every robot (a fleet's pooled critic; setting critic.pooled) "
        "(default: a learner per robot)",
    )
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from services.critic.service import run

    robots = fleet_robots(args)
    settings = settings_from_args(args, any_system=True)  # it fits any system's transitions (settings.wire)
    if args.pooled:
        settings = settings.model_copy(update={"critic": settings.critic.model_copy(update={"pooled": True})})

    return serve(
        settings,
        "critic",
        args.connect_timeout,
        lambda settings, bus, stop: run(settings, bus, stop, args.run_seconds, robots),
        any_system=True,
    )
