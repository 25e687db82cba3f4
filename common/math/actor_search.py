"""The actor's argmin as one compiled call per tick: the search graph (docs/concepts.md, "The argmin").

The stacked objective is minimized over the held actions of one sampling interval each, N - 1
of them: 2 (N - 1) numbers in a box. Written along the predictor's rollout from the measured
state (single shooting) it is smooth but not convex -- the dynamics turn the robot, and a learned
critic may be indefinite -- so it has local minima, near the target often hundreds of them. A
tick therefore does a little of three things, every tick, in one compiled CasADi function:

1. **The warm polish.** The robot's previous plan shifted by one interval (the last held action
   repeated) or its plan of two ticks ago, whichever costs less along the rollout (a loop that
   alternates between two states returns to the state where that plan was optimal), polished by
   projected Newton iterations (:func:`newton_function`) until the projected gradient is below
   :data:`NEWTON_TOLERANCE`. From a plan that was a minimum one interval ago this takes 0-2
   iterations.
2. **The search.** Each robot keeps :attr:`~common.math.actor_problem.ActorProblem.multistart_starts`
   other plans (its *alternatives*), each shifted and descended by ``multistart_iterations``
   iterations of a preconditioned projected gradient every tick, so a global search is spread
   over many ticks instead of repeated at each. The lowest alternative that is below the warm
   answer, or within ``multistart_margin`` of it once it has descended for :data:`MATURE` ticks,
   is polished too; the lower of the two answers wins. An alternative that reached the answer, or
   another alternative, or that has descended for :data:`RETIRE` ticks without coming within the
   margin, is replaced by a fresh start: standing still, full speed ahead or back, turning, or
   the answer with a few entries moved (:func:`fresh_starts`), taken in turn from a fixed table.
3. **The vertex search.** Up to ``multistart_flips`` sweeps over the 2 (N - 1) x 2 neighbours of
   the answer with one entry moved to either bound, moving to the lowest while it lowers the
   objective, and a polish of where it ended. A learned critic concave along an entry puts the
   minimum along it on one of its two bounds, where a polish started on the other cannot see it.

Only the branches a tick takes are evaluated (CasADi's ``Function.if_else``): a tick whose warm
answer is already stationary and whose alternatives offer nothing costs the warm check, the
descent of the alternatives and one vertex sweep. The answer's decision vector comes out with
its projected gradient; where that is above the tolerance (the Newton iterations fell short),
the actor hands it to the interior-point solver (common.math.actor.StackedActor).

Everything works on the stage decisions scaled to the box [-1, 1] (``z = d / bound``,
u_1 first): the held actions, or with the wheel box on, the wheels' rim speeds.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from common.math.actor_problem import ActorProblem
from common.math.agents import agent_row
from common.math.features import phi_q, phi_v, stage_cost
from common.math.integrators import PREDICTORS

# The polish is done when the largest entry of the projected gradient (in z) is at most this.
NEWTON_TOLERANCE = 1e-6
# Step sizes each Newton iteration tries, all at once (no branches in the code): 1/64 .. 1 backs off
# a step the model overestimates; 2 .. 16 follow negative curvature (an indefinite critic) towards
# the box's bounds in a few iterations, where the damped step alone takes dozens.
NEWTON_STEPS = (1 / 64, 1 / 16, 1 / 4, 1 / 2, 1.0, 2.0, 4.0, 8.0, 16.0)
# How many times a Newton step raises its damping tenfold (from 1e-4, times the Hessian's largest
# diagonal entry, up to 1) where the damped reduced Hessian is not positive definite.
DAMPING_TRIES = 5
# Up to this many decision entries (N <= 21) a Newton step factorizes by a Cholesky written out in
# the compiled code (its failure the exact test of positive definiteness); beyond, by CasADi's sparse
# LDL, whose code does not grow as N^3 (N = 30 compiles in ~1.5 minutes instead of ~2), taking the
# step where it descends.
CHOLESKY_ENTRIES = 40
# The objective's relative rounding a Newton step may add (a few units in the last place).
ROUNDING = 8.0 * float(np.finfo(float).eps)
# An alternative within the margin of the warm answer is polished once it has descended this many ticks.
MATURE = 3
# An alternative that has descended this many ticks without coming within the margin is replaced.
RETIRE = 6
# The first alternative is the cold lane: standing still, descended for COLD_PERIOD - 1 ticks, then
# polished and started again -- a cold solve (SLSQP's from standing still, the rcognita way) spread
# over the ticks, which near the target finds minima the warm plans miss.
COLD_PERIOD = 5
# Two plans whose scaled entries all differ by less than this are one plan (the same basin).
SAME_PLAN = 1e-2
# Inputs and outputs of the tick (their order in :func:`search_graph`'s function).
TICK_INPUTS = ("state", "weights", "warm", "alternatives", "fresh", "masks", "ages", "flags")
TICK_OUTPUTS = ("x", "plan", "objective", "stationarity", "kept", "kept_ages", "trace", "report")
# The tick's report (its last output), one entry each: the warm polish's Newton iterations, the
# search ran, an alternative was polished, it (or the cold lane) won, the vertex search moved, what it
# found won, the alternatives replaced, the vertex sweeps evaluated, the cold lane was polished.
REPORT = (
    "warm_iterations",
    "searched",
    "alternative_polished",
    "alternative_won",
    "vertex_moved",
    "vertex_won",
    "replaced",
    "sweeps",
    "cold_polished",
)


def predictor(problem: ActorProblem) -> Callable[[Any, Any, float], Any]:
    """The problem's predictor of its system: ``(s, u, delta) -> s'`` (numpy or CasADi)."""
    integrate, rhs = PREDICTORS[problem.predictor], problem.dynamics.rhs

    def step(state: Any, action: Any, h: float) -> Any:
        return integrate(rhs, state, action, h)

    return step


def objective(problem: ActorProblem, states: list[Any], actions: list[Any], w: Any, v: Any) -> Any:
    """The agent's stacked objective over N states and N - 1 actions (docs/concepts.md):

    | agent   | objective                                                              |
    |---------|------------------------------------------------------------------------|
    | mpc     | sum_i delta r(s_i, u_i)                                                |
    | rlq     | sum_i Qhat(s_i, u_i; w)                                                |
    | rlqv    | sum_i Qhat(s_i, u_i; w) + Jhat(s_N; v)                                 |
    | rlqv+   | sum_i [Qhat(s_i, u_i; w) + (N - i) delta r(s_i, u_i)] + Jhat(s_N; v)   |
    """
    p = problem
    row = agent_row(p.agent)  # its terms: common/math/agents.py AGENT_ROWS
    total: Any = 0
    for i, (s_i, u_i) in enumerate(zip(states[:-1], actions, strict=True)):
        running = p.sampling_time * stage_cost(s_i, u_i, p.cost_diag)
        if row.q_critics:
            total += ca.dot(w, phi_q(s_i, u_i))
        if row.stage_costs == "each":
            total += running
        elif row.stage_costs == "remaining":
            # Remark (complemented stack): (N - i) r with the paper's i = 1..N-1.
            total += (p.horizon - (i + 1)) * running
    if row.value_critic:
        total += ca.dot(v, phi_v(states[-1]))
    return total


def scaled_objective(problem: ActorProblem) -> tuple[Any, Any, Any, Any, ca.Function]:
    """The agent's objective along the predictor's rollout from the state ``s`` (single shooting)
    of the scaled stage decisions ``z``: (z, s, the weights' symbol, the objective, the function
    (z, s) -> the decision vector of the rollout, stage-wise as the solver's ``s_1 d_1 .. s_N``)."""
    p = problem
    n_act, step, m, q_features = p.horizon - 1, predictor(p), p.action_dim, p.dynamics.q_features
    z = ca.SX.sym("z", m * n_act)
    state = ca.SX.sym("s", p.state_dim)
    weights = ca.SX.sym("p", q_features + p.dynamics.v_features)
    scale = ca.DM(p.decision_bounds)
    decisions = [z[m * i : m * (i + 1)] * scale for i in range(n_act)]
    to_action = ca.DM(p.action_matrix)
    actions = [ca.mtimes(to_action, d_i) for d_i in decisions] if p.wheel_box else decisions
    rollout = [state]
    for u_i in actions:
        rollout.append(step(rollout[-1], u_i, p.sampling_time))
    cost = objective(p, rollout, actions, weights[:q_features], weights[q_features:])
    stages: list[Any] = []
    for s_i, d_i in zip(rollout[:-1], decisions, strict=True):
        stages += [s_i, d_i]
    decision_vector = ca.Function("decision_vector", [z, state], [ca.vertcat(*stages, rollout[-1])])
    return z, state, weights, cost, decision_vector


def newton_function(
    z: Any, state: Any, weights: Any, cost: Any, gradient: Any, hessian: Any, stationarity: Any
) -> ca.Function:
    """One projected Newton iteration on the box [-1, 1] (Bertsekas), damped as Levenberg-Marquardt
    where the Hessian is indefinite: a function (z, f, mu, s, weights) -> (z', f', mu').

    The entries at a bound whose gradient pushes outwards (within eps, the projected gradient's
    size capped at 1e-3) go onto it and stay there; on the others the Newton step on the reduced
    Hessian, factorized by Cholesky. Where that is not positive definite (an indefinite critic, the
    dynamics' turns) the Hessian plus mu times its largest diagonal entry: first the mu carried
    over, then tenfold more each time (from 1e-4 to 1) until a factorization succeeds, only those
    factorizations computed; all failing, the gradient scaled by the Hessian's diagonal. The step
    is projected on the box, and of the :data:`NEWTON_STEPS` sizes the one that lowers the
    objective the most by Armijo's rule is taken (none: z stays). mu carries over: a full or longer
    step divides it by ten, a cut step keeps it, a failed one multiplies it by ten -- so along
    negative curvature the iterations take the steps the model can be trusted with, and the longer
    ones follow it to the box's bounds."""
    n = z.numel()
    f = ca.SX.sym("f")
    eps = ca.fmin(1e-3, stationarity)
    active = ca.logic_or(ca.logic_and(z <= -1 + eps, gradient > 0), ca.logic_and(z >= 1 - eps, gradient < 0))
    free = 1 - active
    reduced = ca.diag(free) @ hessian @ ca.diag(free) + ca.diag(active)
    curvature = ca.fabs(ca.diag(hessian))
    scale = ca.mmax(curvature) + 1e-12
    scaled_gradient = -free * gradient / ca.fmax(curvature, 1e-6 * scale)
    # the active entries go onto their bound (one within eps of it would otherwise stay short of it,
    # its distance counted as the projected gradient for ever): the projection stops them there
    onto_bounds = -2.0 * active * ca.sign(gradient)
    parts = ca.Function(
        "newton_parts", [z, state, weights], [reduced, free * gradient, scaled_gradient, onto_bounds, scale]
    )

    if n <= CHOLESKY_ENTRIES:  # a Cholesky factorization written out: NaN where not positive definite
        matrix_s, rhs_s, tau_s = ca.SX.sym("R", n, n), ca.SX.sym("g", n), ca.SX.sym("tau")
        factor = ca.chol(matrix_s + tau_s * ca.SX.eye(n))  # upper triangular
        step_s = -ca.solve(factor, ca.solve(factor.T, rhs_s))
        solve = ca.Function("damped_solve", [matrix_s, rhs_s, tau_s], [step_s, ca.dot(rhs_s, step_s) < 0])
    else:  # CasADi's sparse LDL: compact code at any N (where the Cholesky's grows as N^3)
        matrix, rhs, tau = ca.MX.sym("R", n, n), ca.MX.sym("g", n), ca.MX.sym("tau")
        step = -ca.solve(matrix + tau * ca.MX.eye(n), rhs, "ldl")
        solve = ca.Function("damped_solve", [matrix, rhs, tau], [step, ca.dot(rhs, step) < 0])  # false for NaN

    zm, fm, mu_m = ca.MX.sym("z", n), ca.MX.sym("f"), ca.MX.sym("mu")
    sm, wm = ca.MX.sym("s", state.numel()), ca.MX.sym("w", weights.numel())
    r_m, g_m, fallback, bound_m, scale_m = parts(zm, sm, wm)
    rm, gm, dm, okm, tm = ca.MX.sym("R", n, n), ca.MX.sym("g", n), ca.MX.sym("d", n), ca.MX.sym("ok"), ca.MX.sym("t")
    keep = ca.Function("keep", [okm, dm, rm, gm, tm], [dm, okm])
    again = ca.Function("again", [okm, dm, rm, gm, tm], list(solve(rm, gm, tm)))
    solve_if_needed = ca.Function.if_else("solve_if_needed", keep, again)
    # the plain Newton step first (near a minimum the reduced Hessian is positive definite: quadratic
    # convergence at once), then the damping carried over, then tenfold more each time
    direction, found = solve(r_m, g_m, 0.0)
    mu = ca.if_else(found, 0.0, mu_m)
    direction, found = solve_if_needed(found, found, direction, r_m, g_m, mu * scale_m)
    for _ in range(DAMPING_TRIES):  # a factorization only where the ones before it failed
        mu = ca.if_else(found, mu, ca.fmin(ca.fmax(10.0 * mu, 1e-4), 1.0))
        direction, found = solve_if_needed(found, found, direction, r_m, g_m, mu * scale_m)
    direction = ca.if_else(found, direction, fallback) + bound_m

    d = ca.SX.sym("d", n)
    z_next, f_next, taken = z, f, ca.SX(0)
    for length in NEWTON_STEPS:  # the step that passes with the lowest objective wins
        trial = ca.fmin(ca.fmax(z + length * d, -1.0), 1.0)
        f_trial = ca.substitute(cost, z, trial)
        # Armijo's rule, with the objective's rounding allowed: at a minimum's precision limit the
        # decrease a Newton step predicts is below the objective's last bits (false for NaN)
        passes = f_trial <= f + ca.fmin(1e-4 * ca.dot(gradient, trial - z), 0.0) + ROUNDING * ca.fabs(f)
        better = ca.logic_and(passes, ca.logic_or(taken == 0, f_trial < f_next))
        z_next = ca.if_else(better, trial, z_next)
        f_next = ca.if_else(better, f_trial, f_next)
        taken = ca.if_else(better, length, taken)
    search = ca.Function("line_search", [z, f, d, state, weights], [z_next, f_next, taken])
    z_out, f_out, size = search(zm, fm, direction, sm, wm)
    mu_out = ca.if_else(
        size >= 1.0,
        ca.if_else(mu < 1e-6, 0.0, 0.1 * mu),
        ca.if_else(size > 0, mu, ca.fmin(ca.fmax(10.0 * mu, 1e-4), 1.0)),
    )
    return ca.Function("newton", [zm, fm, mu_m, sm, wm], [z_out, f_out, mu_out])


def descent_iteration(z: Any, state: Any, weights: Any, cost: Any, gradient: Any) -> ca.Function:
    """One iteration of the alternatives' descent: a projected gradient step preconditioned by a
    diagonal, with Nesterov's momentum (k / (k + 3)) restarted when a trial fails; the step grows
    by 1.5 on success and halves on a failed plain step. Monotone (a trial that does not lower the
    objective is refused), and fast along the flat, ill-conditioned valleys near the target: a
    held v moves the robot 0.022 m per interval, a held omega turns it 0.28 rad."""
    n = z.numel()
    last, step, f, k, scaling = (
        ca.SX.sym(name, size) for name, size in (("z_last", n), ("t", 1), ("f", 1), ("k", 1), ("d", n))
    )
    ahead = ca.fmin(ca.fmax(z + k / (k + 3.0) * (z - last), -1.0), 1.0)
    trial = ca.fmin(ca.fmax(ahead - step * scaling * ca.substitute(gradient, z, ahead), -1.0), 1.0)
    f_trial = ca.substitute(cost, z, trial)
    lower = f_trial < f  # false for NaN: the trial is refused
    return ca.Function(
        "descent_iteration",
        [z, last, step, f, k, state, weights, scaling],
        [
            ca.if_else(lower, trial, z),
            z,
            ca.if_else(lower, 1.5 * step, ca.if_else(k > 0, step, 0.5 * step)),
            ca.if_else(lower, f_trial, f),
            ca.if_else(lower, k + 1.0, 0.0),
        ],
    )


def descent_function(
    z: Any, state: Any, weights: Any, cost: Any, gradient: Any, hessian: Any, starts: int, steps: int
) -> ca.Function:
    """(starts as the columns of an (n_z, ``starts``) matrix, s, weights) -> (their ends after
    ``steps`` :func:`descent_iteration` s, the ends' objectives): every start descended on its own,
    its diagonal preconditioner the Hessian's diagonal at the start (its magnitude, floored)."""
    n = z.numel()
    zm, sm, wm = ca.MX.sym("z", n), ca.MX.sym("s", state.numel()), ca.MX.sym("w", weights.numel())
    curvature = ca.fabs(ca.diag(hessian))
    preconditioner = ca.Function(
        "preconditioner", [z, state, weights], [1.0 / ca.fmax(curvature, 1e-6 * ca.mmax(curvature) + 1e-12)]
    )
    value = ca.Function("value", [z, state, weights], [cost])
    walk, _, _, walked, _ = descent_iteration(z, state, weights, cost, gradient).mapaccum(
        "descent_iterations", steps, 5
    )(
        zm,
        zm,
        1.0,
        value(zm, sm, wm),
        0.0,
        ca.repmat(sm, 1, steps),
        ca.repmat(wm, 1, steps),
        ca.repmat(preconditioner(zm, sm, wm), 1, steps),
    )
    one = ca.Function("descend_one", [zm, sm, wm], [walk[:, -1], walked[-1]])
    columns = ca.MX.sym("starts", n, starts)
    ends, end_values = one.map(starts)(columns, ca.repmat(sm, 1, starts), ca.repmat(wm, 1, starts))
    return ca.Function("descent", [columns, sm, wm], [ends, end_values], ["starts", "s", "w"], ["ends", "values"])


@dataclass(frozen=True)
class SearchGraph:
    """The tick and its phases as CasADi functions (not compiled: common.math.actor_nlp.build
    compiles the tick; ``srl bench actor`` the phases, to time each on the tick's own inputs).

    ``tick``: :data:`TICK_INPUTS` -> :data:`TICK_OUTPUTS` (module docstring; its trace: the warm
    start, the alternative chosen for a polish, where the vertex search began and where it ended,
    the cold lane's plan before its polish).
    ``polish``: (z, f, s, weights) -> (z, f, stationarity, Newton iterations). ``descent``:
    (alternatives, s, weights) -> (their ends, objectives). ``sweep``: (z, f, s, weights) -> (z, f,
    moved). ``value``: (z, s, weights) -> the objective. ``decision_vector``: (z, s) -> the
    rollout's decision vector."""

    tick: ca.Function
    polish: ca.Function
    descent: ca.Function
    sweep: ca.Function
    value: ca.Function
    decision_vector: ca.Function
    n_z: int
    starts: int


def search_graph(problem: ActorProblem) -> SearchGraph:
    """The tick of ``problem`` (its multistart settings) as one CasADi function (module docstring)."""
    p = problem
    z, s, w, cost, decision_vector = scaled_objective(p)
    n, count = z.numel(), p.multistart_starts
    n_w = w.numel()
    hessian, gradient = ca.hessian(cost, z)
    stationarity = ca.mmax(ca.fabs(z - ca.fmin(ca.fmax(z - gradient, -1.0), 1.0)))
    value = ca.Function("value", [z, s, w], [cost])
    checked = ca.Function("checked", [z, s, w], [cost, stationarity])
    newton = newton_function(z, s, w, cost, gradient, hessian, stationarity)
    zm, fm, km, sm, wm = (
        ca.MX.sym("z", n),
        ca.MX.sym("f"),
        ca.MX.sym("k"),
        ca.MX.sym("s", p.state_dim),
        ca.MX.sym("w", n_w),
    )
    # -- the polish: up to newton_iterations; once the iterate is stationary the rest only pass it on
    done, mu = ca.MX.sym("done"), ca.MX.sym("mu")
    _, still = checked(zm, sm, wm)
    moving = still > NEWTON_TOLERANCE  # false for NaN: a NaN iterate is not iterated on
    stay = ca.Function("stay", [zm, fm, mu, sm, wm], [zm, fm, mu])
    stepped = ca.Function.if_else("newton_or_stay", newton, stay)(moving, zm, fm, mu, sm, wm)
    work = ca.Function(
        "polish_work", [zm, fm, km, done, mu, sm, wm], [stepped[0], stepped[1], km + moving, 1 - moving, stepped[2]]
    )
    rest = ca.Function("polish_done", [zm, fm, km, done, mu, sm, wm], [zm, fm, km, done, mu])
    iteration = ca.Function.if_else("polish_iteration", rest, work)
    iterations = p.newton_iterations
    path, values, counts, _, _ = ca.Function(
        "polish_step", [zm, fm, km, done, mu, sm, wm], list(iteration(done, zm, fm, km, done, mu, sm, wm))
    ).mapaccum("polish_iterations", iterations, 5)(
        zm, fm, 0.0, 0.0, 0.0, ca.repmat(sm, 1, iterations), ca.repmat(wm, 1, iterations)
    )
    end = path[:, -1]
    polish = ca.Function(
        "polish",
        [zm, fm, sm, wm],
        [end, values[-1], checked(end, sm, wm)[1], counts[-1]],
        ["z0", "f0", "s", "w"],
        ["z", "f", "stationarity", "iterations"],
    )
    unpolished = ca.Function("unpolished", [zm, fm, sm, wm], [zm, fm, 1e300, 0.0])
    polish_if = ca.Function.if_else("polish_if", polish, unpolished)

    # -- the search: every alternative descended multistart_iterations iterations
    descent = descent_function(z, s, w, cost, gradient, hessian, count, p.multistart_iterations)
    alternatives = ca.MX.sym("alternatives", n, count)
    no_descent = ca.Function("no_descent", [alternatives, sm, wm], [alternatives, ca.DM.ones(1, count) * 1e300])
    descent_if = ca.Function.if_else("descent_if", descent, no_descent)

    # the alternative to polish: the lowest of those below the warm answer, or within the margin once mature
    v_s, e_s, a_s = ca.SX.sym("V", count), ca.SX.sym("E", n, count), ca.SX.sym("A", count)
    f_warm, z_warm_s = ca.SX.sym("f_warm"), ca.SX.sym("z_warm", n)
    best_v, best_z, best_i = ca.SX(1e300), e_s[:, 0], ca.SX(-1)
    within = f_warm + p.multistart_margin * ca.fabs(f_warm)
    candidates = []
    for j in range(count):
        apart = ca.mmax(ca.fabs(e_s[:, j] - z_warm_s)) >= SAME_PLAN  # near the warm answer: its basin, renewed
        mature = ca.logic_and(ca.logic_and(a_s[j] >= MATURE, v_s[j] < within), apart)
        candidates.append(ca.logic_or(v_s[j] < f_warm, mature))  # false for NaN
    # the first alternative, the cold lane, is polished once it has descended COLD_PERIOD - 1 ticks
    # (or before, as any alternative, once it is below the warm answer)
    due = ca.logic_and(
        ca.logic_and(a_s[0] >= COLD_PERIOD - 1, v_s[0] < within), ca.mmax(ca.fabs(e_s[:, 0] - z_warm_s)) >= SAME_PLAN
    )
    candidates[0] = ca.logic_or(due, v_s[0] < f_warm)
    for j in range(1, count):  # the first, standing still, has a polish of its own
        better = ca.logic_and(candidates[j], v_s[j] < best_v)
        best_v = ca.if_else(better, v_s[j], best_v)
        best_z = ca.if_else(better, e_s[:, j], best_z)
        best_i = ca.if_else(better, j, best_i)
    choose = ca.Function(
        "choose_alternative",
        [v_s, e_s, a_s, f_warm, z_warm_s],
        [best_z, best_v, best_i, e_s[:, 0], v_s[0], candidates[0]],
    )

    # -- the vertex search: one sweep over the 2 n neighbours with one entry at either bound
    values_s, zs, fs = ca.SX.sym("values", 1, 2 * n), ca.SX.sym("z", n), ca.SX.sym("f")
    lowest, which = fs - 1e-6 * ca.fabs(fs) - 1e-12, ca.SX(-1)  # lower by more than rounding to move
    for j in range(2 * n):
        better = values_s[j] < lowest  # false for NaN
        lowest = ca.if_else(better, values_s[j], lowest)
        which = ca.if_else(better, j, which)
    moved_z = ca.vertcat(*[ca.if_else(which == i, 1.0, ca.if_else(which == n + i, -1.0, zs[i])) for i in range(n)])
    pick = ca.Function("pick_neighbour", [zs, fs, values_s], [moved_z, ca.if_else(which >= 0, lowest, fs), which >= 0])
    eye = np.eye(n)
    neighbours = ca.horzcat(ca.repmat(zm, 1, n) * (1 - eye) + eye, ca.repmat(zm, 1, n) * (1 - eye) - eye)
    neighbour_values = value.map(2 * n)(neighbours, ca.repmat(sm, 1, 2 * n), ca.repmat(wm, 1, 2 * n))
    sweep = ca.Function(
        "sweep", [zm, fm, sm, wm], list(pick(zm, fm, neighbour_values)), ["z0", "f0", "s", "w"], ["z", "f", "moved"]
    )
    again = ca.MX.sym("again")
    sweep_if = ca.Function.if_else(
        "sweep_if",
        ca.Function("sweep_again", [again, zm, fm, sm, wm], list(sweep(zm, fm, sm, wm))),
        ca.Function("no_sweep", [again, zm, fm, sm, wm], [zm, fm, 0.0]),
    )

    # -- the upkeep of the alternatives
    e_u, f_u, m_u, z_u, a_u, v_u, f_u0 = (
        ca.SX.sym("E", n, count), ca.SX.sym("F", n, count), ca.SX.sym("M", n, count), ca.SX.sym("z", n),
        ca.SX.sym("A", count), ca.SX.sym("V", count), ca.SX.sym("f"),
    )  # fmt: skip
    i_u = ca.SX.sym("lost")
    renewed_z, renewed_ages, renewals = [], [], ca.SX(0)
    for i in range(count):
        done = ca.mmax(ca.fabs(e_u[:, i] - z_u)) < SAME_PLAN
        for j in range(i):
            done = ca.logic_or(done, ca.mmax(ca.fabs(e_u[:, i] - e_u[:, j])) < SAME_PLAN)
        hopeless = ca.logic_and(a_u[i] >= RETIRE, ca.logic_not(v_u[i] < f_u0 + p.multistart_margin * ca.fabs(f_u0)))
        renew = ca.logic_or(ca.logic_or(done, hopeless), i_u == i)  # i_u: polished and lost, a worse minimum
        if i == 0:  # the cold lane: standing still again every COLD_PERIOD ticks
            renew = a_u[i] >= COLD_PERIOD - 1
        renewed_z.append(ca.if_else(renew, m_u[:, i] * f_u[:, i] + (1 - m_u[:, i]) * z_u, e_u[:, i]))
        renewed_ages.append(ca.if_else(renew, 0.0, a_u[i] + 1.0))
        renewals += renew
    upkeep = ca.Function(
        "upkeep",
        [e_u, f_u, m_u, z_u, a_u, v_u, f_u0, i_u],
        [ca.horzcat(*renewed_z), ca.vertcat(*renewed_ages), renewals],
    )
    e_p, z_p, i_p = ca.SX.sym("E", n, count), ca.SX.sym("z", n), ca.SX.sym("i")
    put = ca.Function(
        "put", [e_p, z_p, i_p], [ca.horzcat(*[ca.if_else(i_p == j, z_p, e_p[:, j]) for j in range(count)])]
    )

    # -- the tick
    n_s, m = p.state_dim, p.action_dim
    n_x = n_s * p.horizon + m * (p.horizon - 1)
    stage = n_s + m
    warm = ca.MX.sym("warm", n_x, 2)
    given, fresh, masks = (
        ca.MX.sym("alternatives", n, count),
        ca.MX.sym("fresh", n, count),
        ca.MX.sym("masks", n, count),
    )
    given_ages, flags = ca.MX.sym("ages", count), ca.MX.sym("flags", 3)
    has_earlier, search, shift = flags[0], flags[1], flags[2]
    bounds = ca.DM(np.tile(p.decision_bounds, p.horizon - 1))

    def scaled(x: Any) -> Any:  # the decision vector's stage decisions, scaled to [-1, 1]
        return ca.reshape(ca.reshape(x[:-n_s], stage, p.horizon - 1)[n_s:, :], n, 1) / bounds

    def shifted(z_any: Any) -> Any:  # one interval on: the last held decisions repeated
        return ca.vertcat(z_any[m:, :], z_any[-m:, :])

    def plan_of(z_any: Any) -> Any:  # the held actions (v, omega), one column per stage, inside both boxes
        decisions = ca.reshape(ca.fmin(ca.fmax(z_any, -1.0), 1.0) * bounds, m, p.horizon - 1)
        actions = ca.mtimes(ca.DM(p.action_matrix), decisions) if p.wheel_box else decisions
        limits = ca.DM(list(p.action_max))
        return ca.fmin(ca.fmax(actions, -ca.repmat(limits, 1, p.horizon - 1)), ca.repmat(limits, 1, p.horizon - 1))

    previous, earlier = scaled(warm[:, 0]), scaled(warm[:, 1])
    previous = ca.if_else(shift, shifted(previous), previous)
    bank = ca.if_else(shift, shifted(given), given)
    ages = given_ages
    f_previous, f_earlier = value(previous, sm, wm), value(earlier, sm, wm)
    use_earlier = ca.logic_and(has_earlier, f_earlier < f_previous)
    start = ca.if_else(use_earlier, earlier, previous)
    z_warm, f_warm_end, s_warm, warm_iterations = polish(start, ca.if_else(use_earlier, f_earlier, f_previous), sm, wm)
    ends, end_values = descent_if(search, bank, sm, wm)
    z_alt, v_alt, i_alt, z_still, v_still, still_eligible = choose(end_values.T, ends, ages, f_warm_end, z_warm)
    polished = ca.logic_and(search, i_alt >= 0)
    z_chosen = z_alt
    z_alt, f_alt, s_alt, _ = polish_if(polished, z_alt, v_alt, sm, wm)
    alt_won = ca.logic_and(polished, f_alt < f_warm_end)  # false for NaN
    z_mid, f_mid = ca.if_else(alt_won, z_alt, z_warm), ca.if_else(alt_won, f_alt, f_warm_end)
    s_mid = ca.if_else(alt_won, s_alt, s_warm)
    still_polished = ca.logic_and(search, still_eligible)
    z_cold = z_still
    z_still, f_still, s_still, _ = polish_if(still_polished, z_still, v_still, sm, wm)
    still_won = ca.logic_and(still_polished, f_still < f_mid)  # false for NaN
    alt_won = ca.logic_or(ca.logic_and(alt_won, ca.logic_not(still_won)), still_won)
    z_mid, f_mid = ca.if_else(still_won, z_still, z_mid), ca.if_else(still_won, f_still, f_mid)
    s_mid = ca.if_else(still_won, s_still, s_mid)
    z_v, f_v, moved, any_moved, sweeps = z_mid, f_mid, search, ca.MX(0), ca.MX(0)
    for _ in range(p.multistart_flips):
        sweeps += moved
        z_v, f_v, moved = sweep_if(moved, moved, z_v, f_v, sm, wm)
        any_moved = ca.logic_or(any_moved, moved)
    z_vp, f_vp, s_vp, _ = polish_if(any_moved, z_v, f_v, sm, wm)
    vertex_won = ca.logic_and(any_moved, f_vp < f_mid)
    z_out = ca.if_else(vertex_won, z_vp, z_mid)
    f_out = ca.if_else(vertex_won, f_vp, f_mid)
    s_out = ca.if_else(vertex_won, s_vp, s_mid)
    ends = put(ends, z_alt, ca.if_else(polished, i_alt, -1))
    lost = ca.if_else(ca.logic_and(polished, ca.logic_not(alt_won)), i_alt, -1)
    kept: Any
    kept_ages: Any
    replaced: Any
    kept, kept_ages, replaced = upkeep(ends, fresh, masks, z_out, ages, end_values.T, f_out, lost)
    kept = ca.if_else(search, kept, bank)
    kept_ages = ca.if_else(search, kept_ages, ages)
    replaced = ca.if_else(search, replaced, 0)
    report = ca.vertcat(
        warm_iterations, search, polished, alt_won, any_moved, vertex_won, replaced, sweeps, still_polished
    )
    trace = ca.horzcat(start, z_chosen, z_mid, z_v, z_cold)
    outputs: list[Any] = [decision_vector(z_out, sm), plan_of(z_out), f_out, s_out, kept, kept_ages, trace, report]
    inputs: list[Any] = [sm, wm, warm, given, fresh, masks, given_ages, flags]
    tick = ca.Function("argmin_tick", inputs, outputs, list(TICK_INPUTS), list(TICK_OUTPUTS))
    return SearchGraph(tick, polish, descent, sweep, value, decision_vector, n, count)


def fresh_starts(problem: ActorProblem, rows: int = 64, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The table the alternatives are renewed from, in turn: (values, masks), each ``(rows, n_z)``;
    a renewed alternative is ``masks * values + (1 - masks) * answer``. The first rows are whole
    plans -- standing still, each action at either bound alone (the unicycle: full speed ahead
    and back, turning either way), the first action's bounds in turn, both ways -- then,
    alternately, one of those and a random vertex of the box scaled by 0.3-1, half of the random
    ones only on 1-6 entries of the answer (a perturbation of the answer, as an iterated local
    search takes). Seeded: a run never depends on another."""
    p = problem
    n_act, m = p.horizon - 1, p.action_dim
    n = m * n_act
    # the wheel box: both wheels at the rim speed (straight) or opposite (turning in place)
    rim = p.wheel_rim_speed if p.wheel_box else 0.0
    extremes = (rim, 2.0 * rim / p.wheel_separation) if p.wheel_box else p.action_max
    to_decision = np.linalg.inv(p.action_matrix)
    bounds = np.array(p.decision_bounds)

    def held(*actions: tuple[float, ...]) -> np.ndarray:
        stages = [np.clip(to_decision @ np.array(actions[i % len(actions)]) / bounds, -1.0, 1.0) for i in range(n_act)]
        return np.concatenate(stages)

    def only(i: int, value: float) -> tuple[float, ...]:  # action i at value, the others zero
        return tuple(value if j == i else 0.0 for j in range(m))

    # standing still; each action at either bound alone (the unicycle: ahead, back, turning either
    # way); the first action's bounds in turn, both ways
    whole = [held(only(0, 0.0))]
    for i, extreme in enumerate(extremes):
        whole += [held(only(i, extreme)), held(only(i, -extreme))]
    whole += [held(only(0, extremes[0]), only(0, -extremes[0])), held(only(0, -extremes[0]), only(0, extremes[0]))]
    rng = np.random.default_rng(seed)
    values, masks = list(whole), [np.ones(n) for _ in whole]
    while len(values) < rows:
        values.append(rng.choice([-1.0, 1.0], n) * rng.uniform(0.3, 1.0))
        mask = np.ones(n)
        if rng.uniform() < 0.5:
            mask[:] = 0.0
            mask[rng.choice(n, int(rng.integers(1, min(6, n) + 1)), replace=False)] = 1.0
        masks.append(mask)
        values.append(whole[len(values) % len(whole)])
        masks.append(np.ones(n))
    return np.array(values[:rows]), np.array(masks[:rows])
