"""The stacked actors (section III, the actor objective, and Remark on the complemented stack).

Decision variables are the held actions ``u_1 .. u_{N-1}``; ``s_1`` is the measured state and
``s_2 .. s_N`` are predicted (Euler by default, the paper's choice). The problem is written in
multiple-shooting form -- the predicted states are variables too, tied by equality
constraints -- because that gives the stage-wise structure fatrop exploits. It is built ONCE
per (agent, horizon); the measured state enters through the bounds of ``s_1`` (``lbx = ubx``)
and the critic weights through the parameter vector, so a step never rebuilds anything.

| agent   | objective                                                              |
|---------|------------------------------------------------------------------------|
| mpc     | sum_i delta r(s_i, u_i)                                                |
| rlq     | sum_i Qhat(s_i, u_i; w)                                                |
| rlqv    | sum_i Qhat(s_i, u_i; w) + Jhat(s_N; v)                                 |
| rlqv+   | sum_i [Qhat(s_i, u_i; w) + (N - i) delta r(s_i, u_i)] + Jhat(s_N; v)   |

The learned weights may make the problem non-convex (and the dynamics already do). When the
solver fails, :meth:`StackedActor.step` still returns a finite, bounded action: the next
action of the previous plan, else zero velocity, and counts the failure.
"""

from __future__ import annotations

import functools
import logging
import time
from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np

from common.math.agents import AGENTS, Agent, learns, uses_value_critic
from common.math.arrival import ArrivalRule
from common.math.dynamics import ACTION_DIM, PREDICTORS, STATE_DIM
from common.math.features import Q_FEATURES, V_FEATURES, feature_index_pairs, phi_q, phi_v, stage_cost
from common.math.stats import Window
from common.system.jit import build_with_jit, compiler_available

log = logging.getLogger(__name__)

STAGE = STATE_DIM + ACTION_DIM  # entries of one stage (s_i, u_i) in the decision vector
# The global phase's starts (ActorProblem.multistart): the shifted and the earlier plan (or, with
# no plan yet, turning in place either way), standing still, full speed ahead, full speed back.
GLOBAL_STARTS = 5


@dataclass(frozen=True)
class ActorProblem:
    """Everything that fixes the shape of the optimization problem (changing it = rebuild)."""

    agent: Agent
    horizon: int  # N: N - 1 held actions, N predicted states
    sampling_time: float
    cost_diag: tuple[float, ...]  # diag(R), length 5
    v_max: float
    omega_max: float
    predictor: str = "euler"
    solver: str = "fatrop"
    jit: bool = True
    jit_cache: str = ""  # a directory of compiled objects kept across builds ("" = none): common/system/jit.py
    max_iter: int = 100
    tolerance: float = 1e-8
    mu_init: float = 0.01  # interior-point barrier start; small suits the warm start (measured)
    # How far the interior point pushes the initial guess off the action bounds (the solvers'
    # bound_push and bound_frac). The defaults (0.01) move a saturated warm start inward and
    # cost iterations to walk it back; 1e-4 keeps it (measured, README "Actor benchmark").
    bound_push: float = 1e-4
    # The wheel-speed box (issue 21): a differential drive limits each wheel, not v and omega
    # apart: |v +/- omega * wheel_separation / 2| <= wheel_speed_max * wheel_radius. 0 = off
    # (the paper's method boxes v and omega only). See :attr:`wheel_rim_speed`.
    wheel_speed_max: float = 0.0  # [rad/s] at the wheel
    wheel_radius: float = 0.033  # [m] TurtleBot3 Burger
    wheel_separation: float = 0.160  # [m] TurtleBot3 Burger
    # The actor uses the nearest positive semi-definite quadratic to each learned critic
    # (:func:`nearest_psd_weights`) instead of the critic as fitted (the paper's). Issue 21: a
    # fitted Qhat indefinite in (s, u) predicts negative costs near the target that only motion
    # reaches, and the actor chases them at full speed (README "Chatter"). Not a shape change.
    convex_critics: bool = False
    # The argmin (issue 18): before the solver, a cheap global phase -- projected-gradient
    # descent on the objective along a rollout, from several starts at once (the shifted and the
    # earlier plan, standing still, full speed ahead, full speed back; :meth:`StackedActor.
    # _global_guess`) -- and the solver polishes the start whose descent ended lowest. False:
    # the solver starts from the cheaper of the shifted and the earlier plan (merit only), which
    # often stays in a worse local minimum with non-convex critics (README "The argmin").
    multistart: bool = False
    multistart_iterations: int = 50  # projected-gradient iterations per start (compiled, ~1-3 us each at N = 12)
    # The merit cannot tell: also polish the lowest end of the other kind of start (warm: the
    # shifted and earlier plans; fresh: the other three) when its objective is within this share
    # of the lowest's, and keep the lower solution (StackedActor._runner_up). 0: the lowest only.
    multistart_margin: float = 0.1
    # Every this many solves, polish the other kind of start's lowest end whatever the merit says
    # (a fresh descent may stop far short of a lower minimum: near the target its end often
    # looks worse than a converged warm plan whose basin is worse); the warm start then keeps a
    # lower minimum once found. 0: never (the margin alone decides).
    multistart_refresh: int = 3
    # After the polish, a vertex search (StackedActor._flip_search): every single held-action
    # entry set to either bound, the lowest of these 2 (N - 1) x 2 neighbours along the rollout
    # taken while it lowers the objective, up to this many sweeps, and the solver polishes the
    # result (kept when lower). An indefinite critic is concave along some action directions:
    # along them a local minimum sits on one bound while the other may be lower, which neither
    # the descent nor the interior point can see. 0: off.
    multistart_flips: int = 0

    def __post_init__(self) -> None:
        if self.agent not in AGENTS:
            raise ValueError(f"unknown agent {self.agent!r}; choose one of {', '.join(AGENTS)}")
        if self.horizon < 2:
            raise ValueError(f"horizon N must be >= 2 (N - 1 >= 1 actions), got {self.horizon}")
        if not (np.isfinite(self.sampling_time) and self.sampling_time > 0):
            raise ValueError(f"sampling_time must be a positive number, got {self.sampling_time}")
        if len(self.cost_diag) != STATE_DIM + ACTION_DIM or not all(np.isfinite(c) and c >= 0 for c in self.cost_diag):
            raise ValueError(f"cost_diag must be 5 finite non-negative numbers, got {self.cost_diag}")
        for name in ("v_max", "omega_max"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value}")
        if self.predictor not in PREDICTORS:
            raise ValueError(f"unknown predictor {self.predictor!r}; choose one of {sorted(PREDICTORS)}")
        if self.solver not in ("fatrop", "ipopt"):
            raise ValueError(f"unknown solver {self.solver!r}; choose fatrop or ipopt")
        if not (np.isfinite(self.mu_init) and self.mu_init > 0):
            raise ValueError(f"mu_init must be a positive number, got {self.mu_init}")
        if not (np.isfinite(self.bound_push) and 0 < self.bound_push <= 0.5):
            raise ValueError(f"bound_push must be in (0, 0.5], got {self.bound_push}")
        if not (np.isfinite(self.multistart_margin) and self.multistart_margin >= 0):
            raise ValueError(f"multistart_margin must be a number >= 0, got {self.multistart_margin}")
        if self.multistart_refresh < 0:
            raise ValueError(f"multistart_refresh must be >= 0 (0 = never), got {self.multistart_refresh}")
        if self.multistart_iterations < 1:
            raise ValueError(f"multistart_iterations must be >= 1, got {self.multistart_iterations}")
        if self.multistart_flips < 0:
            raise ValueError(f"multistart_flips must be >= 0 (0 = off), got {self.multistart_flips}")
        if not (np.isfinite(self.wheel_speed_max) and self.wheel_speed_max >= 0):
            raise ValueError(f"wheel_speed_max must be >= 0 (0 = no wheel box), got {self.wheel_speed_max}")
        for name in ("wheel_radius", "wheel_separation"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value}")

    @property
    def wheel_box(self) -> bool:
        return self.wheel_speed_max > 0

    @property
    def wheel_rim_speed(self) -> float:
        """The bound on each wheel's rim speed ``v +/- omega * separation / 2`` [m/s].

        ``wheel_speed_max * wheel_radius``, but no more than ``v_max`` and
        ``omega_max * separation / 2``: then the wheel box (a diamond in (v, omega)) lies inside
        the (v, omega) box and is the only bound the problem needs, as simple bounds on the
        wheels' rim speeds (the decision variables when the box is on). TurtleBot3 Burger:
        6.67 rad/s x 0.033 m = 0.2201 m/s, held to v_max = 0.22 m/s; the largest omega is then
        0.22 / 0.08 = 2.75 rad/s < 2.84."""
        half_track = 0.5 * self.wheel_separation
        return min(self.wheel_speed_max * self.wheel_radius, self.v_max, self.omega_max * half_track)

    @property
    def action_matrix(self) -> np.ndarray:
        """``T`` with (v, omega) = ``T`` d for one stage's decision variables d: the identity,
        or with the wheel box on, d = the wheels' rim speeds (right, left), v = (r + l) / 2,
        omega = (r - l) / separation. Linear, so the problem keeps its stage-wise structure."""
        if not self.wheel_box:
            return np.eye(ACTION_DIM)
        return np.array([[0.5, 0.5], [1.0 / self.wheel_separation, -1.0 / self.wheel_separation]])


@functools.cache
def _pair_indices(dim: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows, columns (common.math.features' order) and 1 / 2 (diagonal / off) of the quadratic's weights."""
    rows, cols = np.array(feature_index_pairs(dim)).T
    return rows, cols, np.where(rows == cols, 1.0, 2.0)


def _quadratic_matrix(weights: np.ndarray, dim: int) -> np.ndarray:
    """The symmetric ``M`` with ``<weights, phi(z)> = z^T M z`` (features: common.math.features)."""
    rows, cols, scale = _pair_indices(dim)
    matrix = np.zeros((dim, dim))
    matrix[rows, cols] = weights / scale
    matrix[cols, rows] = weights / scale  # diagonal: w_ii; off-diagonal: w_ij / 2 on both sides
    return matrix


def nearest_psd_weights(weights: np.ndarray, dim: int) -> np.ndarray:
    """The weights of the nearest (Frobenius) positive semi-definite quadratic to
    ``<weights, phi(z)>``: its matrix with the negative eigenvalues set to zero. A PSD quadratic
    is never negative, as a cost-to-go of a non-negative stage cost never is. ~10-20 us."""
    eigenvalues, vectors = np.linalg.eigh(_quadratic_matrix(weights, dim))
    if eigenvalues[0] >= 0.0:
        return np.array(weights, dtype=float)
    projected = (vectors * np.maximum(eigenvalues, 0.0)) @ vectors.T
    rows, cols, scale = _pair_indices(dim)
    out: np.ndarray = scale * projected[rows, cols]
    return out


@dataclass
class ActorStep:
    """What one actor step produced. ``action`` is always finite and within bounds."""

    action: np.ndarray
    plan: np.ndarray  # (N-1, 2) held actions, u_1 first
    objective: float  # nan: no solution (a failed solve, or "arrived": no solve)
    success: bool
    solve_seconds: float
    status: str


@dataclass
class ActorCounters:
    """Solves, failures and the step times (a fixed window: an actor runs for days)."""

    solves: int = 0
    failures: int = 0
    arrived_steps: int = 0  # steps at which the arrival rule held the robot (no solve)
    second_solves: int = 0  # steps that also polished the runner-up end (multistart_margin)
    flip_solves: int = 0  # steps whose vertex search found a lower neighbour and polished it (multistart_flips)
    hurried_solves: int = 0  # steps solved in a hurry: the runner-up polish and vertex search skipped
    solve_seconds: Window = field(default_factory=Window)


@dataclass
class ActorMemory:
    """What one robot's actor carries from one step to the next: its last two plans (the warm
    starts), its arrival rule, its counters and the refresh's phase. Everything else of a :class:`StackedActor` (the
    compiled problem and its buffers, which every step rewrites completely before solving) holds
    nothing between steps, so one built actor serves many robots, one step at a time, each with
    its own memory (:meth:`StackedActor.swap_memory`; services/actor/host.py, issue 16)."""

    previous_x: np.ndarray | None = None
    earlier_x: np.ndarray | None = None
    arrival: ArrivalRule | None = None
    counters: ActorCounters = field(default_factory=ActorCounters)
    episode_solves: int = 0  # solves since the last reset: the phase of multistart_refresh


class StackedActor:
    """One agent at one horizon, built once, stepped every sampling interval."""

    def __init__(self, problem: ActorProblem, arrival: ArrivalRule | None = None) -> None:
        self.problem = problem
        # The goal checker (common.math.arrival): inside its tolerances step() commands exactly
        # zero, status "arrived", without solving. None = the paper's method (never stops).
        self.arrival = arrival
        self.counters = ActorCounters()
        self._previous_x: np.ndarray | None = None
        self._earlier_x: np.ndarray | None = None  # the solution one step before _previous_x
        self._episode_solves = 0  # solves since the last reset (the refresh's phase)
        self._solver, lbx, ubx, n_g = self._build()
        self._n_x = lbx.size
        # Zero-copy calls: CasADi's buffer API reads the inputs from, and writes the outputs
        # into, these numpy arrays in place (converting numpy to DM costs ~25 us per argument,
        # a third of a warm-started solve). They must live as long as the solver and are only
        # ever written element-wise, never rebound.
        self._x0 = np.zeros(self._n_x)
        self._params = np.zeros(Q_FEATURES + V_FEATURES)
        self._lbx_np = lbx
        self._ubx_np = ubx
        self._zeros_g = np.zeros(n_g)
        self._zeros_x = np.zeros(self._n_x)
        self._x_out = np.zeros(self._n_x)
        self._f_out = np.zeros(1)
        self._buffer, self._evaluate = self._solver.buffer()
        for index, array in enumerate(
            (
                self._x0,
                self._params,
                self._lbx_np,
                self._ubx_np,
                self._zeros_g,
                self._zeros_g,
                self._zeros_x,
                self._zeros_g,
            )
        ):
            self._buffer.set_arg(index, memoryview(array))  # type: ignore[call-arg, arg-type]  # casadi's stub
        self._buffer.set_res(0, memoryview(self._x_out))  # type: ignore[call-arg, arg-type]  # casadi's stub
        self._buffer.set_res(1, memoryview(self._f_out))  # type: ignore[call-arg, arg-type]  # casadi's stub
        self._action_bounds = np.array([problem.v_max, problem.omega_max])
        self._decision_bounds = self._ubx_np[STATE_DIM:STAGE].copy()
        # The warm-start merit, called the same zero-copy way: (s_1, actions, weights) -> cost.
        self._merit_state = np.zeros(STATE_DIM)
        self._merit_actions = np.zeros((problem.horizon - 1, ACTION_DIM))  # row-major = u_1, u_2, ...
        self._merit_out = np.zeros(1)
        self._merit_buffer, self._evaluate_merit = self._merit.buffer()
        for index, array in enumerate((self._merit_state, self._merit_actions, self._params)):
            self._merit_buffer.set_arg(index, memoryview(array))  # type: ignore[call-arg, arg-type]  # casadi's stub
        self._merit_buffer.set_res(0, memoryview(self._merit_out))  # type: ignore[call-arg, arg-type]  # casadi's stub
        if problem.multistart:
            self._setup_global_phase()
        if problem.multistart and problem.multistart_flips:
            self._setup_flip_search()

    def _setup_global_phase(self) -> None:
        """The global phase's zero-copy buffers and its fixed starts (see _global_phase).

        ``_starts`` has one row per start (CasADi reads the (n_z, starts) matrix column by
        column, so the rows of a C-ordered array are its columns): rows 0-1 the warm starts,
        rows 2-4 standing still, full speed ahead and full speed back, written once."""
        p = self.problem
        n_act = p.horizon - 1
        self._starts = np.zeros((GLOBAL_STARTS, ACTION_DIM * n_act))
        self._ends = np.zeros_like(self._starts)
        self._end_values = np.zeros(GLOBAL_STARTS)
        self._end_vectors = np.zeros((GLOBAL_STARTS, self._n_x))
        self._global_state = np.zeros(STATE_DIM)
        self._shifted = np.zeros(self._n_x)
        self._segment = np.zeros(self._n_x)
        if p.wheel_box:  # both wheels at the rim speed: straight; opposite: turning in place
            speed, turn = p.wheel_rim_speed, 2.0 * p.wheel_rim_speed / p.wheel_separation
        else:
            speed, turn = p.v_max, p.omega_max
        to_decision = np.linalg.inv(p.action_matrix)

        def scaled(action: tuple[float, float]) -> np.ndarray:
            row: np.ndarray = np.clip(to_decision @ np.array(action) / self._decision_bounds, -1.0, 1.0)
            return np.tile(row, n_act)

        self._turning = (scaled((0.0, turn)), scaled((0.0, -turn)))
        for row, action in zip(range(2, GLOBAL_STARTS), ((0.0, 0.0), (speed, 0.0), (-speed, 0.0)), strict=True):
            self._starts[row] = scaled(action)
        self._global_buffer, self._evaluate_global = self._global.buffer()
        for index, array in enumerate((self._starts, self._global_state, self._params)):
            self._global_buffer.set_arg(index, memoryview(array))  # type: ignore[call-arg, arg-type]  # casadi's stub
        for index, array in enumerate((self._ends, self._end_values, self._end_vectors)):
            self._global_buffer.set_res(index, memoryview(array))  # type: ignore[call-arg, arg-type]  # casadi's stub

    def _setup_flip_search(self) -> None:
        """The vertex search's zero-copy buffers (see _flip_search). ``_candidates`` has one row
        per neighbour (CasADi reads the (n_z, 2 n_z) matrix column by column)."""
        n_z = ACTION_DIM * (self.problem.horizon - 1)
        self._flat_bounds = np.tile(self._decision_bounds, self.problem.horizon - 1)
        self._candidates = np.zeros((2 * n_z, n_z))
        self._candidate_values = np.zeros(2 * n_z)
        self._flip_state = np.zeros(STATE_DIM)
        self._flip_buffer, self._evaluate_flips = self._flips.buffer()
        for index, array in enumerate((self._flip_state, self._candidates, self._params)):
            self._flip_buffer.set_arg(index, memoryview(array))  # type: ignore[call-arg, arg-type]  # casadi's stub
        self._flip_buffer.set_res(0, memoryview(self._candidate_values))  # type: ignore[call-arg, arg-type]  # casadi's stub
        self._rollout_decisions = np.zeros(n_z)
        self._rollout_out = np.zeros(self._n_x)
        self._rollout_buffer, self._evaluate_rollout = self._rollout.buffer()
        for index, array in enumerate((self._flip_state, self._rollout_decisions)):
            self._rollout_buffer.set_arg(index, memoryview(array))  # type: ignore[call-arg, arg-type]  # casadi's stub
        self._rollout_buffer.set_res(0, memoryview(self._rollout_out))  # type: ignore[call-arg, arg-type]  # casadi's stub

    # -- construction -------------------------------------------------------------------
    def _objective(self, states: list[Any], actions: list[Any], w: Any, v: Any) -> Any:
        """The agent's objective (module docstring table) over N states and N - 1 actions."""
        p = self.problem
        objective: Any = 0
        for i, (s_i, u_i) in enumerate(zip(states[:-1], actions, strict=True)):
            running = p.sampling_time * stage_cost(s_i, u_i, p.cost_diag)
            if not learns(p.agent):
                objective += running
            else:
                objective += ca.dot(w, phi_q(s_i, u_i))
                if p.agent == "rlqv+":
                    # Remark (complemented stack): (N - i) r with the paper's i = 1..N-1.
                    objective += (p.horizon - (i + 1)) * running
        if uses_value_critic(p.agent):
            objective += ca.dot(v, phi_v(states[-1]))
        return objective

    def _global_phase(self, state: Any, params: Any, bounds: list[float]) -> tuple[list[Any], list[Any]]:
        """The global phase's function: (starts, s_1, weights) -> (ends, their objective, their
        decision vectors), every start descended on its own (ActorProblem.multistart).

        A start is the stage decisions scaled to the box [-1, 1] (z = d / bound), flattened
        u_1 first; the objective is the agent's along the predictor's rollout from s_1 (single
        shooting, as the merit). Each start takes ``multistart_iterations`` projected-gradient
        iterations with an adaptive step: a trial z - t grad, clipped to the box, is taken if it
        lowers the objective (then t doubles), else t halves. Descent from a start ends in (or
        near) the local minimum whose basin holds it, as a cold SLSQP solve from standing still
        does, at a fraction of the cost of an interior-point solve from there (README "The
        argmin"); the solver then polishes the lowest end. The iterations are a mapaccum and
        the starts a map: compiled once, no Python per iteration.
        """
        p = self.problem
        n_act, step = p.horizon - 1, PREDICTORS[p.predictor]
        n_z = ACTION_DIM * n_act
        z = ca.SX.sym("z", n_z)
        scale = ca.DM(bounds)
        decisions = [z[ACTION_DIM * i : ACTION_DIM * (i + 1)] * scale for i in range(n_act)]
        to_action = ca.DM(p.action_matrix)
        actions = [ca.mtimes(to_action, d_i) for d_i in decisions] if p.wheel_box else decisions
        rollout = [state]
        for u_i in actions:
            rollout.append(step(rollout[-1], u_i, p.sampling_time))
        weights = ca.SX.sym("p", params.numel())
        w, v = weights[:Q_FEATURES], weights[Q_FEATURES:]
        objective = self._objective(rollout, actions, w, v)
        value = ca.Function("descent_value", [z, state, weights], [objective])
        gradient = ca.Function("descent_gradient", [z, state, weights], [ca.gradient(objective, z)])
        # A diagonal preconditioner, the Hessian's diagonal at the start (its magnitude, floored):
        # a held v moves the robot 0.022 m per step, a held omega turns it 0.28 rad, so the
        # scaled problem is badly conditioned and plain gradient steps crawl along v.
        curvature = ca.fabs(ca.diag(ca.hessian(objective, z)[0]))
        curvature = ca.fmax(curvature, 1e-6 * ca.mmax(curvature) + 1e-12)
        diagonal = ca.Function("descent_diagonal", [z, state, weights], [1.0 / curvature])
        stages: list[Any] = []
        for s_i, d_i in zip(rollout[:-1], decisions, strict=True):
            stages += [s_i, d_i]
        decision_vector = ca.Function("descent_rollout", [z, state], [ca.vertcat(*stages, rollout[-1])])

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
        one = ca.Function("descend", [start, s_mx, p_mx], [end, values[-1], decision_vector(end, s_mx)])
        starts = ca.MX.sym("starts", n_z, GLOBAL_STARTS)
        ends = one.map(GLOBAL_STARTS)(starts, ca.repmat(s_mx, 1, GLOBAL_STARTS), ca.repmat(p_mx, 1, GLOBAL_STARTS))
        return [starts, s_mx, p_mx], list(ends)

    def _flip_functions(
        self, merit_args: tuple[list[Any], list[Any]], rollout: list[Any], decisions: list[Any]
    ) -> tuple[tuple[list[Any], list[Any]], tuple[list[Any], list[Any]]]:
        """The vertex search's functions (ActorProblem.multistart_flips): (s_1, candidates,
        weights) -> the objective of each candidate's actions along the rollout (the merit,
        mapped over the 2 n_z columns of the candidates matrix), and (s_1, decisions) -> the
        decision vector of their rollout (the solver's start)."""
        n_z = ACTION_DIM * (self.problem.horizon - 1)
        merit = ca.Function("merit_of_candidate", *merit_args)
        state, candidates = ca.MX.sym("s", STATE_DIM), ca.MX.sym("candidates", n_z, 2 * n_z)
        params = ca.MX.sym("p", merit.size1_in(2))
        values = merit.map(2 * n_z)(ca.repmat(state, 1, 2 * n_z), candidates, ca.repmat(params, 1, 2 * n_z))
        stages: list[Any] = []
        for s_i, d_i in zip(rollout[:-1], decisions, strict=True):
            stages += [s_i, d_i]
        vector = ([rollout[0], ca.vertcat(*decisions)], [ca.vertcat(*stages, rollout[-1])])
        return ([state, candidates, params], [values]), vector

    def _build(self) -> tuple[ca.Function, np.ndarray, np.ndarray, int]:
        p = self.problem
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

        objective = self._objective(states, actions, w, v)
        constraints = [states[i + 1] - step(states[i], actions[i], p.sampling_time) for i in range(n_act)]
        # The same objective along a single-shooting rollout of the actions from s_1 (states
        # consistent with the predictor): the merit by which step() picks its warm start.
        rollout = [states[0]]
        for u_i in actions:
            rollout.append(step(rollout[-1], u_i, p.sampling_time))
        merit_args = ([states[0], ca.vertcat(*decisions), ca.vertcat(w, v)], [self._objective(rollout, actions, w, v)])
        searches = p.multistart and p.multistart_flips > 0
        flip_args = self._flip_functions(merit_args, rollout, decisions) if searches else None
        bounds = [p.wheel_rim_speed] * ACTION_DIM if p.wheel_box else [p.v_max, p.omega_max]
        global_args = self._global_phase(states[0], ca.vertcat(w, v), bounds) if p.multistart else None

        # Stage-wise ordering x1 u1 x2 u2 ... x_N, as fatrop's structure detection expects.
        variables = []
        for i in range(n_act):
            variables += [states[i], decisions[i]]
        variables.append(states[-1])
        nlp = {
            "x": ca.vertcat(*variables),
            "p": ca.vertcat(w, v),
            "f": objective,
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
        # dict (~20 us, 3 % of a solve); step() reads the stats only after a failure.
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

        def functions(compiler: str | None) -> Any:
            solver = ca.nlpsol(name, p.solver, nlp, options | compiled("srl_actor", compiler))
            self._merit = ca.Function("merit", *merit_args, compiled("srl_merit", compiler))
            if global_args is not None:
                self._global = ca.Function("global_phase", *global_args, compiled("srl_global", compiler))
            if flip_args is not None:
                self._flips = ca.Function("vertex_neighbours", *flip_args[0], compiled("srl_flips", compiler))
                self._rollout = ca.Function("rollout", *flip_args[1], compiled("srl_rollout", compiler))
            return solver

        solver = build_with_jit(functions, p.jit_cache) if jit else functions(None)
        elapsed = time.perf_counter() - started
        # a long build is worth a line at the default level; a usual one (N = 12: ~1 s) is not
        log.log(
            logging.WARNING if elapsed > 10.0 else logging.INFO if elapsed > 1.0 else logging.DEBUG,
            "built the actor problem (N = %d, agent %s) in %.1f s",
            p.horizon,
            p.agent,
            elapsed,
        )
        return solver, np.array(lbx, dtype=float), np.array(ubx, dtype=float), n_g

    # -- stepping -----------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the previous plans and arrival (new episode, or the plan no longer matches the robot)."""
        self._previous_x = None
        self._earlier_x = None
        # the refresh's phase (multistart_refresh) counts from here: a run never depends on
        # what the same actor solved before (the experiment's workers reuse their actors)
        self._episode_solves = 0
        if self.arrival is not None:
            self.arrival.reset()

    def swap_memory(self, memory: ActorMemory) -> ActorMemory:
        """Step on with ``memory`` (another robot's plans, arrival rule and counters); returns
        the memory held until now. Not thread-safe: one step at a time per built actor."""
        held = ActorMemory(self._previous_x, self._earlier_x, self.arrival, self.counters, self._episode_solves)
        self._previous_x, self._earlier_x = memory.previous_x, memory.earlier_x
        self.arrival, self.counters = memory.arrival, memory.counters
        self._episode_solves = memory.episode_solves
        return held

    @property
    def arrived(self) -> bool:
        """The arrival rule holds the robot at the target (False without a rule)."""
        return self.arrival is not None and self.arrival.arrived

    def _initial_guess(self, state: np.ndarray, hurry: bool = False) -> None:
        """Warm start, written in place into the solver's input ``self._x0`` (the weights
        must already be in ``self._params``). ``hurry`` with a previous plan: the merit-only warm
        start below instead of the global phase (multistart), ~0.2 ms less at N = 12.

        The usual guess is the previous primal solution shifted by one stage, last stage
        repeated: with multiple shooting it needs not satisfy the dynamics, so shifting the
        whole vector (states and actions) is both cheap and closer than a re-rollout. The
        other candidate is the solution from two steps ago, unshifted, and the one whose
        actions cost less along a rollout from ``state`` is used. That candidate wins when the
        loop alternates between two local minima (period-2 chattering, which the benchmark's
        non-convex "learned" weights produce: the robot returns to the state of two steps
        ago, where that solution is optimal, while the shifted guess lies in the other basin
        and costs 2-4 times the iterations). A merit evaluation (JIT) costs ~2 us.
        """
        x0 = self._x0
        if self.problem.multistart and not (hurry and self._previous_x is not None):
            self._global_guess(state)
        elif self._previous_x is None:
            x0[:] = 0.0
            for k in range(STATE_DIM):
                x0[k::STAGE] = state[k]
        else:
            self._shift_into(x0, self._previous_x)
            if self._earlier_x is not None:
                self._merit_state[:] = state
                if self._merit_of(self._earlier_x) < self._merit_of(x0):
                    x0[:] = self._earlier_x
        x0[:STATE_DIM] = state

    def _global_guess(self, state: np.ndarray) -> None:
        """The multistart guess (ActorProblem.multistart), written into ``self._x0``: every
        start descended by the global phase (_global_phase) from ``state``, and the rollout of
        the end with the lowest objective. The warm starts are the shifted previous plan and the
        plan of two steps ago (the candidates of the merit-only guess, see _initial_guess)."""
        starts, bounds = self._starts, self._decision_bounds
        if self._previous_x is None:
            starts[0], starts[1] = self._turning
        else:
            self._shift_into(self._shifted, self._previous_x)
            np.clip((self._decisions_of(self._shifted) / bounds).ravel(), -1.0, 1.0, out=starts[0])
            if self._earlier_x is None:
                starts[1] = self._turning[0]
            else:
                np.clip((self._decisions_of(self._earlier_x) / bounds).ravel(), -1.0, 1.0, out=starts[1])
        self._global_state[:] = state
        self._evaluate_global()
        values = self._end_values
        best = int(np.argmin(np.where(np.isfinite(values), values, np.inf)))
        self._x0[:] = self._end_vectors[best]

    def _solve(self) -> tuple[bool, str, np.ndarray, float]:
        """One solve from ``self._x0``: (success, status, solution, objective)."""
        try:
            self._evaluate()
            return True, "success", self._x_out.copy(), float(self._f_out[0])
        except RuntimeError as error:  # a failed solve (error_on_fail) or an evaluation error
            stats = self._buffer.stats()
            status = str(stats.get("return_status", "unknown"))
            if "process failed" not in str(error):  # an evaluation error, not a failed solve
                status += f" (error: {str(error).strip().splitlines()[-1]})"
            return False, status, self._x0.copy(), float("nan")

    def _runner_up(self) -> np.ndarray | None:
        """The lowest end of the other kind of start, when the merit cannot tell it from the
        lowest end: the warm starts (rows 0-1: plans the solver converged, their ends at their
        minima) against the fresh ones (rows 2-4, whose descent may stop short of a lower
        minimum, in the flat valleys near the target above all). Returned when the two ends are
        apart and its objective is within ``multistart_margin`` (relative) of the lowest or the
        solve is a ``multistart_refresh``-th one, else None. Read right after
        :meth:`_global_guess` for the same state."""
        refresh = self.problem.multistart_refresh
        values = np.where(np.isfinite(self._end_values), self._end_values, np.inf)
        best = int(np.argmin(values))
        group = range(2, GLOBAL_STARTS) if best < 2 else range(2)
        other = min(group, key=lambda row: values[row])
        if not np.isfinite(values[other]):
            return None
        due = refresh > 0 and self._episode_solves % refresh == 0
        if not due and values[other] > values[best] + self.problem.multistart_margin * abs(values[best]) + 1e-12:
            return None
        if np.max(np.abs(self._ends[best] - self._ends[other])) < 1e-3:  # the same end
            return None
        vector: np.ndarray = self._end_vectors[other]
        return vector

    def _same_basin(self, state: np.ndarray, start: np.ndarray, solution: np.ndarray) -> bool:
        """Does the objective fall all the way from ``start``'s actions to the ``solution``'s along
        the straight line between them (the merit at 1/4, 1/2, 3/4)? Then both likely lie in one
        basin and polishing ``start`` would find ``solution`` again; a rise on the way is a ridge
        between two basins. ~10 us against a solve's 0.1-0.3 ms: with convex critics the fresh
        ends are near the polished minimum's basin at most steps."""
        self._merit_state[:] = state
        segment = self._segment
        previous = self._merit_of(start)
        for fraction in (0.25, 0.5, 0.75, 1.0):
            np.multiply(start, 1.0 - fraction, out=segment)
            segment += fraction * solution
            value = self._merit_of(segment)
            if value > previous + 1e-12 * (1.0 + abs(previous)):
                return False
            previous = value
        return True

    def _flip_search(self, state: np.ndarray, x: np.ndarray) -> np.ndarray | None:
        """The vertex search (ActorProblem.multistart_flips) from the solution ``x``: the
        decision vector of the rollout of a lower vertex neighbour's actions, or None.

        A sweep evaluates the 2 n_z neighbours -- one decision entry set to its lower or its
        upper bound, the others as they are -- along the rollout from ``state`` (one compiled
        call) and moves to the lowest while it is lower by more than 1e-6 relative (rounding and
        flat entries never move it). Where a learned critic is concave along an entry the
        objective along it is lowest at one of its two bounds: the polished solution sits on one
        and cannot see the other."""
        bounds, candidates, values = self._flat_bounds, self._candidates, self._candidate_values
        decisions = np.clip(self._decisions_of(x).ravel(), -bounds, bounds)
        self._merit_state[:] = state
        self._merit_actions[:] = decisions.reshape(-1, ACTION_DIM)
        self._evaluate_merit()
        current = float(self._merit_out[0])
        self._flip_state[:] = state
        n_z = decisions.size
        diagonal = np.arange(n_z)
        moved = False
        for _ in range(self.problem.multistart_flips):
            candidates[:] = decisions
            candidates[diagonal, diagonal] = bounds
            candidates[n_z + diagonal, diagonal] = -bounds
            self._evaluate_flips()
            best = int(np.argmin(np.where(np.isfinite(values), values, np.inf)))
            if not values[best] < current - 1e-6 * abs(current) - 1e-12:
                break
            decisions[:] = candidates[best]
            current = float(values[best])
            moved = True
        if not moved:
            return None
        self._rollout_decisions[:] = decisions
        self._evaluate_rollout()
        return self._rollout_out.copy()

    @staticmethod
    def _shift_into(out: np.ndarray, x: np.ndarray) -> None:
        """``out`` = ``x`` shifted by one stage, its last held action and state repeated."""
        out[:-STAGE] = x[STAGE:]
        out[-STAGE:-STATE_DIM] = x[-STAGE:-STATE_DIM]
        out[-STATE_DIM:] = x[-STATE_DIM:]

    def _merit_of(self, x: np.ndarray) -> float:
        """The objective of ``x``'s actions along a rollout from ``self._merit_state``."""
        self._merit_actions[:] = self._decisions_of(x)
        self._evaluate_merit()
        return float(self._merit_out[0])

    def _decisions_of(self, x: np.ndarray) -> np.ndarray:
        """The per-stage decision variables of a decision vector, one row per stage (a view):
        the held actions, or with the wheel box on the wheels' rim speeds."""
        return x[:-STATE_DIM].reshape(-1, STAGE)[:, STATE_DIM:]

    def _plan_of(self, x: np.ndarray) -> np.ndarray:
        """The held actions (v, omega) of a decision vector, one row per stage, inside the
        action box and the wheel box: the solver meets its bounds only to its tolerance, so the
        decisions are clipped to their bounds first (a clipped pair of rim speeds gives an
        action inside both boxes, see ActorProblem.wheel_rim_speed)."""
        decisions = np.clip(self._decisions_of(x), -self._decision_bounds, self._decision_bounds)
        if self.problem.wheel_box:  # (r + l) / 2, (r - l) / separation: exactly 0 when r = -l or r = l
            right, left = decisions[:, 0], decisions[:, 1]
            decisions = np.stack([0.5 * (right + left), (right - left) / self.problem.wheel_separation], axis=1)
        bounded: np.ndarray = np.clip(decisions, -self._action_bounds, self._action_bounds)
        return bounded

    def step(self, state: np.ndarray, q_weights: np.ndarray, v_weights: np.ndarray, hurry: bool = False) -> ActorStep:
        """Minimize the agent's objective from ``state``; return the first held action.

        ``solve_seconds`` is the whole step (guess, solve, checks), not the solver alone.
        ``hurry``: the caller is behind its schedule (an actor host serving its robots' ticks
        late, services/actor/host.py): one fatrop polish of the warm start (the previous plan,
        as with ``multistart`` off; the global phase only while there is no plan yet), without
        the runner-up polish and the vertex search (counted in ``hurried_solves``): ~0.26 ms
        instead of ~0.5 at N = 12, so a host that fell behind catches up instead of missing
        deadlines.
        """
        started = time.perf_counter()
        state = np.asarray(state, dtype=float)
        q_weights = np.asarray(q_weights, dtype=float)
        v_weights = np.asarray(v_weights, dtype=float)
        if state.shape != (STATE_DIM,) or not np.all(np.isfinite(state)):
            raise ValueError(f"state must be {STATE_DIM} finite numbers, got {state}")
        for name, weights, size in (("q_weights", q_weights, Q_FEATURES), ("v_weights", v_weights, V_FEATURES)):
            if weights.shape != (size,) or not np.all(np.isfinite(weights)):
                raise ValueError(f"{name} must be {size} finite numbers, got shape {weights.shape}")
        if self.arrival is not None and self.arrival.update(state):
            # Arrived: exactly zero, no solve. The plan is void: resuming starts cold.
            self._previous_x = self._earlier_x = None
            self.counters.arrived_steps += 1
            return ActorStep(
                action=np.zeros(ACTION_DIM),
                plan=np.zeros((self.problem.horizon - 1, ACTION_DIM)),
                objective=float("nan"),
                success=True,
                solve_seconds=time.perf_counter() - started,
                status="arrived",
            )
        if self.problem.convex_critics and learns(self.problem.agent):
            q_weights = nearest_psd_weights(q_weights, STATE_DIM + ACTION_DIM)
            v_weights = nearest_psd_weights(v_weights, STATE_DIM)
        self._params[:Q_FEATURES] = q_weights
        self._params[Q_FEATURES:] = v_weights
        self._initial_guess(state, hurry)
        self._lbx_np[:STATE_DIM] = state
        self._ubx_np[:STATE_DIM] = state
        success, status, x_opt, objective = self._solve()
        extras = self.problem.multistart and not hurry  # the runner-up polish and the vertex search
        if hurry and self.problem.multistart:
            self.counters.hurried_solves += 1
        runner_up = self._runner_up() if extras else None
        if runner_up is not None and success and self._same_basin(state, runner_up, x_opt):
            runner_up = None
        if runner_up is not None:
            # The merit cannot tell a warm end (at its minimum) from a fresh one (whose descent
            # may stop short of a lower minimum, near the target above all): polish both, keep
            # the lower.
            self._x0[:] = runner_up
            self._x0[:STATE_DIM] = state
            self.counters.second_solves += 1
            second = self._solve()
            if second[0] and (not success or second[3] < objective):
                success, status, x_opt, objective = second
        flips = extras and self.problem.multistart_flips > 0
        neighbour = self._flip_search(state, x_opt) if success and flips else None
        if neighbour is not None:
            # A lower vertex neighbour of the solution: polish it, keep the lower.
            self._x0[:] = neighbour
            self.counters.flip_solves += 1
            flipped = self._solve()
            if flipped[0] and flipped[3] < objective:
                success, status, x_opt, objective = flipped

        if success and np.isfinite(objective) and np.all(np.isfinite(x_opt)):
            plan = self._plan_of(x_opt)
            self._earlier_x, self._previous_x = self._previous_x, x_opt
        else:
            success = False
            self.counters.failures += 1
            log.debug("actor solve failed (%s); falling back", status)
            # Safe fallback: the previous plan shifted by one step with zero velocity appended,
            # so repeated failures run the plan out and then stand still. Else standing
            # still. Finite and bounded.
            if self._previous_x is not None:
                fallback = np.empty(self._n_x)
                self._shift_into(fallback, self._previous_x)
                fallback[-ACTION_DIM - STATE_DIM : -STATE_DIM] = 0.0
                plan = self._plan_of(fallback)
                self._earlier_x, self._previous_x = self._previous_x, fallback
            else:
                plan = np.zeros((self.problem.horizon - 1, ACTION_DIM))
            objective = float("nan")
        elapsed = time.perf_counter() - started
        self.counters.solves += 1
        self._episode_solves += 1
        self.counters.solve_seconds.append(elapsed)
        return ActorStep(
            action=plan[0].copy(),
            plan=plan,
            objective=objective,
            success=success,
            solve_seconds=elapsed,
            status=status,
        )
