"""``srl up``: the router and every service as separate processes, one run of the robot of the
settings or of a fleet (``--robots``), both by tools/launch/up.py; a live status line and the summary."""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from pathlib import Path
from typing import Any

from common.config.arguments import (
    COMMAND_SETTINGS,
    UsageError,
    add_bridge_arguments,
    add_circle_argument,
    add_mode_argument,
    add_robot_endpoints_argument,
    add_robots_argument,
    add_settings_arguments,
    bridge_argv,
    fleet_robots,
    ros_fleet_endpoints,
    settings_argv,
    settings_from_args,
)
from common.config.settings import Settings
from common.math.fleet import AUTO_HOSTS_HELP, ROS_FLEET_PREFIX
from common.math.systems import system_row
from tools.commands.run import fmt_state, how_far, truth_lines
from tools.commands.view import VIEW_PORT
from tools.launch.plants import LAUNCH_PLANTS, LAYOUTS, launch_plant, launch_plant_help

NAME = "up"
HELP = "router + every service as separate processes, one run"
DESCRIPTION = (
    "The router and every service as separate processes, one run, a live status line once a second.\n"
    "Each service's JSON summary is written to a file (--summary-dir); --json prints the merged one."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, COMMAND_SETTINGS[NAME])
    add_bridge_arguments(parser)
    parser.add_argument(
        "--plant",
        choices=list(LAUNCH_PLANTS),
        default="sim",
        help=f"{launch_plant_help()} (default: sim)",
    )
    add_mode_argument(parser)
    parser.add_argument(
        "--secure",
        action="store_true",
        help="Zenoh user/password login with fresh random credentials per role, and access rules "
        "at the router: only the actor publishes actions, the critic weights, the plant state; "
        "a tcp/ router endpoint becomes tls/ with mutual TLS (fresh private CA); --plant robot: the emulated "
        "robot's own router too (TLS, the bridge's login, the robot's access rules), and a warning if the "
        "robot at --robot-endpoint lets in sessions without credentials",
    )
    parser.add_argument("--json", action="store_true", help="last stdout line: the merged summary as one JSON object")
    parser.add_argument(
        "--summary-dir",
        type=Path,
        metavar="DIR",
        help="write each service's JSON summary to DIR/<service>.json (default: a fresh directory "
        "under the system's temporary directory, named in the summary)",
    )
    parser.add_argument(
        "--record",
        type=Path,
        metavar="FILE.mcap",
        help="record every robot to an MCAP file (rosbag2 layout) with an srl record process (default: none)",
    )
    parser.add_argument(
        "--view",
        type=int,
        nargs="?",
        const=VIEW_PORT,
        metavar="PORT",
        help="serve the run live to Foxglove (srl view) on ws://127.0.0.1:PORT; PORT defaults to 8765 "
        "(default: no live view)",
    )
    add_fleet_arguments(parser)
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from tools.launch.supervisor import ServiceDiedError, Stopped, local_router_endpoint, tls_endpoint
    from tools.launch.up import UpOptions, actor_hosts, check_options, format_fleet_summary, run_up

    settings = settings_from_args(args, any_system=True)  # what serves the robot only: check_options
    run_name = time.strftime("up-%Y%m%d-%H%M%S", time.gmtime()) + f"-{os.getpid()}"
    summary_dir = args.summary_dir or default_runs_dir() / run_name
    robots, endpoints, bridge_args = fleet_of(args, settings)
    if robots is None:
        router = settings.transport.router
        if args.secure:  # the same address over mutual TLS (tools/launch/supervisor.py Logins)
            router = tls_endpoint(router) or router
        listens = f"srl up: the router listens on {router}"
    else:  # a fleet's router: a free port unless given (docs/fleets.md)
        router = local_router_endpoint(settings.transport.router, given=args.router is not None)
        default_router = Settings.load(args.config).transport.router  # where srl record and srl view look
        if args.view is not None:
            why = "" if args.router is not None else f": {default_router} is taken"
            again = "" if router == default_router else f" (with `--router {router}`{why})"
            raise UsageError(
                f"--view does not start with --robots yet: run the fleet without it{again} and, beside "
                f"it, {beside_commands(args, router, default_router)} (both carry every robot)"
            )
        listens = f"srl up: the fleet's router listens on {router}"
        if settings.system.wheeled:  # a recording and a live view carry the robot's pose
            listens += "; beside it: " + beside_commands(args, router, default_router)

    def show(line: str) -> None:
        print(f"srl up {line}", file=sys.stderr, flush=True)

    options = UpOptions(
        settings_argv(args),
        mode=args.mode,
        plant=args.plant,
        duration=settings.episode.duration,
        sync_critic=args.mode == "lockstep",
        bridge_args=bridge_args,
        secure=args.secure,
        on_status=show,
        summary_dir=summary_dir,
        record=args.record,
        view_port=args.view,
        robots=robots,
        layout=args.layout,
        circle=args.circle,
        actor_hosts=1 if robots is None else actor_hosts(str(args.actor_hosts), len(robots)),
        pooled=settings.critic.pooled if args.critic is None else args.critic == "pooled",
        robot_endpoints=endpoints,
        router=None if robots is None else router,
    )
    try:  # a run that cannot be is one line, before anything is said or started
        check_options(options, robots or [settings.transport.robot], settings)
    except ValueError as error:
        raise UsageError(str(error)) from error
    print(listens, file=sys.stderr, flush=True)
    try:
        summary = run_up(settings, options)
    except Stopped as stopped:  # SIGINT, SIGTERM, SIGHUP: everything was stopped, credentials removed
        print(f"srl up: stopped by {stopped}: every service stopped", file=sys.stderr)
        return stopped.exit_code
    except ServiceDiedError as error:
        return error.say("srl up")
    except (TimeoutError, ValueError) as error:
        raise UsageError(str(error)) from error
    summary.pop("trajectory", None)
    # one robot (the settings' or a fleet of one): its own summary; a fleet: a row per robot
    print(format_up_summary(summary) if len(summary["robots"]) == 1 else format_fleet_summary(summary))
    if args.json:
        print(json.dumps(summary))
    return 0


def fleet_of(args: argparse.Namespace, settings: Settings) -> tuple[list[str] | None, dict[str, str], list[str]]:
    """``--robots``' fleet (None: the robot of the settings), the real robots' endpoints and the
    bridges' flags; one line (UsageError) for fleet options without a fleet or a namespace with one."""
    if args.robots is None:
        if args.critic is not None:
            raise UsageError("--critic per-robot|pooled chooses a fleet's critic: give --robots K too")
        if getattr(args, "robot_endpoints", None):
            raise UsageError("--robot-endpoints is for a fleet: give --robots K too (one robot: --robot-endpoint)")
        return None, {}, bridge_argv(args)
    bridged = launch_plant(args.plant).behind_bridge  # the parser's choices are the rows
    robots = fleet_robots(args, ROS_FLEET_PREFIX if bridged else "robot")
    assert robots is not None
    if not bridged:
        if getattr(args, "robot_endpoints", None):
            raise UsageError("--robot-endpoints is for --plant robot")
        return robots, {}, bridge_argv(args)
    if settings.bridge.namespace:
        raise UsageError(
            f"bridge.namespace {settings.bridge.namespace!r} with --robots: each robot's namespace is its id"
        )
    endpoints = ros_fleet_endpoints(args, robots, settings.bridge.robot_endpoint)
    # each robot's namespace and endpoint are the fleet's own (tools/launch/bridged.py)
    flags = [a for a in bridge_argv(args) if a.split("=", 1)[0] not in ("--namespace", "--robot-endpoint")]
    return robots, endpoints, flags


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
        help=f"with --robots (host layout): split the robots over H actor hosts; {AUTO_HOSTS_HELP} (default: auto)",
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


def default_runs_dir() -> Path:
    """Where ``srl up`` writes its runs' JSON summaries: ``SRL_RUNS_DIR`` or ~/.local/state/srl/runs."""
    return Path(os.environ.get("SRL_RUNS_DIR") or Path.home() / ".local/state/srl/runs")


def format_up_summary(summary: dict[str, Any]) -> str:
    lines = [
        f"srl up: {summary['mode']} run, plant {summary['plant']}, agent {summary.get('agent')}, "
        f"N = {summary.get('horizon')}"
    ]
    lines.append("  services       " + ", ".join(f"{k} (pid {v})" for k, v in summary["services"].items()))
    if summary.get("secure"):
        lines.append(
            "  security       user/password login per role + access rules at the router (common/net/security.py)"
            + (", mutual TLS" if str(summary.get("router", "")).startswith("tls/") else "")
        )
        if summary.get("emulator"):  # srl up secures the emulated robot's own router (tools/launch/up.py)
            lines.append(
                "  robot router   the emulated robot's own: mutual TLS, the bridge's login and the "
                "robot's access rules (services/robot_bridge/robot_router.py)"
            )
    lines.append(f"  steps          {summary.get('steps')}   accumulated J {summary.get('accumulated_cost', 0):.4f}")
    system = system_row(summary.get("system", "unicycle"))
    if summary.get("start_state"):
        whose = "the robot's" if system.wheeled else "its"
        lines.append(f"  start          {fmt_state(summary['start_state'], system)} ({whose} first state)")
    if summary.get("final_state"):
        far = "" if system.wheeled else "   " + how_far(summary["final_distance"], system)
        lines.append(f"  final state    {fmt_state(summary['final_state'], system)}{far}")
    emulated = summary.get("emulator_truth")
    if emulated:  # the bridge carries only odometry; the emulator behind it knows the truth
        lines.append(
            f"  true final     {fmt_state(emulated['final_state'])}   distance to target "
            f"{emulated['final_distance']:.3f} m   (the emulator's, {emulated['model']} model; "
            f"commands beyond a wheel's limit {emulated['saturated_commands']})"
        )
    else:
        lines.extend(truth_lines(summary, system))
    # what the robot's pose is: odometry drifts with wheel slip (docs/turtlebot-localization.md)
    if summary.get("bridge"):
        lines.append(f"  localization   {summary['bridge'].get('localization', 'odometry only')}")
    critic = summary.get("critic") or {}
    lines.append(
        f"  critic         {critic.get('transitions_received')} transitions received, "
        f"actor used weights version {summary.get('weights_version')}"
    )
    if critic.get("checkpoint"):
        lines.append(
            f"  checkpoint     {critic['checkpoint']} "
            f"({'restored' if critic.get('restored') else 'fresh critic; --resume to restore'})"
        )
    if summary.get("summary_dir"):
        lines.append(f"  summaries      {summary['summary_dir']}/<service>.json")
    if summary.get("recording"):
        lines.append(f"  recording      {summary['recording']}")
    if "loop" in summary:
        period = summary["loop"]["period_ms"]
        lines.append(
            f"  loop [ms]      period median {period['median']:.3f} p99 {period['p99']:.3f} "
            f"max {period['max']:.3f}, missed deadlines {summary['loop']['missed_deadlines']}"
        )
    staleness = summary.get("staleness_steps")
    if staleness:
        lines.append(f"  staleness      median {staleness['median']} max {staleness['max']} steps")
    return "\n".join(lines)
