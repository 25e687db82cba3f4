"""``srl robot-bridge`` / ``python -m services.robot_bridge``: a ROS 2 robot as the plant."""

from __future__ import annotations

import argparse

from common.arguments import COMMAND_SETTINGS, add_bridge_arguments, add_settings_arguments, settings_from_args
from common.runtime import add_lifetime_arguments, serve

NAME = "robot-bridge"
HELP = "a ROS 2 robot as the plant: odom in, cmd_vel out, over Zenoh"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, COMMAND_SETTINGS[NAME])
    add_bridge_arguments(parser)
    add_lifetime_arguments(parser)
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from services.robot_bridge.service import run

    return serve(
        settings_from_args(args),
        "plant",
        args.connect_timeout,
        lambda settings, bus, stop: run(settings, bus, stop, args.run_seconds),
    )
