"""``srl bench KIND``: the benchmarks (tools/bench/), each a table with its targets as PASS/FAIL and,
with ``--json``, one JSON object. Each benchmark takes only its own options: an option it would
ignore is refused."""

from __future__ import annotations

import argparse

from common.config.arguments import (
    COMMAND_SETTINGS,
    UsageError,
    add_bridge_arguments,
    add_seconds_argument,
    add_settings_arguments,
    bridge_argv,
    settings_argv,
    settings_from_args,
)
from common.config.settings import METHODS
from common.math.agents import AGENTS
from common.math.fleet import AUTO_HOSTS_HELP

NAME = "bench"
HELP = "benchmarks that print a table (and JSON)"
DESCRIPTION = (
    "Benchmarks that print a table with the targets as PASS/FAIL (and, with --json, one JSON object\n"
    "as the last stdout line): srl bench actor | loop | bridge | parking | fleet | capacity | critic | messages\n"
    "--help for each one's options."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    kinds = parser.add_subparsers(dest="what", required=True, metavar="KIND")

    def kind(name: str, helptext: str) -> argparse.ArgumentParser:
        parser = kinds.add_parser(name, help=helptext, description=helptext[0].upper() + helptext[1:] + ".")
        add_settings_arguments(parser, COMMAND_SETTINGS[f"bench {name}"])
        parser.add_argument("--json", action="store_true", help="last stdout line: one JSON object")
        parser.set_defaults(func=main)
        return parser

    actor_bench = kind("actor", "the actor's solve time and argmin against the slow SLSQP baseline, per agent and N")
    actor_bench.add_argument(
        "--agents", default=",".join(AGENTS), help=f"comma-separated agents (default: {','.join(AGENTS)})"
    )
    actor_bench.add_argument(
        "--quick",
        action="store_true",
        help="N = 12 only, no reference rows, a 10-step baseline, the best known minimum at 20 states: "
        "the speed and the argmin in a few minutes (the full bench: the benchmark page)",
    )
    actor_bench.add_argument(
        "--horizons", default=None, help="comma-separated N values (default: 6,12,30; --quick: 12)"
    )
    actor_bench.add_argument(
        "--steps", type=int, default=300, help="closed-loop steps per row (>= 300 for p99) (default: 300)"
    )
    actor_bench.add_argument(
        "--baseline-steps",
        type=int,
        default=None,
        help="steps of the slow SLSQP baseline per row (default: 30; --quick: 10)",
    )
    actor_bench.add_argument(
        "--judged-states",
        type=int,
        default=None,
        help="closed-loop states per row at which the argmin is judged against the best known minimum "
        "(default: 40; --quick: 20)",
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
        default=None,
        help="N values for the reference rows, the paper's plain actor with IPOPT ('' = none) "
        "(default: 12; --quick: none)",
    )

    loop_bench = kind("loop", "the real-time loop through the services: tick jitter, latency, staleness")
    add_seconds_argument(loop_bench, 60.0, "real-time run length [s] (default: 60)")
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
        help=f"actor processes of the host layout: a number, or {AUTO_HOSTS_HELP} (default: auto)",
    )
    fleet_bench.add_argument(
        "--record",
        action="store_true",
        help="every row with an srl record process attached for the whole run, writing every robot to an MCAP "
        "file in a temporary directory removed after the row (its CPU and memory count with the fleet's)",
    )
    fleet_bench.add_argument(
        "--outside",
        action="store_true",
        help="every row with a client outside srl subscribed to every robot's own transition key "
        "(srl/*/transition), which srl then sends besides its batches; its count in the row (its own CPU not "
        "counted: it is not srl's)",
    )
    add_seconds_argument(fleet_bench, 30.0, "real-time run per row [s] (default: 30)")
    capacity = kind(
        "capacity", "a fleet's cost per robot and component (CPU, messages), and what 1,000 and 10,000 need"
    )
    capacity.add_argument("--robots", default="10,25,50", help="fleet sizes to fit the costs on (default: 10,25,50)")
    add_seconds_argument(capacity, 30.0, "real-time run per size [s] (default: 30)")
    capacity.add_argument(
        "--utilisation", type=float, default=0.5, help="the share of each core the model plans to use (default: 0.5)"
    )
    capacity.add_argument("--host-cores", type=int, default=8, help="cores of each host in the model (default: 8)")
    bridge_bench = kind("bridge", "the robot bridge's latencies against an echo robot (ROS 2 over Zenoh)")
    add_bridge_arguments(bridge_bench)
    add_seconds_argument(bridge_bench, 60.0, "both phases together [s] (default: 60)")
    from tools.bench.critic import add_parser as add_critic_bench  # light: numpy loads when it runs

    add_critic_bench(kinds)
    from tools.bench.messages import add_parser as add_messages_bench  # light: pydantic loads when it runs

    add_messages_bench(kinds)

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
        help="grid (the paper's 25), random:COUNT:SEED (within 3 m, any heading), or X,Y[,ALPHA] starts "
        "separated by ';', e.g. --starts='-1,2;2,0,1.57' (default: 2,2;-2,2;-1,-2;2,-1;-2,0, five nodes "
        "of the paper's grid)",
    )
    parking.add_argument(
        "--localization",
        help="comma-separated poses the actor sees: none (odometry only), amcl (sparse fixes after 0.25 m "
        "/ 0.2 rad), mocap (10 Hz), fused as the robot bridge fuses them (default: none)",
    )
    parking.add_argument(
        "--localization-noise",
        help="SIGMA_XY,SIGMA_THETA of each fix [m, rad] (default: amcl 0.01,0.01; mocap 0.001,0.002)",
    )
    parking.add_argument("--parking-seconds", type=float, default=35.0, help="episode length per run [s] (default: 35)")


def main(args: argparse.Namespace) -> int:
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
