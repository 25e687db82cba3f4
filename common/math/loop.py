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
from common.math.actor_problem import ActorMemory
from common.math.arrival import ArrivalTolerances
from common.math.critic import DoubleCritic, PooledLearner, Sample, at_rest
from common.math.dynamics import Plant, exact_step
from common.math.features import stage_cost

log = logging.getLogger(__name__)


class CriticPort(Protocol):
    """Where samples go and critic weights come from."""

    def reset(self) -> tuple[np.ndarray, np.ndarray]: ...
    def record(self, sample: Sample) -> tuple[np.ndarray, np.ndarray]: ...


class ExactPlant:
    """The simulated robot in process: exact sample-and-hold integration (the paper's plant).

    It reports the true state and has no wheels to saturate."""

    def __init__(self) -> None:
        self.state = np.zeros(3)

    def reset(self, state: np.ndarray) -> np.ndarray:
        self.state = np.asarray(state, dtype=float).copy()
        return self.state.copy()

    def apply(self, action: np.ndarray, duration: float) -> np.ndarray:
        self.state = exact_step(self.state, action, duration)
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
    solve_seconds: list[float] = field(default_factory=list)
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
    plant: Plant,
    critic: CriticPort,
    start: np.ndarray,
    steps: int,
    sampling_time: float,
    r_diag: tuple[float, ...],
    stop: threading.Event | None = None,
) -> Episode:
    """Algorithm 1 for ``steps`` sampling intervals from ``start`` (the paper's lines 4-6).

    ``stop`` (set by a signal handler) ends the episode between two steps: a signal never
    interrupts a solve or a fit half way (CasADi callbacks cannot take an exception).
    :func:`common.config.assembly.run_episode` runs it from settings."""
    delta = sampling_time
    agent, horizon = actor.problem.agent, actor.problem.horizon
    actor.reset()
    failures_before = actor.counters.failures
    q_weights, v_weights = critic.reset()
    state = plant.reset(start)
    episode = Episode(agent=agent, horizon=horizon, states=[state])
    _record_truth(episode, plant)
    log.info("episode started: %s, N = %d, %d steps", agent, horizon, steps)
    for k in range(steps):
        if stop is not None and stop.is_set():
            break
        episode.q_weights.append(np.array(q_weights, dtype=float))
        episode.v_weights.append(np.array(v_weights, dtype=float))
        step = actor.step(state, q_weights, v_weights)  # line 4: update actor
        cost = delta * float(stage_cost(state, step.action, r_diag))
        next_state = plant.apply(step.action, delta)  # line 5: apply u_1
        q_weights, v_weights = critic.record(Sample(k, state, step.action, cost))  # line 6
        episode.td_residuals.append(getattr(critic, "last_residuals", (float("nan"), float("nan"))))
        episode.actions.append(step.action)
        episode.costs.append(cost)
        if step.status != "arrived":  # held by the arrival rule: no solve to time
            episode.solve_seconds.append(step.solve_seconds)
        episode.states.append(next_state)
        _record_truth(episode, plant)
        state = next_state
    episode.solver_failures = actor.counters.failures - failures_before
    episode.saturated_commands = getattr(plant, "saturated_commands", None)
    return episode


def _record_truth(episode: Episode, plant: Plant) -> None:
    """The true state beside the reported one, while the plant knows it (all or nothing)."""
    truth = getattr(plant, "true_state", None)
    if truth is None:
        episode.true_states.clear()
    elif len(episode.true_states) == len(episode.states) - 1:
        episode.true_states.append(np.asarray(truth, dtype=float).copy())


def run_fleet_lockstep(
    actor: StackedActor,
    memories: Sequence[ActorMemory],
    plants: Sequence[Plant],
    learners: Sequence[PooledLearner],
    starts: Sequence[np.ndarray],
    steps: int,
    sampling_time: float,
    r_diag: tuple[float, ...],
    learn: bool = True,
    stop: threading.Event | None = None,
) -> list[Episode]:
    """Algorithm 1 for a fleet stepping together, in one process: at every step each
    robot in turn acts with the weights its learner holds, is moved and records its transition.

    ``learners[i]`` is robot ``i``'s: per-robot critics are K pools of one, a pooled critic is the
    SAME :class:`~common.math.critic.PooledLearner` for every robot (it fits once the fleet's step is
    in, and every robot acts on that fit at the next step). ``memories[i]`` is robot ``i``'s
    share of the one built ``actor`` (:meth:`~common.math.actor.StackedActor.swap_memory`: the fleet
    acts bit for bit as one actor per robot). With per-robot learners each robot's episode is
    exactly :func:`run_algorithm1`'s from its start."""
    count = len(starts)
    if not (len(memories) == len(plants) == len(learners) == count):
        raise ValueError(
            f"a fleet of {count} starts needs as many memories, plants and learners "
            f"(got {len(memories)}, {len(plants)}, {len(learners)})"
        )
    delta = sampling_time
    agent, horizon = actor.problem.agent, actor.problem.horizon
    robots = [f"robot{i + 1}" for i in range(count)]
    held = list(memories)
    states = [plant.reset(start) for plant, start in zip(plants, starts, strict=True)]
    episodes = [Episode(agent=agent, horizon=horizon, states=[state]) for state in states]
    failures = [memory.counters.failures for memory in held]
    for episode, plant in zip(episodes, plants, strict=True):
        _record_truth(episode, plant)
    for k in range(steps):
        if stop is not None and stop.is_set():
            break
        for i in range(count):
            learner, episode, state = learners[i], episodes[i], states[i]
            q_weights, v_weights = learner.critic.q_weights, learner.critic.v_weights
            episode.q_weights.append(np.array(q_weights, dtype=float))
            episode.v_weights.append(np.array(v_weights, dtype=float))
            own = actor.swap_memory(held[i])
            try:
                step = actor.step(state, q_weights, v_weights)
            finally:
                held[i] = actor.swap_memory(own)
            cost = delta * float(stage_cost(state, step.action, r_diag))
            next_state = plants[i].apply(step.action, delta)
            residuals = (float("nan"), float("nan"))
            if learner.record(robots[i], Sample(k, state, step.action, cost)) and learn:
                update = learner.fit()
                residuals = (float(update.q.residual), float(update.v.residual))
            episode.td_residuals.append(residuals)
            episode.actions.append(step.action)
            episode.costs.append(cost)
            if step.status != "arrived":
                episode.solve_seconds.append(step.solve_seconds)
            episode.states.append(next_state)
            _record_truth(episode, plants[i])
            states[i] = next_state
    for i, episode in enumerate(episodes):
        episode.solver_failures = held[i].counters.failures - failures[i]
        episode.saturated_commands = getattr(plants[i], "saturated_commands", None)
    return episodes
