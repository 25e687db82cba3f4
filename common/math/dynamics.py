"""The unicycle (three-wheel robot) model of the paper, eq. (3w-robot).

State ``s = (x, y, alpha)`` [m, m, rad] in the goal frame; action ``u = (v, omega)``
[m/s, rad/s], held constant over each sampling interval (sample-and-hold).

One definition of the right-hand side, :func:`unicycle_rhs`, serves both the actor's
predictor (numerically, or symbolically with CasADi) and, through its closed-form
integral :func:`exact_step`, the plant. The heading is never wrapped: it stays continuous.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from common.math.integrators import euler, rk4

FloatArray = NDArray[np.float64]
STATE_DIM = 3
ACTION_DIM = 2


def is_symbolic(value: Any) -> bool:
    # CasADi types are detected by duck typing so that this module never needs casadi
    # for numeric use (the plant); the actor passes SX/MX symbols.
    return type(value).__module__.startswith("casadi")


def unicycle_rhs(state: Any, action: Any) -> Any:
    """``f(s, u) = (v cos alpha, v sin alpha, omega)``; numpy arrays or CasADi symbols."""
    alpha = state[2]
    v, omega = action[0], action[1]
    if is_symbolic(state) or is_symbolic(action):
        import casadi as ca

        return ca.vertcat(v * ca.cos(alpha), v * ca.sin(alpha), omega)
    return np.array([v * np.cos(alpha), v * np.sin(alpha), omega], dtype=float)


def euler_step(state: Any, action: Any, sampling_time: float) -> Any:
    """The paper's predictor, eq. (Euler), for the unicycle: ``s + delta f(s, u)``."""
    return euler(unicycle_rhs, state, action, sampling_time)


def rk4_step(state: Any, action: Any, sampling_time: float) -> Any:
    """Classic fourth-order Runge-Kutta over one held interval, for the unicycle."""
    return rk4(unicycle_rhs, state, action, sampling_time)


def exact_step(state: FloatArray, action: FloatArray, duration: float) -> FloatArray:
    """Exact sample-and-hold integration of the unicycle over ``duration`` seconds.

    The textbook closed form is ``x += v/omega (sin(a + omega t) - sin a)`` and
    ``y -= v/omega (cos(a + omega t) - cos a)``, a straight line when ``omega == 0``.
    Using ``sin(b) - sin(a) = 2 cos((a+b)/2) sin((b-a)/2)`` it becomes
    ``x += v t cos(a + omega t/2) sinc(omega t/2)``, which is the same function but has no
    branch and no cancellation for tiny ``omega`` (``np.sinc(z) = sin(pi z)/(pi z)``).
    """
    x, y, alpha = (float(c) for c in state)
    v, omega = (float(c) for c in action)
    half_turn = omega * duration / 2.0
    chord = v * duration * float(np.sinc(half_turn / np.pi))
    mid_heading = alpha + half_turn
    return np.array([x + chord * np.cos(mid_heading), y + chord * np.sin(mid_heading), alpha + omega * duration])


def exact_steps(states: FloatArray, actions: FloatArray, duration: float) -> FloatArray:
    """:func:`exact_step` of many robots at once: ``states`` (K, 3), ``actions`` (K, 2) -> (K, 3)
    (the plant host steps a whole fleet per period). The same formula, element-wise."""
    states = np.asarray(states, dtype=float)
    actions = np.asarray(actions, dtype=float)
    half_turn = actions[:, 1] * duration / 2.0
    chord = actions[:, 0] * duration * np.sinc(half_turn / np.pi)
    mid_heading = states[:, 2] + half_turn
    return np.stack(
        [
            states[:, 0] + chord * np.cos(mid_heading),
            states[:, 1] + chord * np.sin(mid_heading),
            states[:, 2] + actions[:, 1] * duration,
        ],
        axis=1,
    )


def heading_away_from_target(x: float, y: float) -> float:
    """The paper's start heading: turned away from the target at the origin.

    ``atan2(y, x)``; at the origin itself (no direction) ``pi`` (docs/concepts.md).
    """
    if x == 0.0 and y == 0.0:
        return float(np.pi)
    return float(np.arctan2(y, x))


def unwrap_heading(previous: float, measured: float) -> float:
    """Continuous heading: the representative of ``measured`` (mod 2 pi) nearest ``previous``."""
    return previous + float(np.remainder(measured - previous + np.pi, 2.0 * np.pi) - np.pi)


class Plant(Protocol):
    """A plant of Algorithm 1 (common/math/loop.py): ``reset`` and ``apply`` return the state the
    robot reports (a real robot: its odometry).

    ``true_state`` is where it really is, if the plant knows (a simulator does, a real robot
    does not: None); ``saturated_commands`` counts commands a wheel could not follow (None:
    not known)."""

    def reset(self, state: np.ndarray) -> np.ndarray: ...
    def apply(self, action: np.ndarray, duration: float) -> np.ndarray: ...
    @property
    def true_state(self) -> np.ndarray | None: ...
    @property
    def saturated_commands(self) -> int | None: ...
