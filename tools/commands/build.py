"""``srl build``: the actor problems of some agents and horizons compiled into the JIT cache
(``actor.jit_cache``) ahead of the runs that need them, a few at a time.

A run's actor compiles its problem the first time that problem's shape is seen on the machine
(N = 12: 15-25 s of the C compiler on one core), then loads it from the cache in milliseconds.
``srl build`` pays those compiles before a run, side by side on the cores: for a grid of runs
(``srl experiment``), an image or a robot that should start at once, or the test suite (its runner
compiles the documented commands' problems into its own cache before its tests start).
"""

from __future__ import annotations

import argparse
import os
import signal
import time
from typing import Any

from common.config.arguments import UsageError, add_settings_arguments, settings_from_args
from common.config.settings import METHODS, Settings, with_method
from common.math.agents import AGENTS, parse_agents, parse_horizons
from common.process.runtime import SignalledError

NAME = "build"
HELP = "compile actor problems into the JIT cache ahead of the runs that need them"
DESCRIPTION = (
    "Compile the actor problem of each agent, horizon and method into the JIT cache "
    "(actor.jit_cache), JOBS at a time; a run then loads its compiled problem instead of compiling it. "
    "Prints one line per problem: compiled (seconds) or already cached."
)
DEFAULT_HORIZONS = "6,12"  # the paper's N


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, ("config", "solver", "predictor"))
    parser.add_argument(
        "--agents", default=",".join(AGENTS), help=f"comma-separated agents (default: {','.join(AGENTS)})"
    )
    parser.add_argument(
        "--horizons", default=DEFAULT_HORIZONS, help=f"comma-separated N values (default: {DEFAULT_HORIZONS})"
    )
    parser.add_argument(
        "--methods",
        default=",".join(METHODS),
        help="paper: the paper's problem (srl experiment's default); robot: the actor as configured "
        f"(srl run and srl up) (default: {','.join(METHODS)})",
    )
    parser.add_argument("--jobs", type=int, default=0, help="problems compiled at a time (default: 0, one per core)")
    parser.set_defaults(func=main)


def problem_settings(settings: Settings, agent: str, horizon: int, method: str) -> Settings:
    """The settings of one problem: the agent and N, and for ``paper`` the paper's method."""
    return with_method(settings, method, agent=agent, horizon=horizon)


def build_one(data: dict[str, Any]) -> float:
    """Build one problem (a worker process): the seconds it took. The actor's own "built the actor
    problem" warning is left out: :func:`main` prints a line per problem."""
    import logging

    from common.config.assembly import build_actor

    logging.getLogger("common.math.actor_nlp").setLevel(logging.ERROR)

    started = time.perf_counter()
    build_actor(Settings.model_validate(data))
    return time.perf_counter() - started


def main(args: argparse.Namespace) -> int:
    import multiprocessing

    from common.config.assembly import jit_cache_path
    from common.system.jit import cached_objects, compiler_available, remove_orphan_build_directories

    settings = settings_from_args(args)
    try:
        agents = parse_agents(args.agents)
        horizons = parse_horizons(args.horizons, "--horizons")
    except ValueError as error:
        raise UsageError(str(error)) from None
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = [m for m in methods if m not in METHODS]
    if unknown or not methods:
        raise UsageError(
            f"--methods: unknown method(s) {', '.join(unknown) or '(none)'}; choose from {', '.join(METHODS)}"
        )
    if args.jobs < 0:
        raise UsageError(f"--jobs must be >= 0, got {args.jobs}")
    if not settings.actor.jit:
        raise UsageError("actor.jit is off: there is nothing to compile")
    if settings.actor.jit_cache == "off":
        raise UsageError("actor.jit_cache is off: the compiled problems would not be kept")
    if not compiler_available():
        raise UsageError("no C compiler found (cc, gcc or clang): the actor runs interpreted, nothing to compile")
    problems: dict[str, Settings] = {}  # the paper's problem and the robot's may be the same
    for method in methods:
        for agent in agents:
            for horizon in horizons:
                one = problem_settings(settings, agent, horizon, method)
                problems.setdefault(one.actor.model_dump_json(), one)
    cache = jit_cache_path(settings.actor.jit_cache)
    before = cached_objects(cache)
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    jobs = min(args.jobs or cores, len(problems))
    started = time.perf_counter()
    context = multiprocessing.get_context("spawn")  # a fresh interpreter per worker, as the experiment's
    pool = context.Pool(jobs)
    previous = signal.signal(signal.SIGTERM, _raise_signalled)  # SIGTERM as Ctrl-C: the same stop, exit 143
    try:
        pending = [
            (pool.apply_async(build_one, (one.model_dump(mode="json"),)), one.actor) for one in problems.values()
        ]
        pool.close()  # nothing more to come: the workers end once the queue is done
        for result, actor in pending:
            seconds = result.get()
            box = "wheel box" if actor.wheel_speed_max > 0 else "no wheel box"
            print(f"{actor.agent:6s} N = {actor.horizon:3d} ({box}): ready in {seconds:.1f} s", flush=True)
    except BaseException:
        # Ctrl-C, a signal or a failed build: no problem starts after it and the running builds
        # end now (SIGTERM; the JIT wrapper stops its compiler and removes its directory when
        # its process is gone, common/system/jit.py), instead of the pool finishing its queue
        pool.terminate()
        raise
    finally:
        signal.signal(signal.SIGTERM, previous)
        pool.join()
        remove_orphan_build_directories()  # a worker ended before its compiler started leaves its directory
    count = f"{len(problems)} actor problem{'' if len(problems) == 1 else 's'}"
    print(
        f"srl build: {count} ready in {time.perf_counter() - started:.1f} s, {jobs} at a "
        f"time; {len(cached_objects(cache) - before)} compiled objects added to the JIT cache {cache}"
    )
    return 0


def _raise_signalled(signum: int, _frame: object) -> None:
    raise SignalledError(signum)
