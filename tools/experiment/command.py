"""``srl experiment paper|fleet|baselines``: its options, and the command that runs it
(tools/experiment/runner.py; baselines: tools/experiment/baselines.py)."""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import os
import shlex
import sys
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from common.config.settings import METHODS, Settings
from common.math.agents import AGENTS, PAPER_AGENTS, parse_agents, parse_horizons
from common.math.plant_models import PLANT_MODELS
from common.math.systems import SYSTEMS
from tools.experiment.grid import STARTS, make_starts
from tools.experiment.options import DEFAULT_HORIZONS, ExperimentOptions
from tools.experiment.output import experiment_settings
from tools.experiment.report import summary_markdown
from tools.experiment.runner import run_experiment

NAME = "experiment"
DEFAULT_EXTENT = 2.0  # [m] the paper's starts, within 2 m of the target
HELP = "the paper's experiment: grid of starts, cost ratios, plots; SAC and PPO beside it"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "which",
        choices=["paper", "fleet", "baselines"],
        help="paper: section IV, the grid of starts and cost ratios; fleet: the same starts as ONE fleet in "
        "lockstep, per-robot vs pooled critics (docs/fleets.md); baselines: SAC and PPO (stable-baselines3, "
        "the extra srl[baselines]) trained on srl's Gymnasium environments, beside srl's agents on the paper's "
        "and the held-out starts (docs/gym.md)",
    )
    parser.add_argument(
        "--system",
        choices=tuple(SYSTEMS),
        help="paper: the sampled system (plant.system; docs/reference/variants.md): another than the robot's "
        "starts span its start box; baselines: its Gymnasium environment, e.g. srl/Pendulum-v0 "
        "(default: the settings', the robot)",
    )
    parser.add_argument("--grid", type=int, default=5, help="K: K x K starts (default 5: the paper's 25)")
    parser.add_argument(
        "--extent", type=float, help=f"the robot's starts over [-E, E]^2 [m] (default {DEFAULT_EXTENT:g})"
    )
    parser.add_argument(
        "--starts",
        choices=STARTS,
        default="paper",
        help="paper: the K x K lattice; held-out: one seeded random start in each of K x K cells (default: paper)",
    )
    parser.add_argument(
        "--seed", type=int, default=0, help="seed of everything random (the held-out starts) (default: 0)"
    )
    parser.add_argument(
        "--agents",
        default=",".join(PAPER_AGENTS),
        help=f"comma-separated, of {','.join(AGENTS)} (default: {','.join(PAPER_AGENTS)})",
    )
    parser.add_argument(
        "--horizons", default=",".join(str(h) for h in DEFAULT_HORIZONS), help="comma-separated N values (default 12,6)"
    )
    parser.add_argument("--duration", type=float, help="episode length [s] (default from the config: 30)")
    parser.add_argument(
        "--method",
        choices=METHODS,
        default="paper",
        help="paper: the paper's method exactly (no arrival rule, no wheel-speed box, the critics as fitted, "
        "whatever the config says); robot: with them as configured ([actor] in srl.toml: on) (default: paper)",
    )
    parser.add_argument(
        "--plant",
        choices=list(PLANT_MODELS),
        default="ideal",
        help="the simulated robot (plant.model): ideal, the paper's exact unicycle; actuator, the TurtleBot3 "
        "model; physics, the MuJoCo TurtleBot3; J is on what the robot reported, true J beside it (default: ideal)",
    )
    parser.add_argument(
        "--localization",
        choices=["none", "amcl", "mocap"],
        default="none",
        help="the pose the actor sees (inproc): none, the robot's odometry; amcl, corrected by a fix at start and "
        "after every 0.25 m or 0.2 rad; mocap, by a fix every 0.1 s (the robot bridge's fusion, "
        "docs/turtlebot-localization.md) (default: none)",
    )
    parser.add_argument(
        "--config", type=Path, help="a TOML file overriding common/config/srl.toml (any subset) (default: none)"
    )
    parser.add_argument("--out", type=Path, help="output directory (default out/paper-<UTC time>)")
    parser.add_argument(
        "--transport",
        choices=["inproc", "zenoh"],
        default="inproc",
        help="inproc: workers run Algorithm 1 in process; zenoh: through router, plant_sim "
        "and critic service processes (lockstep, synchronous critic) (default: inproc)",
    )
    parser.add_argument("--workers", type=int, default=0, help="worker processes (default: every core)")
    parser.add_argument(
        "--critic",
        default="per-robot,pooled",
        help="fleet: the critic layouts compared, of per-robot,pooled (default: both)",
    )
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    baselines = parser.add_argument_group("baselines")
    baselines.add_argument(
        "--algos", default="sac,ppo", help="baselines: comma-separated, of sac,ppo (default: sac,ppo)"
    )
    baselines.add_argument(
        "--envs",
        help="baselines: comma-separated Gymnasium ids (srl/ optional), of Unicycle-v0,TurtleBot3-v0,"
        "TurtleBot3Physics-v0 and the other systems' (Pendulum-v0, ...) (default: Unicycle-v0,TurtleBot3-v0; "
        "--system S: S's)",
    )
    baselines.add_argument(
        "--budgets",
        help="baselines: comma-separated environment steps, one training per seed copied at each "
        "(default: 10000,30000,100000; --quick: 1000,5000)",
    )
    baselines.add_argument(
        "--seeds", type=int, help="baselines: training seeds --seed, --seed + 1, ... (default: 3; --quick: 1)"
    )
    baselines.add_argument(
        "--quick",
        action="store_true",
        help="baselines: 1 seed, budgets 1000,5000, the 3 x 3 grids of starts (under 10 minutes on 2 cores)",
    )
    baselines.add_argument(
        "--hyper",
        action="append",
        default=[],
        metavar="ALGO.NAME=VALUE",
        help="baselines: override one of the RL Zoo's hyperparameters, e.g. ppo.n_steps=64, repeatable (default: none)",
    )
    parser.add_argument(
        "--record",
        type=Path,
        metavar="FILE.mcap",
        help="one MCAP recording (rosbag2 layout) of every run, each run a robot /<run_id>/..., all "
        "starting together (default: none)",
    )
    parser.set_defaults(func=main)


def _load_settings(args: argparse.Namespace) -> Settings:
    from pydantic import ValidationError

    overrides: dict[str, Any] = json.loads(json.dumps(METHODS[args.method]))  # the method's row, a copy
    if args.duration is not None:
        overrides["episode"] = {"duration": args.duration}
    overrides["plant"] = {"model": args.plant} | ({"system": args.system} if args.system else {})
    try:
        settings = Settings.load(args.config, **overrides)
        # another system: the paper's experiment, in process or over the lockstep services
        settings.robot_only(
            "srl experiment",
            (args.which, args.which != "paper"),
            ("--record", args.record is not None),
            (f"--localization {args.localization}", args.localization != "none"),
            ("--extent (another system's starts span its start box)", args.extent is not None),
        )
        return settings
    except ValidationError as error:
        problems = "; ".join(f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in error.errors())
        raise ValueError(f"invalid settings: {problems}") from error
    except FileNotFoundError as error:
        raise ValueError(str(error)) from error


def main(args: argparse.Namespace) -> int:
    try:
        if args.grid < 1:
            raise ValueError(f"--grid must be >= 1, got {args.grid}")
        if args.extent is not None and not (math.isfinite(args.extent) and args.extent > 0):
            raise ValueError(f"--extent must be a positive number, got {args.extent}")
        if args.localization != "none" and (args.transport != "inproc" or args.which == "fleet"):
            raise ValueError("--localization is for `srl experiment paper --transport inproc` (the in-process plant)")
        if args.workers < 0:
            raise ValueError(f"--workers must be >= 0 (0 = every core), got {args.workers}")
        if args.which == "baselines":
            if args.extent is None:
                args.extent = DEFAULT_EXTENT
            return _cmd_baselines(args)
        base = _load_settings(args)
        if args.extent is None:  # the robot's default; another system's starts span its start box
            args.extent = DEFAULT_EXTENT
        options = ExperimentOptions(
            grid=args.grid,
            extent=args.extent,
            starts=args.starts,
            seed=args.seed,
            agents=parse_agents(args.agents),
            horizons=parse_horizons(args.horizons),
            transport=args.transport,
            localization=args.localization,
            workers=args.workers,
            out=args.out or Path("out") / f"paper-{datetime.now(UTC):%Y%m%d-%H%M%S}",
            plots=not args.no_plots,
            progress=not args.no_progress,
            record=args.record,
        )
        options.command = "srl experiment " + " ".join(shlex.quote(a) for a in _argv_of(args, base))
        if args.which == "fleet":
            return _cmd_fleet(args, base)
    except ValueError as error:
        print(f"srl experiment: error: {error}", file=sys.stderr)
        return 2
    from tools.recording.record import RecordingError

    try:
        code, summary = run_experiment(options, base)
    except RecordingError as error:
        print(f"srl experiment: error: {error}", file=sys.stderr)
        return 2
    print(summary_markdown(summary), end="")
    print(f"\nresults in {options.out}/", file=sys.stderr)
    if summary.get("error"):
        print(f"srl experiment: error: {summary['error']}", file=sys.stderr)
    elif summary["interrupted"]:
        print(
            f"srl experiment: interrupted; {summary['runs_completed']} of {summary['runs_planned']} runs "
            f"written to {options.out}/",
            file=sys.stderr,
        )
    return code


def _cmd_fleet(args: argparse.Namespace, base: Settings) -> int:
    """``srl experiment fleet`` (tools/experiment/fleet.py): in process, one fleet per (agent, N, critic)."""
    from tools.experiment.fleet import cmd_fleet

    if args.transport != "inproc" or args.record is not None:
        raise ValueError("experiment fleet runs in process: --transport zenoh and --record are for `experiment paper`")
    starts = make_starts(args.starts, args.grid, args.extent, args.seed)
    argv = [a for a in _argv_of(args) if not a.startswith("--transport=")]
    command = "srl experiment " + " ".join(shlex.quote(a) for a in [*argv, f"--critic={args.critic}"])
    return cmd_fleet(args, experiment_settings(base), starts, command)


def _cmd_baselines(args: argparse.Namespace) -> int:
    """``srl experiment baselines`` (tools/experiment/baselines.py): in process, one thread."""
    if args.transport != "inproc" or args.record is not None or args.localization != "none":
        raise ValueError("experiment baselines runs in process: --transport, --record and --localization are not its")
    if args.plant != "ideal" or args.starts != "paper":
        raise ValueError("experiment baselines: choose the robots with --envs; it evaluates on both sets of starts")
    # the extra's packages are imported where the trainings run; here only found (torch takes ~1.5 s)
    if args.workers < 0:
        raise ValueError(f"--workers must be >= 0 (0 = every core), got {args.workers}")
    # the options are checked first (gymnasium is all they need), then the trainings' packages:
    # a bad option is named whether or not the extra is installed
    extra = ("gymnasium", "stable_baselines3", "torch")
    missing = [name for name in extra if importlib.util.find_spec(name) is None]
    if "gymnasium" in missing:
        raise ValueError(
            f"experiment baselines needs the extra: pip install 'srl[baselines]' (missing {', '.join(missing)})"
        )
    from tools.experiment import baselines as bl

    seeds = args.seeds if args.seeds is not None else (1 if args.quick else bl.DEFAULT_SEEDS)
    if seeds < 1:
        raise ValueError(f"--seeds must be >= 1, got {seeds}")
    if args.system is not None and args.envs is not None:
        raise ValueError("experiment baselines: --system names the environment; give --system or --envs, not both")
    envs = bl.parse_envs(args.envs) if args.envs is not None else bl.DEFAULT_ENVS
    if args.system is not None:
        envs = bl.system_environments(args.system)
        args.system = None  # the environments carry the system; the base settings stay the robot's
    options = bl.BaselineOptions(
        algos=bl.parse_choices(args.algos, bl.ALGOS, "algorithm"),
        envs=envs,
        budgets=bl.parse_budgets(args.budgets)
        if args.budgets
        else (bl.QUICK_BUDGETS if args.quick else bl.DEFAULT_BUDGETS),
        seeds=seeds,
        seed=args.seed,
        grid=bl.QUICK_GRID if args.quick else args.grid,
        extent=args.extent,
        agents=parse_agents(args.agents),
        horizons=parse_horizons(args.horizons),
        method=args.method,
        hyper=bl.parse_hyper(args.hyper),
        out=args.out or Path("out") / f"baselines-{datetime.now(UTC):%Y%m%d-%H%M%S}",
        plots=not args.no_plots,
        progress=not args.no_progress,
        quick=args.quick,
        workers=args.workers or os.cpu_count() or 1,
    )
    if missing:
        raise ValueError(
            f"experiment baselines needs the extra: pip install 'srl[baselines]' (missing {', '.join(missing)})"
        )
    argv = [
        "baselines",
        f"--algos={','.join(options.algos)}",
        f"--envs={','.join(e.removeprefix('srl/') for e in options.envs)}",
        f"--budgets={','.join(str(b) for b in options.budgets)}",
        f"--seeds={options.seeds}",
        f"--seed={options.seed}",
        f"--grid={options.grid}",
        f"--extent={options.extent:g}",
        f"--agents={args.agents}",
        f"--horizons={args.horizons}",
        f"--method={args.method}",
        *(f"--hyper={item}" for item in args.hyper),
    ]
    if args.duration is not None:
        argv.append(f"--duration={args.duration:g}")
    if args.config is not None:
        argv.append(f"--config={args.config}")
    options.command = "srl experiment " + " ".join(shlex.quote(a) for a in argv)
    summary, _ = bl.run_baselines(options, experiment_settings(_load_settings(args)))
    print(bl.table_markdown(summary) + "\n" + bl.notes_markdown(summary), end="")
    print(f"\nresults in {options.out}/", file=sys.stderr)
    return 0


def _argv_of(args: argparse.Namespace, base: Settings | None = None) -> list[str]:
    """A re-runnable command line for the summary (what was given, defaults spelled out; another
    system than the robot named, with no --extent)."""
    robot = base is None or base.system.wheeled
    argv = [
        args.which,
        *([] if robot or base is None else [f"--system={base.plant.system}"]),
        f"--grid={args.grid}",
        *([f"--extent={args.extent:g}"] if robot else []),
        f"--starts={args.starts}",
        f"--seed={args.seed}",
        f"--agents={args.agents}",
        f"--horizons={args.horizons}",
        f"--transport={args.transport}",
        f"--method={args.method}",
        f"--plant={args.plant}",
    ]
    if args.localization != "none":
        argv.append(f"--localization={args.localization}")
    if args.duration is not None:
        argv.append(f"--duration={args.duration:g}")
    if args.config is not None:
        argv.append(f"--config={args.config}")
    if args.workers:
        argv.append(f"--workers={args.workers}")
    if args.record is not None:
        argv.append(f"--record={args.record}")
    return argv
