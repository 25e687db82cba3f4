"""``srl actor`` / ``python -m services.actor``: the delta-periodic actor loop."""

from __future__ import annotations

import argparse

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
from common.math.fleet import AUTO_HOSTS_HELP, split_evenly
from common.process.runtime import fleet_hosts, serve
from services.actor.split import fork_shares

NAME = "actor"
HELP = "the delta-periodic actor loop"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, COMMAND_SETTINGS[NAME])
    add_mode_argument(parser)
    add_lifetime_arguments(
        parser, "stop after this long (default: until signalled; a lockstep actor stops after one episode)"
    )
    parser.add_argument(
        "--sync-critic", action="store_true", help="lockstep: wait for the weights trained on the previous step"
    )
    add_robots_argument(parser, "serve every robot of the list (real time): ")
    parser.add_argument(
        "--hosts",
        metavar="H|auto",
        default="1",
        help="with --robots: split the robots over H actor host processes started by this command, "
        f"{AUTO_HOSTS_HELP} (a host's solves use one core; default: 1)",
    )
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from services.actor.service import run

    robots = fleet_robots(args)
    if robots is not None:
        share, children = fork_shares(split_evenly(robots, fleet_hosts(args.hosts, len(robots), "--hosts")))
        # below here: one host per process, of its own share (a child returns from here too)
        from common.contracts.summaries import printed_summary
        from services.actor.host import run_host

        try:
            code = serve(
                settings_from_args(args, any_system=True),
                "actor",
                args.connect_timeout,
                lambda settings, bus, stop: printed_summary(
                    run_host(settings, bus, share, stop, args.run_seconds), True
                ),
                any_system=True,
            )
        finally:
            worst = children.stop() if children is not None else 0
        return code or worst
    if args.hosts != "1":
        raise UsageError("--hosts splits the robots of --robots over processes: give --robots too")
    return serve(  # any system's actor (settings.wire)
        settings_from_args(args, any_system=True),
        "actor",
        args.connect_timeout,
        lambda settings, bus, stop: run(settings, bus, args.mode, stop, args.run_seconds, args.sync_critic),
        any_system=True,
    )
