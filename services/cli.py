"""The ``srl`` command: one subcommand per service or tool.

``python -m services.cli ...`` runs the same code. Logging is configured here, once.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from common.settings import Settings, parse_start

log = logging.getLogger(__name__)


class UsageError(Exception):
    """A problem with what the user asked for: printed as one clear line, exit code 2."""


def _start_arg(text: str) -> tuple[float, ...]:
    try:
        return parse_start(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from error


def add_settings_arguments(parser: argparse.ArgumentParser) -> None:
    """Flags that override the config file (only those given take effect)."""
    parser.add_argument("--config", type=Path, help="a TOML file overriding common/srl.toml (any subset)")
    parser.add_argument("--agent", choices=["mpc", "rlq", "rlqv", "rlqv+"])
    parser.add_argument("--horizon", type=int, help="N (N - 1 held actions)")
    parser.add_argument("--start", type=_start_arg, help="X,Y (heading away from the target) or X,Y,ALPHA")
    parser.add_argument("--duration", type=float, help="episode length [s]")
    parser.add_argument("--solver", choices=["fatrop", "ipopt"])
    parser.add_argument("--predictor", choices=["euler", "rk4"])
    parser.add_argument("--no-jit", action="store_true", help="do not JIT-compile the actor problem")


def settings_from_args(args: argparse.Namespace) -> Settings:
    overrides: dict[str, dict[str, Any]] = {"actor": {}, "episode": {}}
    for name in ("agent", "horizon", "solver", "predictor"):
        if getattr(args, name, None) is not None:
            overrides["actor"][name] = getattr(args, name)
    if getattr(args, "no_jit", False):
        overrides["actor"]["jit"] = False
    if getattr(args, "start", None) is not None:
        overrides["episode"]["start"] = args.start
    if getattr(args, "duration", None) is not None:
        overrides["episode"]["duration"] = args.duration
    try:
        return Settings.load(getattr(args, "config", None), **{k: v for k, v in overrides.items() if v})
    except ValidationError as error:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in error.errors()
        )
        raise UsageError(f"invalid settings: {problems}") from error
    except (FileNotFoundError, ValueError) as error:
        raise UsageError(str(error)) from error


# -- srl run ---------------------------------------------------------------------------
def cmd_run(args: argparse.Namespace) -> int:
    from common.loop import episode_summary, run_episode

    settings = settings_from_args(args)
    if args.transport != "inproc":
        raise UsageError(f"transport {args.transport!r} is not available in this build")
    started = time.perf_counter()
    episode = run_episode(settings)
    summary = episode_summary(episode, settings)
    summary["wall_seconds"] = time.perf_counter() - started
    summary["transport"] = args.transport
    if args.plot:
        from services.plots import plot_episode

        plot_episode(episode, settings.plant.sampling_time, args.plot)
        summary["plot"] = str(args.plot)
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
        f"  final state    {_fmt_state(summary['final_state'])}   "
        f"distance to target {summary['final_distance']:.3f} m",
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
    return "\n".join(lines)


def _fmt_state(state: Sequence[float]) -> str:
    return f"x = {state[0]:+.3f} m, y = {state[1]:+.3f} m, alpha = {state[2]:+.3f} rad"


# -- srl bench -------------------------------------------------------------------------
def cmd_bench(args: argparse.Namespace) -> int:
    if args.what == "actor":
        from services.bench_actor import run_actor_benchmark

        return run_actor_benchmark(args, settings_from_args(args))
    raise UsageError(f"unknown benchmark {args.what!r}")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="srl", description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--log-level", default="WARNING", help="DEBUG, INFO, WARNING (default), ERROR")
    sub = parser.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="one closed-loop episode of Algorithm 1 (actor, plant, critic)")
    add_settings_arguments(run)
    run.add_argument("--transport", choices=["inproc"], default="inproc")
    run.add_argument("--json", action="store_true", help="last stdout line: one JSON object")
    run.add_argument("--plot", type=Path, help="write the trajectory and costs to this PNG")
    run.set_defaults(func=cmd_run)

    bench = sub.add_parser("bench", help="benchmarks that print a table (and JSON)")
    bench.add_argument("what", choices=["actor"])
    add_settings_arguments(bench)
    bench.add_argument("--json", action="store_true", help="last stdout line: one JSON object")
    bench.add_argument("--steps", type=int, default=300, help="closed-loop steps per row (>= 300 for p99)")
    bench.add_argument("--horizons", default="6,12,30", help="comma-separated N values")
    bench.add_argument("--agents", default="mpc,rlq,rlqv,rlqv+", help="comma-separated agents")
    bench.add_argument(
        "--baseline-steps", type=int, default=30, help="steps of the slow SLSQP baseline per row"
    )
    bench.set_defaults(func=cmd_bench)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=getattr(logging, str(args.log_level).upper(), logging.WARNING),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except UsageError as error:
        print(f"srl: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("srl: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
