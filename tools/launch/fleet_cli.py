"""``srl up --robots``'s options and command (issue 16), kept apart from tools/launch/fleet.py so that
building the ``srl`` parser does not import Zenoh."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from common.config.arguments import (
    UsageError,
    add_robot_endpoints_argument,
    add_robots_argument,
    fleet_robots,
    ros_fleet_endpoints,
)
from common.config.settings import Settings
from common.math.fleet import ROS_FLEET_PREFIX

LAYOUTS = ("host", "process")


def add_fleet_arguments(parser: argparse.ArgumentParser) -> None:
    """``srl up``'s fleet options (issue 16)."""
    add_robots_argument(
        parser,
        f"a fleet (real time; with --plant robot each robot's id is its ROS namespace, K: {ROS_FLEET_PREFIX}1.."
        f"{ROS_FLEET_PREFIX}K): ",
    )
    add_robot_endpoints_argument(parser)
    parser.add_argument(
        "--layout",
        choices=LAYOUTS,
        default="host",
        help="with --robots: host = one actor and one plant process for every robot; "
        "process = one actor and one plant_sim per robot (default: host)",
    )
    parser.add_argument(
        "--circle",
        type=float,
        default=1.5,
        metavar="R",
        help="with --robots: starts evenly on a circle of R metres around the target (default: 1.5)",
    )
    parser.add_argument(
        "--actor-hosts",
        default="auto",
        metavar="H|auto",
        help="with --robots (host layout): split the robots over H actor hosts; auto = 1 below 50 robots, "
        "else one per core (default: auto)",
    )
    parser.add_argument(
        "--critic",
        choices=("per-robot", "pooled"),
        help="with --robots: a learner per robot, or one pooled learner trained on every robot's transitions "
        "(default: setting critic.pooled, false: per-robot)",
    )


def cmd_up_fleet(args: argparse.Namespace, settings: Settings, settings_args: list[str], summary_dir: Path) -> int:
    """``srl up --robots``: the fleet's run, a status line a second, the per-robot table, ``--json``."""
    robots = fleet_robots(args, ROS_FLEET_PREFIX if args.plant == "robot" else "robot")
    assert robots is not None
    if args.plant not in ("sim", "physics", "robot"):
        raise UsageError("--robots runs --plant sim, physics or robot")
    endpoints: dict[str, str] = {}
    bridge_args: list[str] = []
    if args.plant == "robot":
        from common.config.arguments import bridge_argv

        if settings.bridge.namespace:
            raise UsageError(
                f"bridge.namespace {settings.bridge.namespace!r} with --robots: each robot's namespace is its id"
            )
        endpoints = ros_fleet_endpoints(args, robots, settings.bridge.robot_endpoint)
        # each robot's namespace and endpoint are the fleet's own (tools/launch/fleet_robot.py)
        bridge_args = [a for a in bridge_argv(args) if a.split("=", 1)[0] not in ("--namespace", "--robot-endpoint")]
    elif getattr(args, "robot_endpoints", None):
        raise UsageError("--robot-endpoints is for --plant robot")
    if getattr(args, "record", None) is not None or getattr(args, "view", None) is not None:
        raise UsageError(
            "--record and --view do not start with --robots yet: run `srl record FILE.mcap` or `srl view` "
            "beside the fleet (both carry every robot)"
        )
    from tools.launch.fleet import actor_hosts

    args.actor_hosts = actor_hosts(str(args.actor_hosts), len(robots))
    if not (math.isfinite(args.circle) and args.circle > 0):
        raise UsageError(f"--circle {args.circle}: the start circle's radius must be a positive number of metres")

    def show(line: str) -> None:
        print(f"srl up {line}", file=sys.stderr, flush=True)

    from tools.launch.fleet import format_fleet_summary, run_fleet
    from tools.launch.up import ServiceDiedError

    try:
        summary = run_fleet(
            settings,
            settings_args,
            robots,
            settings.episode.duration,
            layout=args.layout,
            circle=args.circle,
            on_status=show,
            actor_hosts=args.actor_hosts,
            summary_dir=summary_dir,
            plant=args.plant,
            robot_endpoints=endpoints,
            bridge_args=bridge_args,
            pooled=settings.critic.pooled if args.critic is None else args.critic == "pooled",
            secure=args.secure,
        )
    except ServiceDiedError as error:  # as srl up says it: one line and the service's last words
        print(f"srl up: error: {error}", file=sys.stderr)
        for line in error.tail:
            print(f"  [{error.name}] {line}", file=sys.stderr)
        return 1
    except TimeoutError as error:
        raise UsageError(str(error)) from error
    print(format_fleet_summary(summary))
    if args.json:
        print(json.dumps(summary))
    return 0
