"""``srl experiment paper``: the paper's section IV experiment, end to end.

A grid of starts over the ``2 extent x 2 extent`` polygon (default 5 x 5 over ``[-2, 2]^2``),
each turned away from the target (``alpha_0 = atan2(y_0, x_0)``, ``pi`` at the centre); every
agent at every horizon parks from every start with Algorithm 1 in lockstep, each RL run
learning online from the initial weights (no pretraining). The marks are the paper's
``J_agent / J_mpc * 100 %`` per start and horizon (eqs. rql, rql-v), drawn as contour plots
(figures 3-4) and summarized in a table.

Runs are spread over worker processes (spawned, so no Zenoh or CasADi state is forked). A
worker builds each ``(agent, N)`` actor once and reuses it for every run of that pair (the
solver is stateless between episodes except for the warm start, which ``reset`` clears; the
same run is bit-identical on a fresh and on a reused actor). The scheduler hands a worker
runs of the pair it already built while any are left, so the ~1 s JIT builds happen about
once per pair and worker.

Transports:

* ``inproc``: each worker runs :func:`common.config.assembly.run_episode` with the exact plant and the
  local critic, as ``srl run`` does.
* ``zenoh``: a router and, per worker, one ``srl plant-sim --mode lockstep`` and one
  ``srl critic`` process (robot id ``exp<worker>``), all on a free loopback port with
  multicast scouting off, started once and kept up across runs: the plant is reset and the
  critic starts a fresh learner per episode id. Each worker is that robot's actor: it runs
  the actor service's lockstep code (``ZenohPlant``, ``ZenohCriticPort`` with the synchronous
  critic, ``WeightsInbox``) through :func:`run_episode`, so the distributed system executes
  Algorithm 1 exactly and reproduces the inproc numbers.

Outputs (``--out``): ``runs.csv``, ``trajectories.npz``, ``config.toml`` (loadable with
``--config``) and ``settings.json``, ``summary.md`` and ``summary.json``, ``ratio_N<N>.png``
per horizon and ``trajectories.png``. Ctrl-C stops the workers and services, writes what has
finished (marked interrupted) and exits with 130.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import os
import queue
import shlex
import signal
import socket
import sys
import threading
import time
import traceback
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from common.config.settings import METHODS, PAPER_METHOD, Settings
from common.math.agents import AGENTS, PAPER_AGENTS, learns, parse_agents, parse_horizons
from tools.experiment.grid import STARTS, RunSpec, make_starts, plan_runs, run_settings
from tools.experiment.marks import PARK_TOLERANCE_M, TIE_PERCENT
from tools.experiment.report import (
    check_claims,
    git_commit,
    group_summary,
    head_to_head,
    ratio_table,
    sorted_rows,
    summary_markdown,
    toml_dumps,
    write_runs_csv,
    write_trajectories,
)

log = logging.getLogger(__name__)

DEFAULT_HORIZONS = (12, 6)
EXIT_INTERRUPTED = 130
PEER_MODE, PEER_LISTEN = "peer", ["tcp/127.0.0.1:0"]  # the zenoh transport's sessions (see transport_for)
OUTPUT_FILES = (
    "runs.csv",
    "trajectories.npz",
    "config.toml",
    "settings.json",
    "summary.md",
    "summary.json",
    "trajectories.png",
)


class ExperimentError(RuntimeError):
    """A run or a service failed: the experiment stops (partial results are still written)."""


@dataclass
class WorkerConfig:
    slot: int
    base: dict[str, Any]  # Settings.model_dump(mode="json") of the resolved base settings
    transport: str
    robot: str = ""


class _InprocRunner:
    def run(self, settings: Settings, actor: Any) -> tuple[Any, dict[str, Any]]:
        from common.config.assembly import build_plant, local_critic, run_episode

        critic = local_critic(settings, learn=learns(settings.actor.agent))
        return run_episode(settings, actor=actor, plant=build_plant(settings), critic=critic), {}

    def close(self) -> None:
        pass


class _ZenohRunner:
    """This worker as the actor of robot ``config.robot``, the actor service's lockstep code."""

    def __init__(self, base: Settings) -> None:
        from common.contracts.keys import WEIGHTS
        from common.net.transport import Bus
        from services.actor.ports import WeightsInbox

        self.robot = base.transport.robot
        self.bus = Bus.open(base.transport, "actor")
        self.inbox = WeightsInbox(base, self.bus)  # initial weights depend on cost and delta only
        self.bus.subscribe(WEIGHTS, WEIGHTS.key(self.robot), self.inbox.offer)
        self.bus.declare_alive(self.robot)
        self.bus.wait_alive(self.robot, "plant", timeout=60.0)
        self.bus.wait_alive(self.robot, "critic", timeout=60.0)
        self.episode_id = 0
        self.port: Any = None

    def _port(self, settings: Settings) -> Any:
        """The critic port for this episode: ONE per worker, so one transition publisher
        (a cached, heartbeating advanced publisher) for the worker's life, as the actor
        service has; only the per-episode state is reset."""
        from services.actor.ports import ZenohCriticPort

        if self.port is None:
            self.port = ZenohCriticPort(settings, self.bus, self.inbox, self.episode_id, sync=True)
        self.port.new_episode(settings, self.episode_id)  # the port's own public reset
        return self.port

    def run(self, settings: Settings, actor: Any) -> tuple[Any, dict[str, Any]]:
        from common.config.assembly import local_critic, run_episode
        from services.actor.ports import ZenohPlant, new_episode_id

        # Episode ids must increase (the critic starts a fresh learner on a newer one).
        self.episode_id = max(new_episode_id(), self.episode_id + 1)
        plant = ZenohPlant(settings, self.bus, self.episode_id)
        if settings.actor.agent == "mpc":
            # MPC has no critic: nothing to send to the learner (inproc fits nothing either).
            critic = local_critic(settings, learn=False)
            return run_episode(settings, actor=actor, plant=plant, critic=critic), {}
        port = self._port(settings)
        episode = run_episode(settings, actor=actor, plant=plant, critic=port)
        return episode, {"critic_timeouts": port.timeouts, "max_staleness_steps": int(max(port.staleness, default=0))}

    def close(self) -> None:
        self.bus.close()


def _run_one(
    runner: Any, actors: dict[tuple[str, int], Any], base: dict[str, Any], spec: RunSpec, slot: int
) -> dict[str, Any]:
    from common.config.assembly import build_actor
    from common.math.parking import parking
    from common.math.stats import summarize

    settings = run_settings(base, spec)
    actor = actors.get(spec.group)
    if actor is None:
        actor = actors[spec.group] = build_actor(settings)
    started = time.perf_counter()
    episode, extra = runner.run(settings, actor)
    wall = time.perf_counter() - started
    final = episode.final_state
    solve = summarize(episode.solve_seconds, scale=1e3)
    # "at rest" beside "parked" (issue 21): no chatter over the last 10 s, on the true states where
    # the plant knows them
    rest = parking(
        episode.true_states if episode.truth_known else episode.states, episode.actions, settings.plant.sampling_time
    )
    row = {
        "run_id": spec.run_id,
        "agent": spec.agent,
        "horizon": spec.horizon,
        "start_index": spec.start.index,
        "start_x": spec.start.x,
        "start_y": spec.start.y,
        "start_alpha": spec.start.alpha,
        "accumulated_cost": episode.accumulated_cost,
        "final_x": float(final[0]),
        "final_y": float(final[1]),
        "final_alpha": float(final[2]),
        "final_distance": float(np.hypot(final[0], final[1])),
        "at_rest": int(rest.at_rest),
        "last_span_m": rest.span,
        "sign_changes": rest.sign_changes,
        "steps": episode.steps,
        "solver_failures": episode.solver_failures,
        "solve_ms_median": solve["median"],
        "solve_ms_p99": solve["p99"],
        "solve_ms_max": solve["max"],
        "wall_seconds": wall,
        "worker": slot,
        "critic_timeouts": extra.get("critic_timeouts", 0),
        "max_staleness_steps": extra.get("max_staleness_steps", 0),
    }
    arrays = {
        "states": np.asarray(episode.states, dtype=float),
        "actions": np.asarray(episode.actions, dtype=float),
        "costs": np.asarray(episode.costs, dtype=float),
    }
    return {"row": row, "arrays": arrays}


def _worker_main(config: WorkerConfig, tasks: Any, results: Any) -> None:
    """A worker process: build actors lazily, run what the scheduler sends, until ``None``."""
    # Ctrl-C is the parent's business (it stops us by pid); SIGTERM ends us through
    # SystemExit so that ``finally`` blocks (the runner's close) and atexit still run.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    logging.basicConfig(
        level=logging.WARNING,
        format=f"%(asctime)s %(levelname)s [worker {config.slot}] %(name)s: %(message)s",
        stream=sys.stderr,
    )
    # A late weight message of a finished episode is refused by design (its episode id), which
    # is expected between episodes here and not worth a warning.
    logging.getLogger("common.net.transport").setLevel(logging.ERROR)
    runner: Any = None
    try:
        base = Settings.model_validate(config.base)
        runner = _ZenohRunner(base) if config.transport == "zenoh" else _InprocRunner()
        actors: dict[tuple[str, int], Any] = {}
        results.put(("ready", config.slot, None))
        while (spec := tasks.get()) is not None:
            try:
                outcome = _run_one(runner, actors, config.base, spec, config.slot)
            except Exception:
                results.put(("error", config.slot, f"run {spec.run_id}: {traceback.format_exc()}"))
                return
            results.put(("done", config.slot, outcome))
    except Exception:
        results.put(("error", config.slot, f"worker {config.slot}: {traceback.format_exc()}"))
    finally:
        if runner is not None:
            runner.close()


class Scheduler:
    """Hand each worker runs of the ``(agent, N)`` it already built, while any are left;
    else the pair with most runs left that no other worker is on (else the largest)."""

    def __init__(self, specs: Iterable[RunSpec]) -> None:
        self.pending: dict[tuple[str, int], deque[RunSpec]] = {}
        for spec in specs:
            self.pending.setdefault(spec.group, deque()).append(spec)
        self.current: dict[int, tuple[str, int] | None] = {}

    def next_for(self, slot: int) -> RunSpec | None:
        group = self.current.get(slot)
        if group is None or not self.pending.get(group):
            left = [g for g, q in self.pending.items() if q]
            if not left:
                self.current[slot] = None
                return None
            taken = {g for s, g in self.current.items() if s != slot}
            free = [g for g in left if g not in taken]
            group = max(free or left, key=lambda g: len(self.pending[g]))
            self.current[slot] = group
        return self.pending[group].popleft()


# -- options ----------------------------------------------------------------------------
@dataclass
class ExperimentOptions:
    grid: int = 5
    extent: float = 2.0
    starts: str = "paper"
    seed: int = 0
    agents: tuple[str, ...] = PAPER_AGENTS
    horizons: tuple[int, ...] = DEFAULT_HORIZONS
    transport: str = "inproc"
    workers: int = 0  # 0 = every core this process may use
    out: Path = field(default_factory=lambda: Path("out"))
    plots: bool = True
    progress: bool = True
    command: str = ""
    record: Path | None = None  # one MCAP file of every run (tools/recording/record.py)

    def worker_count(self, runs: int) -> int:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        return max(1, min(self.workers or cores, runs))


# -- the experiment ---------------------------------------------------------------------
def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class _Services:
    """Router + one plant_sim (lockstep) and one critic per worker, kept up across runs."""

    def __init__(self, config_path: Path, base: Settings, workers: int) -> None:
        from tools.launch.up import Supervisor

        self.endpoint = f"tcp/127.0.0.1:{_free_port()}"
        self.robots = [f"exp{slot}" for slot in range(workers)]
        # No critic checkpoint (see experiment_settings), even if the environment names one:
        # SRL_ variables outrank the --config file the services read.
        env = {
            **os.environ,
            "PYTHONUNBUFFERED": "1",
            "SRL_CRITIC__CHECKPOINT": "",
            "SRL_TRANSPORT__MODE": PEER_MODE,
            "SRL_TRANSPORT__LISTEN": json.dumps(PEER_LISTEN),
        }
        self.supervisor = Supervisor([], env, quiet=True)
        self.common = ["--config", str(config_path), "--router", self.endpoint]
        self.base = base

    def transport_for(self, robot: str) -> dict[str, Any]:
        # Peers that listen on a free loopback port and learn each other from the router
        # (gossip, no multicast): the worker's queries, transitions and weights go straight to
        # its plant and critic instead of through the router. Measured on the 3 x 3 grid:
        # 12-20 % less wall time than client mode, the router's CPU a third.
        return {
            "router": self.endpoint,
            "robot": robot,
            "multicast_scouting": False,
            "connect": [],
            "mode": PEER_MODE,
            "listen": PEER_LISTEN,
        }

    def start(self) -> None:
        from tools.launch.up import ServiceDiedError

        try:
            self._start()
        except ServiceDiedError as error:
            raise ExperimentError(f"{error}: {' | '.join(error.tail)}") from error
        except TimeoutError as error:
            raise ExperimentError(str(error)) from error

    def _start(self) -> None:
        from tools.launch.up import alive_probe, router_reachable

        sup = self.supervisor
        sup.spawn("router", ["router", *self.common, "--robot", self.robots[0]])
        router_settings = self._settings(self.robots[0])
        sup.wait_for("router", lambda: router_reachable(router_settings), timeout=30)
        for robot in self.robots:
            sup.spawn(f"plant-{robot}", ["plant-sim", "--mode", "lockstep", *self.common, "--robot", robot])
            # each critic learns from its own worker's robot only (critic.robots; "*" would make
            # every critic fit every robot's transitions, W times the work)
            sup.spawn(f"critic-{robot}", ["critic", *self.common, "--robot", robot], {"SRL_CRITIC__ROBOTS": robot})
        for robot in self.robots:
            settings = self._settings(robot)
            sup.wait_for(f"plant of {robot}", alive_probe(settings, "plant"), timeout=60)
            sup.wait_for(f"critic of {robot}", alive_probe(settings, "critic"), timeout=60)

    def _settings(self, robot: str) -> Settings:
        data = self.base.model_dump(mode="json")
        data["transport"].update(self.transport_for(robot))
        return Settings.model_validate(data)

    def check(self) -> None:
        from tools.launch.up import ServiceDiedError

        try:
            self.supervisor.check()
        except ServiceDiedError as error:
            raise ExperimentError(f"{error}: {' | '.join(error.tail)}") from error

    def pids(self) -> dict[str, int]:
        return {name: child.process.pid for name, child in self.supervisor.children.items()}

    def stop(self) -> dict[str, int | None]:
        self.supervisor.stop_all()  # SIGINT by process group (= pid), SIGKILL after the grace
        return {name: child.process.returncode for name, child in self.supervisor.children.items()}

    def resources(self) -> dict[str, Any]:
        """CPU seconds and peak RSS each service reported when it stopped (its last JSON line)."""
        report: dict[str, Any] = {}
        for name, child in self.supervisor.children.items():
            summary = child.summary() or {}
            report[name] = {
                **summary.get("resources", {}),
                **(
                    {"transitions": summary["transitions_received"], "fit_ms": summary.get("fit_ms")}
                    if "transitions_received" in summary
                    else {}
                ),
            }
        return report


@dataclass
class Outcome:
    rows: list[dict[str, Any]]
    arrays: dict[str, dict[str, np.ndarray]]
    planned: int
    interrupted: bool
    error: str | None
    wall_seconds: float
    setup_seconds: float
    workers: int
    services: dict[str, Any]
    worker_pids: list[int]


def run_grid(options: ExperimentOptions, base: Settings, specs: list[RunSpec], config_path: Path) -> Outcome:
    """Run every spec over the workers; on Ctrl-C or a failure return what finished."""
    import multiprocessing

    workers = options.worker_count(len(specs))
    context = multiprocessing.get_context("spawn")  # never fork a process that holds Zenoh threads
    results = context.Queue()
    task_queues = [context.Queue() for _ in range(workers)]
    processes: list[Any] = []
    services: _Services | None = None
    services_info: dict[str, Any] = {}
    done: list[dict[str, Any]] = []
    arrays: dict[str, dict[str, np.ndarray]] = {}
    interrupted = False
    error: str | None = None
    started = time.perf_counter()
    setup_seconds = 0.0
    progress = _progress(options.progress)
    previous_sigterm = _set_signal(signal.SIGTERM, _sigterm_as_interrupt)
    try:
        with progress:
            task = progress.add_task("starting workers", total=len(specs))
            base_data = base.model_dump(mode="json")
            if options.transport == "zenoh":
                progress.update(task, description="starting router, plant_sim and critic services")
                services = _Services(config_path, base, workers)
                services.start()
                services_info["endpoint"] = services.endpoint
            setup_seconds = time.perf_counter() - started
            for slot in range(workers):
                data = json.loads(json.dumps(base_data))
                robot = ""
                if services is not None:
                    robot = services.robots[slot]
                    data["transport"].update(services.transport_for(robot))
                process = context.Process(
                    target=_worker_main,
                    args=(WorkerConfig(slot, data, options.transport, robot), task_queues[slot], results),
                    name=f"srl-experiment-worker-{slot}",
                    daemon=True,
                )
                # Started with SIGINT ignored, a spawned interpreter never installs its own
                # KeyboardInterrupt handler: a Ctrl-C while it still imports cannot kill it.
                handler = _set_signal(signal.SIGINT, signal.SIG_IGN)
                try:
                    process.start()
                finally:
                    _set_signal(signal.SIGINT, handler)
                processes.append(process)
            scheduler = Scheduler(specs)
            released: set[int] = set()  # workers told to finish (None sent): they may exit
            progress.update(task, description="building actors")
            while len(done) < len(specs):
                try:
                    kind, slot, payload = results.get(timeout=0.5)
                except queue.Empty:
                    for index, process in enumerate(processes):
                        if process.exitcode is not None and index not in released:
                            raise ExperimentError(
                                f"worker {index} (pid {process.pid}) exited with code {process.exitcode}"
                            ) from None
                    if services is not None:
                        services.check()
                    continue
                if kind == "error":
                    raise ExperimentError(str(payload))
                if kind == "done":
                    row = payload["row"]
                    done.append(row)
                    arrays[row["run_id"]] = payload["arrays"]
                    progress.update(task, advance=1, description=f"{row['run_id']}  J = {row['accumulated_cost']:.2f}")
                    log.info(
                        "run %s done (%d/%d): J = %.4f", row["run_id"], len(done), len(specs), row["accumulated_cost"]
                    )
                spec = scheduler.next_for(slot)
                task_queues[slot].put(spec)
                if spec is None:
                    released.add(slot)
    except KeyboardInterrupt:
        interrupted = True
    except ExperimentError as failure:
        error = str(failure)
    finally:
        # A second Ctrl-C must not cut the cleanup short (it is bounded: a few seconds).
        previous_sigint = _set_signal(signal.SIGINT, signal.SIG_IGN)
        try:
            _stop_workers(processes, task_queues)
            if services is not None:
                services_info["pids"] = services.pids()
                services_info["exit_codes"] = services.stop()
                services_info["resources"] = services.resources()
        finally:
            _set_signal(signal.SIGINT, previous_sigint)
            _set_signal(signal.SIGTERM, previous_sigterm)
    return Outcome(
        done,
        arrays,
        len(specs),
        interrupted,
        error,
        time.perf_counter() - started,
        setup_seconds,
        workers,
        services_info,
        [p.pid for p in processes],
    )


def _sigterm_as_interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def _set_signal(signum: int, handler: Any) -> Any:
    """``signal.signal`` where Python allows it (the main thread); elsewhere a no-op."""
    if handler is None or threading.current_thread() is not threading.main_thread():
        return None
    return signal.signal(signum, handler)


def _stop_workers(processes: list[Any], task_queues: list[Any]) -> None:
    """Ask idle workers to finish, end busy ones by pid (SIGTERM, then SIGKILL)."""
    for task_queue in task_queues:
        with contextlib.suppress(Exception):
            task_queue.put(None)
    deadline = time.monotonic() + 0.5
    for process in processes:
        process.join(timeout=max(0.0, deadline - time.monotonic()))
    for process in processes:
        if process.is_alive():
            process.terminate()
    deadline = time.monotonic() + 5.0
    for process in processes:
        process.join(timeout=max(0.1, deadline - time.monotonic()))
        if process.is_alive():
            log.warning("worker pid %d did not stop: killing it", process.pid)
            process.kill()
            process.join(timeout=5.0)
    for task_queue in task_queues:
        task_queue.cancel_join_thread()


def _progress(enabled: bool) -> Any:
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    return Progress(
        TextColumn("[bold]srl experiment[/bold]"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("runs"),
        TimeElapsedColumn(),
        TextColumn("ETA"),
        TimeRemainingColumn(),
        TextColumn("{task.description}"),
        console=Console(stderr=True),
        disable=not enabled,
        transient=False,
    )


def write_outputs(out: Path, options: ExperimentOptions, base: Settings, outcome: Outcome) -> dict[str, Any]:
    rows = sorted_rows(outcome.rows, options.agents, options.horizons)
    ratios = ratio_table(rows)
    groups = group_summary(rows, options.agents, options.horizons, ratios)
    duels = [d for h in options.horizons if (d := head_to_head(rows, "rlqv", "rlq", h)) is not None]
    write_runs_csv(out / "runs.csv", rows, ratios)
    write_trajectories(out / "trajectories.npz", rows, outcome.arrays)
    summary: dict[str, Any] = {
        "experiment": {
            "starts": options.starts,
            "grid": options.grid,
            "extent": options.extent,
            "seed": options.seed,
            "agents": list(options.agents),
            "horizons": list(options.horizons),
            "transport": options.transport,
            "duration": base.episode.duration,
            "steps": base.steps,
            "command": options.command,
        },
        "status": "interrupted" if outcome.interrupted else ("failed" if outcome.error else "complete"),
        "interrupted": outcome.interrupted,
        "error": outcome.error,
        "runs_planned": outcome.planned,
        "runs_completed": len(rows),
        "wall_seconds": outcome.wall_seconds,
        "setup_seconds": outcome.setup_seconds,
        "workers": outcome.workers,
        "cpu_count": os.cpu_count(),
        "git": git_commit(),
        "finished_at": datetime.now(UTC).isoformat(timespec="seconds"),
        "park_tolerance_m": PARK_TOLERANCE_M,
        "tie_percent": TIE_PERCENT,
        "groups": groups,
        "head_to_head": duels,
        "claims": check_claims(groups, rows, options.horizons) if not outcome.interrupted else [],
        "ratios": [
            {k: t[k] for k in ("run_id", "agent", "horizon", "start_index", "start_x", "start_y", "ratio_percent")}
            for t in ratios
        ],
        "services": outcome.services,
        "worker_pids": outcome.worker_pids,
        "settings": base.as_dict(),
        "plots": [],
    }
    if options.plots and rows:
        from tools.experiment.plots import plot_ratio_contours, plot_trajectory_overview

        for horizon in options.horizons:
            path = out / f"ratio_N{horizon}.png"
            if plot_ratio_contours([t for t in ratios if t["horizon"] == horizon], horizon, options.extent, path):
                summary["plots"].append(path.name)
        plot_trajectory_overview(
            rows,
            outcome.arrays,
            options.agents,
            options.horizons,
            options.extent,
            out / "trajectories.png",
            PARK_TOLERANCE_M,
        )
        summary["plots"].append("trajectories.png")
    (out / "summary.json").write_text(json.dumps(summary, indent=2, allow_nan=True) + "\n")
    (out / "summary.md").write_text(summary_markdown(summary))
    return summary


def record_experiment(recorder: Any, rows: list[dict[str, Any]], arrays: dict[str, dict[str, np.ndarray]]) -> None:
    """Every run that finished into one recording: run ``<run_id>`` is the robot ``/<run_id>/...``
    (ROS-named: ``rlqv_N12_s000``), and every run starts at the same moment, so a player shows the
    whole grid parking at once. States, actions and costs as trajectories.npz holds them (the
    experiment keeps no per-step weights or solve times: those topics are absent)."""
    from common.math.loop import Episode
    from tools.recording.record import record_episode

    origin_ns = time.time_ns()
    try:
        for row in rows:
            run = arrays[row["run_id"]]
            episode = Episode(
                agent=row["agent"],
                horizon=row["horizon"],
                states=list(run["states"]),
                actions=list(run["actions"]),
                costs=[float(c) for c in run["costs"]],
            )
            record_episode(recorder, episode, row["run_id"], origin_ns)
    finally:
        recorder.close()


def prepare_output(out: Path, base: Settings) -> Path:
    """Create ``out``, remove our own stale files, write the resolved config; return its path."""
    out.mkdir(parents=True, exist_ok=True)
    for name in OUTPUT_FILES:
        (out / name).unlink(missing_ok=True)
    for stale in out.glob("ratio_N*.png"):
        stale.unlink()
    config_path = out / "config.toml"
    config_path.write_text(
        "# Every setting of this experiment, resolved (packaged srl.toml < --config < SRL_ env < flags).\n"
        "# Runs override only actor.agent, actor.horizon and episode.start. Reuse: --config config.toml\n"
        + toml_dumps(base.model_dump(mode="json"))
    )
    # The file must reproduce these settings exactly (as the experiment uses them: an SRL_
    # environment variable naming a checkpoint still applies on load, and is switched off again).
    reloaded, expected = experiment_settings(Settings.load(config_path)), experiment_settings(base)
    if reloaded != expected:
        differ = [k for k, v in expected.model_dump().items() if reloaded.model_dump()[k] != v]
        raise ExperimentError(f"{config_path} does not reproduce the resolved settings (sections {differ})")
    (out / "settings.json").write_text(json.dumps(base.as_dict(), indent=2) + "\n")
    return config_path


def experiment_settings(base: Settings) -> Settings:
    """The base settings as the experiment uses them: no critic checkpoint file.

    Every episode starts from the initial weights by design, and a checkpoint per robot id
    (``exp<worker>``) would be shared by concurrent experiments and cost a synced write per step.
    """
    data = base.model_dump(mode="json")
    if data["critic"].get("checkpoint"):
        data["critic"]["checkpoint"] = ""
        return Settings.model_validate(data)
    return base


def run_experiment(options: ExperimentOptions, base: Settings) -> tuple[int, dict[str, Any]]:
    """Everything ``srl experiment paper`` does after parsing: (exit code, summary)."""
    base = experiment_settings(base)
    starts = make_starts(options.starts, options.grid, options.extent, options.seed)
    specs = plan_runs(starts, options.agents, options.horizons)
    recorder = None
    if options.record is not None:  # created now: a bad path fails before the first run
        from tools.recording.record import episode_recorder

        recorder = episode_recorder(
            options.record,
            base.plant.sampling_time,
            {"source": "srl experiment", "command": options.command, "horizons": list(options.horizons)},
        )
    config_path = prepare_output(options.out, base)
    try:
        outcome = run_grid(options, base, specs, config_path)
    except BaseException:
        if recorder is not None:
            recorder.close()  # a valid, empty recording: never a torn file
        raise
    summary = write_outputs(options.out, options, base, outcome)
    if recorder is not None:
        record_experiment(recorder, sorted_rows(outcome.rows, options.agents, options.horizons), outcome.arrays)
        summary["recording"] = str(options.record)
    if outcome.interrupted:
        return EXIT_INTERRUPTED, summary
    return (1 if outcome.error else 0), summary


# -- command line -----------------------------------------------------------------------
def add_experiment_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "which",
        choices=["paper", "fleet"],
        help="paper: section IV, the grid of starts and cost ratios; fleet: the same starts as ONE fleet in "
        "lockstep, per-robot vs pooled critics (issue 16)",
    )
    parser.add_argument("--grid", type=int, default=5, help="K: K x K starts (default 5: the paper's 25)")
    parser.add_argument("--extent", type=float, default=2.0, help="starts over [-E, E]^2 [m] (default 2)")
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
        choices=["ideal", "actuator", "physics"],
        default="ideal",
        help="the simulated robot (plant.model): ideal, the paper's exact unicycle; actuator, the TurtleBot3 "
        "model; physics, the MuJoCo TurtleBot3; J is on what the robot reported, true J beside it (default: ideal)",
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
    parser.add_argument(
        "--record",
        type=Path,
        metavar="FILE.mcap",
        help="one MCAP recording (rosbag2 layout) of every run, each run a robot /<run_id>/..., all "
        "starting together (default: none)",
    )


def _load_settings(args: argparse.Namespace) -> Settings:
    from pydantic import ValidationError

    overrides: dict[str, Any] = json.loads(json.dumps(PAPER_METHOD)) if args.method == "paper" else {}
    if args.duration is not None:
        overrides["episode"] = {"duration": args.duration}
    overrides["plant"] = {"model": args.plant}
    try:
        return Settings.load(args.config, **overrides)
    except ValidationError as error:
        problems = "; ".join(f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in error.errors())
        raise ValueError(f"invalid settings: {problems}") from error
    except FileNotFoundError as error:
        raise ValueError(str(error)) from error


def cmd_experiment(args: argparse.Namespace) -> int:
    try:
        if args.grid < 1:
            raise ValueError(f"--grid must be >= 1, got {args.grid}")
        if not (math.isfinite(args.extent) and args.extent > 0):
            raise ValueError(f"--extent must be a positive number, got {args.extent}")
        if args.workers < 0:
            raise ValueError(f"--workers must be >= 0 (0 = every core), got {args.workers}")
        options = ExperimentOptions(
            grid=args.grid,
            extent=args.extent,
            starts=args.starts,
            seed=args.seed,
            agents=parse_agents(args.agents),
            horizons=parse_horizons(args.horizons),
            transport=args.transport,
            workers=args.workers,
            out=args.out or Path("out") / f"paper-{datetime.now(UTC):%Y%m%d-%H%M%S}",
            plots=not args.no_plots,
            progress=not args.no_progress,
            record=args.record,
        )
        options.command = "srl experiment " + " ".join(shlex.quote(a) for a in _argv_of(args))
        base = _load_settings(args)
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


def _argv_of(args: argparse.Namespace) -> list[str]:
    """A re-runnable command line for the summary (what was given, defaults spelled out)."""
    argv = [
        args.which,
        f"--grid={args.grid}",
        f"--extent={args.extent:g}",
        f"--starts={args.starts}",
        f"--seed={args.seed}",
        f"--agents={args.agents}",
        f"--horizons={args.horizons}",
        f"--transport={args.transport}",
        f"--method={args.method}",
        f"--plant={args.plant}",
    ]
    if args.duration is not None:
        argv.append(f"--duration={args.duration:g}")
    if args.config is not None:
        argv.append(f"--config={args.config}")
    if args.workers:
        argv.append(f"--workers={args.workers}")
    if args.record is not None:
        argv.append(f"--record={args.record}")
    return argv
