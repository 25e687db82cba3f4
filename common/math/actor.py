"""The stacked actor's step (Algorithm 1, line 4): the first held action of the agent's
objective minimized from the measured state, warm-started from the previous plans.

The problem is built once (common/math/actor_nlp.py, from an
:class:`~common.math.actor_problem.ActorProblem`); a step writes the state, the critic weights
and the initial guess into the compiled solver's buffers and solves. With ``multistart`` a
global phase picks the start the solver polishes (docs/concepts.md).

The learned weights may make the problem non-convex (and the dynamics already do). When the
solver fails, :meth:`StackedActor.step` still returns a finite, bounded action: the next
action of the previous plan, else zero velocity, and counts the failure.
"""

from __future__ import annotations

import logging
import time

import casadi as ca
import numpy as np

from common.math.actor_nlp import build
from common.math.actor_problem import (
    GLOBAL_STARTS,
    NEWTON_TOLERANCE,
    ActorCounters,
    ActorMemory,
    ActorProblem,
    ActorStep,
    nearest_psd_weights,
)
from common.math.agents import learns
from common.math.arrival import ArrivalRule
from common.math.dynamics import ACTION_DIM, STATE_DIM
from common.math.features import Q_FEATURES, V_FEATURES
from common.math.stats import all_finite

log = logging.getLogger(__name__)

STAGE = STATE_DIM + ACTION_DIM  # entries of one stage (s_i, u_i) in the decision vector


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
        self._runner_up_shortfall = 0.0  # the last runner-up polish's, relative (multistart_hopeless)
        # The compiled functions: they must live as long as the buffers below read from them.
        self._functions = built = build(problem)
        lbx, ubx, n_g = built.lbx, built.ubx, built.n_g
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
        self._buffer, self._evaluate = built.solver.buffer()
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
        self._decision_bounds = np.array(problem.decision_bounds)
        # The warm-start merit, called the same zero-copy way: (s_1, actions, weights) -> cost.
        self._merit_state = np.zeros(STATE_DIM)
        self._merit_actions = np.zeros((problem.horizon - 1, ACTION_DIM))  # row-major = u_1, u_2, ...
        self._merit_out = np.zeros(1)
        self._merit_buffer, self._evaluate_merit = built.merit.buffer()
        for index, array in enumerate((self._merit_state, self._merit_actions, self._params)):
            self._merit_buffer.set_arg(index, memoryview(array))  # type: ignore[call-arg, arg-type]  # casadi's stub
        self._merit_buffer.set_res(0, memoryview(self._merit_out))  # type: ignore[call-arg, arg-type]  # casadi's stub
        if built.global_phase is not None:
            self._setup_global_phase(built.global_phase)
        self._descent_ready = built.descent is not None
        if built.descent is not None:
            self._setup_descent(built.descent)
        self._newton_ready = built.newton is not None
        if built.newton is not None:
            self._setup_newton(built.newton)
        if built.flips is not None and built.rollout is not None:
            self._setup_flip_search(built.flips, built.rollout)

    def _setup_global_phase(self, function: ca.Function) -> None:
        """The global phase's zero-copy buffers and its fixed starts (common.math.actor_nlp.global_phase).

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
        self._global_buffer, self._evaluate_global = function.buffer()
        for index, array in enumerate((self._starts, self._global_state, self._params)):
            self._global_buffer.set_arg(index, memoryview(array))  # type: ignore[call-arg, arg-type]  # casadi's stub
        for index, array in enumerate((self._ends, self._end_values, self._end_vectors)):
            self._global_buffer.set_res(index, memoryview(array))  # type: ignore[call-arg, arg-type]  # casadi's stub

    def _setup_descent(self, function: ca.Function) -> None:
        """The hurried step's descent (ActorProblem.hurry "descend"): zero-copy buffers of the
        global phase's descent of one start (common.math.actor_nlp.global_phase)."""
        n_z = ACTION_DIM * (self.problem.horizon - 1)
        self._descent_start = np.zeros(n_z)
        self._descent_state = np.zeros(STATE_DIM)
        self._descent_end = np.zeros(n_z)
        self._descent_value = np.zeros(1)
        self._descent_vector = np.zeros(self._n_x)
        self._descent_buffer, self._evaluate_descent = function.buffer()
        for index, array in enumerate((self._descent_start, self._descent_state, self._params)):
            self._descent_buffer.set_arg(index, memoryview(array))  # type: ignore[call-arg, arg-type]  # casadi's stub
        for index, array in enumerate((self._descent_end, self._descent_value, self._descent_vector)):
            self._descent_buffer.set_res(index, memoryview(array))  # type: ignore[call-arg, arg-type]  # casadi's stub

    def _setup_newton(self, function: ca.Function) -> None:
        """The polish's Newton iterations (ActorProblem.newton_iterations): zero-copy buffers of
        (start, s_1, weights) -> (end, objective, stationarity, decision vector)."""
        n_z = ACTION_DIM * (self.problem.horizon - 1)
        self._newton_start = np.zeros(n_z)
        self._newton_state = np.zeros(STATE_DIM)
        self._newton_end = np.zeros(n_z)
        self._newton_value = np.zeros(1)
        self._newton_stationarity = np.zeros(1)
        self._newton_vector = np.zeros(self._n_x)
        self._newton_buffer, self._evaluate_newton = function.buffer()
        inputs = (self._newton_start, self._newton_state, self._params)
        outputs = (self._newton_end, self._newton_value, self._newton_stationarity, self._newton_vector)
        for index, array in enumerate(inputs):
            self._newton_buffer.set_arg(index, memoryview(array))  # type: ignore[call-arg, arg-type]  # casadi's stub
        for index, array in enumerate(outputs):
            self._newton_buffer.set_res(index, memoryview(array))  # type: ignore[call-arg, arg-type]  # casadi's stub

    def _setup_flip_search(self, flips: ca.Function, rollout: ca.Function) -> None:
        """The vertex search's zero-copy buffers (see _flip_search). ``_candidates`` has one row
        per neighbour (CasADi reads the (n_z, 2 n_z) matrix column by column)."""
        n_z = ACTION_DIM * (self.problem.horizon - 1)
        self._flat_bounds = np.tile(self._decision_bounds, self.problem.horizon - 1)
        self._candidates = np.zeros((2 * n_z, n_z))
        self._candidate_values = np.zeros(2 * n_z)
        self._flip_state = np.zeros(STATE_DIM)
        self._flip_buffer, self._evaluate_flips = flips.buffer()
        for index, array in enumerate((self._flip_state, self._candidates, self._params)):
            self._flip_buffer.set_arg(index, memoryview(array))  # type: ignore[call-arg, arg-type]  # casadi's stub
        self._flip_buffer.set_res(0, memoryview(self._candidate_values))  # type: ignore[call-arg, arg-type]  # casadi's stub
        self._rollout_decisions = np.zeros(n_z)
        self._rollout_out = np.zeros(self._n_x)
        self._rollout_buffer, self._evaluate_rollout = rollout.buffer()
        for index, array in enumerate((self._flip_state, self._rollout_decisions)):
            self._rollout_buffer.set_arg(index, memoryview(array))  # type: ignore[call-arg, arg-type]  # casadi's stub
        self._rollout_buffer.set_res(0, memoryview(self._rollout_out))  # type: ignore[call-arg, arg-type]  # casadi's stub

    # -- stepping -----------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the previous plans and arrival (new episode, or the plan no longer matches the robot)."""
        self._previous_x = None
        self._earlier_x = None
        # the refresh's phase (multistart_refresh) counts from here: a run never depends on
        # what the same actor solved before (the experiment's workers reuse their actors)
        self._episode_solves = 0
        self._runner_up_shortfall = 0.0
        if self.arrival is not None:
            self.arrival.reset()

    def swap_memory(self, memory: ActorMemory) -> ActorMemory:
        """Step on with ``memory`` (another robot's plans, arrival rule and counters); returns
        the memory held until now. Not thread-safe: one step at a time per built actor."""
        held = ActorMemory(
            self._previous_x,
            self._earlier_x,
            self.arrival,
            self.counters,
            self._episode_solves,
            self._runner_up_shortfall,
        )
        self._previous_x, self._earlier_x = memory.previous_x, memory.earlier_x
        self.arrival, self.counters = memory.arrival, memory.counters
        self._episode_solves, self._runner_up_shortfall = memory.episode_solves, memory.runner_up_shortfall
        return held

    @property
    def arrived(self) -> bool:
        """The arrival rule holds the robot at the target (False without a rule)."""
        return self.arrival is not None and self.arrival.arrived

    def _initial_guess(self, state: np.ndarray, hurry: bool = False) -> tuple[bool, bool]:
        """Warm start, written in place into the solver's input ``self._x0`` (the weights
        must already be in ``self._params``). ``hurry`` with a previous plan: the merit-only warm
        start below instead of the global phase (multistart), ~0.2 ms less at N = 12. Returns
        whether the global phase ran and whether the guess is warm: a previous plan of the
        robot, after its descent if the global phase ran (:meth:`_polish`).

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
        settled = self._previous_x is not None and (hurry or self._episode_solves % self.problem.global_every != 0)
        global_phase = self.problem.multistart and not settled
        warm = self._previous_x is not None  # the shifted or the earlier plan
        if global_phase:
            best = self._global_guess(state)
            warm = warm and best < 2
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
        return global_phase, warm

    def _global_guess(self, state: np.ndarray) -> int:
        """The multistart guess (ActorProblem.multistart), written into ``self._x0``: every
        start descended by the global phase (common.math.actor_nlp.global_phase) from
        ``state``, and the rollout of the end with the lowest objective. The warm starts are the
        shifted previous plan and the plan of two steps ago (the candidates of the merit-only
        guess, see _initial_guess). Returns the row of the start whose end it is."""
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
        return best

    def _phase_done(self, phase: str, since: float) -> float:
        """Count one run of ``phase`` that began at ``since`` (perf_counter); return now."""
        now = time.perf_counter()
        self.counters.add_phase(phase, now - since)
        return now

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

    def _polish(self, warm: bool) -> tuple[bool, str, np.ndarray, float]:
        """The polish of the start in ``self._x0`` (the solver's bounds already hold the state).
        A ``warm`` start (a previous plan of this robot, shifted or not, after the global phase's
        descent if it ran: it lies in the basin of the minimum it was polished to) goes to the
        compiled Newton iterations (ActorProblem.newton_iterations), whose end is the answer when
        it is stationary (projected gradient <= NEWTON_TOLERANCE). A fresh start (standing still,
        full speed, a vertex neighbour), and a warm one whose iterations fall short, goes to the
        solver from the start itself: the interior point's path may leave a fresh start's basin
        for a lower minimum, where the Newton iterations only descend into the nearest one."""
        if warm and self._newton_ready:
            np.clip((self._decisions_of(self._x0) / self._decision_bounds).ravel(), -1.0, 1.0, out=self._newton_start)
            self._newton_state[:] = self._x0[:STATE_DIM]
            self._evaluate_newton()
            value = float(self._newton_value[0])
            if np.isfinite(value) and self._newton_stationarity[0] <= NEWTON_TOLERANCE:
                return True, "success", self._newton_vector.copy(), value
            self.counters.newton_fallbacks += 1
        return self._solve()

    def _descend(self) -> tuple[bool, str, np.ndarray, float]:
        """The hurried step's answer (ActorProblem.hurry "descend"): the warm start in
        ``self._x0`` descended by the global phase's projected gradient, no solver: (success,
        status, the rollout's decision vector, its objective). The descent only takes steps that
        lower the objective, so the answer is never worse than the warm start along the rollout."""
        np.clip((self._decisions_of(self._x0) / self._decision_bounds).ravel(), -1.0, 1.0, out=self._descent_start)
        self._descent_state[:] = self._x0[:STATE_DIM]
        self._evaluate_descent()
        value = float(self._descent_value[0])
        return bool(np.isfinite(value)), "descended", self._descent_vector.copy(), value

    def _runner_up(self) -> tuple[np.ndarray, bool] | None:
        """The lowest end of the other kind of start, when the merit cannot tell it from the
        lowest end: the warm starts (rows 0-1: plans the solver converged, their ends at their
        minima) against the fresh ones (rows 2-4, whose descent may stop short of a lower
        minimum, in the flat valleys near the target above all). Returned when the two ends are
        apart and its objective is within ``multistart_margin`` (relative) of the lowest or the
        solve is a ``multistart_refresh``-th one, with whether it is warm (:meth:`_polish`), else
        None; between refreshes, None while the last runner-up polish lost by more than
        ``multistart_hopeless``. Read right after :meth:`_global_guess` for the same state, and
        not at all when the polish of the lowest end fell back to the solver (:meth:`step`)."""
        refresh = self.problem.multistart_refresh
        values = np.where(np.isfinite(self._end_values), self._end_values, np.inf)
        best = int(np.argmin(values))
        group = range(2, GLOBAL_STARTS) if best < 2 else range(2)
        other = min(group, key=lambda row: values[row])
        if not np.isfinite(values[other]):
            return None
        due = refresh > 0 and self._episode_solves % refresh == 0
        hopeless = self.problem.multistart_hopeless
        if not due and hopeless > 0 and self._runner_up_shortfall > hopeless:
            return None
        if not due and values[other] > values[best] + self.problem.multistart_margin * abs(values[best]) + 1e-12:
            return None
        if np.max(np.abs(self._ends[best] - self._ends[other])) < 1e-3:  # the same end
            return None
        vector: np.ndarray = self._end_vectors[other]
        return vector, self._previous_x is not None and other < 2

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
        ``hurry``: the caller is behind its schedule or over its CPU budget (an actor host,
        services/actor/host.py): the warm start (the previous plan, as with ``multistart`` off;
        the global phase only while there is no plan yet) polished once (ActorProblem.hurry
        "polish": its Newton iterations, the solver where they fall short) or descended by the
        compiled projected gradient ("descend", no solver: a fifth of the global phase), without
        the runner-up polish and the vertex search (counted in ``hurried_solves``), so a host that
        fell behind catches up instead of missing deadlines.
        """
        started = time.perf_counter()
        state = np.asarray(state, dtype=float)
        q_weights = np.asarray(q_weights, dtype=float)
        v_weights = np.asarray(v_weights, dtype=float)
        if state.shape != (STATE_DIM,) or not all_finite(state):
            raise ValueError(f"state must be {STATE_DIM} finite numbers, got {state}")
        for name, weights, size in (("q_weights", q_weights, Q_FEATURES), ("v_weights", v_weights, V_FEATURES)):
            if weights.shape != (size,) or not all_finite(weights):
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
        counters = self.counters
        mark = time.perf_counter()
        fallbacks = counters.newton_fallbacks
        global_phase, warm = self._initial_guess(state, hurry)
        if global_phase:
            mark = self._phase_done("global", mark)
        if hurry and self._descent_ready and not global_phase:
            success, status, x_opt, objective = self._descend()
        else:
            self._lbx_np[:STATE_DIM] = state
            self._ubx_np[:STATE_DIM] = state
            success, status, x_opt, objective = self._polish(warm)
            mark = self._phase_done("polish", mark)
        extras = self.problem.multistart and not hurry  # the runner-up polish and the vertex search
        if hurry and self.problem.multistart:
            counters.hurried_solves += 1
        # A polish that fell back to the solver has run its interior point from the warm end
        # (which may leave that basin for a lower minimum): a runner-up polish too would be a
        # second interior-point solve in one step, the slowest steps (docs/concepts.md, item 3).
        fell_back = counters.newton_fallbacks > fallbacks
        runner_up = self._runner_up() if extras and global_phase and not fell_back else None
        if runner_up is not None and success and self._same_basin(state, runner_up[0], x_opt):
            runner_up = None
        if runner_up is not None:
            # The merit cannot tell a warm end (at its minimum) from a fresh one (whose descent
            # may stop short of a lower minimum, near the target above all): polish both, keep
            # the lower.
            self._x0[:] = runner_up[0]
            self._x0[:STATE_DIM] = state
            counters.second_solves += 1
            second = self._polish(runner_up[1])
            mark = self._phase_done("runner_up", mark)
            won = second[0] and (not success or second[3] < objective)
            lost_by = (second[3] - objective) / max(abs(objective), 1e-12) if second[0] and success else 0.0
            self._runner_up_shortfall = 0.0 if won else lost_by
            if won:
                success, status, x_opt, objective = second
        flips = extras and self.problem.multistart_flips > 0
        neighbour = None
        if success and flips:
            mark = time.perf_counter()
            neighbour = self._flip_search(state, x_opt)
            mark = self._phase_done("flip_search", mark)
        if neighbour is not None:
            # A lower vertex neighbour of the solution: polish it, keep the lower.
            self._x0[:] = neighbour
            counters.flip_solves += 1
            flipped = self._solve()  # a fresh start: a vertex of the box moved (_polish)
            self._phase_done("flip_polish", mark)
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
        if self.arrival is not None:  # the wheels' deadband at the output (common.math.arrival)
            plan[0] = self.arrival.last_word(plan[0], state)
        return ActorStep(
            action=plan[0].copy(),
            plan=plan,
            objective=objective,
            success=success,
            solve_seconds=elapsed,
            status=status,
        )
