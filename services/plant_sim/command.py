"""``srl plant-sim`` / ``python -m services.plant_sim``: the simulated robot (real-time or lockstep queryable)."""

from __future__ import annotations

import argparse
import threading
from typing import Any

import numpy as np

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
from common.config.settings import Settings
from common.net.transport import Bus
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
    """Real time: a plant host of the robot list, or of the one robot (``transport.robot``);
    lockstep: the one robot's queryable plant."""
    robots = fleet_robots(args)
    if args.mode == "lockstep" and robots is None:
        from services.plant_sim.service import run

        return serve(
            settings_from_args(args, any_system=True),
            "plant",
            args.connect_timeout,
            lambda settings, bus, stop: run(settings, bus, stop, args.run_seconds),
            any_system=True,
        )
    return serve(  # a plant host of any system (settings.wire)
        settings_from_args(args, any_system=True),
        "plant",
        args.connect_timeout,
        lambda settings, bus, stop: host(settings, bus, stop, args, robots),
        any_system=True,
    )


def host(
    settings: Settings, bus: Bus, stop: threading.Event, args: argparse.Namespace, robots: list[str] | None
) -> dict[str, Any]:
    from common.contracts.summaries import printed_summary
    from common.math.fleet import fleet_starts
    from services.plant_sim.host import plant_host_summary, run_plant_host

    synced = settings.transport.state_sync  # a host of one robot as of K: its states as its actor reads them
    if robots is None:  # one robot, from its start: its row of the host's summary
        fleet, starts = [settings.transport.robot], np.array([settings.start_state()])
    else:
        fleet, starts = robots, np.array(fleet_starts(settings.system, len(robots), args.circle))
    run = run_plant_host(settings, bus, fleet, starts, stop, args.run_seconds, synced)
    return printed_summary(plant_host_summary(run, settings, bus, args.circle), robots is not None)
