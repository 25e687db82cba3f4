"""``srl plant-sim`` / ``python -m services.plant_sim``: the simulated robot (real-time or lockstep queryable)."""

from __future__ import annotations

import argparse

from common.arguments import COMMAND_SETTINGS, add_settings_arguments, settings_from_args
from common.runtime import add_lifetime_arguments, add_mode_argument, serve

NAME = "plant-sim"
HELP = "the simulated robot (real-time or lockstep queryable)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, COMMAND_SETTINGS[NAME])
    add_mode_argument(parser)
    add_lifetime_arguments(
        parser, "stop after this long (default: until signalled; a lockstep actor stops after one episode)"
    )
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from services.plant_sim.service import run

    return serve(
        settings_from_args(args),
        "plant",
        args.connect_timeout,
        lambda settings, bus, stop: run(settings, bus, args.mode, stop, args.run_seconds),
    )
