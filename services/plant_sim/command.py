"""``srl plant-sim`` / ``python -m services.plant_sim``: the simulated robot (real-time or lockstep queryable)."""

from __future__ import annotations

import argparse

from common.config.arguments import (
    COMMAND_SETTINGS,
    add_circle_argument,
    add_lifetime_arguments,
    add_mode_argument,
    add_robots_argument,
    add_settings_arguments,
    fleet_robots,
    settings_from_args,
)
from common.process.runtime import serve

NAME = "plant-sim"
HELP = "the simulated robot (real-time or lockstep queryable)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, COMMAND_SETTINGS[NAME])
    add_mode_argument(parser)
    add_lifetime_arguments(
        parser,
        "[s] simulate this long: publish states (realtime) or answer the actor's steps (lockstep), then "
        "stop (default: until signalled; srl up stops it after the actor)",
    )
    add_robots_argument(parser, "simulate every robot of the list in this one process (real time): ")
    add_circle_argument(parser)
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from services.plant_sim.service import run

    robots = fleet_robots(args)
    if robots is not None:
        from services.plant_sim.host import run_plant_host

        return serve(
            settings_from_args(args),
            "plant",
            args.connect_timeout,
            lambda settings, bus, stop: run_plant_host(settings, bus, robots, args.circle, stop, args.run_seconds),
        )
    return serve(
        settings_from_args(args),
        "plant",
        args.connect_timeout,
        lambda settings, bus, stop: run(settings, bus, args.mode, stop, args.run_seconds),
    )
