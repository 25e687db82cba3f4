"""``srl experiment fleet``: the paper's starts as ONE fleet, per-robot vs pooled critics (docs/fleets.md).

Every start of the grid is a robot of one fleet; the fleet runs Algorithm 1 in lockstep in one
process (:func:`common.config.assembly.run_fleet_episode`: one built actor, every robot stepping
together). ``per-robot``: each robot learns its own critic, exactly as in ``srl experiment
paper`` (the same J, bit for bit); ``pooled``: one critic learns from every robot's transitions
(TD pairs only within one robot's consecutive steps) and every robot acts on it. MPC runs once
per horizon as a fleet too (it learns nothing: the critic layout does not matter) and gives
J_mpc. The marks are the paper's ``J / J_mpc * 100 %`` per start, their median, the starts
better than MPC and the robots parked.

Fleets run in worker processes (spawned), one fleet per task.
"""

from __future__ import annotations

import json
import logging
import math
import multiprocessing
import sys
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.config.assembly import CRITIC_LAYOUTS, CriticLayout
from common.config.settings import Settings
from common.math.agents import AGENT_ROWS, REFERENCE_AGENT, learns
from common.process.plugins import load_from_environment
from tools.experiment.grid import Start
from tools.experiment.marks import PARK_TOLERANCE_M, TIE_PERCENT

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FleetTask:
    agent: str
    horizon: int
    critic: CriticLayout


def parse_critics(text: str) -> tuple[CriticLayout, ...]:
    """``"per-robot,pooled"`` -> both, in order, each once; anything else is refused."""
    names = tuple(dict.fromkeys(c.strip() for c in str(text).split(",") if c.strip()))
    unknown = [c for c in names if c not in CRITIC_LAYOUTS]
    if not names or unknown:
        raise ValueError(f"--critic: {text!r}; a comma-separated list of {', '.join(CRITIC_LAYOUTS)}")
    return tuple(c for c in CRITIC_LAYOUTS if c in names)


def plan_fleets(agents: Sequence[str], horizons: Sequence[int], critics: Sequence[CriticLayout]) -> list[FleetTask]:
    """One MPC fleet per horizon (J_mpc) and one fleet per (agent, horizon, critic) of the rest."""
    tasks = []
    for horizon in horizons:
        tasks.append(FleetTask(REFERENCE_AGENT, horizon, "per-robot"))
        tasks += [FleetTask(agent, horizon, critic) for agent in agents if learns(agent) for critic in critics]
    return tasks


def run_fleet_task(base: dict[str, Any], task: FleetTask, starts: list[list[float]]) -> dict[str, Any]:
    """A worker: one fleet from every start; J and the final distance per robot."""
    from common.config.assembly import run_fleet_episode

    data = json.loads(json.dumps(base))
    data["actor"].update(agent=task.agent, horizon=task.horizon)
    settings = Settings.model_validate(data)
    started = time.perf_counter()
    episodes = run_fleet_episode(settings, [np.array(s) for s in starts], task.critic)
    return {
        "agent": task.agent,
        "horizon": task.horizon,
        "critic": task.critic,
        "wall_seconds": time.perf_counter() - started,
        "costs": [e.accumulated_cost for e in episodes],
        "final_distances": [float(np.hypot(*e.final_state[:2])) for e in episodes],
        "solver_failures": sum(e.solver_failures for e in episodes),
    }


def fleet_marks(results: Sequence[dict[str, Any]], starts: Sequence[Start]) -> dict[str, Any]:
    """Per (agent, N, critic): J / J_mpc per start, median, better than MPC, parked."""
    mpc = {r["horizon"]: r["costs"] for r in results if r["agent"] == REFERENCE_AGENT}
    groups = []
    for r in results:
        if r["agent"] == REFERENCE_AGENT:
            continue
        ratios = [100.0 * j / jm for j, jm in zip(r["costs"], mpc[r["horizon"]], strict=True)]
        groups.append(
            {
                "agent": r["agent"],
                "horizon": r["horizon"],
                "critic": r["critic"],
                "median_ratio_percent": float(np.median(ratios)),
                "better_than_mpc": sum(x < 100.0 - TIE_PERCENT for x in ratios),
                "parked": sum(d <= PARK_TOLERANCE_M for d in r["final_distances"]),
                "robots": len(ratios),
                "ratio_percent": ratios,
                "solver_failures": r["solver_failures"],
                "wall_seconds": r["wall_seconds"],
            }
        )
    mpc_parked = {
        r["horizon"]: sum(d <= PARK_TOLERANCE_M for d in r["final_distances"])
        for r in results
        if r["agent"] == REFERENCE_AGENT
    }
    return {
        "starts": [[s.x, s.y, s.alpha] for s in starts],
        "mpc_costs": {str(h): costs for h, costs in mpc.items()},
        "mpc_parked": {str(h): n for h, n in mpc_parked.items()},
        "groups": groups,
    }


def fleet_markdown(marks: dict[str, Any], command: str) -> str:
    """The summary table and the per-start table per horizon."""
    groups = marks["groups"]
    lines = [
        f"`{command}`",
        "",
        "| agent | N | critic | median J/J_mpc | better than MPC | parked |",
        "|---|---|---|---|---|---|",
    ]
    for g in groups:
        lines.append(
            f"| {AGENT_ROWS[g['agent']].title} | {g['horizon']} | {g['critic']} | "
            f"{g['median_ratio_percent']:.1f} % | {g['better_than_mpc']}/{g['robots']} | {g['parked']}/{g['robots']} |"
        )
    robots = len(marks["starts"])
    parked = ", ".join(f"{n}/{robots} at N = {h}" for h, n in marks["mpc_parked"].items())
    lines += ["", f"MPC (J_mpc, the same fleet without learning) parked: {parked}."]
    # per start, every horizon side by side: J_mpc, then J / J_mpc of each (agent, critic)
    horizons = list(dict.fromkeys(g["horizon"] for g in groups))
    columns = {h: [g for g in groups if g["horizon"] == h] for h in horizons}
    header = "".join(
        f" N = {h}: J_mpc |" + "".join(f" {AGENT_ROWS[g['agent']].title} {g['critic']} |" for g in columns[h])
        for h in horizons
    )
    lines += ["", "J / J_mpc per start (%):", "", "| start (x, y) |" + header]
    lines.append("|---|" + "---|" * sum(1 + len(columns[h]) for h in horizons))
    for i, (x, y, _) in enumerate(marks["starts"]):
        cells = []
        for h in horizons:
            cells.append(f"{marks['mpc_costs'][str(h)][i]:.1f}")
            cells += [f"{g['ratio_percent'][i]:.1f}" for g in columns[h]]
        lines.append(f"| ({x:g}, {y:g}) | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def run_fleet_experiment(
    base: Settings,
    starts: Sequence[Start],
    agents: Sequence[str],
    horizons: Sequence[int],
    critics: Sequence[CriticLayout],
    workers: int,
) -> dict[str, Any]:
    tasks = plan_fleets(agents, horizons, critics)
    data = base.model_dump(mode="json")
    data["critic"]["checkpoint"] = ""  # in process: no checkpoint file (as the paper experiment)
    points = [[s.x, s.y, s.alpha] for s in starts]
    count = min(len(tasks), workers or multiprocessing.cpu_count())
    results = []
    context = multiprocessing.get_context("spawn")  # each worker loads SRL_PLUGINS afresh
    with ProcessPoolExecutor(count, mp_context=context, initializer=load_from_environment) as pool:
        futures = [pool.submit(run_fleet_task, data, task, points) for task in tasks]
        for task, future in zip(tasks, futures, strict=True):
            result = future.result()
            log.info("fleet %s N=%d %s: %.1f s", task.agent, task.horizon, task.critic, result["wall_seconds"])
            results.append(result)
    return fleet_marks(results, starts)


def cmd_fleet(args: Any, base: Settings, starts: Sequence[Start], command: str) -> int:
    """``srl experiment fleet`` after the shared parsing: run, print the tables, write ``--out``."""
    from common.math.agents import parse_agents, parse_horizons

    agents, horizons = parse_agents(args.agents), parse_horizons(args.horizons)
    critics = parse_critics(args.critic)
    if not any(learns(a) for a in agents):
        raise ValueError("--agents: a fleet experiment compares learning agents with MPC; name rlq, rlqv or rlqv+")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", stream=sys.stderr)
    marks = run_fleet_experiment(base, starts, agents, horizons, critics, args.workers)
    marks["command"] = command
    text = fleet_markdown(marks, command)
    print(text, end="")
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "fleet.json").write_text(json.dumps(marks, indent=2, allow_nan=True) + "\n")
        (args.out / "fleet.md").write_text(text)
        print(f"\nresults in {args.out}/", file=sys.stderr)
    return 0 if all(math.isfinite(x) for g in marks["groups"] for x in g["ratio_percent"]) else 1
