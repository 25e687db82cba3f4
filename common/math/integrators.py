"""One held interval of ``ds/dt = f(s, u)``: the actor's predictors and the plant's fixed-step
integration of a system with no closed form (common/math/systems.py).

Each takes the system's right-hand side ``f`` (numpy arrays or CasADi symbols, the same code)
and returns the state after ``h`` seconds with ``u`` held.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

Rhs = Callable[[Any, Any], Any]  # f(s, u): numpy arrays or CasADi symbols
Predictor = Callable[[Rhs, Any, Any, float], Any]


def euler(rhs: Rhs, state: Any, action: Any, h: float) -> Any:
    """The paper's predictor, eq. (Euler): ``s + h f(s, u)``."""
    return state + h * rhs(state, action)


def rk4(rhs: Rhs, state: Any, action: Any, h: float) -> Any:
    """Classic fourth-order Runge-Kutta over one held interval: local error O(h^5)."""
    k1 = rhs(state, action)
    k2 = rhs(state + h / 2 * k1, action)
    k3 = rhs(state + h / 2 * k2, action)
    k4 = rhs(state + h * k3, action)
    return state + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


PREDICTORS: dict[str, Predictor] = {"euler": euler, "rk4": rk4}


def rk4_substeps(rhs: Rhs, state: Any, action: Any, duration: float, substeps: int) -> Any:
    """``substeps`` RK4 steps of ``duration / substeps`` each: a held interval integrated where no
    closed form is known (the global error falls as ``(duration / substeps)^4``)."""
    h = duration / substeps
    for _ in range(substeps):
        state = rk4(rhs, state, action, h)
    return state
