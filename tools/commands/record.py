"""``srl record``: join a running system over Zenoh and record every robot to an MCAP file
(tools/recording/record.py, imported when it runs: building the parser never imports the
recorder's libraries)."""

from __future__ import annotations

import argparse
from pathlib import Path

from common.config.arguments import (
    COMMAND_SETTINGS,
    add_connect_timeout_argument,
    add_seconds_argument,
    add_settings_arguments,
)

NAME = "record"
HELP = "join a running system over Zenoh and record every robot to an MCAP file until Ctrl-C"
DESCRIPTION = (
    "Join a running system (srl up, the containers) over Zenoh and record every robot to an MCAP\n"
    "file in the rosbag2 layout (ROS 2 messages: /<robot>/odom, cmd_vel, path, srl/*) until Ctrl-C\n"
    "or --seconds; SIGINT and SIGTERM close the file properly and print one summary line."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "file",
        type=Path,
        nargs="?",
        metavar="FILE.mcap",
        help="the recording to write, replaced if it exists, its parts too (default: srl-<UTC time>.mcap here)",
    )
    add_settings_arguments(parser, COMMAND_SETTINGS[NAME])
    parser.add_argument(
        "--clock",
        choices=["wall", "steps"],
        default="wall",
        help="wall: states stamped on arrival (a real-time system); steps: one state per step "
        "at origin + k delta (a lockstep system) (default: wall)",
    )
    parser.add_argument(
        "--split-minutes",
        type=float,
        default=60.0,
        metavar="M",
        help="a new file (FILE_1.mcap, FILE_2.mcap, ...) every M minutes of messages, each readable "
        "alone: a recorder's memory grows with its file's length; 0 = one file (default: 60)",
    )
    add_seconds_argument(parser)
    add_connect_timeout_argument(parser)
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from tools.recording.record import cmd_record

    return cmd_record(args)
