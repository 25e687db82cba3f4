"""The sampled systems srl controls, one row each: everything the method needs to know of a plant
(docs/extending.md, "Your own sampled system"; the table: docs/reference/variants.md): its state
and action (names, so dimensions), the model ``ds/dt = f(s, u)`` (numpy or CasADi, one code), the
box of the held actions, the stage cost's default weights, the default start, and what
"stabilized" means. The goal is the origin of the state: a system is
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
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.math.dynamics import (
    FloatArray,
    exact_step,
    exact_steps,
    heading_away_from_target,
    is_symbolic,
    unicycle_rhs,
)
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


def ca_or_np(*values: Any) -> Any:
    """The module whose ``sin``, ``cos``, ... take ``values``: casadi for a CasADi symbol, else numpy."""
    if any(is_symbolic(value) for value in values):
        import casadi as ca

        return ca
    return np


def state_norm(state: FloatArray) -> float:
    """The Euclidean norm of the state: how far from the goal (the origin) a system is."""
    return float(np.linalg.norm(state))


def position_distance(state: FloatArray) -> float:
    """A wheeled robot's distance to its target: ``hypot(x, y)``, whatever its heading."""
    return float(np.hypot(state[0], state[1]))


def name_and_unit(entry: str) -> tuple[str, str]:
    """A state's or action's name with its unit, ``"x [m]"``, as ``("x", "m")``; ``("h", "")`` for ``"h"``."""
    name, _, unit = entry.partition(" [")
    return name, unit.removesuffix("]")


def check_box_and_cost(action_max: Sequence[float], cost_diag: Sequence[float], n: int, m: int) -> None:
    """ValueError (one line) unless ``action_max`` is ``m`` positive numbers and ``cost_diag``
    ``n + m`` finite numbers >= 0: a system's row and an actor's problem keep the same rule."""
    if len(action_max) != m or not all(math.isfinite(b) and b > 0 for b in action_max):
        raise ValueError(f"action_max: {m} positive numbers (one per action), got {tuple(action_max)}")
    if len(cost_diag) != n + m or not all(math.isfinite(c) and c >= 0 for c in cost_diag):
        raise ValueError(f"cost_diag: {n + m} finite numbers >= 0 (states, then actions), got {tuple(cost_diag)}")


@dataclass(frozen=True)
class System:
    """One sampled system (a row of :data:`SYSTEMS`).

    ``states`` and ``actions``: the entries' names with units, ``("x [m]", ...)``: their counts are
    the dimensions. ``rhs``: ``f(s, u)``, numpy arrays or CasADi symbols. ``action_max``: the box
    ``|u_i| <= action_max[i]`` (a wheeled robot's come from the settings' ``plant.v_max`` and
    ``plant.omega_max``). ``cost_diag``: the default ``diag(R)`` of the stage cost ``r(s, u) =
    (s, u)^T R (s, u)``. ``start``: the default start. ``exact_step``: the exact sample-and-hold,
    where known (``exact_steps``: the same for many states at once, as arrays). ``wheeled``: the
    actions are a differential drive's ``(v, omega)`` and the state its pose ``(x, y, alpha)``: the
    wheel box, the arrival rule and the robot bridge serve only such a system. ``distance``: how
    far a state is from the goal, in the system's own terms; ``stabilized``: the distance under
    which it is."""

    what: str
    states: tuple[str, ...]
    actions: tuple[str, ...]
    rhs: Rhs
    action_max: tuple[float, ...]
    cost_diag: tuple[float, ...]
    start: tuple[float, ...]
    exact_step: ExactStep | None = None
    exact_steps: ExactStep | None = None  # exact_step of many at once, (K, n) and (K, m) arrays
    wheeled: bool = False
    distance: Callable[[FloatArray], float] = state_norm
    stabilized: float = 0.05
    substeps: int = 10
    # The actor's horizon N the system's runs take unless the settings name one (actor.horizon = 0):
    # its look-ahead must span the time the system takes to answer (the dynamic robot: 2 s)
    horizon: int = 12
    # Where episodes start when drawn (Gymnasium's resets: uniform in the box |s_i| <= start_box[i])
    # and the experiment's starts (a lattice over its first two entries); () = |start_i| each.
    start_box: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        n, m = len(self.states), len(self.actions)
        if n < 1 or m < 1:
            raise ValueError(f"a system has at least one state and one action, got {n} and {m}")
        check_box_and_cost(self.action_max, self.cost_diag, n, m)
        if len(self.start) != n or not all(math.isfinite(c) for c in self.start):
            raise ValueError(f"start: {n} finite numbers, got {self.start}")
        if self.wheeled and (n, m) != (3, 2):
            raise ValueError(f"a wheeled system's state is (x, y, alpha) and its action (v, omega), got {n} and {m}")
        if not (math.isfinite(self.stabilized) and self.stabilized > 0):
            raise ValueError(f"stabilized: a positive distance, got {self.stabilized}")
        if not 2 <= self.horizon <= 100:
            raise ValueError(f"horizon: N of 2 to 100 (N - 1 held actions), got {self.horizon}")
        if not 1 <= self.substeps <= 1000:
            raise ValueError(f"substeps: 1 to 1000 RK4 steps per held interval, got {self.substeps}")
        if self.start_box and (
            len(self.start_box) != n or not all(math.isfinite(w) and w >= 0 for w in self.start_box)
        ):
            raise ValueError(f"start_box: {n} half-widths >= 0, got {self.start_box}")

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

    @property
    def box_of_starts(self) -> FloatArray:
        """:attr:`start_box`'s half-widths (``|start_i|`` each when not given)."""
        return np.array(self.start_box or [abs(c) for c in self.start], dtype=float)

    def state_labels(self) -> list[tuple[str, str]]:
        """Each state entry's ``(name, unit)``: ``"x [m]"`` is ``("x", "m")``, ``"h"`` is ``("h", "")``."""
        return [name_and_unit(entry) for entry in self.states]

    def action_labels(self) -> list[tuple[str, str]]:
        """Each action entry's ``(name, unit)``."""
        return [name_and_unit(entry) for entry in self.actions]

    def draw_start(self, rng: np.random.Generator) -> FloatArray:
        """A start drawn uniformly in :attr:`start_box` (``rng``: the caller's, seeded)."""
        box = self.box_of_starts
        return np.asarray(rng.uniform(-box, box), dtype=float)

    def step(self, state: FloatArray, action: FloatArray, duration: float) -> FloatArray:
        """The state after ``duration`` seconds of ``action`` held from ``state``: exact where known,
        else ``substeps`` RK4 steps."""
        state, action = np.asarray(state, dtype=float), np.asarray(action, dtype=float)
        if self.exact_step is not None:
            return np.asarray(self.exact_step(state, action, duration), dtype=float)
        return np.asarray(rk4_substeps(self.rhs, state, action, duration, self.substeps), dtype=float)

    def steps(self, states: FloatArray, actions: FloatArray, duration: float) -> FloatArray:
        """:meth:`step` of many: ``states`` ``(K, n)``, ``actions`` ``(K, m)`` -> ``(K, n)`` (a plant
        host's round): :attr:`exact_steps` as arrays where the row has it, else each row's step."""
        states, actions = np.asarray(states, dtype=float), np.asarray(actions, dtype=float)
        if self.exact_steps is not None:
            return np.asarray(self.exact_steps(states, actions, duration), dtype=float)
        stepped = [self.step(state, action, duration) for state, action in zip(states, actions, strict=True)]
        return np.array(stepped, dtype=float).reshape(states.shape)

    @property
    def still_at_zero(self) -> bool:
        """A zero action holds every state where it is (``f(s, 0) = 0``): a wheeled robot's zero
        ``(v, omega)``. A plant host skips the step of such a system whose actions are all zero."""
        return self.wheeled


UNICYCLE = System(
    what="the paper's three-wheel robot, kinematic: a unicycle driven by (v, omega), eq. (3w-robot)",
    states=("x [m]", "y [m]", "alpha [rad]"),
    actions=("v [m/s]", "omega [rad/s]"),
    rhs=unicycle_rhs,
    action_max=(0.22, 2.84),  # the TurtleBot3 Burger's; the settings' plant.v_max, plant.omega_max
    cost_diag=(1.0, 10.0, 1.0, 0.01, 0.01),
    start=(2.0, 2.0, heading_away_from_target(2.0, 2.0)),  # srl.toml's [2, 2]: heading away from the target
    exact_step=exact_step,
    exact_steps=exact_steps,
    wheeled=True,
    distance=position_distance,
    stabilized=0.05,
)

# -- the built-in systems beside the robot (regelum-control's presets, docs/reference/variants.md)

G = 9.81  # [m/s^2]
PENDULUM_MASS, PENDULUM_LENGTH = 0.127, 0.337  # [kg], [m]: a uniform rod on a motor's shaft


def pendulum_rhs(state: Any, action: Any) -> Any:
    """A rod hinged at one end, driven at the hinge: ``theta`` from upright; its weight at half its
    length, its inertia ``m l^2 / 3``: ``theta'' = (m g l / 2 sin theta + tau) / (m l^2 / 3)``."""
    m, length = PENDULUM_MASS, PENDULUM_LENGTH
    sin = ca_or_np(state, action).sin
    return vector(state[1], (m * G * length / 2 * sin(state[0]) + action[0]) / (m * length**2 / 3))


CART_MASS, POLE_MASS, POLE_HALF_LENGTH = 1.0, 0.1, 0.5  # [kg], [kg], [m]: the classic cart-pole's


def cartpole_rhs(state: Any, action: Any) -> Any:
    """The classic cart-pole (Barto, Sutton and Anderson, 1983; Gymnasium's CartPole), its force
    continuous: the cart at ``x``, the pole ``theta`` from upright."""
    lib = ca_or_np(state, action)
    theta, x_dot, theta_dot, force = state[1], state[2], state[3], action[0]
    sin, cos = lib.sin(theta), lib.cos(theta)
    total = CART_MASS + POLE_MASS
    push = (force + POLE_MASS * POLE_HALF_LENGTH * theta_dot**2 * sin) / total
    theta_acc = (G * sin - cos * push) / (POLE_HALF_LENGTH * (4.0 / 3.0 - POLE_MASS * cos**2 / total))
    x_acc = push - POLE_MASS * POLE_HALF_LENGTH * theta_acc * cos / total
    return vector(x_dot, theta_dot, x_acc, theta_acc)


# The two-tank system (regelum-control's preset), its time constants a tenth of the preset's
# (18.4 s, 24.4 s), so that a horizon of a second sees the levels move: pumped inflow into tank 1,
# tank 1 into tank 2, tank 2's outflow, and a level term K3 h2^2. Written as deviations from the
# levels (h1, h2) = (0.368, 0.4) held by the pump at p = 0.283.
TANK_TIME = (1.84, 2.44)  # [s]
TANK_GAINS = (1.3, 1.0, 0.2)  # K1, K2, K3
TANK_LEVELS = (0.368, 0.4)  # [m]: the goal


def two_tank_rhs(state: Any, action: Any) -> Any:
    """The levels' deviations ``(e1, e2)`` from :data:`TANK_LEVELS` under the pump's deviation ``u``
    from its holding rate: ``tau1 e1' = -e1 + K1 u``, ``tau2 e2' = -e2 + K2 e1 + K3 (e2^2 + 2 h2 e2)``
    (at the goal, ``h2 = K2 h1 + K3 h2^2`` and ``h1 = K1 p``)."""
    (tau1, tau2), (k1, k2, k3), h2 = TANK_TIME, TANK_GAINS, TANK_LEVELS[1]
    e1, e2 = state[0], state[1]
    return vector((-e1 + k1 * action[0]) / tau1, (-e2 + k2 * e1 + k3 * (e2 * e2 + 2.0 * h2 * e2)) / tau2)


ROBOT_MASS, ROBOT_INERTIA = 10.0, 1.0  # [kg], [kg m^2]


def dynamic_unicycle_rhs(state: Any, action: Any) -> Any:
    """The three-wheel robot with its dynamics: a force ``F`` along its heading and a torque ``M``
    about its centre accelerate its speed ``v`` and turning rate ``omega``."""
    lib = ca_or_np(state, action)
    alpha, v, omega = state[2], state[3], state[4]
    return vector(v * lib.cos(alpha), v * lib.sin(alpha), omega, action[0] / ROBOT_MASS, action[1] / ROBOT_INERTIA)


PENDULUM = System(
    what="an inverted pendulum driven by a torque too weak to hold it beyond 28 degrees",
    states=("theta [rad]", "omega [rad/s]"),
    actions=("tau [N m]",),
    rhs=pendulum_rhs,
    action_max=(0.1,),
    cost_diag=(10.0, 1.0, 1.0),
    start=(0.4, 0.0),
    start_box=(0.4, 0.5),
)
CARTPOLE = System(
    what="the classic cart-pole: a pole balanced on a cart pushed along a line",
    states=("x [m]", "theta [rad]", "x_dot [m/s]", "theta_dot [rad/s]"),
    actions=("F [N]",),
    rhs=cartpole_rhs,
    action_max=(10.0,),
    cost_diag=(1.0, 10.0, 0.1, 0.1, 0.01),
    start=(0.5, 0.2, 0.0, 0.0),
)
TWO_TANK = System(
    what="two tanks in series filled by a pump, both levels held at a goal",
    states=("e1 [m]", "e2 [m]"),
    actions=("u [pump rate]",),
    rhs=two_tank_rhs,
    action_max=(0.283,),
    cost_diag=(10.0, 10.0, 1.0),
    start=(-0.2, -0.2),
    stabilized=0.01,
)
DYNAMIC_UNICYCLE = System(
    what="the three-wheel robot with its dynamics: pushed by a force and turned by a torque",
    states=("x [m]", "y [m]", "alpha [rad]", "v [m/s]", "omega [rad/s]"),
    actions=("F [N]", "M [N m]"),
    rhs=dynamic_unicycle_rhs,
    action_max=(10.0, 2.0),
    cost_diag=(1.0, 10.0, 1.0, 0.1, 0.1, 0.01, 0.01),
    start=(1.0, 1.0, math.atan2(1.0, 1.0), 0.0, 0.0),
    start_box=(1.0, 1.0, 0.0, 0.0, 0.0),  # at rest, heading along x, anywhere in the square
    distance=position_distance,
    stabilized=0.05,
    horizon=20,  # at N = 12 (1.2 s) RL-QV ends 0.07 m away in 20 s; MPC 0.05 m (docs/reference/systems)
)

SYSTEMS: dict[str, System] = {
    "unicycle": UNICYCLE,
    "dynamic_unicycle": DYNAMIC_UNICYCLE,
    "pendulum": PENDULUM,
    "cartpole": CARTPOLE,
    "two_tank": TWO_TANK,
}
BUILT_IN_SYSTEMS = tuple(SYSTEMS)


def system_row(name: str) -> System:
    """The row of ``name``; an unknown name raises ValueError naming the known ones (one line)."""
    row = SYSTEMS.get(name)
    if row is None:
        raise ValueError(f"unknown system {name!r} ({', '.join(SYSTEMS)})")
    return row


def gymnasium_id(name: str) -> str:
    """The system's Gymnasium id (tools/gym/envs.py): ``srl/Pendulum-v0``, ``srl/TwoTank-v0``; the
    robot's is ``srl/Unicycle-v0``, beside its TurtleBot3 plants' ids."""
    return "srl/" + "".join(part.capitalize() for part in name.split("_")) + "-v0"


def register_system(name: str, system: System) -> None:
    """Add a system: every consumer of this process then builds ``name`` from ``system``. A name
    that is taken, or not 1-32 of a-z 0-9 _ starting with a letter, raises ValueError."""
    add_row(SYSTEMS, "system", name, system)


def systems_text() -> str:
    """``unicycle: the paper's ...``: the rows as one line (help texts)."""
    return "; ".join(f"{name}: {row.what}" for name, row in SYSTEMS.items())
