"""``srl up --robots``'s options and command (docs/fleets.md), kept apart from tools/launch/fleet.py so that
building the ``srl`` parser does not import Zenoh."""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

from common.config.arguments import (
    UsageError,
    add_circle_argument,
    add_robot_endpoints_argument,
    add_robots_argument,
    fleet_robots,
    ros_fleet_endpoints,
)
from common.config.settings import Settings
from common.math.fleet import ROS_FLEET_PREFIX
from tools.commands.view import VIEW_PORT
from tools.launch.plants import launch_plant

LAYOUTS = ("host", "process")


def add_fleet_arguments(parser: argparse.ArgumentParser) -> None:
    """``srl up``'s fleet options (docs/fleets.md)."""
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
    add_circle_argument(parser)
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


def beside_commands(args: argparse.Namespace, router: str, default_router: str) -> str:
    """The exact ``srl record`` and ``srl view`` commands that join this fleet: ``--router`` when
    the fleet's router is not where they look by default, ``--config`` when one was given."""
    flags = "" if router == default_router else f" --router {router}"
    if args.config is not None:
        flags += f" --config {shlex.quote(str(args.config))}"
    record = shlex.quote(str(args.record)) if getattr(args, "record", None) is not None else "FILE.mcap"
    port = f" --port {args.view}" if getattr(args, "view", None) not in (None, VIEW_PORT) else ""
    return f"`srl record {record}{flags}`, `srl view{port}{flags}`"


def cmd_up_fleet(args: argparse.Namespace, settings: Settings, settings_args: list[str], summary_dir: Path) -> int:
    """``srl up --robots``: the fleet's run, a status line a second, the per-robot table, ``--json``."""
    bridged = launch_plant(args.plant).behind_bridge  # the parser's choices are the rows
    robots = fleet_robots(args, ROS_FLEET_PREFIX if bridged else "robot")
    assert robots is not None
    endpoints: dict[str, str] = {}
    bridge_args: list[str] = []
    if bridged:
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
    from tools.launch.supervisor import local_router_endpoint

    router = local_router_endpoint(settings.transport.router, given=args.router is not None)
    default_router = Settings.load(args.config).transport.router  # where srl record and srl view look
    if getattr(args, "view", None) is not None:
        why = "" if args.router is not None else f": {default_router} is taken"
        again = "" if router == default_router else f" (with `--router {router}`{why})"
        raise UsageError(
            f"--view does not start with --robots yet: run the fleet without it{again} and, beside "
            f"it, {beside_commands(args, router, default_router)} (both carry every robot)"
        )
    record = getattr(args, "record", None)
    if record is not None:
        if args.secure:
            raise UsageError(
                "--record does not run with --secure yet: the read-only monitor role may read only states and "
                "status, not the transitions and weights a recording carries"
            )
        from tools.recording.record import RecordingError, open_for_writing

        try:  # a bad path is one line now, before anything starts
            open_for_writing(record).close()
        except RecordingError as error:
            raise UsageError(str(error)) from error
    print(
        f"srl up: the fleet's router listens on {router}; beside it: {beside_commands(args, router, default_router)}",
        file=sys.stderr,
        flush=True,
    )
    from tools.launch.fleet import actor_hosts

    args.actor_hosts = actor_hosts(str(args.actor_hosts), len(robots))

    def show(line: str) -> None:
        print(f"srl up {line}", file=sys.stderr, flush=True)

    from tools.launch.fleet import format_fleet_summary, run_fleet
    from tools.launch.supervisor import ServiceDiedError

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
            router=router,
            record=record,
        )
    except ServiceDiedError as error:
        return error.say("srl up")
    except TimeoutError as error:
        raise UsageError(str(error)) from error
    print(format_fleet_summary(summary))
    if args.json:
        print(json.dumps(summary))
    return 0
