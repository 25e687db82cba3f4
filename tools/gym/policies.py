"""srl's agents as policies of an ordinary ``obs -> action -> env.step`` loop (docs/gym.md).

:class:`SrlPolicy` is one of srl's agents (``mpc``, ``rlq``, ``rlqv``, ``rlqv+``:
common/math/agents.py) with its learner: the actor and the local critic that ``srl run`` builds
(:func:`common.config.assembly.build_actor`, :func:`common.config.assembly.local_critic`).
:meth:`SrlPolicy.act` is one step of the paper's Algorithm 1 as :func:`common.math.loop.run_algorithm1`
runs it, without the plant: the actor's solve from the observed state with the weights the
critic holds (line 4), then the transition ``(s_k, u_k, c_k)`` to the critic, which fits and
hands back the weights of step ``k + 1`` (line 6). The critic learns from ``c_k = delta r(s_k,
u_k)``, which the agent computes from what it saw and did: the environment's reward is
``-c_k``, the same number (tools/gym/envs.py). So the loop (docs/gym.md)

    obs, _ = env.reset(options={"start": (2.0, 2.0)})
    policy.reset()
    for _ in range(300):
        obs, reward, terminated, truncated, _ = env.step(policy.act(obs))

on ``srl/Unicycle-v0`` is ``srl run --start 2,2`` step for step, bit for bit (tests/test_gym.py). Like
``srl run``, every episode learns from the initial weights: call :meth:`SrlPolicy.reset` when
the environment resets (a fresh critic and no plan). Act on the environment's own ``(v, omega)``
actions, not through :func:`tools.gym.envs.normalized_actions`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from common.config.assembly import build_actor, local_critic
from common.config.settings import Settings, with_method
from common.math.actor_problem import ActorStep
from common.math.agents import agent_row, learns
from common.math.critic import Sample
from common.math.features import stage_cost

FloatArray = NDArray[np.float64]


def policy_settings(settings: Settings | None, agent: str, horizon: int, method: str = "robot") -> Settings:
    """``settings`` (default: the packaged srl.toml and ``SRL_*``) with this agent and horizon;
    ``method = "paper"``: the paper's method exactly (no arrival rule, no wheel-speed box, the
    critics as fitted: ``METHODS``' row, as ``srl experiment paper`` runs it), ``"robot"``: the
    ``[actor]`` settings as configured (as ``srl run``). Raises ValueError for an unknown agent or
    method, or a horizon the actor refuses."""
    agent_row(agent)  # an unknown agent: one line naming the known ones
    chosen = with_method(settings if settings is not None else Settings.load(), method, agent=agent, horizon=horizon)
    return Settings.model_validate(chosen.model_dump())  # the horizon is the user's: validated


class SrlPolicy:
    """An srl agent that acts on observations of srl's environments and learns online (module
    docstring). ``settings``: those of the environment (``env.unwrapped.settings``) so that the
    actor's model, limits and cost are the task's; ``learn = False`` keeps the initial critics."""

    def __init__(
        self,
        agent: str = "rlqv",
        horizon: int = 12,
        settings: Settings | None = None,
        method: str = "robot",
        learn: bool = True,
    ) -> None:
        self.settings = policy_settings(settings, agent, horizon, method)
        self.agent, self.horizon = agent, horizon
        self.actor = build_actor(self.settings)
        self.critic = local_critic(self.settings, learn=learn and learns(agent))
        self.delta = self.settings.plant.sampling_time
        self.r_diag = tuple(self.settings.r_diag)
        self.steps = 0
        self.last: ActorStep | None = None  # the newest solve: its plan, objective, status, time
        self.reset()

    def reset(self) -> None:
        """A new episode, as ``srl run`` starts one: no plan, the critics at their initial weights."""
        self.actor.reset()
        self.q_weights, self.v_weights = self.critic.reset()
        self.steps = 0
        self.last = None

    def act(self, observation: Any) -> FloatArray:
        """The action (the robot's ``(v, omega)``) for the observed state (the robot's ``(x, y,
        alpha)``; another system's whole state), after which the critic has learned from this
        step. Raises ValueError for a state that is not the system's size of finite numbers (the
        actor never solves from one)."""
        state = np.asarray(observation, dtype=np.float64)
        system = self.settings.system
        if state.shape != (system.state_dim,) or not np.all(np.isfinite(state)):
            names = ", ".join(label for label, _ in system.state_labels())
            raise ValueError(f"an observation is ({names}): {system.state_dim} finite numbers, got {state.tolist()}")
        step = self.actor.step(state, self.q_weights, self.v_weights)  # Algorithm 1, line 4
        cost = self.delta * float(stage_cost(state, step.action, self.r_diag))
        self.q_weights, self.v_weights = self.critic.record(Sample(self.steps, state, step.action, cost))  # line 6
        self.steps += 1
        self.last = step
        action: FloatArray = np.array(step.action, dtype=np.float64)
        return action

    __call__ = act
