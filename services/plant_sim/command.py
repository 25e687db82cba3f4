"""``srl plant-sim`` / ``python -m services.plant_sim``: the simulated robot (real-time or lockstep queryable)."""

from __future__ import annotations

import argparse
import math

from common.config.arguments import (
    COMMAND_SETTINGS,
    UsageError,
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
        parser, "stop after this long (default: until signalled; a lockstep actor stops after one episode)"
    )
    add_robots_argument(parser, "simulate every robot of the list in this one process (real time): ")
    parser.add_argument(
        "--circle",
        type=float,
        default=1.5,
        metavar="R",
        help="with --robots: the robots start evenly on a circle of R metres around the target, "
        "each heading away from it (default: 1.5)",
    )
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from services.plant_sim.service import run

    robots = fleet_robots(args)
    if robots is not None:
        from services.plant_sim.host import run_plant_host

        if not (math.isfinite(args.circle) and args.circle > 0):
            raise UsageError(f"--circle {args.circle}: the start circle's radius must be a positive number of metres")
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
