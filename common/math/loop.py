"""The paper's Algorithm 1 (actor step, apply to the plant, critic update, repeat).

The loop is written against two small interfaces so that the same code runs in one process
(``transport = inproc``: the exact plant and a local critic) and through the distributed
services (the Zenoh plant queryable and the off-board critic): the distributed system runs
the algorithm itself, not an approximation of it.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from common.math.actor import StackedActor
from common.math.actor_problem import ActorCounters, ActorMemory
from common.math.arrival import ArrivalTolerances
from common.math.critic import DoubleCritic, PooledLearner, Sample, at_rest
from common.math.dynamics import Plant
from common.math.features import stage_cost
from common.math.systems import UNICYCLE, System

log = logging.getLogger(__name__)


class CriticPort(Protocol):
    """Where one robot's samples go and its critic weights come from: ``reset`` starts an
    episode, ``record`` takes a sample (and returns the weights after it), ``weights`` are what
    the robot acts on at its next step (a pooled critic may have fitted since its record, on
    another robot's)."""

    last_residuals: tuple[float, float]  # the TD residuals (Q, V) of a fit after the last record; nan: none

    def reset(self) -> tuple[np.ndarray, np.ndarray]: ...

    def record(self, sample: Sample) -> tuple[np.ndarray, np.ndarray]: ...

    def weights(self) -> tuple[np.ndarray, np.ndarray]: ...


class ExactPlant:
    """A simulated system in process (the unicycle by default: the paper's plant): its exact
    sample-and-hold where known, else its fixed-step integration (:meth:`System.step`).

    It reports the true state and has no wheels to saturate."""

    def __init__(self, system: System = UNICYCLE) -> None:
        self.system = system
        self.state = np.zeros(system.state_dim)

    def reset(self, state: np.ndarray) -> np.ndarray:
        self.state = np.asarray(state, dtype=float).copy()
        return self.state.copy()

    def apply(self, action: np.ndarray, duration: float) -> np.ndarray:
        self.state = self.system.step(self.state, action, duration)
        return self.state.copy()

    @property
    def true_state(self) -> np.ndarray:
        return self.state.copy()

    @property
    def saturated_commands(self) -> int:
        return 0


class LocalCritic:
    """The critic learner in process: replay of size M and a TD fit every ``update_every``.

    One robot's learner is a pool of one (:class:`~common.math.critic.PooledLearner`): the per-robot
    and the pooled fleet critic are one code. Built from settings by
    :func:`common.config.assembly.local_critic`; here only numbers and arrays."""

    ROBOT = "robot"  # the pool's one stream

    def __init__(
        self,
        q_init: np.ndarray,
        v_init: np.ndarray,
        discount: float,
        ridge: float,
        bounds: tuple[float, float] | None,
        replay_size: int,
        update_every: int,
        learn: bool = True,
        rest: ArrivalTolerances | None = None,
    ) -> None:
        self.q_init, self.v_init = q_init, v_init
        self.discount, self.ridge, self.bounds = discount, ridge, bounds
        self.replay_size, self.update_every = replay_size, update_every
        self.learn = learn
        self.rest = rest  # the arrival rule's tolerances: no fit on a robot held at rest (critic.at_rest)
        self.pool = self._fresh_pool()
        self.updates = 0
        self.last_residuals = (float("nan"), float("nan"))  # of the newest fit (Q, V)

    def _fresh_pool(self) -> PooledLearner:
        critic = DoubleCritic(self.q_init, self.v_init, self.discount, self.ridge, self.bounds)
        return PooledLearner(critic, self.replay_size, self.update_every, robots=1)

    @property
    def critic(self) -> DoubleCritic:
        return self.pool.critic

    def reset(self) -> tuple[np.ndarray, np.ndarray]:
        self.pool = self._fresh_pool()
        self.updates = 0
        return self.critic.q_weights, self.critic.v_weights

    def record(self, sample: Sample) -> tuple[np.ndarray, np.ndarray]:
        previous = self.pool.replay.stream(self.ROBOT).newest
        due = self.pool.record(self.ROBOT, sample)
        self.last_residuals = (float("nan"), float("nan"))
        if self.learn and due and not at_rest(previous, sample, self.rest):
            update = self.pool.fit()
            self.last_residuals = (float(update.q.residual), float(update.v.residual))
            self.updates += 1
        return self.critic.q_weights, self.critic.v_weights

    def weights(self) -> tuple[np.ndarray, np.ndarray]:
        return self.critic.q_weights, self.critic.v_weights


class PoolPort:
    """One robot's port to a fleet's learner (:class:`~common.math.critic.PooledLearner`): its
    own pool of one (per-robot critics) or the pool every robot of the fleet shares, which fits
    once the fleet's step is in (``record`` of the step's last robot) and every robot then acts
    on that fit. Unlike :class:`LocalCritic` it fits a robot held at rest too (a fleet's rows
    are what ``srl experiment fleet`` measured with it)."""

    def __init__(self, learner: PooledLearner, robot: str, learn: bool = True) -> None:
        self.learner, self.robot, self.learn = learner, robot, learn
        self.last_residuals = (float("nan"), float("nan"))

    def reset(self) -> tuple[np.ndarray, np.ndarray]:
        return self.weights()

    def record(self, sample: Sample) -> tuple[np.ndarray, np.ndarray]:
        self.last_residuals = (float("nan"), float("nan"))
        if self.learner.record(self.robot, sample) and self.learn:
            update = self.learner.fit()
            self.last_residuals = (float(update.q.residual), float(update.v.residual))
        return self.weights()

    def weights(self) -> tuple[np.ndarray, np.ndarray]:
        return self.learner.critic.q_weights, self.learner.critic.v_weights


@dataclass
class Episode:
    """Everything one run produced; ``states`` has ``steps + 1`` rows (start included).

    ``states`` are what the robot reported (the actor's view); ``true_states`` where it really
    was, as many rows, or empty when the plant does not know (a real robot: odometry only)."""

    agent: str
    horizon: int
    states: list[np.ndarray] = field(default_factory=list)
    true_states: list[np.ndarray] = field(default_factory=list)
    saturated_commands: int | None = None
    actions: list[np.ndarray] = field(default_factory=list)
    costs: list[float] = field(default_factory=list)
    solve_seconds: list[float] = field(default_factory=list)  # the steps that solved (not held at rest)
    held: list[bool] = field(default_factory=list)  # per step: held by the arrival rule (no solve)
    solver_failures: int = 0
    # the learning, one row per step (bounded by the episode's length): the weights the actor
    # used at step k, and the TD residuals (Q, V) of the fit after step k (nan: no fit / unknown)
    q_weights: list[np.ndarray] = field(default_factory=list)
    v_weights: list[np.ndarray] = field(default_factory=list)
    td_residuals: list[tuple[float, float]] = field(default_factory=list)

    @property
    def steps(self) -> int:
        return len(self.actions)

    @property
    def accumulated_cost(self) -> float:
        """``J = sum_k c_k`` with ``c_k = delta r(s_k, u_k)``: the score of every agent."""
        return float(np.sum(self.costs))

    @property
    def final_state(self) -> np.ndarray:
        return self.states[-1]

    @property
    def truth_known(self) -> bool:
        return len(self.true_states) == len(self.states) > 0

    def true_accumulated_cost(self, sampling_time: float, r_diag: tuple[float, ...]) -> float | None:
        """``J`` on the true states with the actions applied (None: the truth is not known)."""
        if not self.truth_known:
            return None
        return float(
            sum(sampling_time * stage_cost(s, u, r_diag) for s, u in zip(self.true_states, self.actions, strict=False))
        )


def run_algorithm1(
    actor: StackedActor,
    plants: Sequence[Plant],
    critics: Sequence[CriticPort],
    starts: Sequence[np.ndarray],
    steps: int,
    sampling_time: float,
    r_diag: tuple[float, ...],
    memories: Sequence[ActorMemory] | None = None,
    stop: threading.Event | None = None,
) -> list[Episode]:
    """Algorithm 1 (the paper's lines 4-6) for ``steps`` sampling intervals, for K robots stepping
    together (K = 1: one robot): at every step each robot in turn acts with the weights its
    critic port holds (line 4), is moved (line 5) and records its transition (line 6).

    ``memories``: robot ``i``'s share of the one built ``actor``
    (:meth:`~common.math.actor.StackedActor.swap_memory`: a fleet acts bit for bit as one actor per
    robot); None (one robot only): the actor's own memory, reset first. ``critics[i]`` is robot
    ``i``'s port: a :class:`LocalCritic`, the off-board critic over Zenoh
    (services/actor/ports.py), or a :class:`PoolPort` of a fleet's learner.

    ``stop`` (set by a signal handler) ends the episode between two steps: a signal never
    interrupts a solve or a fit half way (CasADi callbacks cannot take an exception).
    :func:`common.config.assembly.run_episode` and ``run_fleet_episode`` run it from settings."""
    count = len(starts)
    if not (len(plants) == len(critics) == count and (memories is None or len(memories) == count)):
        raise ValueError(
            f"{count} starts need as many plants, critics and memories "
            f"(got {len(plants)}, {len(critics)}, {'none' if memories is None else len(memories)})"
        )
    if memories is None and count != 1:
        raise ValueError("robots that share an actor need a memory each")
    delta = sampling_time
    agent, horizon = actor.problem.agent, actor.problem.horizon
    if memories is None:
        actor.reset()
    held = None if memories is None else list(memories)
    failures = [c.failures for c in _counters(actor, held)]
    for critic in critics:
        critic.reset()
    states = [plant.reset(start) for plant, start in zip(plants, starts, strict=True)]
    episodes = [Episode(agent=agent, horizon=horizon, states=[state]) for state in states]
    for episode, plant in zip(episodes, plants, strict=True):
        _record_truth(episode, plant)
    log.info("episode started: %s, N = %d, %d steps, %d robots", agent, horizon, steps, count)
    for k in range(steps):
        if stop is not None and stop.is_set():
            break
        for i in range(count):
            critic, episode, state, plant = critics[i], episodes[i], states[i], plants[i]
            q_weights, v_weights = critic.weights()
            episode.q_weights.append(np.array(q_weights, dtype=float))
            episode.v_weights.append(np.array(v_weights, dtype=float))
            if held is None:
                step = actor.step(state, q_weights, v_weights)  # line 4: update actor
            else:
                own = actor.swap_memory(held[i])
                try:
                    step = actor.step(state, q_weights, v_weights)
                finally:
                    held[i] = actor.swap_memory(own)
            cost = delta * float(stage_cost(state, step.action, r_diag))
            next_state = plant.apply(step.action, delta)  # line 5: apply u_1
            critic.record(Sample(k, state, step.action, cost))  # line 6: update critic
            episode.td_residuals.append(critic.last_residuals)
            episode.actions.append(step.action)
            episode.costs.append(cost)
            held_at_rest = step.status == "arrived"
            episode.held.append(held_at_rest)
            if not held_at_rest:  # held by the arrival rule: no solve to time
                episode.solve_seconds.append(step.solve_seconds)
            episode.states.append(next_state)
            _record_truth(episode, plant)
            states[i] = next_state
    for episode, plant, counters, before in zip(episodes, plants, _counters(actor, held), failures, strict=True):
        episode.solver_failures = counters.failures - before
        episode.saturated_commands = getattr(plant, "saturated_commands", None)
    return episodes


def _counters(actor: StackedActor, memories: list[ActorMemory] | None) -> list[ActorCounters]:
    """Each robot's actor counters: the actor's own (one robot, no memories), else its memory's."""
    return [actor.counters] if memories is None else [memory.counters for memory in memories]


def _record_truth(episode: Episode, plant: Plant) -> None:
    """The true state beside the reported one, while the plant knows it (all or nothing)."""
    truth = getattr(plant, "true_state", None)
    if truth is None:
        episode.true_states.clear()
    elif len(episode.true_states) == len(episode.states) - 1:
        episode.true_states.append(np.asarray(truth, dtype=float).copy())
