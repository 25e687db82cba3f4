"""``srl robot-bridge`` / ``python -m services.robot_bridge``: a ROS 2 robot as the plant."""

from __future__ import annotations

import argparse
import threading
from typing import TYPE_CHECKING, Any

from common.config.arguments import (
    COMMAND_SETTINGS,
    UsageError,
    add_bridge_arguments,
    add_lifetime_arguments,
    add_robot_endpoints_argument,
    add_robots_argument,
    add_settings_arguments,
    fleet_robots,
    ros_fleet_endpoints,
    settings_from_args,
)
from common.math.fleet import ROS_FLEET_PREFIX
from common.process.runtime import serve

if TYPE_CHECKING:
    from common.config.settings import Settings
    from common.net.transport import Bus

NAME = "robot-bridge"
HELP = "a ROS 2 robot as the plant: odom in, cmd_vel out, over Zenoh"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, COMMAND_SETTINGS[NAME])
    add_bridge_arguments(parser)
    add_lifetime_arguments(parser)
    add_robots_argument(
        parser,
        "serve several ROS 2 robots in this one process, each robot's id its ROS namespace "
        f"(K: {ROS_FLEET_PREFIX}1..{ROS_FLEET_PREFIX}K): ",
    )
    add_robot_endpoints_argument(parser)
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from common.contracts.summaries import printed_summary
    from services.robot_bridge.host import run_bridge_host

    settings = settings_from_args(args)
    robots = fleet_robots(args, ROS_FLEET_PREFIX)
    if robots is None:  # one robot: its id transport.robot, its ROS namespace bridge.namespace
        if getattr(args, "robot_endpoints", None):
            raise UsageError("--robot-endpoints needs --robots (one bridge for several robots)")
        robot = settings.transport.robot
        fleet = {robot: settings.bridge.robot_endpoint}
        namespaces: dict[str, str] | None = {robot: settings.bridge.namespace}
    else:  # each robot's id is its ROS namespace
        if settings.bridge.namespace:
            raise UsageError(
                f"bridge.namespace {settings.bridge.namespace!r} with --robots: "
                "each robot's ROS namespace is its robot id"
            )
        fleet = ros_fleet_endpoints(args, robots, settings.bridge.robot_endpoint)
        namespaces = None

    def body(settings: Settings, bus: Bus, stop: threading.Event) -> dict[str, Any]:
        return printed_summary(
            run_bridge_host(settings, bus, fleet, stop, args.run_seconds, namespaces), robots is not None
        )

    return serve(settings, "plant", args.connect_timeout, body)
