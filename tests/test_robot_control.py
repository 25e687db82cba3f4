"""The actor's settings for a running robot (docs/turtlebot-parking.md) against independent oracles: the wheel-speed box
(brute force over the feasible grid), the convexified critics (the quadratic form by hand), the
arrival rule inside the actor, and the chatter of the paper's method on the ideal plant."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from common.config.assembly import run_episode
from common.config.settings import PAPER_METHOD, Settings
from common.math.actor import StackedActor
from common.math.actor_problem import ActorProblem, nearest_psd_weights
from common.math.arrival import ArrivalRule, ArrivalTolerances
from tests.test_actor import DELTA, OMEGA_MAX, PAIRS3, PAIRS5, R_DIAG, STATES, V_MAX, hand_objective, psd_weights

HALF_TRACK, RADIUS, WHEEL_MAX = 0.08, 0.033, 6.7  # TurtleBot3 Burger
RIM = min(WHEEL_MAX * RADIUS, V_MAX, OMEGA_MAX * HALF_TRACK)  # 0.22 m/s


def wheel_actor(agent: str, horizon: int, **kwargs) -> StackedActor:
    kwargs.setdefault("jit", False)
    problem = ActorProblem(
        agent, horizon, DELTA, tuple(R_DIAG), (V_MAX, OMEGA_MAX), wheel_speed_max=WHEEL_MAX, **kwargs
    )
    return StackedActor(problem)


def wheel_speeds(action: np.ndarray) -> tuple[float, float]:
    """The wheels' angular speeds [rad/s] as turtlebot3_node computes them from cmd_vel."""
    v, omega = action
    return (v - omega * HALF_TRACK) / RADIUS, (v + omega * HALF_TRACK) / RADIUS


# -- the wheel-speed box ------------------------------------------------------------------
@pytest.mark.parametrize("agent", ["mpc", "rlqv"])
def test_wheel_box_one_action_optimum_beats_brute_force_over_the_feasible_set(agent: str) -> None:
    rng = np.random.default_rng(21)
    actor = wheel_actor(agent, 2)
    grid_v, grid_w = np.meshgrid(np.linspace(-V_MAX, V_MAX, 301), np.linspace(-OMEGA_MAX, OMEGA_MAX, 301))
    feasible = np.abs(grid_v) + HALF_TRACK * np.abs(grid_w) <= RIM
    for state in STATES:
        w, v_w = psd_weights(rng, 5, PAIRS5), psd_weights(rng, 3, PAIRS3)
        result = actor.step(state, w, v_w)
        assert result.success, result.status
        assert max(abs(s) for s in wheel_speeds(result.action)) <= RIM / RADIUS + 1e-12
        values = np.where(feasible, hand_objective(agent, state, [(grid_v, grid_w)], w, v_w), np.inf)
        at_action = float(hand_objective(agent, state, [tuple(np.float64(c) for c in result.action)], w, v_w))
        assert result.objective == pytest.approx(at_action, rel=1e-7, abs=1e-10)
        assert at_action <= float(values.min()) + 1e-7 * max(1.0, abs(float(values.min())))


def test_wheel_box_holds_in_closed_loop_with_indefinite_weights() -> None:
    rng = np.random.default_rng(5)
    actor = wheel_actor("rlqv", 12)
    state = np.array([1.5, -1.0, 2.0])
    for _ in range(60):
        w, v_w = rng.normal(size=15), rng.normal(size=6)  # non-convex: failures fall back
        step = actor.step(state, w, v_w)
        assert np.all(np.isfinite(step.plan))
        for row in step.plan:
            assert max(abs(s) for s in wheel_speeds(row)) <= RIM / RADIUS + 1e-12
            assert abs(row[0]) <= V_MAX and abs(row[1]) <= OMEGA_MAX
        state = state + DELTA * np.array(
            [step.action[0] * math.cos(state[2]), step.action[0] * math.sin(state[2]), step.action[1]]
        )


def test_a_wheel_box_that_never_binds_solves_the_papers_problem() -> None:
    """Where the optimum lies inside the diamond, the wheel-speed variables change nothing."""
    paper = StackedActor(ActorProblem("mpc", 6, DELTA, tuple(R_DIAG), (0.1, 1.0), jit=False))
    wide = StackedActor(ActorProblem("mpc", 6, DELTA, tuple(R_DIAG), (0.1, 1.0), jit=False, wheel_speed_max=1e3))
    assert wide.problem.wheel_rim_speed == pytest.approx(0.08)  # min(33, 0.1, 1.0 x 0.08)
    for state in (np.array([0.005, 0.0, 0.0]), np.array([0.01, -0.004, 0.05])):
        a, b = paper.step(state, np.zeros(15), np.zeros(6)), wide.step(state, np.zeros(15), np.zeros(6))
        assert a.success and b.success
        assert np.all(np.abs(a.plan[:, 0]) + HALF_TRACK * np.abs(a.plan[:, 1]) < 0.08)  # inside: never binds
        np.testing.assert_allclose(b.plan, a.plan, atol=1e-4)
        assert b.objective == pytest.approx(a.objective, rel=1e-5)


# -- the convexified critics --------------------------------------------------------------
def test_nearest_psd_weights_is_the_eigenvalue_clipped_quadratic() -> None:
    rng = np.random.default_rng(3)
    for dim, pairs in ((5, PAIRS5), (3, PAIRS3)):
        weights = rng.normal(size=len(pairs))
        # the matrix written out by hand from the feature pairs (i >= j, i = j on the diagonal)
        matrix = np.zeros((dim, dim))
        for k, (i, j) in enumerate(pairs):
            matrix[i, j] += weights[k] / (1 if i == j else 2)
            matrix[j, i] += weights[k] / (1 if i == j else 2) if i != j else 0.0
        eigenvalues, vectors = np.linalg.eigh(matrix)
        expected = vectors @ np.diag(np.maximum(eigenvalues, 0.0)) @ vectors.T
        projected = nearest_psd_weights(weights, dim)
        for z in rng.normal(size=(50, dim)):
            value = sum(projected[k] * z[i] * z[j] for k, (i, j) in enumerate(pairs))
            assert value == pytest.approx(float(z @ expected @ z), abs=1e-12)
            assert value >= -1e-12  # never a negative predicted cost
        definite = psd_weights(rng, dim, pairs)
        np.testing.assert_array_equal(nearest_psd_weights(definite, dim), definite)  # untouched


# -- the arrival rule inside the actor ------------------------------------------------------
def test_the_actor_commands_exactly_zero_once_arrived_and_resumes_beyond_the_outer_tolerance() -> None:
    tolerances = ArrivalTolerances(position=0.03, heading=0.1, hysteresis=1.5)
    actor = StackedActor(
        ActorProblem("mpc", 6, DELTA, tuple(R_DIAG), (V_MAX, OMEGA_MAX), jit=False), arrival=ArrivalRule(tolerances)
    )
    zeros_q, zeros_v = np.zeros(15), np.zeros(6)
    assert actor.step(np.array([0.5, 0.0, 0.0]), zeros_q, zeros_v).status == "success"
    held = actor.step(np.array([0.02, 0.01, 0.05]), zeros_q, zeros_v)
    assert held.status == "arrived" and held.success and actor.arrived
    assert np.array_equal(held.action, [0.0, 0.0]) and np.array_equal(held.plan, np.zeros((5, 2)))
    assert actor.step(np.array([0.04, 0.0, 0.0]), zeros_q, zeros_v).status == "arrived"  # inside 0.045
    moved = actor.step(np.array([0.05, 0.0, 0.0]), zeros_q, zeros_v)  # beyond 1.5 x 0.03
    assert moved.status == "success" and not actor.arrived and moved.action[0] < 0
    assert actor.counters.arrived_steps == 2
    actor.step(np.array([0.0, 0.0, 0.0]), zeros_q, zeros_v)
    actor.reset()  # a new episode starts not arrived
    assert not actor.arrived


# -- the chatter on the ideal plant ---------------------------------------------------------------
def _v_sign_flips(actions: list[np.ndarray], last: int = 100) -> int:
    """Sign changes of v over the last 10 s, counting only |v| >= 0.01 m/s (docs/experiment.md's measure)."""
    signs = [math.copysign(1.0, a[0]) for a in actions[-last:] if abs(a[0]) >= 0.01]
    return sum(a != b for a, b in itertools.pairwise(signs))


@pytest.mark.parametrize("start", [(-1.0, -2.0), (-2.0, 2.0)])
def test_rlqv_parks_without_chatter_by_default_and_the_papers_method_chatters(start: tuple[float, float]) -> None:
    """rlqv at N = 12 from two of the paper's starts, 35 s on the ideal plant. The paper's method
    with the paper's actor (the warm start alone, multistart off) shuttles at full speed to the
    end (a period-2 limit cycle); with the default settings (arrival rule, wheel box, convex
    critics) it parks: <= 5 flips, final distance <= 0.05 m, at rest. (The global phase alone
    parks from (-1, -2): the next test.)"""
    x, y = start
    common = {"actor": {"agent": "rlqv", "horizon": 12, "jit": False}, "episode": {"duration": 35.0, "start": [x, y]}}
    paper = Settings.load(**{**common, "actor": {**common["actor"], **PAPER_METHOD["actor"], "multistart": False}})
    robot = Settings.load(**common)
    assert robot.actor.arrival and robot.actor.wheel_speed_max > 0 and robot.actor.convex_critics
    shuttle = run_episode(paper)
    assert _v_sign_flips(shuttle.actions) > 5
    parked = run_episode(robot)
    assert _v_sign_flips(parked.actions) <= 5
    final = parked.final_state
    assert math.hypot(final[0], final[1]) <= 0.05
    last = np.array(parked.states[-100:])
    assert np.ptp(last[:, 0]) <= 0.05 and np.ptp(last[:, 1]) <= 0.05
    assert all(np.isfinite(a).all() and abs(a[0]) <= V_MAX and abs(a[1]) <= OMEGA_MAX for a in parked.actions)


def test_the_global_phase_alone_ends_the_limit_cycle_from_one_start_not_from_the_other() -> None:
    """Part of the paper's method's chatter is the actor stuck between two local
    minima. With the global phase (multistart, on by default) rlqv from (-1, -2) parks at rest
    (measured 0 flips, against 79 without it) at a lower J; from (-2, 2) the fitted critic's
    limit cycle remains (23 flips): that one the robot settings above are for."""
    episodes = {}
    for start in ((-1.0, -2.0), (-2.0, 2.0)):
        for multistart in (False, True):
            settings = Settings.load(
                actor={"agent": "rlqv", "horizon": 12, "jit": False, **PAPER_METHOD["actor"], "multistart": multistart},
                episode={"duration": 35.0, "start": list(start)},
            )
            episodes[start, multistart] = run_episode(settings)
    assert _v_sign_flips(episodes[(-1.0, -2.0), False].actions) > 5
    assert _v_sign_flips(episodes[(-1.0, -2.0), True].actions) <= 5
    assert episodes[(-1.0, -2.0), True].accumulated_cost < episodes[(-1.0, -2.0), False].accumulated_cost
    assert _v_sign_flips(episodes[(-2.0, 2.0), True].actions) > 5
