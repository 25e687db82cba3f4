"""``srl up``: the router and every service as separate processes, one run (tools/launch/up.py),
or a fleet with ``--robots`` (tools/launch/fleet_cli.py); a live status line and the merged summary."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

from common.config.arguments import (
    COMMAND_SETTINGS,
    UsageError,
    add_bridge_arguments,
    add_mode_argument,
    add_settings_arguments,
    bridge_argv,
    settings_argv,
    settings_from_args,
)
from common.contracts.summaries import format_status_line
from tools.commands.run import fmt_state, truth_lines
from tools.commands.view import VIEW_PORT
from tools.launch.plants import LAUNCH_PLANTS, launch_plant_help

NAME = "up"
HELP = "router + every service as separate processes, one run"
DESCRIPTION = (
    "The router and every service as separate processes, one run, a live status line once a second.\n"
    "Each service's JSON summary is written to a file (--summary-dir); --json prints the merged one."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from tools.launch.fleet_cli import add_fleet_arguments

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
    from tools.launch.supervisor import ServiceDiedError, Stopped, tls_endpoint
    from tools.launch.up import UpOptions, run_up

    settings = settings_from_args(args)
    run_name = time.strftime("up-%Y%m%d-%H%M%S", time.gmtime()) + f"-{os.getpid()}"
    summary_dir = args.summary_dir or default_runs_dir() / run_name
    if args.robots is None and args.critic is not None:
        raise UsageError("--critic per-robot|pooled chooses a fleet's critic: give --robots K too")
    if args.robots is not None:  # a fleet: tools/launch/fleet.py (docs/fleets.md)
        from tools.launch.fleet_cli import cmd_up_fleet

        return cmd_up_fleet(args, settings, settings_argv(args), summary_dir)
    router = settings.transport.router
    if args.secure:  # the same address over mutual TLS (tools/launch/supervisor.py Logins)
        router = tls_endpoint(router) or router
    print(f"srl up: the router listens on {router}", file=sys.stderr, flush=True)
    started = time.monotonic()

    first_version: list[float] = []

    def show_status(counters: dict[str, float]) -> None:
        line = format_status_line(counters, time.monotonic() - started, first_version)
        print(f"srl up {line}", file=sys.stderr, flush=True)

    options = UpOptions(
        settings_argv(args),
        mode=args.mode,
        plant=args.plant,
        duration=settings.episode.duration,
        sync_critic=args.mode == "lockstep",
        bridge_args=bridge_argv(args),
        secure=args.secure,
        on_status=show_status,
        summary_dir=summary_dir,
        record=args.record,
        view_port=args.view,
    )
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
    print(format_up_summary(summary))
    if args.json:
        print(json.dumps(summary))
    return 0


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
    if summary.get("start_state"):
        lines.append(f"  start          {fmt_state(summary['start_state'])} (the robot's first state)")
    if summary.get("final_state"):
        lines.append(f"  final state    {fmt_state(summary['final_state'])}")
    emulated = summary.get("emulator_truth")
    if emulated:  # the bridge carries only odometry; the emulator behind it knows the truth
        lines.append(
            f"  true final     {fmt_state(emulated['final_state'])}   distance to target "
            f"{emulated['final_distance']:.3f} m   (the emulator's, {emulated['model']} model; "
            f"commands beyond a wheel's limit {emulated['saturated_commands']})"
        )
    else:
        lines.extend(truth_lines(summary))
    # what the robot's pose is: odometry drifts with wheel slip (docs/turtlebot-localization.md)
    if summary.get("bridge"):
        lines.append(f"  localization   {summary['bridge'].get('localization', 'odometry only')}")
    lines.append(
        f"  critic         {summary.get('transitions_received')} transitions received, "
        f"actor used weights version {summary.get('weights_version')}"
    )
    if summary.get("critic_checkpoint"):
        lines.append(
            f"  checkpoint     {summary['critic_checkpoint']} "
            f"({'restored' if summary.get('critic_restored') else 'fresh critic; --resume to restore'})"
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
