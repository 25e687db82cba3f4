"""``srl status``: the actor's live status line once a second, from a monitor session."""

from __future__ import annotations

import argparse
import time

from common.config.arguments import (
    COMMAND_SETTINGS,
    add_connect_timeout_argument,
    add_seconds_argument,
    add_settings_arguments,
    settings_from_args,
)
from common.contracts.summaries import format_status_line
from common.process.runtime import connect_with_retry, stop_on_signals

NAME = "status"
HELP = "the actor's live status line once a second (step, pose, J, weights, deadlines)"
DESCRIPTION = (
    "The actor's live status line once a second, read from srl/<robot>/status/actor by a "
    "monitor session\n(any running system: srl up, the containers); until Ctrl-C or --seconds."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, COMMAND_SETTINGS[NAME])
    add_seconds_argument(parser)
    add_connect_timeout_argument(parser)
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    """The actor's status line once a second, from a monitor session, until Ctrl-C or --seconds."""
    from tools.launch.measure import status_monitor

    settings = settings_from_args(args)
    with stop_on_signals() as stop:
        monitor = connect_with_retry(lambda: status_monitor(settings), settings, "status", args.connect_timeout, stop)
        try:
            started, shown, first_version = time.monotonic(), 0, []  # type: ignore[var-annotated]
            end = None if args.seconds is None else started + args.seconds
            while not stop.is_set() and (end is None or time.monotonic() < end):
                if monitor.seen > shown and monitor.latest is not None:
                    shown = monitor.seen
                    line = format_status_line(monitor.latest, time.monotonic() - started, first_version)
                    print(f"{settings.transport.robot} {line}", flush=True)
                stop.wait(0.05)
        finally:
            monitor.close()
    return 0
