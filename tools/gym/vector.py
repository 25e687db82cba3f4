"""K robots in one ``step`` call: a ``gymnasium.vector.VectorEnv`` (docs/gym.md).

``gymnasium.make_vec("srl/Unicycle-v0", num_envs=K)`` builds :class:`SrlVectorEnv` (each id's
vector entry point, tools/gym/__init__.py). Robot ``i`` is :class:`tools.gym.envs.SrlEnv` of the
same arguments, reset with seed ``seed + i`` (Gymnasium's convention for ``reset(seed=seed)`` of
a vector environment): the same observations, rewards and ends, bit for bit (tests/test_gym.py).
The ideal unicycle of all K robots is one numpy step, the plant host's
(:func:`common.math.dynamics.exact_steps`, services/plant_sim/host.py), and the K stage costs one
vectorized :func:`common.math.features.stage_cost`; the TurtleBot3 plants step one robot after
the other (their wheels are per robot). An episode that ended is reset at the robot's next
``step`` call, whose action it ignores (Gymnasium's default next-step autoreset,
``metadata["autoreset_mode"]``): that step returns the new start with reward 0.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from common.config.assembly import build_plant
from common.config.settings import Settings, start_state
from common.math.dynamics import Plant, exact_steps
from common.math.features import stage_cost
from common.math.plant_models import plant_model_row
from tools.gym.envs import FloatArray, StartDistribution, action_box, env_settings, observation_box

MAX_ROBOTS = 100_000  # far beyond what one core steps usefully (python -m tools.gym.bench)


class SrlVectorEnv(VectorEnv[FloatArray, FloatArray, FloatArray]):
    """``num_envs`` robots of ``plant.model = model`` (module docstring); the other arguments
    are :class:`tools.gym.envs.SrlEnv`'s."""

    metadata: dict[str, Any] = {"render_modes": [], "autoreset_mode": AutoresetMode.NEXT_STEP}  # noqa: RUF012 - gymnasium's

    def __init__(
        self,
        num_envs: int = 1,
        model: str = "ideal",
        starts: str | Sequence[Sequence[float]] = "paper",
        grid: int = 5,
        extent: float = 2.0,
        held_out_seed: int = 0,
        settings: Settings | None = None,
    ) -> None:
        if not 1 <= num_envs <= MAX_ROBOTS:
            raise ValueError(f"num_envs must be 1 to {MAX_ROBOTS}, got {num_envs}")
        self.num_envs = num_envs
        self.settings = env_settings(settings, model)
        self.starts = StartDistribution(starts, grid, extent, held_out_seed)
        self.delta = self.settings.plant.sampling_time
        self.max_steps = self.settings.steps
        self.r_diag = tuple(self.settings.r_diag)
        self.single_action_space = action_box(self.settings)
        self.single_observation_space = observation_box()
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.low, self.high = self.single_action_space.low, self.single_action_space.high
        self.ideal = plant_model_row(self.settings.plant.model).exact
        self.plants: list[Plant] = [] if self.ideal else [build_plant(self.settings) for _ in range(num_envs)]
        self.rngs = [seeding.np_random(None)[0] for _ in range(num_envs)]
        self.states: FloatArray = np.zeros((num_envs, 3))
        self.steps = np.zeros(num_envs, dtype=np.int64)
        self.ended = np.zeros(num_envs, dtype=np.bool_)  # reset at the robot's next step
        self.started = False

    def reset(
        self, *, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[FloatArray, dict[str, Any]]:
        """Every robot at a new start; ``seed``: robot ``i`` draws with seed ``seed + i`` (or the
        list's ``i``-th); ``options = {"starts": [...]}``: one start per robot instead."""
        seeds = [seed + i for i in range(self.num_envs)] if isinstance(seed, int) else seed
        if seeds is not None:
            if len(seeds) != self.num_envs:
                raise ValueError(f"{len(seeds)} seeds for {self.num_envs} robots")
            for i, value in enumerate(seeds):
                if value is not None:
                    self.rngs[i] = seeding.np_random(value)[0]
        given = (options or {}).get("starts")
        if given is not None and len(given) != self.num_envs:
            raise ValueError(f"{len(given)} starts for {self.num_envs} robots")
        for i in range(self.num_envs):
            self._reset_one(i, None if given is None else start_state(given[i]))
        self.ended[:] = False
        self.started = True
        return self.states.copy(), {}

    def _reset_one(self, i: int, start: FloatArray | None) -> None:
        state = self.starts.draw(self.rngs[i]) if start is None else start
        self.states[i] = state if self.ideal else self.plants[i].reset(state)
        self.steps[i] = 0

    def step(self, actions: FloatArray) -> tuple[FloatArray, FloatArray, Any, Any, dict[str, Any]]:
        if not self.started:
            raise RuntimeError("reset the environment before its first step")
        u = np.asarray(actions, dtype=np.float64)
        if u.shape != (self.num_envs, 2):
            raise ValueError(f"actions are (v, omega) per robot, shape ({self.num_envs}, 2); got {u.shape}")
        if not np.all(np.isfinite(u)):
            raise ValueError("an action is not finite; nothing was applied")
        u = np.clip(u, self.low, self.high)
        # c_k of every robot: the same operations as the single environment's, element-wise
        costs = self.delta * stage_cost(self.states.T, u.T, self.r_diag)
        restarting = self.ended.copy()
        if self.ideal:
            self.states = np.where(restarting[:, None], self.states, exact_steps(self.states, u, self.delta))
        else:
            for i in np.flatnonzero(~restarting):
                self.states[i] = self.plants[i].apply(u[i], self.delta)
        self.steps += 1
        for i in np.flatnonzero(restarting):
            self._reset_one(int(i), None)
        rewards: FloatArray = np.where(restarting, 0.0, -costs)
        truncated = ~restarting & (self.steps >= self.max_steps)
        terminated = np.zeros(self.num_envs, dtype=np.bool_)
        self.ended = truncated.copy()
        costs = np.where(restarting, 0.0, costs)
        info = {"cost": costs, "_cost": ~restarting}
        return self.states.copy(), rewards, terminated, truncated, info
