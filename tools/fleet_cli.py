"""``srl up --robots``'s options and command (issue 16), kept apart from tools/fleet.py so that
building the ``srl`` parser does not import Zenoh."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from common.runtime import UsageError, add_robots_argument, fleet_robots
from common.settings import Settings

LAYOUTS = ("host", "process")


def add_fleet_arguments(parser: argparse.ArgumentParser) -> None:
    """``srl up``'s fleet options (issue 16)."""
    add_robots_argument(parser, "a simulated fleet (real time): ")
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
        type=int,
        default=1,
        metavar="H",
        help="with --robots (host layout): split the robots over H actor hosts, e.g. one per core (default: 1)",
    )
    parser.add_argument(
        "--critic",
        choices=("per-robot", "pooled"),
        help="with --robots: a learner per robot, or one pooled learner trained on every robot's transitions "
        "(default: setting critic.pooled, false: per-robot)",
    )


def cmd_up_fleet(args: argparse.Namespace, settings: Settings, settings_args: list[str], summary_dir: Path) -> int:
    """``srl up --robots``: the fleet's run, a status line a second, the per-robot table, ``--json``."""
    robots = fleet_robots(args)
    assert robots is not None
    if args.plant != "sim" or args.secure:
        raise UsageError("--robots runs simulated robots without --secure (--plant sim) for now")
    if getattr(args, "record", None) is not None or getattr(args, "view", None) is not None:
        raise UsageError(
            "--record and --view do not start with --robots yet: run `srl record FILE.mcap` or `srl view` "
            "beside the fleet (both carry every robot)"
        )
    if not 1 <= args.actor_hosts <= len(robots):
        raise UsageError(f"--actor-hosts {args.actor_hosts}: 1 to one per robot ({len(robots)})")
    if not (math.isfinite(args.circle) and args.circle > 0):
        raise UsageError(f"--circle {args.circle}: the start circle's radius must be a positive number of metres")

    def show(line: str) -> None:
        print(f"srl up {line}", file=sys.stderr, flush=True)

    from tools.fleet import format_fleet_summary, run_fleet

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
        pooled=settings.critic.pooled if args.critic is None else args.critic == "pooled",
    )
    print(format_fleet_summary(summary))
    if args.json:
        print(json.dumps(summary))
    return 0
