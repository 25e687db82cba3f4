"""The experiment's worker processes: each builds an ``(agent, N)`` actor once and runs the
scheduler's runs of that pair in process (``inproc``) or as the actor of its own robot through the
services (``zenoh``, tools/experiment/services.py)."""

from __future__ import annotations

import logging
import math
import signal
import sys
import time
import traceback
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.config.settings import Settings
from common.math.agents import learns
from common.math.parking import WINDOW_S
from common.process.plugins import load_from_environment
from tools.experiment.grid import RunSpec, run_settings


@dataclass
class WorkerConfig:
    slot: int
    base: dict[str, Any]  # Settings.model_dump(mode="json") of the resolved base settings
    transport: str
    robot: str = ""
    localization: str = "none"  # inproc: common.config.assembly.localized_plant


class InprocRunner:
    def __init__(self, localization: str = "none") -> None:
        self.localization = localization  # the pose the actor sees: none (odometry), amcl or mocap

    def run(self, settings: Settings, actor: Any) -> tuple[Any, dict[str, Any]]:
        from common.config.assembly import local_critic, localized_plant, run_episode

        critic = local_critic(settings, learn=learns(settings.actor.agent))
        plant = localized_plant(settings, self.localization)
        return run_episode(settings, actor=actor, plant=plant, critic=critic), {}

    def close(self) -> None:
        pass


class ZenohRunner:
    """This worker as the actor of robot ``config.robot``, the actor service's lockstep code."""

    def __init__(self, base: Settings) -> None:
        from common.net.transport import Bus
        from services.actor.ports import WeightsInbox

        self.robot = base.transport.robot
        self.bus = Bus.open(base.transport, "actor")
        self.inbox = WeightsInbox(base, self.bus)  # initial weights depend on cost and delta only
        weights = base.wire.WEIGHTS  # the robot's, or another system's (common/contracts/wire.py)
        self.bus.subscribe(weights, weights.key(self.robot), self.inbox.offer)
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
        if not learns(settings.actor.agent):
            # MPC has no critic: nothing to send to the learner (inproc fits nothing either).
            critic = local_critic(settings, learn=False)
            return run_episode(settings, actor=actor, plant=plant, critic=critic), {}
        port = self._port(settings)
        episode = run_episode(settings, actor=actor, plant=plant, critic=port)
        return episode, {"critic_timeouts": port.timeouts, "max_staleness_steps": int(max(port.staleness, default=0))}

    def close(self) -> None:
        self.bus.close()


def run_one(
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
    final, system = episode.final_state, settings.system
    solve = summarize(episode.solve_seconds, scale=1e3)
    # "at rest" beside "parked": no chatter over the last 10 s, on the true states where
    # the plant knows them (another system: held within its tolerance over the last 10 s)
    path = episode.true_states if episode.truth_known else episode.states
    rest = parking(path, episode.actions, settings.plant.sampling_time) if system.wheeled else held(path, settings)
    first = [*(float(c) for c in final[:3]), *[math.nan] * (3 - min(3, len(final)))]  # runs.csv's columns
    row = {
        "run_id": spec.run_id,
        "agent": spec.agent,
        "horizon": spec.horizon,
        "start_index": spec.start.index,
        "start_x": spec.start.x,
        "start_y": spec.start.y,
        "start_alpha": spec.start.alpha,
        "accumulated_cost": episode.accumulated_cost,
        "final_x": first[0],
        "final_y": first[1],
        "final_alpha": first[2],
        "final_distance": system.distance(final),
        # the truth beside what the robot reported, where the plant knows it (equal on the ideal plant)
        "true_accumulated_cost": episode.true_accumulated_cost(settings.plant.sampling_time, tuple(settings.r_diag)),
        "true_final_distance": system.distance(episode.true_states[-1]) if episode.truth_known else None,
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


@dataclass(frozen=True)
class Held:
    """A system other than the robot "at rest" (the row's ``at_rest``, ``last_span_m``,
    ``sign_changes`` as :class:`~common.math.parking.Parking` gives a robot's)."""

    at_rest: bool
    span: float  # the largest distance to the goal over the last window
    sign_changes: int = 0


def held(states: list[np.ndarray], settings: Settings) -> Held:
    """At rest: over the last :data:`~common.math.parking.WINDOW_S` seconds every state within the
    system's ``stabilized`` distance of its goal."""
    system = settings.system
    last = states[-max(1, round(WINDOW_S / settings.plant.sampling_time)) :]
    span = max(system.distance(state) for state in last)
    return Held(span < system.stabilized, span)


def worker_main(config: WorkerConfig, tasks: Any, results: Any) -> None:
    """A worker process: build actors lazily, run what the scheduler sends, until ``None``."""
    # Ctrl-C is the parent's business (it stops us by pid); SIGTERM ends us through
    # SystemExit so that ``finally`` blocks (the runner's close) and atexit still run.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    load_from_environment()  # a spawned interpreter: the parent's plugins' rows (SRL_PLUGINS), loaded again
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
        runner = ZenohRunner(base) if config.transport == "zenoh" else InprocRunner(config.localization)
        actors: dict[tuple[str, int], Any] = {}
        results.put(("ready", config.slot, None))
        while (spec := tasks.get()) is not None:
            try:
                outcome = run_one(runner, actors, config.base, spec, config.slot)
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
