"""``srl run``: one closed-loop episode of Algorithm 1 in this process (or through the services,
``--transport zenoh``), its summary, and optionally its figure and MCAP recording."""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from common.config.arguments import (
    COMMAND_SETTINGS,
    UsageError,
    add_settings_arguments,
    settings_argv,
    settings_from_args,
)
from common.math.systems import UNICYCLE, System, system_row
from common.process.runtime import SignalledError, stop_on_signals

NAME = "run"
HELP = "one closed-loop episode of Algorithm 1 (actor, plant, critic)"
DESCRIPTION = (
    "One closed-loop episode of Algorithm 1 (actor step, plant, critic update) and a summary.\n"
    "Ctrl-C: exit 130; SIGTERM: 143; a closed stdout pipe (srl run | head): 141."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, COMMAND_SETTINGS[NAME])
    parser.add_argument(
        "--transport",
        choices=["inproc", "zenoh"],
        default="inproc",
        help="inproc: one process; zenoh: router, plant_sim, critic, actor as processes (default: inproc)",
    )
    parser.add_argument("--verbose", action="store_true", help="with --transport zenoh: show the services' logs")
    parser.add_argument("--trajectory", action="store_true", help="include the state trajectory in the JSON")
    parser.add_argument("--json", action="store_true", help="last stdout line: one JSON object")
    parser.add_argument(
        "--plot",
        type=Path,
        metavar="PNG",
        help="write a figure: path, controls, costs and the critic's learning (weights, TD residuals) "
        "(default: no figure)",
    )
    parser.add_argument(
        "--record",
        type=Path,
        metavar="FILE.mcap",
        help="write the episode to an MCAP file (rosbag2 layout, ROS 2 messages; srl plot FILE, Foxglove) "
        "(default: no recording)",
    )
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from common.config.assembly import episode_summary, run_episode

    settings = settings_from_args(args, any_system=True)
    if args.record:  # --transport zenoh: the lockstep services, any system's
        try:
            settings.robot_only("srl run", ("--record", True))
        except ValueError as error:
            raise UsageError(str(error)) from error
    recorder = None
    if args.record is not None and args.transport == "inproc":  # opened now: a bad path fails before the run
        from tools.recording.record import RecordingError, episode_recorder

        try:
            recorder = episode_recorder(
                args.record,
                settings.plant.sampling_time,
                {"agent": settings.actor.agent, "horizon": settings.actor.horizon, "source": "srl run"},
            )
        except RecordingError as error:
            raise UsageError(str(error)) from None
    elif args.record is not None:
        from tools.recording.sinks import RecordingError, open_for_writing

        try:
            open_for_writing(args.record).close()
        except RecordingError as error:
            raise UsageError(str(error)) from None
    started = time.perf_counter()
    origin_ns = time.time_ns()
    if args.transport == "zenoh":
        # The same Algorithm 1 through the real services: lockstep, synchronous critic.
        from common.math.loop import Episode
        from tools.launch.supervisor import ServiceDiedError
        from tools.launch.up import UpOptions, run_up

        options = UpOptions(
            settings_argv(args),
            mode="lockstep",
            plant="sim",
            duration=settings.episode.duration,
            sync_critic=True,
            quiet=not args.verbose,
            record=args.record,
        )
        try:
            summary = run_up(settings, options)
        except (ServiceDiedError, TimeoutError) as error:
            raise UsageError(str(error)) from error
        episode = Episode(
            summary["agent"], summary["horizon"], states=[__import__("numpy").array(s) for s in summary["trajectory"]]
        )
    else:
        with stop_on_signals() as stop:
            try:
                episode = run_episode(settings, stop=stop)
            except BaseException:
                if recorder is not None:
                    recorder.close()  # a valid (empty) file, never a torn one
                raise
        if recorder is not None:  # after the loop, from its trajectory: the loop never waits on the disk
            from tools.recording.record import record_episode

            record_episode(recorder, episode, settings.transport.robot, origin_ns)
            recorder.close()
        if stop.signum is not None:
            raise SignalledError(stop.signum)
        summary = episode_summary(episode, settings)
    summary["wall_seconds"] = time.perf_counter() - started
    summary["transport"] = args.transport
    if args.plot:
        from tools.recording.plots import plot_episode

        plot_episode(episode, settings.plant.sampling_time, args.plot, settings.system)
        summary["plot"] = str(args.plot)
    if args.record is not None:
        summary["recording"] = str(args.record)
    if not args.trajectory:
        summary.pop("trajectory", None)
    elif "trajectory" not in summary:
        summary["trajectory"] = [[float(c) for c in s] for s in episode.states]
    print(format_run_summary(summary))
    if args.json:
        print(json.dumps(summary))
    return 0


def format_run_summary(summary: dict[str, Any]) -> str:
    s = summary["settings"]
    solve = summary["solve_ms"]
    system = system_row(s["plant"]["system"])
    title = "" if system.wheeled else f", system {s['plant']['system']}"
    far = how_far(summary["final_distance"], system)
    lines = [
        f"srl run: agent {summary['agent']}, N = {summary['horizon']}, transport {summary['transport']}{title}",
        f"  start          {fmt_state(summary['start_state'], system)}",
        f"  final state    {fmt_state(summary['final_state'], system)}   {far}",
        *(truth_lines(summary) if system.wheeled else []),
        f"  steps          {summary['steps']} x delta = {s['plant']['sampling_time']} s "
        f"({summary['episode_seconds']:.1f} s episode)",
        f"  accumulated J  {summary['accumulated_cost']:.4f}",
        f"  solve [ms]     median {solve['median']:.3f}  p99 {solve['p99']:.3f}  max {solve['max']:.3f}"
        f"   failures {summary['solver_failures']}",
        f"  wall time      {summary['wall_seconds']:.2f} s",
        f"  settings       R = diag{tuple(s['cost']['r_diag'])}, gamma = {s['critic']['discount_rate']} "
        f"(beta = {s['derived']['discount_beta']:.4f}), M = {s['critic']['replay_size']}, "
        f"lambda = {s['critic']['ridge']}, bounds = {s['critic']['weight_bounds'] or 'none'}, "
        f"solver {s['actor']['solver']}, predictor {s['actor']['predictor']}",
    ]
    if "plot" in summary:
        lines.append(f"  plot           {summary['plot']}")
    if summary.get("recording"):
        lines.append(f"  recording      {summary['recording']} (MCAP, rosbag2 layout: srl plot FILE, Foxglove)")
    return "\n".join(lines)


def truth_lines(summary: dict[str, Any], system: System = UNICYCLE) -> list[str]:
    """The true view beside the robot's own (start, final state, J are what it reported)."""
    if "truth" not in summary:
        return []
    truth = summary["truth"]
    saturated = summary.get("saturated_commands")
    wheels = "" if saturated is None or not system.wheeled else f"   commands beyond a wheel's limit {saturated}"
    if truth is None:
        return ["  truth          unknown: a real robot, only its odometry is known (the states above)" + wheels]
    return [
        f"  true final     {fmt_state(truth['final_state'], system)}   {how_far(truth['final_distance'], system)}"
        f"   (plant {summary.get('plant_model', 'sim')}: the states above are what the robot reported)",
        f"  true J         {truth['accumulated_cost']:.4f} (on the true states; "
        f"the accumulated J is on the reported ones){wheels}",
    ]


def how_far(distance: float, system: System) -> str:
    """The final distance in the system's terms: the robot's to its target in metres, another's
    to its goal, and whether that is stabilized."""
    if system.wheeled:
        return f"distance to target {distance:.3f} m"
    held = "stabilized (<" if distance < system.stabilized else "not stabilized (>="
    return f"distance to the goal {distance:.4f}: {held} {system.stabilized:g})"


def fmt_state(state: Sequence[float], system: System = UNICYCLE) -> str:
    """``x = +1.000 m, ...``: each entry by its name and unit in the system's row."""
    if system.wheeled:
        return f"x = {state[0]:+.3f} m, y = {state[1]:+.3f} m, alpha = {state[2]:+.3f} rad"
    return ", ".join(
        f"{label} = {value:+.3f}" + (f" {unit}" if unit else "")
        for (label, unit), value in zip(system.state_labels(), state, strict=True)
    )
