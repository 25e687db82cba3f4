"""Settings -> the math objects: the one place where the settings tree meets the pure math.

:mod:`common.math.loop` (Algorithm 1), :mod:`common.math.actor`, :mod:`common.math.critic` take numbers and
arrays; this module reads them from :class:`~common.config.settings.Settings` (built once in a
process's ``main``) and hands them over.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np

from common.config.settings import Settings
from common.contracts.summaries import EpisodeSummary, TrueView
from common.math.actor import StackedActor
from common.math.actor_problem import ActorMemory, ActorProblem
from common.math.agents import learns
from common.math.arrival import ArrivalRule, ArrivalTolerances, Docking, TurnFirst, WheelDeadband
from common.math.critic import DoubleCritic, PooledLearner
from common.math.dynamics import Plant
from common.math.localization import SIM_NOISE, SIM_SOURCES, LocalizedPlant, SimLocalization
from common.math.loop import CriticPort, Episode, ExactPlant, LocalCritic, PoolPort, run_algorithm1
from common.math.plant_models import simulated_robot
from common.math.stats import summarize
from common.math.turtlebot import RobotPlant
from common.system.jit import default_jit_cache


def arrival_tolerances(settings: Settings) -> ArrivalTolerances | None:
    """The arrival rule's tolerances, or None (``actor.arrival = false``, the paper's): also what
    the critic needs to know a robot held at rest (common.math.critic.at_rest)."""
    a = settings.actor
    if not a.arrival or not settings.system.wheeled:  # the rule parks a wheeled robot (x, y, alpha)
        return None
    return ArrivalTolerances(a.arrival_position_tolerance, a.arrival_heading_tolerance, a.arrival_hysteresis)


def arrival_rule(settings: Settings) -> ArrivalRule | None:
    """The actor's goal checker of the settings, or None (``actor.arrival = false``, the paper's)."""
    a = settings.actor
    tolerances = arrival_tolerances(settings)
    if tolerances is None:
        return None
    return ArrivalRule(
        tolerances,
        WheelDeadband(a.wheel_breakaway_speed, a.wheel_radius, a.wheel_separation, a.command_resolution),
        TurnFirst(
            a.turn_first_threshold,
            a.arrival_heading_tolerance,
            turn_rate_in_place(settings),
            settings.plant.sampling_time,
            min_distance=a.arrival_hysteresis * a.arrival_position_tolerance,
        ),
        Docking(
            a.docking_radius,
            a.docking_reversals,
            a.wheel_radius * a.wheel_speed_max if a.wheel_speed_max > 0 else settings.plant.v_max,
            turn_rate_in_place(settings),
            settings.plant.sampling_time,
            half_track=a.wheel_separation / 2.0 if a.wheel_speed_max > 0 else 0.0,
        ),
    )


def turn_rate_in_place(settings: Settings) -> float:
    """The actor's top turning rate in place [rad/s]: omega_max, and with the wheel box the wheels
    at +-wheel_speed_max (omega = 2 r w / b)."""
    a = settings.actor
    rate = settings.plant.omega_max
    if a.wheel_speed_max > 0:
        rate = min(rate, 2.0 * a.wheel_radius * a.wheel_speed_max / a.wheel_separation)
    return rate


def jit_cache_path(setting: str) -> str:
    """``actor.jit_cache``: "auto" -> ~/.cache/srl/jit (XDG), "off" -> "" (none), else the path."""
    if setting == "auto":
        return default_jit_cache()
    return "" if setting == "off" else os.path.expanduser(setting)


def build_actor(settings: Settings) -> StackedActor:
    """The actor of the settings."""
    a, p = settings.actor, settings.plant
    return StackedActor(
        ActorProblem(
            agent=a.agent,
            horizon=a.horizon,
            sampling_time=p.sampling_time,
            cost_diag=tuple(settings.r_diag),
            action_max=settings.action_max,
            predictor=a.predictor,
            solver=a.solver,
            jit=a.jit,
            jit_cache=jit_cache_path(a.jit_cache),
            max_iter=a.max_iter,
            tolerance=a.tolerance,
            mu_init=a.mu_init,
            bound_push=a.bound_push,
            wheel_speed_max=a.wheel_speed_max if settings.system.wheeled else 0.0,  # a wheeled robot's
            wheel_radius=a.wheel_radius,
            wheel_separation=a.wheel_separation,
            convex_critics=a.convex_critics,
            multistart=a.multistart,
            multistart_starts=a.multistart_starts,
            multistart_iterations=a.multistart_iterations,
            multistart_margin=a.multistart_margin,
            multistart_flips=a.multistart_flips,
            newton_iterations=a.newton_iterations,
            system=settings.plant.system,
        ),
        arrival=arrival_rule(settings),
    )


def build_plant(settings: Settings) -> ExactPlant | RobotPlant:
    """The in-process simulated plant of ``plant.model``: the system's own model (``ideal``: the exact
    unicycle, or another system's step) or the TurtleBot3."""
    p = settings.plant
    robot = simulated_robot(p.model, settings.turtlebot_params(), settings.physics_params(), np.zeros(3))
    return ExactPlant(settings.system) if robot is None else RobotPlant(robot)


def localized_plant(settings: Settings, localization: str, noise: tuple[float, float] | None = None) -> Plant:
    """The in-process simulated robot (:func:`build_plant`), its odometry corrected by a simulated
    localization (``amcl`` or ``mocap``, :data:`common.math.localization.SIM_NOISE` unless ``noise``)
    fused as the robot bridge fuses one (``bridge.pose_blend_time``); ``none``: the plant as built.
    Raises ValueError for an unknown source."""
    plant = build_plant(settings)
    if localization == "none":
        return plant
    if localization not in SIM_SOURCES:
        raise ValueError(f"a simulated localization is none, {' or '.join(SIM_SOURCES)}; got {localization!r}")
    source = SimLocalization(
        localization,
        noise=SIM_NOISE[localization] if noise is None else noise,
        blend_time=settings.bridge.pose_blend_time,
    )
    return LocalizedPlant(plant, source)


def local_critic(settings: Settings, learn: bool = True) -> LocalCritic:
    """The in-process critic learner of the settings (initial weights, beta, lambda, box, M)."""
    c = settings.critic
    return LocalCritic(
        settings.initial_q_weights(),
        settings.initial_v_weights(),
        settings.discount,
        c.ridge,
        c.bounds,
        c.replay_size,
        c.update_every,
        learn=learn,
        rest=arrival_tolerances(settings),
    )


def run_episode(
    settings: Settings,
    actor: StackedActor | None = None,
    plant: Plant | None = None,
    critic: CriticPort | None = None,
    stop: threading.Event | None = None,
) -> Episode:
    """Algorithm 1 (:func:`common.math.loop.run_algorithm1`) for ``settings.steps`` sampling intervals
    from ``settings.start_state()``; the plant of ``plant.model`` and a local critic unless given."""
    (episode,) = run_algorithm1(
        actor or build_actor(settings),
        [plant or build_plant(settings)],
        [critic or local_critic(settings, learn=learns(settings.actor.agent))],
        [settings.start_state()],
        settings.steps,
        settings.plant.sampling_time,
        tuple(settings.r_diag),
        stop=stop,
    )
    return episode


CriticLayout = Literal["per-robot", "pooled"]
CRITIC_LAYOUTS: tuple[CriticLayout, ...] = ("per-robot", "pooled")


def fleet_learners(settings: Settings, robots: int, critic: CriticLayout) -> list[PooledLearner]:
    """Robot ``i``'s learner for a fleet of ``robots``: its own pool of one (per-robot), or the one
    pool of every robot (pooled); fresh initial weights either way."""

    def pool(size: int) -> PooledLearner:
        c = settings.critic
        double = DoubleCritic(
            settings.initial_q_weights(), settings.initial_v_weights(), settings.discount, c.ridge, c.bounds
        )
        return PooledLearner(double, c.replay_size, c.update_every, robots=size)

    if critic == "pooled":
        shared = pool(robots)
        return [shared] * robots
    if critic == "per-robot":
        return [pool(1) for _ in range(robots)]
    raise ValueError(f"unknown critic layout {critic!r}; choose one of {', '.join(CRITIC_LAYOUTS)}")


def run_fleet_episode(
    settings: Settings,
    starts: Sequence[np.ndarray],
    critic: CriticLayout,
    actor: StackedActor | None = None,
    stop: threading.Event | None = None,
) -> list[Episode]:
    """A fleet from ``starts`` stepping together for ``settings.steps`` intervals, in process
    (:func:`common.math.loop.run_algorithm1` of K robots): one built actor, a memory, a plant of
    ``plant.model`` and a port to its learner per robot (per-robot or pooled critics)."""
    learn = learns(settings.actor.agent)
    ports = [
        PoolPort(learner, f"robot{i + 1}", learn)
        for i, learner in enumerate(fleet_learners(settings, len(starts), critic))
    ]
    return run_algorithm1(
        actor or build_actor(settings),
        [build_plant(settings) for _ in starts],
        ports,
        [np.asarray(start, dtype=float) for start in starts],
        settings.steps,
        settings.plant.sampling_time,
        tuple(settings.r_diag),
        memories=[ActorMemory(arrival=arrival_rule(settings)) for _ in starts],
        stop=stop,
    )


def episode_summary(episode: Episode, settings: Settings) -> dict[str, Any]:
    """The JSON-ready summary of a run (the contract of ``srl run --json``: EpisodeSummary)."""
    final = episode.final_state
    truth = true_view(episode, settings)
    return EpisodeSummary.model_validate(
        {
            "agent": episode.agent,
            "horizon": episode.horizon,
            "steps": episode.steps,
            "episode_seconds": episode.steps * settings.plant.sampling_time,
            "accumulated_cost": episode.accumulated_cost,
            "start_state": [float(c) for c in episode.states[0]],
            "final_state": [float(c) for c in final],
            "final_distance": settings.system.distance(final),
            "solve_ms": summarize(episode.solve_seconds, scale=1e3),
            "solver_failures": episode.solver_failures,
            "plant_model": settings.plant.model,
            "system": settings.plant.system,
            "truth": None if truth is None else truth.model_dump(),
            "saturated_commands": episode.saturated_commands,
            "settings": settings.as_dict(),
        }
    ).to_json_dict()


def true_view(episode: Episode, settings: Settings) -> TrueView | None:
    """Where the robot really was (None: the plant does not know, a real robot's odometry only)."""
    if not episode.truth_known:
        return None
    first, final = episode.true_states[0], episode.true_states[-1]
    cost = episode.true_accumulated_cost(settings.plant.sampling_time, tuple(settings.r_diag))
    return TrueView(
        start_state=[float(c) for c in first],
        final_state=[float(c) for c in final],
        final_distance=settings.system.distance(final),
        accumulated_cost=float(cost if cost is not None else np.nan),
    )
