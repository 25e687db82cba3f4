"""The stacked actor's step (Algorithm 1, line 4): the first held action of the agent's
objective minimized from the measured state, warm-started from the robot's previous plans.

The problem is built once (common/math/actor_nlp.py, from an
:class:`~common.math.actor_problem.ActorProblem`); a step writes the state, the critic weights
and the robot's plans into the compiled functions' buffers and calls them. With ``multistart``
(the default) a step is one call of the argmin's tick (common/math/actor_search.py: the warm
polish, the search over the robot's alternative plans, the vertex search), and the
interior-point solver runs only where the tick's Newton iterations fell short; without it, the
solver from the cheaper of the shifted and the earlier plan (the paper's actor).

The learned weights may make the problem non-convex (and the dynamics already do). When the
solver fails, :meth:`StackedActor.step` still returns a finite, bounded action: the next
action of the previous plan, else zero velocity, and counts the failure.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.math.actor_nlp import build
from common.math.actor_problem import ActorCounters, ActorMemory, ActorProblem, ActorStep, nearest_psd_weights
from common.math.actor_search import NEWTON_TOLERANCE, REPORT, fresh_starts
from common.math.agents import learns
from common.math.arrival import ArrivalRule
from common.math.stats import all_finite

log = logging.getLogger(__name__)

# With no plan yet (the first step of an episode) the tick runs this many times at once: the
# alternatives, fresh starts, descend COLD_ROUNDS x multistart_iterations iterations before the
# first answer, as a global search from scratch would.
COLD_ROUNDS = 5
FRESH_ROWS = 64  # rows of the fresh-start table (actor_search.fresh_starts)
# The phases (ActorProblem PHASES) a tick ran, read from its report (actor_search.REPORT).
_TICK_PHASES = (
    ("warm_polish", REPORT.index("warm_iterations")),
    ("search", REPORT.index("searched")),
    ("alternative_polish", REPORT.index("alternative_polished")),
    ("cold_polish", REPORT.index("cold_polished")),
    ("vertex_search", REPORT.index("sweeps")),
    ("vertex_polish", REPORT.index("vertex_moved")),
)
_REPLACED, _ALTERNATIVE_WON, _VERTEX_WON = (
    REPORT.index(name) for name in ("replaced", "alternative_won", "vertex_won")
)


@dataclass(frozen=True)
class TickRecord:
    """One call of the argmin's tick as ``srl bench actor`` replays it to time its phases: its
    inputs (actor_search.TICK_INPUTS), its report and trace, and how long it took [s]."""

    state: np.ndarray
    weights: np.ndarray
    alternatives: np.ndarray
    flags: np.ndarray
    report: np.ndarray
    trace: np.ndarray
    seconds: float
    step: int  # the robot's solves before this one's step: the rounds of one step share it


def _bind(function: Any, inputs: tuple[np.ndarray, ...], outputs: tuple[np.ndarray, ...]) -> Any:
    """Zero-copy calls: CasADi's buffer API reads the inputs from, and writes the outputs into,
    these numpy arrays in place (converting numpy to DM costs ~25 us per argument). The arrays
    must live as long as the returned evaluator and are only ever written element-wise."""
    buffer, evaluate = function.buffer()
    for index, array in enumerate(inputs):
        buffer.set_arg(index, memoryview(array))  # type: ignore[arg-type]  # numpy arrays are buffers
    for index, array in enumerate(outputs):
        buffer.set_res(index, memoryview(array))  # type: ignore[arg-type]
    return buffer, evaluate


class StackedActor:
    """One agent at one horizon, built once, stepped every sampling interval."""

    def __init__(self, problem: ActorProblem, arrival: ArrivalRule | None = None) -> None:
        self.problem = problem
        self.memory = ActorMemory(arrival=arrival)
        system = problem.dynamics  # its dimensions: the state, the action and the critics' features
        self._n_s, self._n_u = system.state_dim, system.action_dim
        self._stage = self._n_s + self._n_u  # entries of one stage (s_i, u_i) in the decision vector
        self._q_features, self._v_features = system.q_features, system.v_features
        # A list to append every tick's TickRecord to (srl bench actor's phase split); None: none kept.
        self.recorder: list[TickRecord] | None = None
        # The compiled functions: they must live as long as the buffers below read from them.
        self._functions = built = build(problem)
        lbx, ubx, n_g = built.lbx, built.ubx, built.n_g
        self._n_x = lbx.size
        self._x0 = np.zeros(self._n_x)
        self._params = np.zeros(self._q_features + self._v_features)
        self._lbx_np = lbx
        self._ubx_np = ubx
        self._zeros_g = np.zeros(n_g)
        self._zeros_x = np.zeros(self._n_x)
        self._x_out = np.zeros(self._n_x)
        self._f_out = np.zeros(1)
        solver_inputs = (self._x0, self._params, lbx, ubx, self._zeros_g, self._zeros_g, self._zeros_x, self._zeros_g)
        self._buffer, self._evaluate = _bind(built.solver, solver_inputs, (self._x_out, self._f_out))
        self._action_bounds = np.array(problem.action_max)
        self._decision_bounds = np.array(problem.decision_bounds)
        # The warm-start merit of the paper's actor: (s_1, actions, weights) -> cost.
        self._merit_state = np.zeros(self._n_s)
        self._merit_actions = np.zeros((problem.horizon - 1, self._n_u))  # row-major = u_1, u_2, ...
        self._merit_out = np.zeros(1)
        self._merit_buffer, self._evaluate_merit = _bind(
            built.merit, (self._merit_state, self._merit_actions, self._params), (self._merit_out,)
        )
        if built.tick is not None:
            self._setup_tick(built.tick)

    def _setup_tick(self, tick: Any) -> None:
        """The tick's zero-copy buffers (actor_search.TICK_INPUTS, TICK_OUTPUTS) and the fresh starts."""
        p = self.problem
        n_z, count = self._n_u * (p.horizon - 1), p.multistart_starts
        values, masks = fresh_starts(p, FRESH_ROWS)
        # the table twice over: the rows a tick takes (memory.fresh onwards, modulo its length) are one slice
        self._fresh_values, self._fresh_masks = np.vstack([values, values]), np.vstack([masks, masks])
        self._tick_state = np.zeros(self._n_s)
        self._warm = np.zeros((2, self._n_x))  # rows: the previous plan, the earlier one (CasADi's columns)
        self._alternatives = np.zeros((count, n_z))
        self._fresh = np.zeros((count, n_z))
        self._masks = np.zeros((count, n_z))
        self._ages = np.zeros(count)
        self._flags = np.zeros(3)  # has an earlier plan, search, shift
        self._tick_x = np.zeros(self._n_x)
        self._tick_plan = np.zeros((p.horizon - 1, self._n_u))
        self._tick_f = np.zeros(1)
        self._tick_stationarity = np.zeros(1)
        self._kept = np.zeros((count, n_z))
        self._kept_ages = np.zeros(count)
        self._trace = np.zeros((5, n_z))  # actor_search.SearchGraph: what the tick's phases started from
        self._report = np.zeros(len(REPORT))
        inputs = (
            self._tick_state,
            self._params,
            self._warm,
            self._alternatives,
            self._fresh,
            self._masks,
            self._ages,
            self._flags,
        )
        outputs = (
            self._tick_x,
            self._tick_plan,
            self._tick_f,
            self._tick_stationarity,
            self._kept,
            self._kept_ages,
            self._trace,
            self._report,
        )
        self._tick_buffer, self._evaluate_tick = _bind(tick, inputs, outputs)

    # -- one robot's memory ---------------------------------------------------------------
    @property
    def counters(self) -> ActorCounters:
        return self.memory.counters

    @property
    def arrival(self) -> ArrivalRule | None:
        return self.memory.arrival

    @property
    def arrived(self) -> bool:
        """The arrival rule holds the robot at the target (False without a rule)."""
        return self.memory.arrival is not None and self.memory.arrival.arrived

    def reset(self) -> None:
        """Forget the previous plans, the alternatives and the arrival (a new episode, or the plan no
        longer matches the robot): a run never depends on what the same actor solved before."""
        self.memory.forget()

    def swap_memory(self, memory: ActorMemory) -> ActorMemory:
        """Step on with ``memory`` (another robot's plans, alternatives, arrival rule and counters);
        returns the memory held until now. Not thread-safe: one step at a time per built actor."""
        held, self.memory = self.memory, memory
        return held

    # -- stepping -------------------------------------------------------------------------
    def _next_fresh(self) -> None:
        """The next multistart_starts rows of the fresh-start table into the tick's input."""
        first = self.memory.fresh % FRESH_ROWS
        count = self._fresh.shape[0]
        self._fresh[:] = self._fresh_values[first : first + count]
        self._masks[:] = self._fresh_masks[first : first + count]
        self._fresh[0], self._masks[0] = 0.0, 1.0  # the cold lane starts standing still (actor_search.COLD_PERIOD)

    def _tick(self, state: np.ndarray, hurry: bool) -> tuple[bool, str, np.ndarray, float, np.ndarray | None]:
        """The argmin's tick (actor_search): (success, status, decision vector, objective, plan or
        None: the plan of the decision vector); the solver goes on where its Newton iterations ended
        short of stationary."""
        memory, counters = self.memory, self.memory.counters
        self._tick_state[:] = state
        started = time.perf_counter()
        count = self._alternatives.shape[0]
        if memory.previous_x is None or memory.alternatives is None or memory.ages is None:
            # a cold start: the alternatives from the table, descended COLD_ROUNDS times
            self._alternatives[:] = self._fresh_values[:count]
            memory.fresh = count
            self._ages[:] = 0.0
            self._warm[:] = 0.0
            for k in range(self._n_s):  # standing still
                self._warm[0, k :: self._stage] = state[k]
            self._flags[:] = (0.0, 1.0, 0.0)
            rounds = COLD_ROUNDS
        else:
            self._warm[0] = memory.previous_x
            self._warm[1] = memory.earlier_x if memory.earlier_x is not None else memory.previous_x
            self._alternatives[:] = memory.alternatives
            self._ages[:] = memory.ages
            self._flags[:] = (memory.earlier_x is not None, not hurry, 1.0)
            rounds = 1
        report = self._report
        ran = [0.0] * len(REPORT)
        for round_ in range(rounds + 1):
            if round_ == rounds:  # once more only where the polish ended short of stationary
                if not self._tick_stationarity[0] > NEWTON_TOLERANCE or self._tick_f[0] != self._tick_f[0]:
                    break
                # its Newton iterations go on from where they ended (no search: the alternatives stay)
                counters.repolished += 1
                self._warm[0] = self._tick_x
                self._alternatives[:] = self._kept
                self._ages[:] = self._kept_ages
                self._flags[:] = (0.0, 0.0, 0.0)
            self._next_fresh()
            called = time.perf_counter()
            self._evaluate_tick()
            if self.recorder is not None:
                self.recorder.append(
                    TickRecord(
                        state.copy(),
                        self._params.copy(),
                        self._alternatives.copy(),
                        self._flags.copy(),
                        report.copy(),
                        self._trace.copy(),
                        time.perf_counter() - called,
                        counters.solves,
                    )
                )
            said = report.tolist()
            ran = [a + b for a, b in zip(ran, said, strict=True)]
            if said[_REPLACED]:  # renewed alternatives took these rows: the next ones
                memory.fresh += count
            if round_ < rounds - 1:
                self._warm[0] = self._tick_x
                self._alternatives[:] = self._kept
                self._ages[:] = self._kept_ages
                self._flags[:] = (0.0, 1.0, 0.0)
        counters.search_seconds += time.perf_counter() - started
        memory.alternatives = self._kept.copy()
        memory.ages = self._kept_ages.copy()
        phases = counters.phase_counts
        for phase, entry in _TICK_PHASES:
            if ran[entry] > 0:
                phases[phase] += 1
        counters.alternative_wins += ran[_ALTERNATIVE_WON] > 0
        counters.vertex_wins += ran[_VERTEX_WON] > 0
        objective = float(self._tick_f[0])
        if objective == objective and self._tick_stationarity[0] <= NEWTON_TOLERANCE:  # not NaN: x is finite
            return True, "success", self._tick_x.copy(), objective, self._tick_plan.copy()
        # the Newton iterations fell short (or a NaN): the interior point from where they ended
        x = self._tick_x.copy()
        phases["solver"] += 1
        if np.all(np.isfinite(x)):
            self._x0[:] = x
            self._x0[: self._n_s] = state
        else:
            self._warm_guess(state)
        started = time.perf_counter()
        solved = self._solve()
        counters.solver_seconds += time.perf_counter() - started
        if solved[0] or not np.isfinite(objective):
            return (*solved, None)
        return True, "success", x, objective, self._tick_plan.copy()  # the solver failed: the tick's answer stands

    def _warm_guess(self, state: np.ndarray) -> None:
        """The paper's actor's warm start, written in place into the solver's input ``self._x0``:
        the previous primal solution shifted by one stage (last stage repeated), or the solution
        from two steps ago, unshifted, whichever costs less along a rollout from ``state``
        (the merit). That candidate wins when the loop alternates between two local minima
        (period-2 chattering: the robot returns to the state of two steps ago, where that
        solution is optimal). With multiple shooting the guess needs not satisfy the dynamics."""
        x0, memory = self._x0, self.memory
        if memory.previous_x is None:
            x0[:] = 0.0
            for k in range(self._n_s):
                x0[k :: self._stage] = state[k]
        else:
            self._shift_into(x0, memory.previous_x)
            if memory.earlier_x is not None:
                self._merit_state[:] = state
                if self._merit_of(memory.earlier_x) < self._merit_of(x0):
                    x0[:] = memory.earlier_x
        x0[: self._n_s] = state

    def _solve(self) -> tuple[bool, str, np.ndarray, float]:
        """One solve from ``self._x0``: (success, status, solution, objective)."""
        self._lbx_np[: self._n_s] = self._x0[: self._n_s]
        self._ubx_np[: self._n_s] = self._x0[: self._n_s]
        try:
            self._evaluate()
            return True, "success", self._x_out.copy(), float(self._f_out[0])
        except RuntimeError as error:  # a failed solve (error_on_fail) or an evaluation error
            stats = self._buffer.stats()
            status = str(stats.get("return_status", "unknown"))
            if "process failed" not in str(error):  # an evaluation error, not a failed solve
                status += f" (error: {str(error).strip().splitlines()[-1]})"
            return False, status, self._x0.copy(), float("nan")

    def _shift_into(self, out: np.ndarray, x: np.ndarray) -> None:
        """``out`` = ``x`` shifted by one stage, its last held action and state repeated."""
        out[: -self._stage] = x[self._stage :]
        out[-self._stage : -self._n_s] = x[-self._stage : -self._n_s]
        out[-self._n_s :] = x[-self._n_s :]

    def _merit_of(self, x: np.ndarray) -> float:
        """The objective of ``x``'s actions along a rollout from ``self._merit_state``."""
        self._merit_actions[:] = self._decisions_of(x)
        self._evaluate_merit()
        return float(self._merit_out[0])

    def _decisions_of(self, x: np.ndarray) -> np.ndarray:
        """The per-stage decision variables of a decision vector, one row per stage (a view):
        the held actions, or with the wheel box on the wheels' rim speeds."""
        return x[: -self._n_s].reshape(-1, self._stage)[:, self._n_s :]

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

        ``solve_seconds`` is the whole step (checks, the tick or the solver, the plan), not the
        solver alone. ``hurry``: the caller is behind its schedule or over its CPU budget (an actor
        host, services/actor/host.py): the warm polish only, without the search and the vertex
        search (counted in ``hurried_solves``), so a host that fell behind catches up instead of
        missing deadlines; with no plan yet the step is a full one.
        """
        started = time.perf_counter()
        state = np.asarray(state, dtype=float)
        q_weights = np.asarray(q_weights, dtype=float)
        v_weights = np.asarray(v_weights, dtype=float)
        if state.shape != (self._n_s,) or not all_finite(state):
            raise ValueError(f"state must be {self._n_s} finite numbers, got {state}")
        for name, weights, size in (
            ("q_weights", q_weights, self._q_features),
            ("v_weights", v_weights, self._v_features),
        ):
            if weights.shape != (size,) or not all_finite(weights):
                raise ValueError(f"{name} must be {size} finite numbers, got shape {weights.shape}")
        memory, counters = self.memory, self.memory.counters
        if memory.arrival is not None and memory.arrival.update(state):
            memory.held_at_rest()  # exactly zero, no solve
            return ActorStep(
                action=np.zeros(self._n_u),
                plan=np.zeros((self.problem.horizon - 1, self._n_u)),
                objective=float("nan"),
                success=True,
                solve_seconds=time.perf_counter() - started,
                status="arrived",
            )
        if self.problem.convex_critics and learns(self.problem.agent):
            q_weights = nearest_psd_weights(q_weights, self._n_s + self._n_u)
            v_weights = nearest_psd_weights(v_weights, self._n_s)
        self._params[: self._q_features] = q_weights
        self._params[self._q_features :] = v_weights
        planned: np.ndarray | None = None
        if self.problem.multistart:
            hurried = hurry and memory.previous_x is not None
            counters.hurried_solves += hurried
            success, status, x_opt, objective, planned = self._tick(state, hurried)
        else:
            self._warm_guess(state)
            success, status, x_opt, objective = self._solve()

        if planned is not None:  # the tick's answer: finite (its rollout of a plan in the box), planned
            plan = planned
            memory.earlier_x, memory.previous_x = memory.previous_x, x_opt
        elif success and np.isfinite(objective) and np.all(np.isfinite(x_opt)):
            plan = self._plan_of(x_opt)
            memory.earlier_x, memory.previous_x = memory.previous_x, x_opt
        else:
            success = False
            counters.failures += 1
            log.debug("actor solve failed (%s); falling back", status)
            # Safe fallback: the previous plan shifted by one step with zero velocity appended,
            # so repeated failures run the plan out and then stand still. Else standing
            # still. Finite and bounded.
            if memory.previous_x is not None:
                fallback = np.empty(self._n_x)
                self._shift_into(fallback, memory.previous_x)
                fallback[-self._n_u - self._n_s : -self._n_s] = 0.0
                plan = self._plan_of(fallback)
                memory.earlier_x, memory.previous_x = memory.previous_x, fallback
            else:
                plan = np.zeros((self.problem.horizon - 1, self._n_u))
            objective = float("nan")
        elapsed = time.perf_counter() - started
        counters.solves += 1
        counters.solve_seconds.append(elapsed)
        if memory.arrival is not None:  # the wheels' deadband at the output (common.math.arrival)
            plan[0] = memory.arrival.last_word(plan[0], state)
        return ActorStep(
            action=plan[0].copy(),
            plan=plan,
            objective=objective,
            success=success,
            solve_seconds=elapsed,
            status=status,
        )
