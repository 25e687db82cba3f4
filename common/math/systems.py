"""The sampled systems srl controls, one row each: everything the method needs to know of a plant
(docs/concepts.md): its state and action (names, so dimensions), the model ``ds/dt = f(s, u)``
(numpy or CasADi, one code), the box of the held actions, the stage cost's default weights, the
default start, and what "stabilized" means. The goal is the origin of the state: a system is
written in its goal's coordinates, as the paper writes the robot in the goal frame.

The actor's problem (common/math/actor_problem.py ``ActorProblem.system``) is built from its row:
the predictor rolls ``f`` out, the decision variables are ``action_dim`` numbers a stage, the
critics' features are sized by the state and action (``q_features``, ``v_features``). The plant
steps the row's exact sample-and-hold where it is known (``exact_step``), else ``substeps`` RK4
steps over the interval (global error O((delta / substeps)^4); :meth:`System.step`).

A new system is a row: :func:`register_system` from the user's own file, or a row of
:data:`SYSTEMS` for a built-in one. ``unicycle`` is the paper's robot (common/math/dynamics.py).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.math.dynamics import FloatArray, exact_step, is_symbolic, unicycle_rhs
from common.math.features import feature_count
from common.math.integrators import Rhs, rk4_substeps
from common.math.rows import add_row

ExactStep = Callable[[FloatArray, FloatArray, float], FloatArray]  # (s, u, duration) -> s'


def vector(*entries: Any) -> Any:
    """A column of ``entries``: CasADi's ``vertcat`` when one is a CasADi symbol, else a numpy
    array. A system's ``rhs`` returns ``vector(...)``, so one function serves the actor's
    predictor (CasADi) and the plant (numpy)."""
    if any(is_symbolic(entry) for entry in entries):
        import casadi as ca

        return ca.vertcat(*entries)
    return np.array(entries, dtype=float)


def state_norm(state: FloatArray) -> float:
    """The Euclidean norm of the state: how far from the goal (the origin) a system is."""
    return float(np.linalg.norm(state))


def position_distance(state: FloatArray) -> float:
    """A wheeled robot's distance to its target: ``hypot(x, y)``, whatever its heading."""
    return float(math.hypot(state[0], state[1]))


@dataclass(frozen=True)
class System:
    """One sampled system (a row of :data:`SYSTEMS`).

    ``states`` and ``actions``: the entries' names with units, ``("x [m]", ...)``: their counts are
    the dimensions. ``rhs``: ``f(s, u)``, numpy arrays or CasADi symbols. ``action_max``: the box
    ``|u_i| <= action_max[i]`` (a wheeled robot's come from the settings' ``plant.v_max`` and
    ``plant.omega_max``). ``cost_diag``: the default ``diag(R)`` of the stage cost ``r(s, u) =
    (s, u)^T R (s, u)``. ``start``: the default start. ``exact_step``: the exact sample-and-hold,
    where known. ``wheeled``: the actions are a differential drive's ``(v,
    omega)`` and the state its pose ``(x, y, alpha)``: the wheel box, the arrival rule and the robot
    bridge serve only such a system. ``distance``: how far a state is from the goal, in the system's
    own terms; ``stabilized``: the distance under which it is."""

    what: str
    states: tuple[str, ...]
    actions: tuple[str, ...]
    rhs: Rhs
    action_max: tuple[float, ...]
    cost_diag: tuple[float, ...]
    start: tuple[float, ...]
    exact_step: ExactStep | None = None
    wheeled: bool = False
    distance: Callable[[FloatArray], float] = state_norm
    stabilized: float = 0.05
    substeps: int = 10

    def __post_init__(self) -> None:
        n, m = len(self.states), len(self.actions)
        if n < 1 or m < 1:
            raise ValueError(f"a system has at least one state and one action, got {n} and {m}")
        if len(self.action_max) != m or not all(math.isfinite(b) and b > 0 for b in self.action_max):
            raise ValueError(f"action_max: {m} positive numbers (one per action), got {self.action_max}")
        if len(self.cost_diag) != n + m or not all(math.isfinite(c) and c >= 0 for c in self.cost_diag):
            raise ValueError(f"cost_diag: {n + m} finite numbers >= 0 (states, then actions), got {self.cost_diag}")
        if len(self.start) != n or not all(math.isfinite(c) for c in self.start):
            raise ValueError(f"start: {n} finite numbers, got {self.start}")
        if self.wheeled and (n, m) != (3, 2):
            raise ValueError(f"a wheeled system's state is (x, y, alpha) and its action (v, omega), got {n} and {m}")
        if not (math.isfinite(self.stabilized) and self.stabilized > 0):
            raise ValueError(f"stabilized: a positive distance, got {self.stabilized}")
        if not 1 <= self.substeps <= 1000:
            raise ValueError(f"substeps: 1 to 1000 RK4 steps per held interval, got {self.substeps}")

    @property
    def state_dim(self) -> int:
        return len(self.states)

    @property
    def action_dim(self) -> int:
        return len(self.actions)

    @property
    def q_features(self) -> int:
        """phi_Q(s, u)'s length (common/math/features.py): 15 for the unicycle."""
        return feature_count(self.state_dim + self.action_dim)

    @property
    def v_features(self) -> int:
        """phi_V(s)'s length: 6 for the unicycle."""
        return feature_count(self.state_dim)

    def step(self, state: FloatArray, action: FloatArray, duration: float) -> FloatArray:
        """The state after ``duration`` seconds of ``action`` held from ``state``: exact where known,
        else ``substeps`` RK4 steps."""
        state, action = np.asarray(state, dtype=float), np.asarray(action, dtype=float)
        if self.exact_step is not None:
            return np.asarray(self.exact_step(state, action, duration), dtype=float)
        return np.asarray(rk4_substeps(self.rhs, state, action, duration, self.substeps), dtype=float)


UNICYCLE = System(
    what="the paper's three-wheel robot, kinematic: a unicycle driven by (v, omega), eq. (3w-robot)",
    states=("x [m]", "y [m]", "alpha [rad]"),
    actions=("v [m/s]", "omega [rad/s]"),
    rhs=unicycle_rhs,
    action_max=(0.22, 2.84),  # the TurtleBot3 Burger's; the settings' plant.v_max, plant.omega_max
    cost_diag=(1.0, 10.0, 1.0, 0.01, 0.01),
    start=(2.0, 2.0, math.atan2(2.0, 2.0)),  # heading turned away from the target
    exact_step=exact_step,
    wheeled=True,
    distance=position_distance,
    stabilized=0.05,
)

SYSTEMS: dict[str, System] = {"unicycle": UNICYCLE}
BUILT_IN_SYSTEMS = tuple(SYSTEMS)


def system_row(name: str) -> System:
    """The row of ``name``; an unknown name raises ValueError naming the known ones (one line)."""
    row = SYSTEMS.get(name)
    if row is None:
        raise ValueError(f"unknown system {name!r} ({', '.join(SYSTEMS)})")
    return row


def register_system(name: str, system: System) -> None:
    """Add a system: every consumer of this process then builds ``name`` from ``system``. A name
    that is taken, or not 1-32 of a-z 0-9 _ starting with a letter, raises ValueError."""
    add_row(SYSTEMS, "system", name, system)


def systems_text() -> str:
    """``unicycle: the paper's ...``: the rows as one line (help texts)."""
    return "; ".join(f"{name}: {row.what}" for name, row in SYSTEMS.items())
