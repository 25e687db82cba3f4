"""``srl view``: serve a running system live to Foxglove (tools/recording/view.py, imported when
it runs: building the parser never imports foxglove)."""

from __future__ import annotations

import argparse

from common.config.arguments import (
    COMMAND_SETTINGS,
    add_connect_timeout_argument,
    add_seconds_argument,
    add_settings_arguments,
)

NAME = "view"
HELP = "serve a running system live to Foxglove (WebSocket) until Ctrl-C"
DESCRIPTION = (
    "Serve a running system live to Foxglove through the Foxglove WebSocket protocol: every\n"
    "robot's odometry, path, commands, costs, critic weights, solve time and tick jitter, as ROS 2\n"
    "messages (the topics of srl record). Loopback only by default; open docs/foxglove-layout.json."
)
VIEW_PORT = 8765


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, COMMAND_SETTINGS[NAME])
    parser.add_argument(
        "--port", type=int, default=VIEW_PORT, help=f"WebSocket port (0: any free one) (default: {VIEW_PORT})"
    )
    parser.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to bind; keep loopback and reach it from elsewhere by an SSH tunnel (docs/recordings.md) "
        "(default: 127.0.0.1)",
    )
    add_seconds_argument(parser)
    add_connect_timeout_argument(parser)
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from tools.recording.view import cmd_view

    return cmd_view(args)
