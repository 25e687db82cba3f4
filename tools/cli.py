"""The ``srl`` command: one subcommand per service or tool.

``python -m tools.cli ...`` runs the same code. Logging is configured here, once.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from common.config.arguments import (
    COMMAND_SETTINGS,
    Parser,
    UsageError,
    add_bridge_arguments,
    add_log_level,
    add_mode_argument,
    add_settings_arguments,
    bridge_argv,
    settings_argv,
    settings_from_args,
)
from common.config.settings import METHODS
from common.contracts.summaries import RouterSummary, format_status_line
from common.math.agents import AGENTS
from common.process.runtime import (
    SignalledError,
    connect_with_retry,
    own_resources,
    service_stop,
    stop_on_signals,
    zenoh_reason,
)
from common.process.runtime import entry as runtime_entry
from common.process.runtime import main as runtime_main

log = logging.getLogger(__name__)


def cmd_run(args: argparse.Namespace) -> int:
    from common.config.assembly import episode_summary, run_episode

    settings = settings_from_args(args)
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
        from tools.recording.record import RecordingError, open_for_writing

        try:
            open_for_writing(args.record).close()
        except RecordingError as error:
            raise UsageError(str(error)) from None
    started = time.perf_counter()
    origin_ns = time.time_ns()
    if args.transport == "zenoh":
        # The same Algorithm 1 through the real services: lockstep, synchronous critic.
        from common.math.loop import Episode
        from tools.launch.up import ServiceDiedError, run_up

        try:
            summary = run_up(
                settings,
                settings_argv(args),
                mode="lockstep",
                plant="sim",
                sync_critic=True,
                duration=settings.episode.duration,
                quiet=not args.verbose,
                record=args.record,
            )
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

        plot_episode(episode, settings.plant.sampling_time, args.plot)
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
    lines = [
        f"srl run: agent {summary['agent']}, N = {summary['horizon']}, transport {summary['transport']}",
        f"  start          {_fmt_state(summary['start_state'])}",
        f"  final state    {_fmt_state(summary['final_state'])}   distance to target {summary['final_distance']:.3f} m",
        *_truth_lines(summary),
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


def _truth_lines(summary: dict[str, Any]) -> list[str]:
    """The true view beside the robot's own (start, final state, J are what it reported)."""
    if "truth" not in summary:
        return []
    truth = summary["truth"]
    saturated = summary.get("saturated_commands")
    wheels = "" if saturated is None else f"   commands beyond a wheel's limit {saturated}"
    if truth is None:
        return ["  truth          unknown: a real robot, only its odometry is known (the states above)" + wheels]
    return [
        f"  true final     {_fmt_state(truth['final_state'])}   distance to target {truth['final_distance']:.3f} m"
        f"   (plant {summary.get('plant_model', 'sim')}: the states above are what the robot reported)",
        f"  true J         {truth['accumulated_cost']:.4f} (on the true states; "
        f"the accumulated J is on the reported ones){wheels}",
    ]


def _fmt_state(state: Sequence[float]) -> str:
    return f"x = {state[0]:+.3f} m, y = {state[1]:+.3f} m, alpha = {state[2]:+.3f} rad"


# -- services -------------------------------------------------------------------------
ROUTER_CLOSE_SECONDS = 3.0


def cmd_router(args: argparse.Namespace) -> int:

    import zenoh

    from common.net.transport import zenoh_config

    settings = settings_from_args(args)
    stop = service_stop()  # signals (bounded) and srl up's death
    try:
        session = zenoh.open(zenoh_config(settings.transport, router=True))
    except zenoh.ZError as error:
        raise UsageError(
            f"router: cannot listen on {settings.transport.router}: {zenoh_reason(error)} "
            "(another router on that port? choose one with --router)"
        ) from error
    # its one line of normal output, on stdout (not a warning): what it serves and how
    transport = settings.transport
    robots = transport.rule_robots
    whose = f"robot {robots[0]}" if len(robots) == 1 else f"{len(robots)} robots ({robots[0]}..{robots[-1]})"
    rules = f"; users and access rules of {whose} enforced" if transport.secure else ""
    # Zenoh keeps trying an unreachable router (a router's connect never gives up): it links when that one comes up
    links = f"; connecting to {', '.join(transport.connect)}" if transport.connect else ""
    print(
        f"srl router: router listening on {settings.transport.router} (multicast scouting "
        f"{'on' if settings.transport.multicast_scouting else 'off'}{rules}{links})",
        flush=True,
    )
    stop.wait()
    # A router holds no state, so its close is bounded: a close still waiting on its links after
    # ROUTER_CLOSE_SECONDS ends the process anyway (the summary says so), never a hang.
    closer = threading.Thread(target=session.close, name="router-close", daemon=True)
    closer.start()
    closer.join(ROUTER_CLOSE_SECONDS)
    summary = RouterSummary(
        endpoint=settings.transport.router, resources=own_resources(), close_timed_out=closer.is_alive()
    ).to_json_dict()
    if summary["close_timed_out"]:
        print(json.dumps(summary), flush=True)
        sys.stderr.flush()
        os._exit(0)  # the interpreter's exit would wait on the session's runtime
    print(json.dumps(summary), flush=True)
    return 0


def cmd_certs(args: argparse.Namespace) -> int:
    """``srl certs --out DIR``: TLS material (common/net/certs.py) and, with --passwords, credentials."""
    from common.net.certs import write_tls_material
    from common.net.security import ROLES, write_credentials

    out = Path(args.out).expanduser()
    if (out / "ca.pem").exists():
        if args.if_missing:
            print(f"srl certs: {out} already holds a CA: kept", flush=True)
            return 0
        raise UsageError(f"{out} already holds a CA (ca.pem): choose a new directory (or --if-missing)")
    files = write_tls_material(out, ROLES, args.hosts)
    if args.passwords:
        write_credentials(out)
    print(
        f"srl certs: CA, router ({', '.join(['localhost', '127.0.0.1', '::1', *args.hosts])}) and "
        f"{', '.join(ROLES)} certificates{' and passwords' if args.passwords else ''} in {files.directory} "
        "(0700, files 0600)",
        flush=True,
    )
    return 0


def cmd_up(args: argparse.Namespace) -> int:
    from tools.launch.up import ServiceDiedError, Stopped, run_up

    settings = settings_from_args(args)
    run_name = time.strftime("up-%Y%m%d-%H%M%S", time.gmtime()) + f"-{os.getpid()}"
    summary_dir = args.summary_dir or default_runs_dir() / run_name
    if args.robots is None and args.critic is not None:
        raise UsageError("--critic per-robot|pooled chooses a fleet's critic: give --robots K too")
    if args.robots is not None:  # a fleet (issue 16): tools/launch/fleet.py
        from tools.launch.fleet_cli import cmd_up_fleet

        return cmd_up_fleet(args, settings, settings_argv(args), summary_dir)
    started = time.monotonic()

    first_version: list[float] = []

    def show_status(counters: dict[str, float]) -> None:
        line = format_status_line(counters, time.monotonic() - started, first_version)
        print(f"srl up {line}", file=sys.stderr, flush=True)

    try:
        summary = run_up(
            settings,
            settings_argv(args),
            mode=args.mode,
            plant=args.plant,
            sync_critic=args.mode == "lockstep",
            duration=settings.episode.duration,
            bridge_args=bridge_argv(args),
            secure=args.secure,
            on_status=show_status,
            summary_dir=summary_dir,
            record=args.record,
            view_port=args.view,
        )
    except Stopped as stopped:  # SIGINT, SIGTERM, SIGHUP: everything was stopped, credentials removed
        print(f"srl up: stopped by {stopped}: every service stopped", file=sys.stderr)
        return stopped.exit_code
    except ServiceDiedError as error:
        print(f"srl up: error: {error}", file=sys.stderr)
        for line in error.tail:
            print(f"  [{error.name}] {line}", file=sys.stderr)
        return 1
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


def cmd_status(args: argparse.Namespace) -> int:
    """The actor's status line once a second, from a monitor session, until Ctrl-C or --seconds."""
    from tools.launch.up import StatusMonitor

    settings = settings_from_args(args)
    with stop_on_signals() as stop:
        monitor = connect_with_retry(lambda: StatusMonitor(settings), settings, "status", args.connect_timeout, stop)
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
    lines.append(f"  steps          {summary.get('steps')}   accumulated J {summary.get('accumulated_cost', 0):.4f}")
    if summary.get("start_state"):
        lines.append(f"  start          {_fmt_state(summary['start_state'])} (the robot's first state)")
    if summary.get("final_state"):
        lines.append(f"  final state    {_fmt_state(summary['final_state'])}")
    emulated = summary.get("emulator_truth")
    if emulated:  # the bridge carries only odometry; the emulator behind it knows the truth
        lines.append(
            f"  true final     {_fmt_state(emulated['final_state'])}   distance to target "
            f"{emulated['final_distance']:.3f} m   (the emulator's, {emulated['model']} model; "
            f"commands beyond a wheel's limit {emulated['saturated_commands']})"
        )
    else:
        lines.extend(_truth_lines(summary))
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


def cmd_plot(args: argparse.Namespace) -> int:
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


# -- recordings and the live view (tools/recording/record.py, tools/recording/view.py: imported when they run) ----
VIEW_PORT = 8765


def add_record_arguments(parser: argparse.ArgumentParser) -> None:
    """``srl record``'s options (here: building the parser never imports the recorder's libraries)."""
    parser.add_argument(
        "file",
        type=Path,
        nargs="?",
        metavar="FILE.mcap",
        help="the recording to write, replaced if it exists (default: srl-<UTC time>.mcap here)",
    )
    add_settings_arguments(parser, COMMAND_SETTINGS["record"])
    parser.add_argument(
        "--clock",
        choices=["wall", "steps"],
        default="wall",
        help="wall: states stamped on arrival (a real-time system); steps: one state per step "
        "at origin + k delta (a lockstep system) (default: wall)",
    )
    parser.add_argument("--seconds", type=float, help="stop after this long (default: until Ctrl-C)")
    parser.add_argument(
        "--connect-timeout", type=float, default=30.0, help="[s] wait this long for the router (default: 30)"
    )


def add_view_arguments(parser: argparse.ArgumentParser) -> None:
    """``srl view``'s options (here: building the parser never imports foxglove)."""
    add_settings_arguments(parser, COMMAND_SETTINGS["view"])
    parser.add_argument(
        "--port", type=int, default=VIEW_PORT, help=f"WebSocket port (0: any free one) (default: {VIEW_PORT})"
    )
    parser.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to bind; keep loopback and reach it from elsewhere by an SSH tunnel (README) "
        "(default: 127.0.0.1)",
    )
    parser.add_argument("--seconds", type=float, help="stop after this long (default: until Ctrl-C)")
    parser.add_argument(
        "--connect-timeout", type=float, default=30.0, help="[s] wait this long for the router (default: 30)"
    )


def cmd_record(args: argparse.Namespace) -> int:
    from tools.recording.record import cmd_record as record

    return record(args)


def cmd_view(args: argparse.Namespace) -> int:
    from tools.recording.view import cmd_view as view

    return view(args)


# -- srl bench -------------------------------------------------------------------------
def cmd_bench(args: argparse.Namespace) -> int:
    if args.what == "loop":
        from tools.bench.loop import run_loop_benchmark

        return run_loop_benchmark(args, settings_from_args(args), settings_argv(args))
    if args.what == "bridge":
        from tools.bench.bridge import run_bridge_benchmark

        return run_bridge_benchmark(args, settings_from_args(args), settings_argv(args), bridge_argv(args))
    if args.what == "actor":
        from tools.bench.actor import run_actor_benchmark

        return run_actor_benchmark(args, settings_from_args(args))
    if args.what == "parking":
        from tools.bench.parking import run_parking_benchmark

        return run_parking_benchmark(args, settings_from_args(args))
    if args.what == "fleet":
        from tools.bench.fleet import run_fleet_benchmark

        return run_fleet_benchmark(args, settings_from_args(args), settings_argv(args))
    if args.what == "capacity":
        from tools.bench.capacity import run_capacity_benchmark

        return run_capacity_benchmark(args, settings_from_args(args), settings_argv(args))
    raise UsageError(f"unknown benchmark {args.what!r}")


# A value that is a number or a comma-separated list of numbers, negative first: "-1.2,0.7", "-1e9,0".
DESCRIPTION = """srl: stacked RL-QV (actor, critic, plant) as Zenoh services, and the tools around them.

Settings come from common/config/srl.toml, overridden by --config FILE (or SRL_CONFIG), by
SRL_<SECTION>__<NAME> environment variables and by the flags of each subcommand.
Start with:  srl run            (one episode in this process)
             srl up             (router + every service as processes, a live status line)
"""


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="srl", description=DESCRIPTION)
    add_log_level(parser)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def command(name: str, helptext: str, description: str | None = None) -> argparse.ArgumentParser:
        return sub.add_parser(name, help=helptext, description=description or helptext[0].upper() + helptext[1:] + ".")

    run = command(
        "run",
        "one closed-loop episode of Algorithm 1 (actor, plant, critic)",
        "One closed-loop episode of Algorithm 1 (actor step, plant, critic update) and a summary.\n"
        "Ctrl-C: exit 130; SIGTERM: 143; a closed stdout pipe (srl run | head): 141.",
    )
    add_settings_arguments(run, COMMAND_SETTINGS["run"])
    run.add_argument(
        "--transport",
        choices=["inproc", "zenoh"],
        default="inproc",
        help="inproc: one process; zenoh: router, plant_sim, critic, actor as processes (default: inproc)",
    )
    run.add_argument("--verbose", action="store_true", help="with --transport zenoh: show the services' logs")
    run.add_argument("--trajectory", action="store_true", help="include the state trajectory in the JSON")
    run.add_argument("--json", action="store_true", help="last stdout line: one JSON object")
    run.add_argument(
        "--plot",
        type=Path,
        metavar="PNG",
        help="write a figure: path, controls, costs and the critic's learning (weights, TD residuals) "
        "(default: no figure)",
    )
    run.add_argument(
        "--record",
        type=Path,
        metavar="FILE.mcap",
        help="write the episode to an MCAP file (rosbag2 layout, ROS 2 messages; srl plot FILE, Foxglove) "
        "(default: no recording)",
    )
    run.set_defaults(func=cmd_run)

    certs = command("certs", "a private CA, the router's and each role's TLS certificate (mTLS)")
    certs.add_argument(
        "--out",
        required=True,
        help="directory to create (0700; files 0600); never in the repository (default: none, required)",
    )
    certs.add_argument(
        "--hosts",
        nargs="*",
        default=[],
        metavar="HOST",
        help="names/addresses clients use to reach the router, besides localhost, 127.0.0.1, ::1 (default: none)",
    )
    certs.add_argument(
        "--passwords",
        action="store_true",
        help="also a random password per role: users.txt (router) and <role>.password",
    )
    certs.add_argument(
        "--if-missing",
        action="store_true",
        help="exit 0 without writing if DIR already has a CA (default: write, and fail if it has one)",
    )
    certs.set_defaults(func=cmd_certs)

    router = command("router", "a Zenoh router (Python, mode router)")
    add_settings_arguments(router, COMMAND_SETTINGS["router"])
    router.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help="also connect to this endpoint, e.g. another host's router tcp/192.168.1.20:7447; repeat for "
        "several (one router per host) (default: transport.connect, none in common/config/srl.toml)",
    )
    router.set_defaults(func=cmd_router)

    from services.actor import command as actor_command
    from services.critic import command as critic_command
    from services.plant_sim import command as plant_sim_command
    from services.robot_bridge import command as robot_bridge_command
    from services.tb3_emulator import command as tb3_emulator_command

    # the services: each one's own options and main (services/<name>/command.py)
    for service in (plant_sim_command, critic_command, actor_command, robot_bridge_command, tb3_emulator_command):
        service.add_arguments(command(service.NAME, service.HELP))

    up = command(
        "up",
        "router + every service as separate processes, one run",
        "The router and every service as separate processes, one run, a live status line once a second.\n"
        "Each service's JSON summary is written to a file (--summary-dir); --json prints the merged one.",
    )
    add_settings_arguments(up, COMMAND_SETTINGS["up"])
    add_bridge_arguments(up)
    up.add_argument(
        "--plant",
        choices=["sim", "robot", "physics"],
        default="sim",
        help="sim: plant_sim (plant.model); physics: plant_sim with the MuJoCo TurtleBot3 (plant.model = physics); "
        "robot: robot_bridge + tb3-emulator of plant.model (or the robot at --robot-endpoint) (default: sim)",
    )
    add_mode_argument(up)
    up.add_argument(
        "--secure",
        action="store_true",
        help="Zenoh user/password login with fresh random credentials per role, and access rules "
        "at the router: only the actor publishes actions, the critic weights, the plant state; "
        "a tcp/ router endpoint becomes tls/ with mutual TLS (fresh private CA)",
    )
    up.add_argument("--json", action="store_true", help="last stdout line: the merged summary as one JSON object")
    up.add_argument(
        "--summary-dir",
        type=Path,
        metavar="DIR",
        help="write each service's JSON summary to DIR/<service>.json (default: a fresh directory "
        "under the system's temporary directory, named in the summary)",
    )
    up.add_argument(
        "--record",
        type=Path,
        metavar="FILE.mcap",
        help="record every robot to an MCAP file (rosbag2 layout) with an srl record process (default: none)",
    )
    up.add_argument(
        "--view",
        type=int,
        nargs="?",
        const=VIEW_PORT,
        metavar="PORT",
        help="serve the run live to Foxglove (srl view) on ws://127.0.0.1:PORT; PORT defaults to 8765 "
        "(default: no live view)",
    )
    from tools.launch.fleet_cli import add_fleet_arguments

    add_fleet_arguments(up)
    up.set_defaults(func=cmd_up)

    # srl bench KIND: each benchmark takes only its own options (an option it would ignore is refused)
    bench = command(
        "bench",
        "benchmarks that print a table (and JSON)",
        "Benchmarks that print a table with the targets as PASS/FAIL (and, with --json, one JSON object\n"
        "as the last stdout line): srl bench actor | loop | bridge | parking | fleet | capacity --help for each "
        "one's options.",
    )
    kinds = bench.add_subparsers(dest="what", required=True, metavar="KIND")

    def kind(name: str, helptext: str) -> argparse.ArgumentParser:
        parser = kinds.add_parser(name, help=helptext, description=helptext[0].upper() + helptext[1:] + ".")
        add_settings_arguments(parser, COMMAND_SETTINGS[f"bench {name}"])
        parser.add_argument("--json", action="store_true", help="last stdout line: one JSON object")
        parser.set_defaults(func=cmd_bench)
        return parser

    actor_bench = kind("actor", "the actor's solve time and argmin against the slow SLSQP baseline, per agent and N")
    actor_bench.add_argument(
        "--agents", default=",".join(AGENTS), help=f"comma-separated agents (default: {','.join(AGENTS)})"
    )
    actor_bench.add_argument("--horizons", default="6,12,30", help="comma-separated N values (default: 6,12,30)")
    actor_bench.add_argument(
        "--steps", type=int, default=300, help="closed-loop steps per row (>= 300 for p99) (default: 300)"
    )
    actor_bench.add_argument(
        "--baseline-steps", type=int, default=30, help="steps of the slow SLSQP baseline per row (default: 30)"
    )
    actor_bench.add_argument(
        "--method",
        choices=METHODS,
        default="paper",
        help="paper = the paper's problem; robot = with the wheel box and convex critics as configured "
        "(the arrival rule is off in both: it skips solves) (default: paper)",
    )
    actor_bench.add_argument(
        "--reference-horizons",
        default="12",
        help="N values for the IPOPT reference rows ('' = none) (default: 12)",
    )

    loop_bench = kind("loop", "the real-time loop through the services: tick jitter, latency, staleness")
    loop_bench.add_argument("--seconds", type=float, default=60.0, help="real-time run length [s] (default: 60)")
    loop_bench.add_argument(
        "--critic-load", action="store_true", help="the critic fits a replay of M = 1000 every step"
    )
    loop_bench.add_argument(
        "--record",
        action="store_true",
        help="compare: runs without and with a recorder (srl record), interleaved, --rounds pairs of "
        "--seconds each; PASS if the jitter p99 with it is within 0.5 ms of without (default: no recorder)",
    )
    loop_bench.add_argument("--rounds", type=int, help="with --record: pairs of runs (without, with) (default: 2)")

    fleet_bench = kind("fleet", "a fleet on one machine: host layout vs one process per robot, per fleet size")
    fleet_bench.add_argument(
        "--robots", default="1,8,16,32,50,100", help="fleet sizes of the host layout (default: 1,8,16,32,50,100)"
    )
    fleet_bench.add_argument(
        "--baseline", default="8,16", help="fleet sizes of one process per robot, '' for none (default: 8,16)"
    )
    fleet_bench.add_argument(
        "--actor-hosts",
        default="auto",
        metavar="H|auto",
        help="actor processes of the host layout: a number, or auto = 1 below 50 robots, else one per core "
        "(default: auto)",
    )
    fleet_bench.add_argument("--seconds", type=float, default=30.0, help="real-time run per row [s] (default: 30)")
    capacity = kind(
        "capacity", "a fleet's cost per robot and component (CPU, messages), and what 1,000 and 10,000 need"
    )
    capacity.add_argument("--robots", default="10,25,50", help="fleet sizes to fit the costs on (default: 10,25,50)")
    capacity.add_argument("--seconds", type=float, default=30.0, help="real-time run per size [s] (default: 30)")
    capacity.add_argument(
        "--utilisation", type=float, default=0.5, help="the share of each core the model plans to use (default: 0.5)"
    )
    capacity.add_argument("--host-cores", type=int, default=8, help="cores of each host in the model (default: 8)")
    bridge_bench = kind("bridge", "the robot bridge's latencies against an echo robot (ROS 2 over Zenoh)")
    add_bridge_arguments(bridge_bench)
    bridge_bench.add_argument("--seconds", type=float, default=60.0, help="both phases together [s] (default: 60)")

    parking = kind("parking", "parking on the ideal and the TurtleBot3 plants: truth vs odometry, chatter")
    parking.add_argument("--agents", default="mpc,rlq,rlqv", help="comma-separated agents (default: mpc,rlq,rlqv)")
    parking.add_argument("--horizons", default="12", help="N of every run, one value (default: 12)")
    parking.add_argument(
        "--plants", help="comma-separated plant models: ideal, actuator, physics (default: ideal,actuator,physics)"
    )
    parking.add_argument(
        "--methods",
        help="paper (the paper's actor) and/or robot (with srl.toml's arrival rule, wheel box and convex "
        f"critics), side by side (default: {','.join(METHODS)})",
    )
    parking.add_argument(
        "--starts",
        help="X,Y starts separated by ';', e.g. --starts='-1,2;2,0' (default: "
        "2,2;-2,2;-1,-2;2,-1;-2,0, five nodes of the paper's grid)",
    )
    parking.add_argument("--parking-seconds", type=float, default=35.0, help="episode length per run [s] (default: 35)")

    status = command(
        "status",
        "the actor's live status line once a second (step, pose, J, weights, deadlines)",
        "The actor's live status line once a second, read from srl/<robot>/status/actor by a "
        "monitor session\n(any running system: srl up, the containers); until Ctrl-C or --seconds.",
    )
    add_settings_arguments(status, COMMAND_SETTINGS["status"])
    status.add_argument("--seconds", type=float, help="stop after this long (default: until Ctrl-C)")
    status.add_argument(
        "--connect-timeout", type=float, default=30.0, help="[s] wait this long for the router (default: 30)"
    )
    status.set_defaults(func=cmd_status)

    # recordings and the live view (tools/recording/record.py, tools/recording/view.py)
    record = command(
        "record",
        "join a running system over Zenoh and record every robot to an MCAP file until Ctrl-C",
        "Join a running system (srl up, the containers) over Zenoh and record every robot to an MCAP\n"
        "file in the rosbag2 layout (ROS 2 messages: /<robot>/odom, cmd_vel, path, srl/*) until Ctrl-C\n"
        "or --seconds; SIGINT and SIGTERM close the file properly and print one summary line.",
    )
    add_record_arguments(record)
    record.set_defaults(func=cmd_record)

    plot = command(
        "plot",
        "draw the figures of --plot from a recording (one PNG per robot)",
        "Draw the figures of srl run --plot (path, controls, costs, critic weights, TD residuals)\n"
        "from an MCAP recording of srl run, srl up, srl record or the experiment: one PNG per robot.",
    )
    plot.add_argument("file", type=Path, metavar="FILE.mcap", help="a recording")
    plot.add_argument(
        "--out",
        type=Path,
        metavar="PNG",
        help="the figure (one robot) or the stem of one figure per robot, <stem>-<robot>.png (default: FILE with .png)",
    )
    plot.add_argument("--robot", metavar="ID", help="only this robot (default: every robot in the file)")
    plot.set_defaults(func=cmd_plot)

    view = command(
        "view",
        "serve a running system live to Foxglove (WebSocket) until Ctrl-C",
        "Serve a running system live to Foxglove through the Foxglove WebSocket protocol: every\n"
        "robot's odometry, path, commands, costs, critic weights, solve time and tick jitter, as ROS 2\n"
        "messages (the topics of srl record). Loopback only by default; open docs/foxglove-layout.json.",
    )
    add_view_arguments(view)
    view.set_defaults(func=cmd_view)

    # srl experiment paper (tools/experiment/runner.py): the paper's grid of runs, ratios and plots
    from tools.experiment.runner import add_experiment_arguments, cmd_experiment

    experiment = command("experiment", "the paper's experiment: grid of starts, cost ratios, plots")
    add_experiment_arguments(experiment)
    experiment.set_defaults(func=cmd_experiment)

    # srl health (tools/launch/health.py): readiness of a service, for container healthchecks
    from tools.launch.health import add_health_parser

    add_health_parser(sub)
    for action in sub._choices_actions:  # every subcommand's --help opens with what it does
        subparser = sub.choices[action.dest]
        if not subparser.description:
            subparser.description = (action.help or "")[:1].upper() + (action.help or "")[1:] + "."
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """``srl ARGS`` in this process (tests, benchmarks): the exit code."""
    return runtime_main(build_parser(), argv)


def entry(argv: Sequence[str] | None = None) -> None:
    """The ``srl`` console command (common.process.runtime.entry: exit codes, the exit after Zenoh)."""
    runtime_entry(build_parser, argv)


if __name__ == "__main__":
    entry()
