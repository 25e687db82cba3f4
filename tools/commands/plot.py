"""``srl plot FILE.mcap``: the figures of ``srl run --plot``, from a recording (one PNG per robot)."""

from __future__ import annotations

import argparse
from pathlib import Path

from common.config.arguments import UsageError

NAME = "plot"
HELP = "draw the figures of --plot from a recording (one PNG per robot)"
DESCRIPTION = (
    "Draw the figures of srl run --plot (path, controls, costs, critic weights, TD residuals)\n"
    "from an MCAP recording of srl run, srl up, srl record or the experiment: one PNG per robot."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", type=Path, metavar="FILE.mcap", help="a recording")
    parser.add_argument(
        "--out",
        type=Path,
        metavar="PNG",
        help="the figure (one robot) or the stem of one figure per robot, <stem>-<robot>.png (default: FILE with .png)",
    )
    parser.add_argument("--robot", metavar="ID", help="only this robot (default: every robot in the file)")
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    """``srl plot FILE.mcap``: the figures of ``--plot``, from a recording."""
    from tools.recording.plots import plot_episode
    from tools.recording.record import RecordingError, read_episodes

    try:
        episodes, sampling_time = read_episodes(args.file)
    except RecordingError as error:
        raise UsageError(str(error)) from None
    if args.robot is not None:
        if args.robot not in episodes:
            raise UsageError(f"{args.file}: no robot {args.robot!r} (robots: {', '.join(sorted(episodes)) or 'none'})")
        episodes = {args.robot: episodes[args.robot]}
    if not episodes:
        raise UsageError(f"{args.file}: no robot's steps in this recording (no /<robot>/srl/transition messages)")
    out = args.out or Path(args.file).with_suffix(".png")
    for robot, episode in sorted(episodes.items()):
        path = out if len(episodes) == 1 else out.with_name(f"{out.stem}-{robot}{out.suffix or '.png'}")
        plot_episode(episode, sampling_time, path)
        print(f"srl plot: {robot}: {episode.steps} steps, J = {episode.accumulated_cost:.4f} -> {path}", flush=True)
    return 0
