"""The stacked actor's optimization problem in CasADi (section III, the actor objective, and
Remark on the complemented stack), built once per :class:`~common.math.actor_problem.ActorProblem`.

Decision variables are the held actions ``u_1 .. u_{N-1}``; ``s_1`` is the measured state and
``s_2 .. s_N`` are predicted (Euler by default, the paper's choice). The problem is written in
multiple-shooting form -- the predicted states are variables too, tied by equality
constraints -- because that gives the stage-wise structure fatrop exploits. It is built ONCE
per (agent, horizon); the measured state enters through the bounds of ``s_1`` (``lbx = ubx``)
and the critic weights through the parameter vector, so a step never rebuilds anything
(docs/concepts.md).

| agent   | objective                                                              |
|---------|------------------------------------------------------------------------|
| mpc     | sum_i delta r(s_i, u_i)                                                |
| rlq     | sum_i Qhat(s_i, u_i; w)                                                |
| rlqv    | sum_i Qhat(s_i, u_i; w) + Jhat(s_N; v)                                 |
| rlqv+   | sum_i [Qhat(s_i, u_i; w) + (N - i) delta r(s_i, u_i)] + Jhat(s_N; v)   |

Beside the solver, :func:`build` compiles the functions :class:`common.math.actor.StackedActor`
steps with: the merit (the objective along a single-shooting rollout), the global phase
(``multistart``), the hurried step's descent (``hurry`` "descend"), the polish's projected Newton
iterations (``newton_iterations``) and the vertex search (``multistart_flips``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from common.math.actor_problem import GLOBAL_STARTS, ActorProblem
from common.math.agents import learns, uses_value_critic
from common.math.dynamics import ACTION_DIM, PREDICTORS, STATE_DIM
from common.math.features import Q_FEATURES, V_FEATURES, phi_q, phi_v, stage_cost
from common.system.jit import build_with_jit, compiler_available

log = logging.getLogger(__name__)

NEWTON_TRIALS = 10  # step sizes 1, 1/2, .., 1/512 each Newton iteration tries (newton_polish)


@dataclass(frozen=True)
class ActorFunctions:
    """The built problem: the solver, its bounds, and the step's compiled helpers.

    ``solver``: (x0, p, lbx, ubx, lbg, ubg, lam_x0, lam_g0) -> (x, f, ...), x stage-wise
    ``s_1 d_1 s_2 d_2 .. s_N`` (``d_i`` the stage's decision variables: the held action, or the
    wheels' rim speeds with the wheel box on). ``merit``: (s_1, decisions, weights) -> the
    objective along the rollout. ``global_phase`` (multistart): (starts, s_1, weights) -> (ends,
    their objective, their decision vectors). ``descent`` (``hurry`` "descend"): the same for one
    start, (start, s_1, weights) -> (end, its objective, its decision vector). ``newton``
    (``newton_iterations``): the polish's projected Newton iterations, (start, s_1, weights) ->
    (end, its objective, its projected gradient's largest entry, its decision vector). ``flips`` and
    ``rollout`` (multistart_flips): (s_1, candidates, weights) -> each candidate's merit, and
    (s_1, decisions) -> the decision vector of their rollout."""

    solver: ca.Function
    merit: ca.Function
    global_phase: ca.Function | None
    descent: ca.Function | None
    newton: ca.Function | None
    flips: ca.Function | None
    rollout: ca.Function | None
    lbx: np.ndarray
    ubx: np.ndarray
    n_g: int  # equality constraints: STATE_DIM per held action


def objective(problem: ActorProblem, states: list[Any], actions: list[Any], w: Any, v: Any) -> Any:
    """The agent's objective (module docstring table) over N states and N - 1 actions."""
    p = problem
    total: Any = 0
    for i, (s_i, u_i) in enumerate(zip(states[:-1], actions, strict=True)):
        running = p.sampling_time * stage_cost(s_i, u_i, p.cost_diag)
        if not learns(p.agent):
            total += running
        else:
            total += ca.dot(w, phi_q(s_i, u_i))
            if p.agent == "rlqv+":
                # Remark (complemented stack): (N - i) r with the paper's i = 1..N-1.
                total += (p.horizon - (i + 1)) * running
    if uses_value_critic(p.agent):
        total += ca.dot(v, phi_v(states[-1]))
    return total


def scaled_objective(problem: ActorProblem, state: Any, params: Any, bounds: list[float]) -> tuple[Any, Any, Any, Any]:
    """The agent's objective along the predictor's rollout from ``state`` (single shooting, as
    the merit) of the stage decisions scaled to the box [-1, 1] (z = d / bound, u_1 first):
    (z, the weights' symbol, the objective, the function (z, s_1) -> the decision vector of the
    rollout, stage-wise as the solver's)."""
    p = problem
    n_act, step = p.horizon - 1, PREDICTORS[p.predictor]
    z = ca.SX.sym("z", ACTION_DIM * n_act)
    scale = ca.DM(bounds)
    decisions = [z[ACTION_DIM * i : ACTION_DIM * (i + 1)] * scale for i in range(n_act)]
    to_action = ca.DM(p.action_matrix)
    actions = [ca.mtimes(to_action, d_i) for d_i in decisions] if p.wheel_box else decisions
    rollout = [state]
    for u_i in actions:
        rollout.append(step(rollout[-1], u_i, p.sampling_time))
    weights = ca.SX.sym("p", params.numel())
    cost = objective(p, rollout, actions, weights[:Q_FEATURES], weights[Q_FEATURES:])
    stages: list[Any] = []
    for s_i, d_i in zip(rollout[:-1], decisions, strict=True):
        stages += [s_i, d_i]
    decision_vector = ca.Function("descent_rollout", [z, state], [ca.vertcat(*stages, rollout[-1])])
    return z, weights, cost, decision_vector


def newton_polish(problem: ActorProblem, state: Any, params: Any, bounds: list[float]) -> tuple[list[Any], list[Any]]:
    """The polish's projected Newton iterations (ActorProblem.newton_iterations): (start, s_1,
    weights) -> (end, its objective, the largest entry of its projected gradient, its decision
    vector), the start and the end scaled to the box [-1, 1] as the global phase's.

    Each iteration is Bertsekas' projected Newton method for a box: the entries at a bound whose
    gradient pushes outwards (within eps, the projected gradient's size, capped at 1e-3) stay
    there; on the others a Newton step on the exact Hessian of the single-shooting objective
    (22 entries at N = 12: one dense QR), or, where that Hessian is indefinite and the Newton
    step is no descent, the gradient scaled by the Hessian's diagonal. The step is projected on
    the box and halved until the objective falls by Armijo's rule (up to NEWTON_TRIALS sizes,
    all tried at once); none falling, the iterate stays. From a start in a minimum's basin (the
    global phase's end, the shifted plan) the iterations converge quadratically to it, in one
    compiled call; the actor checks the projected gradient and leaves what did not converge to
    the solver (common.math.actor.StackedActor._polish)."""
    p = problem
    z, weights, cost, decision_vector = scaled_objective(p, state, params, bounds)
    hessian, gradient = ca.hessian(cost, z)
    value = ca.Function("newton_value", [z, state, weights], [cost])
    derivatives = ca.Function("newton_derivatives", [z, state, weights], [gradient, hessian])
    n_z = z.numel()
    z_mx, f_mx = ca.MX.sym("z", n_z), ca.MX.sym("f", 1)
    s_mx, p_mx = ca.MX.sym("s", STATE_DIM), ca.MX.sym("p", params.numel())
    g, h = derivatives(z_mx, s_mx, p_mx)
    projected = z_mx - ca.fmin(ca.fmax(z_mx - g, -1.0), 1.0)
    eps = ca.fmin(1e-3, ca.mmax(ca.fabs(projected)))
    active = ca.logic_or(ca.logic_and(z_mx <= -1.0 + eps, g > 0), ca.logic_and(z_mx >= 1.0 - eps, g < 0))
    free = 1 - active
    reduced = ca.diag(free) @ h @ ca.diag(free) + ca.diag(active)
    newton = -ca.solve(reduced, free * g, "qr")
    curvature = ca.fabs(ca.diag(h))
    scaled_gradient = -free * g / ca.fmax(curvature, 1e-6 * ca.mmax(curvature) + 1e-12)
    direction = ca.if_else(ca.dot(g, newton) < 0, newton, scaled_gradient)  # false for NaN too
    z_next, f_next = z_mx, f_mx
    for j in reversed(range(NEWTON_TRIALS)):  # the largest step that passes wins: tried last
        trial = ca.fmin(ca.fmax(z_mx + 0.5**j * direction, -1.0), 1.0)
        f_trial = value(trial, s_mx, p_mx)
        passes = ca.logic_and(f_trial <= f_mx + 1e-4 * ca.dot(g, trial - z_mx), f_trial <= f_mx)  # false for NaN
        z_next = ca.if_else(passes, trial, z_next)
        f_next = ca.if_else(passes, f_trial, f_next)
    iteration = ca.Function("newton_iteration", [z_mx, f_mx, s_mx, p_mx], [z_next, f_next])
    iterations = p.newton_iterations
    start = ca.MX.sym("start", n_z)
    path, values = iteration.mapaccum("newton", iterations, 2)(
        start, value(start, s_mx, p_mx), ca.repmat(s_mx, 1, iterations), ca.repmat(p_mx, 1, iterations)
    )
    end = path[:, -1]
    g_end, _ = derivatives(end, s_mx, p_mx)
    stationarity = ca.mmax(ca.fabs(end - ca.fmin(ca.fmax(end - g_end, -1.0), 1.0)))
    return [start, s_mx, p_mx], [end, values[-1], stationarity, decision_vector(end, s_mx)]


def global_phase(
    problem: ActorProblem, state: Any, params: Any, bounds: list[float]
) -> tuple[tuple[list[Any], list[Any]], tuple[list[Any], list[Any]]]:
    """The global phase's function: (starts, s_1, weights) -> (ends, their objective, their
    decision vectors), every start descended on its own (ActorProblem.multistart); and the
    descent of one start, (start, s_1, weights) -> (end, its objective, its decision vector),
    which a hurried step runs alone (ActorProblem.hurry "descend").

    A start is the stage decisions scaled to the box [-1, 1] (z = d / bound), flattened
    u_1 first; the objective is the agent's along the predictor's rollout from s_1 (single
    shooting, as the merit). Each start takes ``multistart_iterations`` projected-gradient
    iterations with an adaptive step: a trial z - t grad, clipped to the box, is taken if it
    lowers the objective (then t doubles), else t halves. Descent from a start ends in (or
    near) the local minimum whose basin holds it, as a cold SLSQP solve from standing still
    does, at a fraction of the cost of an interior-point solve from there (docs/concepts.md);
    the solver then polishes the lowest end. The iterations are a mapaccum and the starts a
    map: compiled once, no Python per iteration.
    """
    p = problem
    n_z = ACTION_DIM * (p.horizon - 1)
    z, weights, cost, decision_vector = scaled_objective(p, state, params, bounds)
    value = ca.Function("descent_value", [z, state, weights], [cost])
    gradient = ca.Function("descent_gradient", [z, state, weights], [ca.gradient(cost, z)])
    # A diagonal preconditioner, the Hessian's diagonal at the start (its magnitude, floored):
    # a held v moves the robot 0.022 m per step, a held omega turns it 0.28 rad, so the
    # scaled problem is badly conditioned and plain gradient steps crawl along v.
    curvature = ca.fabs(ca.diag(ca.hessian(cost, z)[0]))
    curvature = ca.fmax(curvature, 1e-6 * ca.mmax(curvature) + 1e-12)
    diagonal = ca.Function("descent_diagonal", [z, state, weights], [1.0 / curvature])

    z_mx, z_last, t, f_z, k = (
        ca.MX.sym(n, size) for n, size in (("z", n_z), ("z_last", n_z), ("t", 1), ("f", 1), ("k", 1))
    )
    s_mx, p_mx, scaling = ca.MX.sym("s", STATE_DIM), ca.MX.sym("p", params.numel()), ca.MX.sym("d", n_z)
    # Nesterov's momentum (k / (k + 3)), restarted when a trial fails (then the step halves
    # only if it was a plain gradient step): monotone, and fast along the flat, ill-conditioned
    # valleys near the target where plain projected gradient crawls.
    ahead = ca.fmin(ca.fmax(z_mx + k / (k + 3.0) * (z_mx - z_last), -1.0), 1.0)
    trial = ca.fmin(ca.fmax(ahead - t * scaling * gradient(ahead, s_mx, p_mx), -1.0), 1.0)
    f_trial = value(trial, s_mx, p_mx)
    lower = f_trial < f_z  # false for NaN: the trial is refused
    iteration = ca.Function(
        "descent_iteration",
        [z_mx, z_last, t, f_z, k, s_mx, p_mx, scaling],
        [
            ca.if_else(lower, trial, z_mx),
            z_mx,
            ca.if_else(lower, 1.5 * t, ca.if_else(k > 0, t, 0.5 * t)),
            ca.if_else(lower, f_trial, f_z),
            ca.if_else(lower, k + 1.0, 0.0),
        ],
    )
    iterations = p.multistart_iterations
    descent = iteration.mapaccum("descent", iterations, 5)
    start = ca.MX.sym("start", n_z)
    path, _, _, values, _ = descent(
        start,
        start,
        1.0,
        value(start, s_mx, p_mx),
        0.0,
        ca.repmat(s_mx, 1, iterations),
        ca.repmat(p_mx, 1, iterations),
        ca.repmat(diagonal(start, s_mx, p_mx), 1, iterations),
    )
    end = path[:, -1]
    single = ([start, s_mx, p_mx], [end, values[-1], decision_vector(end, s_mx)])
    one = ca.Function("descend", *single)
    starts = ca.MX.sym("starts", n_z, GLOBAL_STARTS)
    ends = one.map(GLOBAL_STARTS)(starts, ca.repmat(s_mx, 1, GLOBAL_STARTS), ca.repmat(p_mx, 1, GLOBAL_STARTS))
    return ([starts, s_mx, p_mx], list(ends)), single


def flip_functions(
    problem: ActorProblem, merit_args: tuple[list[Any], list[Any]], rollout: list[Any], decisions: list[Any]
) -> tuple[tuple[list[Any], list[Any]], tuple[list[Any], list[Any]]]:
    """The vertex search's functions (ActorProblem.multistart_flips): (s_1, candidates,
    weights) -> the objective of each candidate's actions along the rollout (the merit,
    mapped over the 2 n_z columns of the candidates matrix), and (s_1, decisions) -> the
    decision vector of their rollout (the solver's start)."""
    n_z = ACTION_DIM * (problem.horizon - 1)
    merit = ca.Function("merit_of_candidate", *merit_args)
    state, candidates = ca.MX.sym("s", STATE_DIM), ca.MX.sym("candidates", n_z, 2 * n_z)
    params = ca.MX.sym("p", merit.size1_in(2))
    values = merit.map(2 * n_z)(ca.repmat(state, 1, 2 * n_z), candidates, ca.repmat(params, 1, 2 * n_z))
    stages: list[Any] = []
    for s_i, d_i in zip(rollout[:-1], decisions, strict=True):
        stages += [s_i, d_i]
    vector = ([rollout[0], ca.vertcat(*decisions)], [ca.vertcat(*stages, rollout[-1])])
    return ([state, candidates, params], [values]), vector


def build(problem: ActorProblem) -> ActorFunctions:
    """The problem's solver and helpers, JIT-compiled when ``problem.jit`` and a C compiler is
    present (common/system/jit.py), else interpreted (the same problem, slower solves)."""
    p = problem
    n_act = p.horizon - 1
    step = PREDICTORS[p.predictor]
    w = ca.SX.sym("w", Q_FEATURES)
    v = ca.SX.sym("v", V_FEATURES)
    states = [ca.SX.sym(f"s{i + 1}", STATE_DIM) for i in range(p.horizon)]
    # The decision variables of each stage: the held action u_i itself, or with the wheel
    # box on, the wheels' rim speeds d_i, boxed by simple bounds, and u_i = T d_i.
    decisions = [ca.SX.sym(f"u{i + 1}", ACTION_DIM) for i in range(n_act)]
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
    searches = p.multistart and p.multistart_flips > 0
    flip_args = flip_functions(p, merit_args, rollout, decisions) if searches else None
    bounds = p.decision_bounds
    phases = global_phase(p, states[0], ca.vertcat(w, v), bounds) if p.multistart else None
    global_args = phases[0] if phases is not None else None
    descent_args = phases[1] if phases is not None and p.hurry == "descend" else None
    polishes = p.multistart and p.newton_iterations > 0  # without the global phase: the paper's actor, the solver
    newton_args = newton_polish(p, states[0], ca.vertcat(w, v), bounds) if polishes else None

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
        lbx += [-inf] * STATE_DIM + [-b for b in bounds]
        ubx += [inf] * STATE_DIM + bounds
    lbx += [-inf] * STATE_DIM
    ubx += [inf] * STATE_DIM
    n_g = STATE_DIM * n_act

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

    def compiled(jit_name: str, compiler: str | None) -> dict[str, Any]:
        # The build runs inside a private temporary directory, removed once the compiled
        # code is loaded (common/system/jit.py); CasADi's own cleanup is off.
        if compiler is None:
            return {}
        # jit_temp_suffix off: the generated source (and its symbols) named jit_name, not
        # jit_name plus a random suffix, so the same problem is the same bits every build and
        # the wrapper's cache finds it; the private directory already keeps builds apart.
        jit_options = {"flags": ["-O3"], "verbose": False, "cleanup": False, "compiler": compiler}
        return {"jit": True, "compiler": "shell", "jit_name": jit_name, "jit_cleanup": False,
                "jit_temp_suffix": False, "jit_options": jit_options}  # fmt: skip

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
        solver = ca.nlpsol(name, p.solver, nlp, options | compiled("srl_actor", compiler))
        merit = ca.Function("merit", *merit_args, compiled("srl_merit", compiler))
        global_fn = descent_fn = newton_fn = flips = rollout_fn = None
        if global_args is not None:
            global_fn = ca.Function("global_phase", *global_args, compiled("srl_global", compiler))
        if descent_args is not None:
            descent_fn = ca.Function("descent", *descent_args, compiled("srl_descent", compiler))
        if newton_args is not None:
            newton_fn = ca.Function("newton_polish", *newton_args, compiled("srl_newton", compiler))
        if flip_args is not None:
            flips = ca.Function("vertex_neighbours", *flip_args[0], compiled("srl_flips", compiler))
            rollout_fn = ca.Function("rollout", *flip_args[1], compiled("srl_rollout", compiler))
        return ActorFunctions(
            solver,
            merit,
            global_fn,
            descent_fn,
            newton_fn,
            flips,
            rollout_fn,
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
