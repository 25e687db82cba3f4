"""srl's simulated robots as Gymnasium environments (docs/gym.md).

One class, :class:`SrlEnv`, for the three plants of ``plant.model`` (common/config/srl.toml):
``ideal`` (``srl/Unicycle-v0``), ``actuator`` (``srl/TurtleBot3-v0``) and ``physics``
(``srl/TurtleBot3Physics-v0``), built by :func:`common.config.assembly.build_plant` exactly as
``srl run`` builds them. The task is the paper's parking task as ``srl run`` poses it:

* **observation**: the state the actor sees, ``s = (x, y, alpha)`` in the goal frame (the
  target is the origin with heading 0; common/math/frames.py), float64. The heading ``alpha``
  is in radians and *continuous*: never wrapped, so a robot that turned once around reports
  ``alpha + 2 pi`` (common/math/dynamics.py; the stage cost weighs ``alpha^2``, so the turns
  count). On the TurtleBot3 plants the observation is the robot's odometry (what it reports);
  ``info["true_state"]`` is where it really is.
* **action**: ``u = (v, omega)`` [m/s, rad/s] in the box ``|v| <= plant.v_max``,
  ``|omega| <= plant.omega_max`` (the TurtleBot3 Burger's limits, 0.22 m/s and 2.84 rad/s,
  for every plant). An action outside the box is clipped to it, as plant_sim clips a command
  (services/plant_sim/service.py); a non-finite one is refused with ``ValueError`` and nothing
  moves. :func:`normalized_actions` gives the ``[-1, 1]^2`` box some libraries want.
* **reward**: ``-c_k`` with ``c_k = delta r(s_k, u_k)``, srl's stage cost
  (:func:`common.math.features.stage_cost`, ``R = diag(cost.r_diag)``) on the observed state and
  the applied (clipped) action, as Algorithm 1 scores it (common/math/loop.py); the return of an
  episode is ``-J``. ``info["cost"]`` is ``c_k``.
* **episode**: ``delta = plant.sampling_time`` (0.1 s) per step, ``round(episode.duration /
  delta)`` steps (300), then ``truncated`` (a time limit, not a terminal state: the task goes on
  at the target); never ``terminated``.
* **start**: drawn by a :class:`StartDistribution` at every reset (the paper's grid, the held-out
  grid of ``srl experiment paper``, uniform in a disc, or given starts), each turned away from
  the target as the paper's are; ``reset(options={"start": (x, y[, alpha])})`` sets one.
  ``reset(seed=...)`` seeds the draw, so an episode is reproducible: the plants themselves are
  deterministic (the actuator model's slip stream restarts from ``actuator.seed`` at every reset).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, Final

import gymnasium
import numpy as np
from gymnasium import spaces
from gymnasium.wrappers import RescaleAction
from numpy.typing import NDArray

from common.config.assembly import build_plant
from common.config.settings import Settings, start_state
from common.math.dynamics import Plant
from common.math.features import stage_cost
from common.math.systems import SYSTEMS, gymnasium_id, system_row
from tools.experiment.grid import STARTS, make_starts

FloatArray = NDArray[np.float64]
# env id -> plant.model
ENV_MODELS: Final[dict[str, str]] = {
    "srl/Unicycle-v0": "ideal",
    "srl/TurtleBot3-v0": "actuator",
    "srl/TurtleBot3Physics-v0": "physics",
}


def system_envs() -> dict[str, str]:
    """env id -> system, for every row of common/math/systems.py but the robot's (whose ids are
    :data:`ENV_MODELS`), built in or registered when asked."""
    return {gymnasium_id(name): name for name, row in SYSTEMS.items() if not row.wheeled}


START_KINDS: Final[tuple[str, ...]] = (*STARTS, "disc")


class StartDistribution:
    """Where episodes start: ``paper`` (the paper's ``grid x grid`` lattice over ``[-extent,
    extent]^2``), ``held-out`` (one seeded start in each cell of that square, ``seed``), both as
    ``srl experiment paper`` makes them (tools/experiment/grid.py) and drawn uniformly among
    them; ``disc`` (uniform in the disc of radius ``extent`` around the target); or a sequence of
    starts ``(x, y)`` / ``(x, y, alpha)`` drawn uniformly. A start given as ``(x, y)`` heads away
    from the target (``alpha = atan2(y, x)``, the paper's)."""

    def __init__(
        self, starts: str | Sequence[Sequence[float]] = "paper", grid: int = 5, extent: float = 2.0, seed: int = 0
    ) -> None:
        if not (math.isfinite(extent) and extent > 0):
            raise ValueError(f"extent must be a positive number of metres, got {extent}")
        self.extent = float(extent)
        self.kind = starts if isinstance(starts, str) else "given"
        if isinstance(starts, str):
            if starts not in START_KINDS:
                raise ValueError(f"unknown starts {starts!r}; choose one of {', '.join(START_KINDS)} or give a list")
            points = [] if starts == "disc" else [(s.x, s.y, s.alpha) for s in make_starts(starts, grid, extent, seed)]
        else:
            points = [tuple(start_state(list(start))) for start in starts]
            if not points:
                raise ValueError("a list of starts needs at least one start")
        self.points: FloatArray = np.array(points, dtype=float).reshape(-1, 3)

    def given(self, start: Sequence[float]) -> FloatArray:
        """A start the caller gives: ``(x, y)`` (heading away from the target) or ``(x, y, alpha)``."""
        return start_state(list(start))

    def draw(self, rng: np.random.Generator) -> FloatArray:
        """One start ``(x, y, alpha)``, drawn with ``rng``."""
        if self.kind == "disc":
            radius = self.extent * math.sqrt(float(rng.uniform()))  # uniform in area
            angle = float(rng.uniform(0.0, 2.0 * math.pi))
            return start_state((radius * math.cos(angle), radius * math.sin(angle)))
        return self.points[int(rng.integers(len(self.points)))].copy()


class SystemStarts:
    """Where the episodes of a system other than the robot start: ``"box"``, drawn uniformly in its
    row's start box (:meth:`common.math.systems.System.draw_start`), or a sequence of whole states
    drawn uniformly."""

    def __init__(self, system: str, starts: str | Sequence[Sequence[float]] = "box") -> None:
        self.system = system_row(system)
        self.kind = starts if isinstance(starts, str) else "given"
        if isinstance(starts, str):
            if starts not in ("box", "paper"):  # "paper": SrlEnv's default, the robot's grid: here the box
                raise ValueError(f"starts of system {system}: 'box' or a list of its states, got {starts!r}")
            self.points: FloatArray = np.zeros((0, self.system.state_dim))
        else:
            self.points = np.array([self.given(start) for start in starts], dtype=float).reshape(
                -1, self.system.state_dim
            )
            if not len(self.points):
                raise ValueError("a list of starts needs at least one start")

    def given(self, start: Sequence[float]) -> FloatArray:
        """A whole state of the system, finite; ValueError (one line) otherwise."""
        state = np.asarray(start, dtype=float)
        if state.shape != (self.system.state_dim,) or not np.all(np.isfinite(state)):
            raise ValueError(f"a start is {self.system.state_dim} finite numbers ({', '.join(self.system.states)})")
        return state

    def draw(self, rng: np.random.Generator) -> FloatArray:
        if self.kind == "given":
            return self.points[int(rng.integers(len(self.points)))].copy()
        return self.system.draw_start(rng)


def env_settings(settings: Settings | None, model: str, system: str = "unicycle") -> Settings:
    """``settings`` (default: the packaged srl.toml and ``SRL_*``) with ``plant.model = model`` and
    ``plant.system = system`` (an id's own, whatever ``SRL_PLANT__SYSTEM`` says)."""
    base = settings if settings is not None else Settings.load()
    data = base.model_dump()
    data["plant"]["model"], data["plant"]["system"] = model, system
    if base.plant.system != system:  # the start and cost of another system are not this one's
        data["episode"]["start"], data["cost"]["r_diag"] = (), ()
    return Settings.model_validate(data)


def action_box(settings: Settings) -> spaces.Box[np.float64]:
    """The held action within its box (the robot's ``(v, omega)`` limits), float64 (unrounded)."""
    high = np.array(settings.action_max, dtype=np.float64)
    return spaces.Box[np.float64](low=-high, high=high, dtype=np.float64)


def observation_box(dim: int = 3) -> spaces.Box[np.float64]:
    """The state (the robot's ``(x, y, alpha)``): unbounded (the heading is continuous), float64."""
    return spaces.Box[np.float64](low=-np.inf, high=np.inf, shape=(dim,), dtype=np.float64)


def checked_action(action: Any, box: spaces.Box[np.float64]) -> FloatArray:
    """``action`` as the robot applies it: two finite numbers clipped to ``box``. Raises
    ValueError for another shape or a non-finite value (no NaN reaches a robot)."""
    u = np.asarray(action, dtype=np.float64)
    if u.shape != box.shape:
        raise ValueError(f"an action is of shape {box.shape} (the robot's (v, omega)), got shape {u.shape}")
    if not np.all(np.isfinite(u)):
        raise ValueError(f"action {u.tolist()} is not finite; nothing was applied")
    clipped: FloatArray = np.clip(u, box.low, box.high)
    return clipped


class SrlEnv(gymnasium.Env[FloatArray, FloatArray]):
    """One simulated robot parking at the origin (module docstring). ``plant``: another
    :class:`common.math.dynamics.Plant` of the same robot (tools/gym/zenoh_env.py passes the
    lockstep plant_sim's); by default the in-process plant of ``model``."""

    metadata: dict[str, Any] = {"render_modes": []}  # noqa: RUF012 - gymnasium's class attribute

    def __init__(
        self,
        model: str = "ideal",
        starts: str | Sequence[Sequence[float]] = "paper",
        grid: int = 5,
        extent: float = 2.0,
        held_out_seed: int = 0,
        settings: Settings | None = None,
        plant: Plant | None = None,
        system: str = "unicycle",
    ) -> None:
        self.settings = env_settings(settings, model, system)
        self.system = system_row(system)
        self.plant: Plant = plant if plant is not None else build_plant(self.settings)
        # the robot's starts: the experiment's grids, a disc or given ones; another system's: drawn
        # in its row's start box (SystemStarts), or given
        self.starts: StartDistribution | SystemStarts = (
            StartDistribution(starts, grid, extent, held_out_seed)
            if self.system.wheeled
            else SystemStarts(system, starts)
        )
        self.delta = self.settings.plant.sampling_time
        self.max_steps = self.settings.steps
        self.r_diag = tuple(self.settings.r_diag)
        self.box = action_box(self.settings)
        self.action_space = self.box
        self.observation_space = observation_box(self.system.state_dim)
        self.state: FloatArray | None = None
        self.steps = 0

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[FloatArray, dict[str, Any]]:
        super().reset(seed=seed)
        given = (options or {}).get("start")
        start = self.starts.draw(self.np_random) if given is None else self.starts.given(given)
        self.state = np.asarray(self.plant.reset(start), dtype=np.float64)
        self.steps = 0
        return self.state.copy(), {"true_state": self._truth()}

    def step(self, action: FloatArray) -> tuple[FloatArray, float, bool, bool, dict[str, Any]]:
        if self.state is None:
            raise RuntimeError("reset the environment before its first step")
        u = checked_action(action, self.box)
        cost = self.delta * float(stage_cost(self.state, u, self.r_diag))  # c_k, as common/math/loop.py
        self.state = np.asarray(self.plant.apply(u, self.delta), dtype=np.float64)
        self.steps += 1
        truncated = self.steps >= self.max_steps
        return self.state.copy(), -cost, False, truncated, {"cost": cost, "true_state": self._truth()}

    def _truth(self) -> FloatArray | None:
        truth = self.plant.true_state
        return None if truth is None else np.asarray(truth, dtype=np.float64).copy()


def normalized_actions(env: gymnasium.Env[Any, Any]) -> RescaleAction[Any, Any]:
    """``env`` with actions in ``[-1, 1]^2``, mapped linearly onto its ``(v, omega)`` box
    (Gymnasium's :class:`~gymnasium.wrappers.RescaleAction`): what SAC and PPO implementations
    assume of a continuous action space."""
    return RescaleAction(env, min_action=np.float64(-1.0), max_action=np.float64(1.0))
