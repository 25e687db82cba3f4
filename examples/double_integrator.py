"""A sampled system of your own, in one file: a cart on a line pushed by a bounded acceleration.

Its state is the position and speed ``(p, v)``, its action the acceleration ``a``; the goal is the
origin (at rest at p = 0). Its model ``f(s, u) = (v, a)`` is written once with
:func:`~common.math.systems.vector`, which the actor's predictor evaluates in CasADi and the plant
in numpy; with no closed form given, the plant integrates it by RK4 substeps. Run it by naming
this file in ``SRL_PLUGINS`` (common/process/plugins.py)::

    SRL_PLUGINS=examples/double_integrator.py ./srl run --system double_integrator --duration 12
"""

from __future__ import annotations

from typing import Any

from common.math.systems import System, register_system, vector


def double_integrator(state: Any, action: Any) -> Any:
    """``(p, v)' = (v, a)``."""
    return vector(state[1], action[0])


SYSTEM = System(
    what="a cart on a line pushed by a bounded acceleration (examples/double_integrator.py)",
    states=("p [m]", "v [m/s]"),
    actions=("a [m/s^2]",),
    rhs=double_integrator,
    action_max=(1.0,),
    cost_diag=(1.0, 0.5, 0.05),  # diag(R) over (p, v, a)
    start=(1.0, 0.0),
)


def register() -> None:
    register_system("double_integrator", SYSTEM)
