"""The stacked actor's optimization problem in CasADi (section III, the actor objective, and
Remark on the complemented stack), built once per :class:`~common.math.actor_problem.ActorProblem`.

Decision variables are the held actions ``u_1 .. u_{N-1}``; ``s_1`` is the measured state and
``s_2 .. s_N`` are predicted (Euler by default, the paper's choice). The problem is written in
multiple-shooting form -- the predicted states are variables too, tied by equality
constraints -- because that gives the stage-wise structure fatrop exploits. It is built ONCE
per (agent, horizon); the measured state enters through the bounds of ``s_1`` (``lbx = ubx``)
and the critic weights through the parameter vector, so a step never rebuilds anything
(docs/concepts.md). The objectives are :func:`common.math.actor_search.objective`'s.

Beside the solver, :func:`build` compiles the merit (the objective along a single-shooting
rollout, by which the paper's actor picks its warm start) and, with ``multistart``, the argmin's
tick (common/math/actor_search.py), which does the step's work in one call.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from common.math.actor_problem import ActorProblem
from common.math.actor_search import objective, predictor, search_graph
from common.system.jit import build_with_jit, compiler_available

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ActorFunctions:
    """The built problem: the solver, its bounds, and the step's compiled helpers.

    ``solver``: (x0, p, lbx, ubx, lbg, ubg, lam_x0, lam_g0) -> (x, f, ...), x stage-wise
    ``s_1 d_1 s_2 d_2 .. s_N`` (``d_i`` the stage's decision variables: the held action, or the
    wheels' rim speeds with the wheel box on). ``merit``: (s_1, decisions, weights) -> the
    objective along the rollout. ``tick`` (multistart): the argmin's tick,
    :data:`common.math.actor_search.TICK_INPUTS` -> ``TICK_OUTPUTS``."""

    solver: ca.Function
    merit: ca.Function
    tick: ca.Function | None
    lbx: np.ndarray
    ubx: np.ndarray
    n_g: int  # equality constraints: state_dim per held action


def build(problem: ActorProblem) -> ActorFunctions:
    """The problem's solver and helpers, JIT-compiled when ``problem.jit`` and a C compiler is
    present (common/system/jit.py), else interpreted (the same problem, slower solves)."""
    p = problem
    n_act = p.horizon - 1
    step = predictor(p)
    n_s, n_u = p.state_dim, p.action_dim
    w = ca.SX.sym("w", p.dynamics.q_features)
    v = ca.SX.sym("v", p.dynamics.v_features)  # the critics' weights: actor_search.scaled_objective's order
    states = [ca.SX.sym(f"s{i + 1}", n_s) for i in range(p.horizon)]
    # The decision variables of each stage: the held action u_i itself, or with the wheel
    # box on, the wheels' rim speeds d_i, boxed by simple bounds, and u_i = T d_i.
    decisions = [ca.SX.sym(f"u{i + 1}", n_u) for i in range(n_act)]
    to_action = ca.DM(p.action_matrix)
    actions = [ca.mtimes(to_action, d_i) for d_i in decisions] if p.wheel_box else decisions

    cost = objective(p, states, actions, w, v)
    constraints = [states[i + 1] - step(states[i], actions[i], p.sampling_time) for i in range(n_act)]
    # The same objective along a single-shooting rollout of the actions from s_1 (states
    # consistent with the predictor): the merit by which a step picks its warm start.
    rollout = [states[0]]
    for u_i in actions:
        rollout.append(step(rollout[-1], u_i, p.sampling_time))
    merit_args = ([states[0], ca.vertcat(*decisions), ca.vertcat(w, v)], [objective(p, rollout, actions, w, v)])
    tick = search_graph(p).tick if p.multistart else None
    bounds = p.decision_bounds

    # Stage-wise ordering x1 u1 x2 u2 ... x_N, as fatrop's structure detection expects.
    variables = []
    for i in range(n_act):
        variables += [states[i], decisions[i]]
    variables.append(states[-1])
    nlp = {
        "x": ca.vertcat(*variables),
        "p": ca.vertcat(w, v),
        "f": cost,
        "g": ca.vertcat(*constraints),
    }

    inf = float("inf")
    lbx, ubx = [], []
    for _ in range(n_act):
        lbx += [-inf] * n_s + [-b for b in bounds]
        ubx += [inf] * n_s + bounds
    lbx += [-inf] * n_s
    ubx += [inf] * n_s
    n_g = n_s * n_act

    # error_on_fail: a failed solve raises, so a successful step never builds the stats
    # dict (~20 us, 3 % of a solve); a step reads the stats only after a failure.
    options: dict[str, Any] = {"print_time": False, "error_on_fail": True}
    interior_point = {
        "print_level": 0,
        "max_iter": p.max_iter,
        "tol": p.tolerance,
        "mu_init": p.mu_init,
        "bound_push": p.bound_push,
        "bound_frac": p.bound_push,
    }
    if p.solver == "fatrop":
        options.update({"structure_detection": "auto", "equality": [True] * n_g, "fatrop": interior_point})
    else:
        options["ipopt"] = interior_point | {"sb": "yes"}

    jit = p.jit and compiler_available()
    if p.jit and not jit:
        log.warning("no C compiler found: building the actor without JIT (slower solves)")

    name = f"actor_{p.agent.replace('+', 'plus')}_N{p.horizon}"
    started = time.perf_counter()
    log.log(
        logging.WARNING if p.horizon > 30 else logging.INFO,  # large N: the build takes a while
        "building the actor problem (N = %d, agent %s, solver %s%s) ...",
        p.horizon,
        p.agent,
        p.solver,
        ", JIT-compiled with the C compiler" if jit else "",
    )

    def functions(compiler: str | None) -> ActorFunctions:
        solver = ca.nlpsol(name, p.solver, nlp, options | jit_options("srl_actor", compiler))
        merit = ca.Function("merit", *merit_args, jit_options("srl_merit", compiler))
        tick_fn = None if tick is None else compile_function(tick, "srl_tick", jit_options("srl_tick", compiler))
        return ActorFunctions(
            solver,
            merit,
            tick_fn,
            np.array(lbx, dtype=float),
            np.array(ubx, dtype=float),
            n_g,
        )

    built = build_with_jit(functions, p.jit_cache) if jit else functions(None)
    elapsed = time.perf_counter() - started
    # a long build is worth a line at the default level; a usual one (N = 12: ~1 s) is not
    log.log(
        logging.WARNING if elapsed > 10.0 else logging.INFO if elapsed > 1.0 else logging.DEBUG,
        "built the actor problem (N = %d, agent %s) in %.1f s",
        p.horizon,
        p.agent,
        elapsed,
    )
    return built


def jit_options(jit_name: str, compiler: str | None) -> dict[str, Any]:
    """CasADi's options that JIT-compile a function with ``compiler`` (None: none, interpreted).

    The build runs inside a private temporary directory, removed once the compiled code is
    loaded (common/system/jit.py); CasADi's own cleanup is off. jit_temp_suffix off: the generated
    source (and its symbols) named jit_name, not jit_name plus a random suffix, so the same
    problem is the same bits every build and the wrapper's cache finds it; the private directory
    already keeps builds apart."""
    if compiler is None:
        return {}
    compiling = {"flags": ["-O3"], "verbose": False, "cleanup": False, "compiler": compiler}
    return {"jit": True, "compiler": "shell", "jit_name": jit_name, "jit_cleanup": False,
            "jit_temp_suffix": False, "jit_options": compiling}  # fmt: skip


def compile_function(function: ca.Function, name: str, options: dict[str, Any]) -> ca.Function:
    """``function`` again with ``options`` (the JIT's, or none): a built graph compiled as a whole."""
    inputs = [ca.MX.sym(function.name_in(i), function.sparsity_in(i)) for i in range(function.n_in())]
    called = function(*inputs)
    outputs = list(called) if isinstance(called, list | tuple) else [called]
    return ca.Function(name, inputs, outputs, function.name_in(), function.name_out(), options)


def compiled(functions: dict[str, ca.Function], jit: bool = True, cache: str = "") -> dict[str, ca.Function]:
    """Each of ``functions`` (name -> function) JIT-compiled as a whole where ``jit`` and a C compiler
    is present (common/system/jit.py; ``cache`` a directory of compiled objects, "" none), else as given."""
    if not (jit and compiler_available()):
        return dict(functions)

    def build_all(compiler: str | None) -> dict[str, ca.Function]:
        return {
            name: compile_function(f, f"srl_{name}", jit_options(f"srl_{name}", compiler))
            for name, f in functions.items()
        }

    return build_with_jit(build_all, cache)
