"""``srl experiment baselines``: SAC and PPO (stable-baselines3) against srl's agents, on one task
and one cost (docs/gym.md, "Train SAC on it, compare with stacked RL-QV").

For each environment (``srl/Unicycle-v0``, ``srl/TurtleBot3-v0``, or another system's, e.g.
``srl/Pendulum-v0``; tools/gym/envs.py), algorithm
and seed, ONE training runs to the largest budget of environment steps; the policy is copied at
every budget on the way (the learning curve: the model "at 10^4 steps" is the one the longer run
had after 10^4 steps). Each copy acts deterministically (the mean action) from every start of the
paper's ``K x K`` grid and of the held-out grid (tools/experiment/grid.py), one 300-step episode
each, on srl's environment and cost: ``J`` is the sum of the environment's ``c_k``. Beside them,
srl's agents (tools/gym/policies.py :class:`SrlPolicy`, the paper's method as ``srl experiment
paper`` runs it) run one episode per start: stacked RL-QV and RL-Q learn inside that one episode,
from the initial critic weights, so they consume 300 environment steps per start, and their actor
solves a finite-horizon problem over the known model at every step (the model is given, not
sampled). ``J / J_mpc`` divides by the MPC agent's ``J`` at the reference horizon (the first of
``--horizons``, 12) from the same start; "parked" and "at rest" are judged as ``srl experiment
paper`` judges them (tools/experiment/marks.py, common/math/parking.py).

Hyperparameters: the RL Zoo's tuned sets for ``Pendulum-v1`` (rl-baselines3-zoo,
hyperparams/sac.yml and ppo.yml): the closest task there, a low-dimensional state driven to a set
point under a quadratic stage cost, continuous actions, time-limited episodes. SAC and PPO act
through :func:`tools.gym.envs.normalized_actions` (``[-1, 1]^2``) and train on starts uniform in
the disc of radius ``extent * sqrt(2)``, which covers the square of both grids: neither grid's
starts are training starts. Another system's train on starts uniform in its start box and are
evaluated on the lattice ``srl experiment paper --system`` makes over it (tools/experiment/grid.py
system_starts; the held-out set one seeded start per cell); "parked" there is "stabilized" in
the system's terms (its row's distance below its ``stabilized``), "at rest" held so over the
last 10 s (tools/experiment/workers.py held).
"""

from __future__ import annotations

import ast
import csv
import io
import json
import math
import os
import platform
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from datetime import UTC, datetime
from functools import partial
from pathlib import Path
from typing import Any, Final, Protocol

import gymnasium
import numpy as np
from numpy.typing import NDArray

from common.config.settings import Settings
from common.math.agents import PAPER_AGENTS, REFERENCE_AGENT
from common.math.parking import parking
from common.math.systems import System, gymnasium_id, system_row
from common.process.plugins import load_from_environment
from common.system.jit import srl_cache
from tools.experiment.grid import STARTS, Start, make_starts
from tools.experiment.marks import PARK_TOLERANCE_M
from tools.experiment.workers import held
from tools.gym.envs import (
    ENV_MODELS,
    env_settings,
    normalized_actions,
    system_envs,
)  # registers the srl/ ids
from tools.gym.policies import SrlPolicy

FloatArray = NDArray[np.float64]
ALGOS: Final[tuple[str, ...]] = ("sac", "ppo")
DEFAULT_ENVS: Final[tuple[str, ...]] = ("srl/Unicycle-v0", "srl/TurtleBot3-v0")
# Up to 5 times the RL Zoo's budget for SAC on Pendulum-v1 (2 x 10^4) and its budget for PPO (10^5):
# SAC takes 17-20 ms a step on one core here, so the 6 SAC trainings to 10^5 take 1.5-2.5 h on 2 workers
DEFAULT_BUDGETS: Final[tuple[int, ...]] = (10_000, 30_000, 100_000)
DEFAULT_SEEDS = 3
# --quick: one seed, two small budgets, the 3 x 3 grids of starts (under 10 minutes on 2 cores)
QUICK_BUDGETS: Final[tuple[int, ...]] = (1_000, 5_000)
QUICK_GRID = 3
ZOO_SOURCE = "the RL Zoo's Pendulum-v1 set (github.com/DLR-RM/rl-baselines3-zoo, hyperparams/{algo}.yml, 2026-04-23)"
# The Zoo's tuned sets for Pendulum-v1; a key not named is stable-baselines3's default.
ZOO: Final[dict[str, dict[str, Any]]] = {
    "sac": {"policy": "MlpPolicy", "learning_rate": 1e-3},
    "ppo": {
        "policy": "MlpPolicy",
        "n_envs": 4,
        "n_steps": 1024,
        "gae_lambda": 0.95,
        "gamma": 0.9,
        "n_epochs": 10,
        "ent_coef": 0.0,
        "learning_rate": 1e-3,
        "clip_range": 0.2,
        "use_sde": True,
        "sde_sample_freq": 4,
    },
}
PROGRESS_EVERY = 100  # environment steps between progress bar updates


@dataclass
class BaselineOptions:
    algos: tuple[str, ...] = ALGOS
    envs: tuple[str, ...] = DEFAULT_ENVS
    budgets: tuple[int, ...] = DEFAULT_BUDGETS
    seeds: int = DEFAULT_SEEDS
    seed: int = 0  # the first training seed and the held-out starts' seed
    grid: int = 5
    extent: float = 2.0
    agents: tuple[str, ...] = PAPER_AGENTS
    horizons: tuple[int, ...] = (12, 6)
    method: str = "paper"
    hyper: dict[str, dict[str, Any]] = field(default_factory=dict)  # per algorithm, over ZOO
    out: Path = field(default_factory=lambda: Path("out"))
    plots: bool = True
    progress: bool = True
    quick: bool = False
    workers: int = 1  # trainings side by side, one process each (torch on one thread in each)
    command: str = ""


# -- parsing ------------------------------------------------------------------------------
def parse_budgets(text: str) -> tuple[int, ...]:
    """``"10000,50000"`` -> ``(10000, 50000)``, ascending; each a positive whole number."""
    try:
        values = sorted({int(float(part)) for part in text.split(",") if part.strip()})
    except ValueError as error:
        raise ValueError(f"--budgets takes comma-separated step counts, got {text!r}") from error
    if not values or values[0] < 1:
        raise ValueError(f"--budgets takes positive step counts, got {text!r}")
    return tuple(values)


def parse_choices(text: str, choices: Sequence[str], what: str) -> tuple[str, ...]:
    values = tuple(dict.fromkeys(part.strip() for part in text.split(",") if part.strip()))
    unknown = [v for v in values if v not in choices]
    if unknown or not values:
        named = ", ".join(unknown) if unknown else repr(text)
        raise ValueError(f"unknown {what} {named}; choose from {', '.join(choices)}")
    return values


def env_system(env_id: str) -> str:
    """The sampled system of an environment id: the robot's (``unicycle``) or another's row."""
    return system_envs().get(env_id, "unicycle")


def system_environments(system: str) -> tuple[str, ...]:
    """``--system S``'s environments: the robot's defaults (:data:`DEFAULT_ENVS`), another system's own id."""
    if system_row(system).wheeled:
        return DEFAULT_ENVS
    return (gymnasium_id(system),)


def parse_envs(text: str) -> tuple[str, ...]:
    """Environment names with or without the ``srl/`` namespace -> full ids: the robot's
    (:data:`ENV_MODELS`) and every other system's (``Pendulum-v0``, ...)."""
    names = tuple(name.removeprefix("srl/") for name in (*ENV_MODELS, *system_envs()))
    return tuple(f"srl/{name}" for name in parse_choices(text.replace("srl/", ""), names, "environment"))


def parse_hyper(items: Sequence[str]) -> dict[str, dict[str, Any]]:
    """``["ppo.n_steps=64", "sac.batch_size=64"]`` -> ``{"ppo": {"n_steps": 64}, ...}`` (Python
    literals; a value that is not one stays a string)."""
    hyper: dict[str, dict[str, Any]] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        algo, dot, name = key.partition(".")
        if not (sep and dot and name) or algo not in ALGOS:
            raise ValueError(f"--hyper takes ALGO.NAME=VALUE with ALGO of {', '.join(ALGOS)}, got {item!r}")
        try:
            value: Any = ast.literal_eval(raw)
        except (ValueError, SyntaxError):
            value = raw
        hyper.setdefault(algo, {})[name] = value
    return hyper


def use_torch() -> None:
    """torch as every training and evaluation here uses it: on one thread (one core per
    training: the machine's others stay free), its compiler's cache in srl's
    (``~/.cache/srl/torchinductor``) unless the user chose one -- torch makes
    ``torchinductor_<user>`` in the temporary directory when its compiler is first imported (an
    optimizer's first step) and leaves it there."""
    os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", os.path.join(srl_cache(), "torchinductor"))
    import torch

    torch.set_num_threads(1)


def hyperparameters(algo: str, hyper: dict[str, dict[str, Any]] | None = None) -> dict[str, Any]:
    """The Zoo's set for ``algo`` with the overrides of ``hyper``."""
    return {**ZOO[algo], **(hyper or {}).get(algo, {})}


# -- training -----------------------------------------------------------------------------
@dataclass
class Snapshot:
    """The policy at one budget of one training run."""

    env_id: str
    algo: str
    seed: int
    budget: int
    steps: int  # environment steps consumed (PPO: whole rollouts, so at least the budget)
    wall_seconds: float  # of the training up to here
    cpu_seconds: float
    policy: Any  # a copy of the stable-baselines3 policy (torch module)


def training_env(env_id: str, settings: Settings, extent: float, seed: int, n_envs: int) -> Any:
    """``n_envs`` copies of ``env_id`` in ``[-1, 1]^m`` actions, starting uniformly in the disc of
    radius ``extent * sqrt(2)`` (the square of the grids inside it; another system: in its start
    box), seeded ``seed + i``."""
    from stable_baselines3.common.env_util import make_vec_env

    where: dict[str, Any] = {"starts": "box"}
    if settings.system.wheeled:
        where = {"starts": "disc", "extent": extent * math.sqrt(2.0)}

    def make() -> gymnasium.Env[Any, Any]:
        return normalized_actions(gymnasium.make(env_id, settings=settings, **where))

    return make_vec_env(make, n_envs=n_envs, seed=seed)


def train(
    env_id: str,
    algo: str,
    budgets: Sequence[int],
    seed: int,
    settings: Settings,
    extent: float = 2.0,
    hyper: dict[str, dict[str, Any]] | None = None,
    advance: Callable[[int], None] | None = None,
) -> list[Snapshot]:
    """Train ``algo`` on ``env_id`` to the largest budget, one ``learn`` call per budget (the
    step counter carries on: one run), and copy the policy at each. ``advance(steps)`` is told the
    steps consumed as training goes (the progress bar)."""
    use_torch()
    from stable_baselines3 import PPO, SAC
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.logger import Logger

    params = hyperparameters(algo, hyper)
    n_envs = int(params.pop("n_envs", 1))
    policy = params.pop("policy")
    env = training_env(env_id, settings, extent, seed, n_envs)
    model = (SAC if algo == "sac" else PPO)(policy, env, seed=seed, device="cpu", verbose=0, **params)
    # A logger with no outputs: without one, each learn() makes an empty SB3-<date> folder in the
    # temporary directory (stable_baselines3.common.logger.configure) and leaves it there.
    model.set_logger(Logger(folder=None, output_formats=[]))

    class Progress(BaseCallback):
        def _on_step(self) -> bool:
            if advance is not None and self.num_timesteps % PROGRESS_EVERY < n_envs:
                advance(self.num_timesteps)
            return True

    snapshots: list[Snapshot] = []
    wall, cpu = time.perf_counter(), time.process_time()
    for budget in sorted(budgets):
        model.learn(
            total_timesteps=max(0, budget - model.num_timesteps), callback=Progress(), reset_num_timesteps=False
        )
        snapshots.append(
            Snapshot(
                env_id,
                algo,
                seed,
                budget,
                int(model.num_timesteps),
                time.perf_counter() - wall,
                time.process_time() - cpu,
                policy_copy(model.policy),
            )
        )
        if advance is not None:
            advance(int(model.num_timesteps))
    env.close()
    return snapshots


def policy_copy(policy: Any) -> Any:
    """A copy of a stable-baselines3 policy through its own ``save`` and ``load`` (in memory), on
    the CPU and in evaluation mode."""
    buffer = io.BytesIO()
    policy.save(buffer)
    buffer.seek(0)
    fresh = type(policy).load(buffer, device="cpu")
    fresh.set_training_mode(False)
    return fresh


# -- evaluation ---------------------------------------------------------------------------
class Controller(Protocol):
    def reset(self) -> None: ...

    def act(self, observation: FloatArray) -> FloatArray: ...


class ModelController:
    """A trained policy, deterministic, its ``[-1, 1]^2`` action mapped onto ``(v, omega)`` as
    :func:`normalized_actions` maps it."""

    def __init__(self, policy: Any, env: gymnasium.Env[Any, Any]) -> None:
        self.policy = policy
        self.wrapper = normalized_actions(env)

    def reset(self) -> None:
        pass

    def act(self, observation: FloatArray) -> FloatArray:
        action, _ = self.policy.predict(observation, deterministic=True)
        return np.asarray(self.wrapper.action(action), dtype=np.float64)


@dataclass
class Episode:
    """One controller from one start: ``J`` and what ``srl experiment paper`` judges."""

    start_set: str
    start: Start
    cost: float  # J = sum of the environment's c_k
    final_distance: float  # of the observed final state to the goal, in the system's terms ([m]: the robot)
    tolerance: float  # "parked" (another system: stabilized) at a final distance up to this
    at_rest: bool  # common/math/parking.py, on the true states where the plant knows them
    solves: int  # the actor's solves (srl's agents; 0 for a trained policy)
    costs: FloatArray = field(repr=False)
    actions: FloatArray = field(repr=False)

    @property
    def parked(self) -> bool:
        return self.final_distance <= self.tolerance


def episode(env: gymnasium.Env[Any, Any], controller: Controller, start_set: str, start: Start) -> Episode:
    """Run ``controller`` from ``start`` until the environment truncates the episode."""
    obs, info = env.reset(options={"start": start.values})
    controller.reset()
    task: Any = env.unwrapped  # the SrlEnv: its action box and delta
    actor = getattr(controller, "actor", None)
    solves_before = _solves(actor)
    states, truths, actions, costs = [obs], [info.get("true_state")], [], []
    done = False
    while not done:
        action = controller.act(obs)
        obs, _reward, terminated, truncated, info = env.step(action)
        states.append(obs)
        truths.append(info.get("true_state"))
        actions.append(np.clip(action, task.box.low, task.box.high))
        costs.append(info["cost"])
        done = terminated or truncated
    known = all(t is not None for t in truths)
    path = np.array(truths if known else states, dtype=float)
    system = task.system
    rest = parking(path, actions, task.delta) if system.wheeled else held(list(path), task.settings)
    return Episode(
        start_set,
        start,
        float(np.sum(costs)),
        system.distance(states[-1]),
        tolerance(system),
        bool(rest.at_rest),
        _solves(actor) - solves_before,
        np.asarray(costs, dtype=np.float64),
        np.asarray(actions, dtype=np.float64),
    )


def _solves(actor: Any) -> int:
    if actor is None:
        return 0
    counters = actor.counters
    return int(counters.solves)


def tolerance(system: System) -> float:
    """ "Parked": the robot's final distance up to :data:`PARK_TOLERANCE_M`, another system's up to
    its row's ``stabilized`` (the tolerance ``srl experiment paper --system`` reports)."""
    return PARK_TOLERANCE_M if system.wheeled else system.stabilized


def evaluation_starts(grid: int, extent: float, seed: int, system: str = "unicycle") -> dict[str, list[Start]]:
    """The paper's grid and the held-out grid, as ``srl experiment paper`` makes them (another
    system: over its start box)."""
    return {kind: make_starts(kind, grid, extent, seed, system_row(system)) for kind in STARTS}


def evaluate(
    env: gymnasium.Env[Any, Any],
    controller: Controller,
    starts: dict[str, list[Start]],
    advance: Callable[[], None] | None = None,
) -> tuple[list[Episode], float, float]:
    """Every start of every set: (episodes, wall seconds, CPU seconds)."""
    wall, cpu = time.perf_counter(), time.process_time()
    episodes = []
    for kind, points in starts.items():
        for start in points:
            episodes.append(episode(env, controller, kind, start))
            if advance is not None:
                advance()
    return episodes, time.perf_counter() - wall, time.process_time() - cpu


# -- the experiment -----------------------------------------------------------------------
@dataclass
class Row:
    """One line of the table: a controller on one environment, over its seeds and starts."""

    env_id: str
    controller: str  # sac, ppo, or srl's agent name
    horizon: int | None  # srl's agents
    budget: int | None  # SAC / PPO
    steps: int  # environment steps consumed per model (srl: per start, one episode)
    models: int  # seeds (srl's agents: 1, deterministic)
    wall_seconds: float  # training to this budget and evaluation, all seeds
    cpu_seconds: float
    episodes: list[tuple[int, Episode]] = field(default_factory=list, repr=False)  # (seed, episode)

    @property
    def label(self) -> str:
        return f"{self.controller} N={self.horizon}" if self.horizon is not None else f"{self.controller}"


def env_settings_for(base: Settings, env_id: str) -> Settings:
    """``base`` with the environment's plant model and system (tools/gym/envs.py env_settings)."""
    return env_settings(base, ENV_MODELS.get(env_id, "ideal"), env_system(env_id))


def run_baselines(options: BaselineOptions, base: Settings, progress: Any = None) -> tuple[dict[str, Any], list[Row]]:
    """Train, evaluate, and write OUT/baselines.{md,csv,json,png}; returns the summary (what
    baselines.json holds) and the rows with their episodes (costs and actions)."""
    use_torch()
    started = datetime.now(UTC)
    wall0, cpu0 = time.perf_counter(), time.process_time()
    starts = {
        env: evaluation_starts(options.grid, options.extent, options.seed, env_system(env)) for env in options.envs
    }
    reference = options.horizons[0]
    srl_runs = list(
        dict.fromkeys([(REFERENCE_AGENT, reference), *((a, n) for n in options.horizons for a in options.agents)])
    )
    seeds = [options.seed + i for i in range(options.seeds)]
    bar = progress if progress is not None else _progress(options.progress)
    by_env: dict[str, list[Row]] = {env_id: [] for env_id in options.envs}  # srl's agents, then SAC, PPO
    with bar:
        for env_id in options.envs:
            settings = env_settings_for(base, env_id)
            env = gymnasium.make(env_id, settings=settings)
            # srl's agents first: J_mpc is every row's reference
            per_model = sum(len(points) for points in starts[env_id].values())
            task = bar.add_task(f"{env_id}: srl's agents", total=len(srl_runs) * per_model)
            for agent, horizon in srl_runs:
                policy = SrlPolicy(agent, horizon, settings=settings, method=options.method)
                episodes, wall, cpu = evaluate(env, policy, starts[env_id], partial(bar.advance, task))
                row = Row(env_id, agent, horizon, None, settings.steps, 1, wall, cpu)
                row.episodes = [(0, e) for e in episodes]
                by_env[env_id].append(row)
            env.close()
        jobs = [Job(env_id, algo, seed) for env_id in options.envs for algo in options.algos for seed in seeds]
        results = _run_jobs(jobs, options, base, starts, bar)
        for env_id in options.envs:
            for algo in options.algos:
                by_budget: dict[int, Row] = {}
                for job, evaluated in zip(jobs, results, strict=True):
                    if (job.env_id, job.algo) != (env_id, algo):
                        continue
                    for snap, episodes, wall, cpu in evaluated:
                        row = by_budget.setdefault(
                            snap.budget, Row(env_id, algo, None, snap.budget, snap.steps, 0, 0.0, 0.0)
                        )
                        row.steps = max(row.steps, snap.steps)
                        row.models += 1
                        row.wall_seconds += snap.wall_seconds + wall
                        row.cpu_seconds += snap.cpu_seconds + cpu
                        row.episodes += [(job.seed, e) for e in episodes]
                by_env[env_id] += [by_budget[b] for b in sorted(by_budget)]
    rows = [row for env_id in options.envs for row in by_env[env_id]]
    summary = summarize(rows, options, reference, started, time.perf_counter() - wall0, time.process_time() - cpu0)
    write_outputs(options.out, rows, summary, options.plots)
    return summary, rows


@dataclass(frozen=True)
class Job:
    """One training: ``algo`` on ``env_id`` from ``seed``, copied and evaluated at every budget."""

    env_id: str
    algo: str
    seed: int


Evaluated = list[tuple[Snapshot, list[Episode], float, float]]  # per budget: the snapshot, episodes, wall, CPU


def train_and_evaluate(
    job: Job,
    options: BaselineOptions,
    base: Settings,
    starts: dict[str, list[Start]],
    bar: Any = None,
) -> Evaluated:
    """``job``'s training to every budget and each copy's episodes from ``starts`` (the snapshots
    keep no policy: what crosses back from a worker process is numbers only). ``bar``: a rich
    progress to report on (in the calling process only)."""
    use_torch()
    settings = env_settings_for(base, job.env_id)
    advance = None
    if bar is not None:
        task = bar.add_task(f"{job.env_id}: {job.algo} seed {job.seed} training", total=max(options.budgets))
        advance = partial(_completed, bar, task)
    snapshots = train(job.env_id, job.algo, options.budgets, job.seed, settings, options.extent, options.hyper, advance)
    env = gymnasium.make(job.env_id, settings=settings)
    evaluated: Evaluated = []
    for snap in snapshots:
        episodes, wall, cpu = evaluate(env, ModelController(snap.policy, env), starts)
        evaluated.append((replace(snap, policy=None), episodes, wall, cpu))
    env.close()
    return evaluated


def _run_jobs(
    jobs: list[Job], options: BaselineOptions, base: Settings, starts: dict[str, dict[str, list[Start]]], bar: Any
) -> list[Evaluated]:
    """Every job, in order: here one after another (``workers`` 1, with the progress bar), else in
    ``workers`` processes side by side (each job's numbers are its own: the same either way, seeded;
    the bar then counts finished trainings)."""
    if options.workers <= 1 or len(jobs) <= 1:
        return [train_and_evaluate(job, options, base, starts[job.env_id], bar) for job in jobs]
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    task = bar.add_task(f"{len(jobs)} trainings in {options.workers} processes", total=len(jobs))
    context = multiprocessing.get_context("spawn")  # torch's state never forked
    workers = min(options.workers, len(jobs))  # each loads SRL_PLUGINS afresh, as every srl process
    with ProcessPoolExecutor(max_workers=workers, mp_context=context, initializer=load_from_environment) as pool:
        futures = [pool.submit(train_and_evaluate, job, options, base, starts[job.env_id]) for job in jobs]
        results = []
        for future in futures:
            results.append(future.result())
            bar.advance(task)
    return results


def _completed(bar: Any, task: Any, steps: int) -> None:
    bar.update(task, completed=steps)


def _progress(enabled: bool) -> Any:
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(
        TextColumn("[bold]srl experiment baselines[/bold]"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TextColumn("{task.description}"),
        console=Console(stderr=True),
        disable=not enabled,
    )


# -- the outputs --------------------------------------------------------------------------
def reference_costs(rows: Sequence[Row], reference: int) -> dict[tuple[str, str, int], float]:
    """``J_mpc`` per (environment, start set, start index)."""
    return {
        (row.env_id, e.start_set, e.start.index): e.cost
        for row in rows
        if row.controller == REFERENCE_AGENT and row.horizon == reference
        for _, e in row.episodes
    }


def row_records(row: Row, j_mpc: dict[tuple[str, str, int], float]) -> list[dict[str, Any]]:
    """One record per (seed, start) of ``row``: its lines of the CSV."""
    records = []
    for seed, e in row.episodes:
        ref = j_mpc[(row.env_id, e.start_set, e.start.index)]
        records.append(
            {
                "env": row.env_id,
                "controller": row.controller,
                "horizon": row.horizon if row.horizon is not None else "",
                "budget": row.budget if row.budget is not None else "",
                "steps": row.steps,
                "seed": seed,
                "start_set": e.start_set,
                "start_index": e.start.index,
                "start_x": e.start.x,
                "start_y": e.start.y,
                "start_alpha": e.start.alpha,
                "J": e.cost,
                "J_mpc": ref,
                "ratio_percent": 100.0 * e.cost / ref if ref > 0 else math.nan,
                "final_distance": e.final_distance,
                "parked": int(e.parked),
                "at_rest": int(e.at_rest),
                "parked_at_rest": int(e.parked and e.at_rest),
                "solves": e.solves,
            }
        )
    return records


def row_summary(row: Row, records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """A line of the table from the row's records: medians and counts per start set."""
    entry: dict[str, Any] = {
        "env": row.env_id,
        "controller": row.controller,
        "horizon": row.horizon,
        "budget": row.budget,
        "steps": row.steps,
        "models": row.models,
        "wall_seconds": row.wall_seconds,
        "cpu_seconds": row.cpu_seconds,
        "solves_per_episode": float(np.mean([r["solves"] for r in records])) if records else 0.0,
    }
    for kind in STARTS:
        part = [r for r in records if r["start_set"] == kind]
        entry[kind] = {
            "episodes": len(part),
            "median_ratio_percent": float(np.median([r["ratio_percent"] for r in part])) if part else math.nan,
            "median_J": float(np.median([r["J"] for r in part])) if part else math.nan,
            "parked": int(sum(r["parked"] for r in part)),
            "at_rest": int(sum(r["at_rest"] for r in part)),
            "parked_at_rest": int(sum(r["parked_at_rest"] for r in part)),
            "seed_medians_percent": [
                float(np.median([r["ratio_percent"] for r in part if r["seed"] == s]))
                for s in sorted({r["seed"] for r in part})
            ],
        }
    return entry


def summarize(
    rows: Sequence[Row],
    options: BaselineOptions,
    reference: int,
    started: datetime,
    wall_seconds: float,
    cpu_seconds: float,
) -> dict[str, Any]:
    j_mpc = reference_costs(rows, reference)
    per_row = [row_records(row, j_mpc) for row in rows]
    return {
        "command": options.command,
        "started_utc": started.isoformat(timespec="seconds"),
        "wall_seconds": wall_seconds,
        "cpu_seconds": cpu_seconds,
        "machine": machine(),
        "versions": versions(),
        "options": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(options).items()},
        "reference": f"MPC at N = {reference}, the paper's method, from the same start",
        "park_tolerance_m": PARK_TOLERANCE_M,
        "tolerances": {env: tolerance(system_row(env_system(env))) for env in options.envs},
        "hyperparameters": {a: hyperparameters(a, options.hyper) for a in options.algos},
        "hyperparameter_source": {a: ZOO_SOURCE.format(algo=a) for a in options.algos},
        "training_starts": "; ".join(
            f"{env.removeprefix('srl/')}: " + training_starts(env_system(env), options.extent) for env in options.envs
        ),
        "rows": [row_summary(row, records) for row, records in zip(rows, per_row, strict=True)],
        "episodes": [record for records in per_row for record in records],
    }


def training_starts(system: str, extent: float) -> str:
    """Where the trainings' episodes start, in words."""
    row = system_row(system)
    if row.wheeled:
        return f"uniform in the disc of radius {extent * math.sqrt(2.0):.3f} m"
    return "uniform in the start box |s| <= (" + ", ".join(f"{w:g}" for w in row.box_of_starts) + ")"


def machine() -> dict[str, Any]:
    load = os.getloadavg() if hasattr(os, "getloadavg") else (math.nan,) * 3
    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cores": os.cpu_count(),
        "load_average_1_5_15": [round(x, 2) for x in load],
        "python": sys.version.split()[0],
    }


def versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    found = {}
    for name in ("stable-baselines3", "torch", "gymnasium", "numpy"):
        try:
            found[name] = version(name)
        except PackageNotFoundError:
            found[name] = "absent"
    return found


def _percent(value: float) -> str:
    return "-" if not math.isfinite(value) else f"{value:.1f} %"


def table_markdown(summary: dict[str, Any]) -> str:
    """The table of OUT/baselines.md, and what it is."""
    lines = [
        "| env | controller | env steps | models | paper: median J/J_mpc | parked | parked at rest "
        "| held-out: median J/J_mpc | parked | parked at rest | wall s | CPU s |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in summary["rows"]:
        name = r["controller"] + (f" N={r['horizon']}" if r["horizon"] is not None else "")
        steps = f"{r['steps']:,}" + (" / start" if r["horizon"] is not None else "")
        cells = [r["env"].removeprefix("srl/"), name, steps, str(r["models"])]
        for kind in STARTS:
            part = r[kind]
            n = part["episodes"]
            cells += [_percent(part["median_ratio_percent"]), f"{part['parked']}/{n}", f"{part['parked_at_rest']}/{n}"]
        cells += [f"{r['wall_seconds']:.1f}", f"{r['cpu_seconds']:.1f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def notes_markdown(summary: dict[str, Any]) -> str:
    options = summary["options"]
    m = summary["machine"]
    hyper = "; ".join(
        f"{algo}: " + ", ".join(f"{k}={v}" for k, v in values.items())
        for algo, values in summary["hyperparameters"].items()
    )
    return (
        "\n".join(
            [
                f"* J / J_mpc: the controller's J (sum of c_k over {options['grid']}x{options['grid']} starts' "
                f"300-step episodes) over J of {summary['reference']}; the median over starts and seeds.",
                f"* parked: final distance to the target <= {summary['park_tolerance_m']} m; parked at rest: "
                "parked, and no chatter over the last 10 s (common/math/parking.py), as `srl experiment paper` "
                "judges a run; counted over starts x seeds." + _stabilized_note(summary),
                "* env steps: SAC / PPO, consumed in training (one run per seed, its policy copied at each budget; "
                "PPO in whole rollouts); srl's agents: one 300-step episode per start, learning inside it from the "
                "initial critic weights, plus the actor's solves over the known model "
                "(counted below: the model is given, not sampled).",
                f"* hyperparameters: {hyper} (the RL Zoo's tuned sets for Pendulum-v1, rl-baselines3-zoo "
                f"hyperparams/sac.yml and ppo.yml; the rest stable-baselines3's defaults); training starts "
                f"{summary['training_starts']}; actions through normalized_actions; torch on one thread.",
                "* the actor's solves per episode (each over the known model, N steps ahead): "
                + "; ".join(
                    f"{r['env'].removeprefix('srl/')} {r['controller']} N={r['horizon']} {r['solves_per_episode']:.0f}"
                    for r in summary["rows"]
                    if r["horizon"] is not None
                )
                + ".",
                "* wall / CPU: SAC / PPO, training to the budget plus the evaluation, summed over seeds; srl's agents, "
                "their episodes.",
                f"* {m['processor']}, {m['cores']} cores, load {m['load_average_1_5_15']}, Python {m['python']}, "
                + ", ".join(f"{k} {v}" for k, v in summary["versions"].items())
                + f"; started {summary['started_utc']}, {summary['wall_seconds']:.0f} s wall, "
                f"{summary['cpu_seconds']:.0f} s CPU.",
                f"* `{summary['command']}`" if summary["command"] else "",
            ]
        ).rstrip()
        + "\n"
    )


def _stabilized_note(summary: dict[str, Any]) -> str:
    """What "parked" means on the other systems' environments (none: nothing)."""
    robot = set(ENV_MODELS)
    others = {env: value for env, value in summary.get("tolerances", {}).items() if env not in robot}
    if not others:
        return ""
    named = ", ".join(f"{env.removeprefix('srl/')} {value:g}" for env, value in others.items())
    return (
        f" Another system: parked is stabilized (its distance to the goal, in its own terms, at most {named}), "
        "at rest held within it over the last 10 s."
    )


def write_outputs(out: Path, rows: Sequence[Row], summary: dict[str, Any], plots: bool = True) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "baselines.md").write_text(
        "# srl experiment baselines\n\n" + table_markdown(summary) + "\n" + notes_markdown(summary)
    )
    records = summary["episodes"]
    with (out / "baselines.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(records[0]) if records else ["env"])
        writer.writeheader()
        writer.writerows(records)
    (out / "baselines.json").write_text(json.dumps(summary, indent=1, allow_nan=True) + "\n")
    if plots:
        figure(summary, out / "baselines.png")


def figure(summary: dict[str, Any], path: Path) -> None:
    """Median J / J_mpc against environment steps consumed, per environment: SAC and PPO along
    their budgets, srl's learning agents at their one episode (solid / filled: the paper's starts,
    dashed / hollow: the held-out starts)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter

    envs = list(dict.fromkeys(r["env"] for r in summary["rows"]))
    fig, axes = plt.subplots(1, len(envs), figsize=(max(8.0, 6.2 * len(envs)), 5.0), squeeze=False)
    colours = iter(plt.rcParams["axes.prop_cycle"].by_key()["color"] * 4)
    by_name: dict[str, str] = {}
    for ax, env_id in zip(axes[0], envs, strict=True):
        rows = [r for r in summary["rows"] if r["env"] == env_id]
        for algo in dict.fromkeys(r["controller"] for r in rows if r["horizon"] is None):
            colour = by_name.setdefault(algo, next(colours))
            line = [r for r in rows if r["controller"] == algo]
            steps = [r["steps"] for r in line]
            ax.plot(steps, [r["paper"]["median_ratio_percent"] for r in line], "-o", color=colour, label=algo)
            ax.plot(steps, [r["held-out"]["median_ratio_percent"] for r in line], "--o", color=colour, mfc="none")
        for r in rows:
            if r["horizon"] is None or r["controller"] == REFERENCE_AGENT:
                continue
            name = f"{r['controller']} N={r['horizon']}"
            colour = by_name.setdefault(name, next(colours))
            ax.plot([r["steps"]], [r["paper"]["median_ratio_percent"]], "*", color=colour, ms=12, label=name)
            ax.plot([r["steps"]], [r["held-out"]["median_ratio_percent"]], "*", color=colour, ms=12, mfc="none")
        ax.axhline(100.0, color="grey", lw=0.8)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_minor_formatter(NullFormatter())  # decades only: the minor ticks' labels overlap
        ax.set_xlabel("environment steps consumed")
        ax.set_ylabel("median J / J_mpc [%]")
        ax.set_title(env_id, fontsize=10)
        ax.legend(fontsize=7)
        ax.grid(True, which="both", alpha=0.3)
    fig.suptitle(
        f"J / J_mpc, 100 % = {summary['reference']}\nfilled: the paper's starts, hollow: held-out; "
        "srl's agents (stars): one 300-step episode per start,\nlearning inside it; their actor also solves "
        "over the known model at every step",
        fontsize=8,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
