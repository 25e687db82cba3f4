"""The stacked actors against brute-force grid search, plus bounds, validation and failures.

The oracle objective is written out here in numpy from the stacked objectives of docs/concepts.md
(Euler prediction, features from a hand-written pair list), evaluated on a grid of held actions.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest

from common.math.actor import StackedActor
from common.math.actor_problem import ActorMemory, ActorProblem
from common.math.dynamics import exact_step

DELTA = 0.1
R_DIAG = np.array([1.0, 10.0, 1.0, 0.01, 0.01])
V_MAX, OMEGA_MAX = 0.22, 2.84
PAIRS5 = [(0, 0), (1, 1), (2, 2), (3, 3), (4, 4), (1, 0), (2, 1), (3, 2), (4, 3),
          (2, 0), (3, 1), (4, 2), (3, 0), (4, 1), (4, 0)]  # fmt: skip
PAIRS3 = [(0, 0), (1, 1), (2, 2), (1, 0), (2, 1), (2, 0)]


def make_actor(agent: str, horizon: int, **kwargs) -> StackedActor:
    kwargs.setdefault("jit", False)  # no C files in the working directory; same problem
    problem = ActorProblem(
        agent,
        horizon,
        sampling_time=DELTA,
        cost_diag=tuple(R_DIAG),
        v_max=V_MAX,
        omega_max=OMEGA_MAX,
        **kwargs,
    )
    return StackedActor(problem)


def indefinite_problems(
    seed: int, count: int, spread: float = 2.0
) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """``count`` random indefinite critics and states: ``(q_weights, v_weights, state)``, the state
    uniform in ``[-spread, spread]^3``."""
    rng = np.random.default_rng(seed)
    for _ in range(count):
        w, v_w = 3 * rng.normal(size=15), 3 * rng.normal(size=6)
        yield w, v_w, rng.uniform(-spread, spread, size=3)


def _quad(weights: np.ndarray, pairs, z: list[np.ndarray]) -> np.ndarray:
    return sum(weights[k] * z[i] * z[j] for k, (i, j) in enumerate(pairs))


def hand_objective(agent: str, state, plan: list[tuple[np.ndarray, np.ndarray]], w, v_w) -> np.ndarray:
    """The agent's stacked objective (docs/concepts.md); ``plan`` is a list of (v_i, omega_i) arrays
    (broadcastable)."""
    n = len(plan) + 1  # N
    x, y, a = (np.float64(c) for c in state)
    total = 0.0
    for i, (vel, om) in enumerate(plan, start=1):  # the paper's i = 1 .. N-1
        running = DELTA * (R_DIAG[0] * x**2 + R_DIAG[1] * y**2 + R_DIAG[2] * a**2
                           + R_DIAG[3] * vel**2 + R_DIAG[4] * om**2)  # fmt: skip
        if agent == "mpc":
            total = total + running
        else:
            total = total + _quad(w, PAIRS5, [x, y, a, vel, om])
            if agent == "rlqv+":
                total = total + (n - i) * running
        # Euler predictor
        x, y, a = x + DELTA * vel * np.cos(a), y + DELTA * vel * np.sin(a), a + DELTA * om
    if agent in ("rlqv", "rlqv+"):
        total = total + _quad(v_w, PAIRS3, [x, y, a])
    return total


def psd_weights(rng: np.random.Generator, dim: int, pairs) -> np.ndarray:
    """Weights of a random positive-definite quadratic z' M z in the feature order."""
    L = rng.normal(size=(dim, dim))
    M = L @ L.T / dim + 0.05 * np.eye(dim)
    return np.array([M[i, j] if i == j else 2 * M[i, j] for i, j in pairs])


STATES = [np.array([1.0, 0.5, 0.3]), np.array([-0.7, 1.2, -2.5]), np.array([2.0, 2.0, math.pi / 4])]


@pytest.mark.parametrize("agent", ["mpc", "rlq", "rlqv", "rlqv+"])
def test_one_action_optimum_beats_grid_search(agent: str) -> None:
    rng = np.random.default_rng({"mpc": 1, "rlq": 2, "rlqv": 3, "rlqv+": 4}[agent])
    actor = make_actor(agent, 2)
    grid_v, grid_w = np.meshgrid(np.linspace(-V_MAX, V_MAX, 201), np.linspace(-OMEGA_MAX, OMEGA_MAX, 201))
    for state in STATES:  # the same actor, warm-started from its previous solution
        w = psd_weights(rng, 5, PAIRS5)
        v_w = psd_weights(rng, 3, PAIRS3)
        result = actor.step(state, w, v_w)
        assert result.success, result.status
        v, om = result.action
        assert abs(v) <= V_MAX and abs(om) <= OMEGA_MAX
        values = hand_objective(agent, state, [(grid_v, grid_w)], w, v_w)
        best = float(values.min())
        at_action = float(hand_objective(agent, state, [(np.float64(v), np.float64(om))], w, v_w))
        assert result.objective == pytest.approx(at_action, rel=1e-7, abs=1e-10)
        assert at_action <= best + 1e-7 * max(1.0, abs(best))
        # and the grid is fine enough to be near the optimum (sanity of the oracle)
        assert best - at_action < 1e-2 * max(1.0, abs(best))


def test_mpc_one_action_is_zero() -> None:
    # with N = 2 the MPC objective is delta r(s_1, u_1): only the action weights depend on u
    result = make_actor("mpc", 2).step(np.array([1.0, -1.0, 0.5]), np.zeros(15), np.zeros(6))
    np.testing.assert_allclose(result.action, [0.0, 0.0], atol=1e-6)
    assert result.objective == pytest.approx(DELTA * (1 + 10 + 0.25), rel=1e-9)


def test_mpc_two_actions_beats_grid_search() -> None:
    actor = make_actor("mpc", 3)
    axes = (np.linspace(-V_MAX, V_MAX, 31), np.linspace(-OMEGA_MAX, OMEGA_MAX, 31))
    v1, w1, v2, w2 = np.meshgrid(axes[0], axes[1], axes[0], axes[1], indexing="ij", sparse=True)
    for state in STATES:
        result = actor.step(state, np.zeros(15), np.zeros(6))
        assert result.success, result.status
        assert result.plan.shape == (2, 2)
        assert np.all(np.abs(result.plan) <= [V_MAX, OMEGA_MAX])
        best = float(hand_objective("mpc", state, [(v1, w1), (v2, w2)], None, None).min())
        plan = [(np.float64(p[0]), np.float64(p[1])) for p in result.plan]
        at_plan = float(hand_objective("mpc", state, plan, None, None))
        assert result.objective == pytest.approx(at_plan, rel=1e-7)
        assert at_plan <= best + 1e-7 * max(1.0, abs(best))
        assert best - at_plan < 1e-2 * max(1.0, abs(best))


@pytest.mark.parametrize("agent", ["mpc", "rlq", "rlqv", "rlqv+"])
def test_longer_horizon_objective_and_local_optimality(agent: str) -> None:
    # N = 5: the reported objective is docs/concepts.md's at the returned plan, and no feasible
    # perturbation of the plan does better (a local minimum of the hand-written objective).
    rng = np.random.default_rng(21)
    actor = make_actor(agent, 5)
    bounds = np.array([V_MAX, OMEGA_MAX])
    for state in STATES:
        w, v_w = psd_weights(rng, 5, PAIRS5), psd_weights(rng, 3, PAIRS3)
        result = actor.step(state, w, v_w)
        assert result.success, result.status
        assert result.plan.shape == (4, 2)
        plan = [(np.float64(p[0]), np.float64(p[1])) for p in result.plan]
        at_plan = float(hand_objective(agent, state, plan, w, v_w))
        assert result.objective == pytest.approx(at_plan, rel=1e-7, abs=1e-10)
        kicks = rng.normal(size=(500, 4, 2)) * bounds * rng.choice([1e-3, 1e-2, 1e-1], size=(500, 1, 1))
        trial = np.clip(result.plan + kicks, -bounds, bounds)
        values = hand_objective(agent, state, [(trial[:, i, 0], trial[:, i, 1]) for i in range(4)], w, v_w)
        assert values.min() >= at_plan - 1e-7 * max(1.0, abs(at_plan))


def test_ipopt_and_fatrop_agree() -> None:
    rng = np.random.default_rng(12)
    w, v_w = psd_weights(rng, 5, PAIRS5), psd_weights(rng, 3, PAIRS3)
    state = np.array([0.8, -0.6, 1.0])
    fatrop = make_actor("rlqv", 2).step(state, w, v_w)
    ipopt = make_actor("rlqv", 2, solver="ipopt").step(state, w, v_w)
    assert fatrop.success and ipopt.success
    np.testing.assert_allclose(fatrop.action, ipopt.action, atol=1e-5)
    assert fatrop.objective == pytest.approx(ipopt.objective, rel=1e-7)


@pytest.mark.integration
def test_jit_build_solves_the_same_problem_and_leaves_no_files(tmp_path, monkeypatch) -> None:
    import tempfile

    work, scratch = tmp_path / "work", tmp_path / "tmp"
    work.mkdir()
    scratch.mkdir()
    monkeypatch.chdir(work)
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    rng = np.random.default_rng(13)
    w, v_w = psd_weights(rng, 5, PAIRS5), psd_weights(rng, 3, PAIRS3)
    state = np.array([0.8, -0.6, 1.0])
    plain = make_actor("rlqv+", 3)
    jitted = make_actor("rlqv+", 3, jit=True)
    # the build directory is removed once the compiled code is loaded: nothing is left for a
    # SIGKILL to orphan, and nothing is written where the user runs the command
    assert list(scratch.iterdir()) == [] and list(work.iterdir()) == []
    for _ in range(3):  # the jitted solver and merit keep working without their files
        expected, got = plain.step(state, w, v_w), jitted.step(state, w, v_w)
        np.testing.assert_allclose(got.plan, expected.plan, atol=1e-7)
        assert got.objective == pytest.approx(expected.objective, rel=1e-9)
        state = exact_step(state, got.action, DELTA)


def _cached_objects(cache) -> dict[str, float]:
    return {path.name: path.stat().st_mtime for path in cache.glob("*.o")}


def _same_steps(one: StackedActor, other: StackedActor, steps: int = 3) -> None:
    """Bit for bit: the same plans and objectives from the same states and weights."""
    one.reset()
    other.reset()
    rng = np.random.default_rng(5)
    w, v_w = psd_weights(rng, 5, PAIRS5), psd_weights(rng, 3, PAIRS3)
    state = np.array([0.8, -0.6, 1.0])
    for _ in range(steps):
        a, b = one.step(state, w, v_w), other.step(state, w, v_w)
        np.testing.assert_array_equal(a.plan, b.plan)
        assert a.objective == b.objective
        state = exact_step(state, a.action, DELTA)


@pytest.mark.integration
@pytest.mark.needs_compiler
def test_the_jit_cache_compiles_a_problem_once_and_the_cached_build_solves_bit_for_bit(tmp_path) -> None:
    """actor.jit_cache: the first build stores each compiled object (private directory); the next
    build of the same problem takes every one from there (each touched, none added) and solves
    exactly as a build without the cache. The control, a build without the cache, stores nothing."""
    cache = tmp_path / "jit"
    uncached = make_actor("rlqv+", 3, jit=True)
    assert not cache.exists()
    first = make_actor("rlqv+", 3, jit=True, jit_cache=str(cache))
    stored = _cached_objects(cache)
    assert len(stored) >= 2 and cache.stat().st_mode & 0o777 == 0o700
    for name in stored:
        os.utime(cache / name, (1e9, 1e9))  # 2001: a hit touches it
    second = make_actor("rlqv+", 3, jit=True, jit_cache=str(cache))
    again = _cached_objects(cache)
    assert set(again) == set(stored) and min(again.values()) > 1e9, again
    _same_steps(second, uncached)
    _same_steps(first, uncached)


@pytest.mark.integration
@pytest.mark.needs_compiler
def test_a_damaged_cached_object_is_compiled_again_and_replaced(tmp_path, caplog) -> None:
    cache = tmp_path / "jit"
    make_actor("rlqv", 3, jit=True, jit_cache=str(cache))
    stored = _cached_objects(cache)
    for name in stored:
        (cache / name).write_bytes(b"not an object file")
    with caplog.at_level("WARNING", logger="common.system.jit"):
        rebuilt = make_actor("rlqv", 3, jit=True, jit_cache=str(cache))
    assert "the JIT build with cached objects failed" in caplog.text
    assert set(_cached_objects(cache)) == set(stored)
    assert all((cache / name).read_bytes()[:4] == b"\x7fELF" for name in stored)  # replaced by real objects
    _same_steps(rebuilt, make_actor("rlqv", 3, jit=True))


@pytest.mark.integration
@pytest.mark.needs_compiler
def test_a_jit_cache_another_user_could_write_is_not_used(tmp_path, caplog) -> None:
    cache = tmp_path / "shared"
    cache.mkdir()
    cache.chmod(0o777)
    with caplog.at_level("WARNING", logger="common.system.jit"):
        make_actor("mpc", 3, jit=True, jit_cache=str(cache))
    assert "is not private to this user" in caplog.text
    assert list(cache.iterdir()) == []


def test_the_jit_cache_keeps_the_most_recently_used_objects_and_drops_old_leftovers(tmp_path) -> None:
    from common.system.jit import prune_jit_cache

    for i in range(6):
        path = tmp_path / f"{i:064x}.o"
        path.write_bytes(b"x")
        os.utime(path, (1e9 + i, 1e9 + i))
    stale, fresh = tmp_path / ".abc.123", tmp_path / ".def.456"  # stores of killed builds, and one running
    stale.write_bytes(b"x")
    fresh.write_bytes(b"x")
    os.utime(stale, (1e9, 1e9))
    prune_jit_cache(str(tmp_path), keep=4)
    assert sorted(p.name for p in tmp_path.glob("*.o")) == [f"{i:064x}.o" for i in range(2, 6)]
    assert not stale.exists() and fresh.exists()


@pytest.mark.parametrize("agent", ["mpc", "rlq", "rlqv", "rlqv+"])
def test_actions_stay_within_bounds_in_closed_loop(agent: str) -> None:
    rng = np.random.default_rng(99)
    actor = make_actor(agent, 5)
    state = np.array([1.5, -1.0, 2.0])
    for _ in range(15):
        w = 3 * rng.normal(size=15)  # mixed signs: indefinite, possibly non-convex problems
        v_w = 3 * rng.normal(size=6)
        result = actor.step(state, w, v_w)
        assert result.action.shape == (2,)
        assert np.all(np.isfinite(result.action))
        assert abs(result.action[0]) <= V_MAX and abs(result.action[1]) <= OMEGA_MAX
        assert np.all(np.abs(result.plan) <= [V_MAX, OMEGA_MAX])
        state = exact_step(state, result.action, DELTA)
    assert actor.counters.solves == 15
    assert len(actor.counters.solve_seconds) == 15


@pytest.mark.parametrize(
    ("state", "w", "v_w"),
    [
        ([np.nan, 0.0, 0.0], np.zeros(15), np.zeros(6)),
        ([0.0, np.inf, 0.0], np.zeros(15), np.zeros(6)),
        ([1.0, 2.0], np.zeros(15), np.zeros(6)),
        ([1.0, 2.0, 0.0], np.zeros(14), np.zeros(6)),
        ([1.0, 2.0, 0.0], np.zeros(15), np.zeros(7)),
        ([1.0, 2.0, 0.0], np.r_[np.zeros(14), np.nan], np.zeros(6)),
        ([1.0, 2.0, 0.0], np.zeros(15), np.r_[np.zeros(5), np.inf]),
    ],
)
def test_step_rejects_bad_inputs(state, w, v_w) -> None:
    actor = make_actor("rlqv", 2)
    with pytest.raises(ValueError):
        actor.step(np.array(state), w, v_w)
    assert actor.counters.solves == 0


def test_step_rejects_weights_split_wrongly() -> None:
    # 16 + 5 has the right total length but is not 15 Q weights + 6 V weights: the first
    # V weight would be read as a Q weight. Each vector must be checked on its own.
    actor = make_actor("rlqv", 2)
    with pytest.raises(ValueError):
        actor.step(np.array([1.0, 2.0, 0.0]), np.zeros(16), np.zeros(5))


@pytest.mark.parametrize(
    "changes",
    [
        {"horizon": 1},
        {"horizon": 0},
        {"sampling_time": -0.1},
        {"sampling_time": 0.0},
        {"sampling_time": float("nan")},
        {"agent": "dqn"},
        {"cost_diag": (1.0, 10.0, 1.0, 0.01)},
        {"cost_diag": (1.0, -10.0, 1.0, 0.01, 0.01)},
        {"v_max": 0.0},
        {"omega_max": -1.0},
        {"predictor": "midpoint"},
        {"solver": "snopt"},
        {"bound_push": 0.0},
        {"bound_push": 0.6},
        {"bound_push": float("nan")},
    ],
)
def test_bad_actor_problem_raises(changes: dict) -> None:
    args = {
        "agent": "rlqv", "horizon": 4, "sampling_time": DELTA, "cost_diag": tuple(R_DIAG),
        "v_max": V_MAX, "omega_max": OMEGA_MAX, **changes,
    }  # fmt: skip
    with pytest.raises(ValueError):
        ActorProblem(**args)


def test_forced_failure_on_first_step_gives_zero_action() -> None:
    actor = make_actor("rlqv", 4, max_iter=1)
    rng = np.random.default_rng(5)
    w, v_w = psd_weights(rng, 5, PAIRS5), psd_weights(rng, 3, PAIRS3)
    result = actor.step(np.array([1.0, 0.5, 0.3]), w, v_w)
    assert not result.success
    assert result.status not in ("", "success") and "error" not in result.status  # fatrop's own code
    assert actor.counters.failures == 1
    np.testing.assert_array_equal(result.action, [0.0, 0.0])
    assert np.all(np.isfinite(result.plan)) and result.plan.shape == (3, 2)
    result = actor.step(np.array([1.0, 0.5, 0.3]), w, v_w)
    assert actor.counters.failures == 2
    assert np.all(np.isfinite(result.action))
    assert abs(result.action[0]) <= V_MAX and abs(result.action[1]) <= OMEGA_MAX


def _broken_solve() -> None:
    """Stands in for the solver's evaluation: CasADi raises RuntimeError on evaluation errors."""
    raise RuntimeError("forced failure")


def test_failure_after_success_falls_back_to_shifted_plan() -> None:
    actor = make_actor("mpc", 4)
    state = np.array([1.0, 0.5, 0.3])
    first = actor.step(state, np.zeros(15), np.zeros(6))
    assert first.success and actor.counters.failures == 0
    actor._evaluate = _broken_solve  # force every further solve to fail
    second = actor.step(exact_step(state, first.action, DELTA), np.zeros(15), np.zeros(6))
    assert not second.success
    assert actor.counters.failures == 1
    np.testing.assert_allclose(second.action, first.plan[1], atol=1e-12)  # u_2 of the last plan
    third = actor.step(np.array([0.9, 0.5, 0.3]), np.zeros(15), np.zeros(6))
    assert actor.counters.failures == 2
    np.testing.assert_allclose(third.action, first.plan[2], atol=1e-12)
    for r in (second, third):
        assert np.all(np.isfinite(r.action))
        assert abs(r.action[0]) <= V_MAX and abs(r.action[1]) <= OMEGA_MAX


def test_fallback_stops_once_the_previous_plan_is_used_up() -> None:
    # On a failed solve the actor takes the shifted previous plan, then zero velocity
    # (docs/concepts.md). A plan of N - 1 actions covers N - 2 failed steps after the solved
    # one; after that the robot must stand still, not repeat the last held action for ever.
    rng = np.random.default_rng(31)
    w, v_w = psd_weights(rng, 5, PAIRS5), psd_weights(rng, 3, PAIRS3)
    actor = make_actor("rlqv", 3)
    first = actor.step(np.array([1.0, 0.5, 0.3]), w, v_w)
    assert first.success
    assert np.linalg.norm(first.plan[-1]) > 1e-3  # the last planned action is not standing still
    actor._evaluate = _broken_solve
    second = actor.step(np.array([1.0, 0.5, 0.3]), w, v_w)
    np.testing.assert_allclose(second.action, first.plan[1], atol=1e-12)
    for _ in range(3):
        later = actor.step(np.array([1.0, 0.5, 0.3]), w, v_w)
        np.testing.assert_array_equal(later.action, [0.0, 0.0])
    assert actor.counters.failures == 4


def test_reset_forgets_the_previous_plan() -> None:
    actor = make_actor("mpc", 3)
    actor.step(np.array([1.0, 0.5, 0.3]), np.zeros(15), np.zeros(6))
    actor.reset()
    actor._evaluate = _broken_solve
    result = actor.step(np.array([1.0, 0.5, 0.3]), np.zeros(15), np.zeros(6))
    np.testing.assert_array_equal(result.action, [0.0, 0.0])


def _actions_of(x: np.ndarray) -> list[tuple[float, float]]:
    stages = x[:-3].reshape(-1, 5)
    return [(float(v), float(om)) for v, om in stages[:, 3:]]


@pytest.mark.parametrize("agent", ["mpc", "rlq", "rlqv", "rlqv+"])
def test_warm_start_merit_is_the_objective_along_a_rollout(agent: str) -> None:
    rng = np.random.default_rng(11)
    actor = make_actor(agent, 5)
    for _ in range(5):
        w, v_w = rng.normal(size=15), rng.normal(size=6)
        state = rng.uniform(-2, 2, size=3)
        x = rng.uniform(-1, 1, size=actor._n_x)  # the state entries must not matter
        actor._params[:15], actor._params[15:] = w, v_w
        plan = [(np.float64(v), np.float64(om)) for v, om in _actions_of(x)]
        expected = hand_objective(agent, state, plan, w, v_w)
        actor._merit_state[:] = state
        assert actor._merit_of(x) == pytest.approx(float(expected), rel=1e-10, abs=1e-12)


def test_warm_start_takes_the_cheaper_of_shifted_and_earlier_solution() -> None:
    # A period-2 loop: state S, then S', then S again. At S the solution from two steps ago
    # was computed at this very state; the guess must be whichever of it and the shifted
    # previous solution has the lower objective along a rollout (the oracle: hand_objective).
    rng = np.random.default_rng(3)
    w, v_w = rng.normal(size=15) * 3.0, rng.normal(size=6)
    actor = make_actor("rlqv", 6)
    chosen = {"earlier": 0, "shifted": 0}
    for trial in range(6):
        s_a = rng.uniform(-2, 2, size=3)
        s_b = rng.uniform(-2, 2, size=3)
        actor.reset()
        first = actor.step(s_a, w, v_w)
        second = actor.step(s_b, w, v_w)
        assert first.success and second.success
        earlier, previous = actor._earlier_x.copy(), actor._previous_x.copy()
        actor._initial_guess(s_a)
        guess = _actions_of(actor._x0)
        shifted = _actions_of(np.concatenate([previous[5:], previous[-5:]]))
        costs = {
            "earlier": hand_objective("rlqv", s_a, _actions_of(earlier), w, v_w),
            "shifted": hand_objective("rlqv", s_a, shifted, w, v_w),
        }
        best = min(costs, key=costs.get)
        if abs(costs["earlier"] - costs["shifted"]) < 1e-9 * (1 + abs(costs[best])):
            continue  # a tie within rounding: either guess is right
        assert guess == (_actions_of(earlier) if best == "earlier" else shifted), (trial, costs)
        np.testing.assert_array_equal(actor._x0[:3], s_a)
        chosen[best] += 1
    assert chosen["earlier"] >= 1  # the case the candidate exists for did occur


@pytest.mark.parametrize("agent", ["rlq", "rlqv", "rlqv+"])
def test_earlier_solution_candidate_saves_iterations_in_the_learned_weight_loop(agent: str) -> None:
    # The benchmark's non-convex "learned" weights make the closed loop alternate between two
    # local minima; starting from the solution of two steps ago when it is cheaper must save
    # solver iterations there (measured: 25-51 % fewer over 150 steps at N = 12).
    from common.config.assembly import build_actor
    from common.config.settings import Settings
    from common.math.loop import ExactPlant
    from tools.bench.actor import learned_weights

    # the merit-only warm start (multistart off); the global phase takes both plans as starts.
    # Solver iterations are what is counted: the solver polishes every step (no Newton iterations)
    actor_settings = {"agent": agent, "horizon": 12, "jit": False, "multistart": False, "newton_iterations": 0}
    settings = Settings.load(actor=actor_settings)
    weights = learned_weights(settings)
    iterations = {}
    for use_earlier in (True, False):
        actor = build_actor(settings)
        plant = ExactPlant()
        state = plant.reset(settings.start_state())
        iterations[use_earlier] = 0
        for _ in range(150):
            if not use_earlier:
                actor._earlier_x = None  # only the shifted previous solution is a candidate
            result = actor.step(state, weights.q, weights.v)
            assert result.success
            iterations[use_earlier] += int(actor._buffer.stats()["iter_count"])
            state = plant.apply(result.action, settings.plant.sampling_time)
    assert iterations[True] < 0.9 * iterations[False], iterations


# -- the argmin -----------------------------------------------------------------------------------
def test_global_phase_ends_are_rollouts_no_worse_than_their_starts() -> None:
    # Oracle: hand_objective along the Euler rollout. Each start descends monotonically inside
    # the box; the reported end value is the objective of the end's actions, and the decision
    # vector handed to the solver is that end's rollout from the state.
    actor = make_actor("rlqv+", 5, multistart=True, multistart_iterations=20)
    bounds = np.array([V_MAX, OMEGA_MAX])
    for w, v_w, state in indefinite_problems(18, 4):
        actor._params[:15], actor._params[15:] = w, v_w
        actor.reset()
        actor._global_guess(state)
        for row in range(actor._starts.shape[0]):
            start = [(np.float64(a), np.float64(b)) for a, b in actor._starts[row].reshape(-1, 2) * bounds]
            end_plan = actor._ends[row].reshape(-1, 2) * bounds
            end = [(np.float64(a), np.float64(b)) for a, b in end_plan]
            assert np.all(np.abs(actor._ends[row]) <= 1.0)
            assert actor._end_values[row] == pytest.approx(float(hand_objective("rlqv+", state, end, w, v_w)), rel=1e-9)
            assert actor._end_values[row] <= float(hand_objective("rlqv+", state, start, w, v_w)) + 1e-12
            x = actor._end_vectors[row]
            np.testing.assert_allclose(_actions_of(x), end_plan, atol=1e-12)
            s = state
            for k, u in enumerate(end_plan):  # the states are the Euler rollout of the actions
                np.testing.assert_allclose(x[5 * k : 5 * k + 3], s, atol=1e-12)
                s = s + DELTA * np.array([u[0] * np.cos(s[2]), u[0] * np.sin(s[2]), u[1]])
            np.testing.assert_allclose(x[-3:], s, atol=1e-12)
        best = int(np.argmin(actor._end_values))
        np.testing.assert_array_equal(actor._x0, actor._end_vectors[best])


@pytest.mark.parametrize(
    "changes",
    [{"multistart_iterations": 0}, {"multistart_margin": -0.1}, {"multistart_refresh": -1}, {"multistart_flips": -1}],
)
def test_bad_multistart_settings_raise(changes: dict) -> None:
    with pytest.raises(ValueError):
        ActorProblem("rlqv", 4, DELTA, tuple(R_DIAG), V_MAX, OMEGA_MAX, **changes)


@pytest.mark.parametrize(("agent", "horizon"), [("rlq", 6), ("rlqv+", 6), ("rlqv+", 12)])
def test_actor_in_the_loop_is_not_worse_than_a_cold_slsqp_solve(agent: str, horizon: int) -> None:
    # The minimizer the actor takes in the closed loop (warm-started from its own plans, the
    # benchmark's non-convex "learned" weights) is no worse than the paper framework's way, a
    # cold SLSQP solve from standing still at the same state (tools/bench/actor.py): the global
    # phase finds the minima the warm start alone misses.
    # Generous bounds: not worse (to 1e-6 relative) at >= 75 % of the states, median gap <= 1e-6.
    from common.config.assembly import build_actor
    from common.config.settings import PAPER_METHOD, Settings
    from common.math.loop import ExactPlant
    from tools.bench.actor import NumpyObjective, learned_weights, slsqp_solve

    settings = Settings.load(actor={"agent": agent, "horizon": horizon, "jit": False, **PAPER_METHOD["actor"]})
    weights = learned_weights(settings)
    actor = build_actor(settings)
    objective = NumpyObjective(actor.problem, weights.q, weights.v)
    plant = ExactPlant()
    state = plant.reset(settings.start_state())
    ours, cold, seconds = [], [], []
    for k in range(80):
        result = actor.step(state, weights.q, weights.v)
        assert result.success, result.status
        seconds.append(result.solve_seconds)
        if k % 8 == 0:
            ours.append(objective(result.plan, state))
            cold.append(slsqp_solve(objective, state).value)
        state = plant.apply(result.action, settings.plant.sampling_time)
    ours_a, cold_a = np.array(ours), np.array(cold)
    not_worse = ours_a <= cold_a + 1e-6 * np.abs(cold_a) + 1e-7
    gaps = (ours_a - cold_a) / np.maximum(np.abs(cold_a), 1e-6)
    assert np.mean(not_worse) >= 0.75, list(zip(ours, cold, strict=True))
    assert np.median(gaps) <= 1e-6, gaps
    assert np.median(seconds) < 0.05  # generous: ~1 ms without JIT on 2 shared cores


@pytest.mark.parametrize(("margin", "refresh"), [(10.0, 0), (0.0, 1)])
def test_runner_up_polish_keeps_the_lower_solution(margin: float, refresh: int) -> None:
    # With a wide margin, or a refresh at every solve, the actor also polishes the other kind of
    # start's lowest end and keeps the lower of the two solutions: never above the single polish.
    single = make_actor("rlqv+", 6, multistart=True, multistart_margin=0.0, multistart_refresh=0)
    double = make_actor("rlqv+", 6, multistart=True, multistart_margin=margin, multistart_refresh=refresh)
    for w, v_w, state in indefinite_problems(7, 6, spread=1):
        single.reset()
        double.reset()
        one, two = single.step(state, w, v_w), double.step(state, w, v_w)
        assert one.success and two.success
        assert two.objective <= one.objective + 1e-9 * (1 + abs(one.objective))
        plan = [(np.float64(a), np.float64(b)) for a, b in two.plan]
        assert two.objective == pytest.approx(float(hand_objective("rlqv+", state, plan, w, v_w)), rel=1e-6, abs=1e-9)
    assert single.counters.second_solves == 0 and double.counters.second_solves >= 1


def test_a_runner_up_that_lost_by_a_lot_is_skipped_until_a_refresh_measures_again() -> None:
    # StackedActor._runner_up with multistart_hopeless: the other kind of start's end is offered
    # (within the margin) unless the last runner-up polish lost by more than the share; a
    # refresh's solve offers it whatever; 0 never skips (the negative control).
    actor = make_actor("mpc", 4, multistart=True, multistart_margin=0.1, multistart_refresh=3, multistart_hopeless=0.02)
    actor.step(np.array([1.0, 0.5, 0.3]), np.zeros(15), np.zeros(6))  # a plan: the ends are set up
    actor._end_values[:] = [1.0, 2.0, 1.05, 3.0, 3.0]  # warm row 0 lowest, fresh row 2 within 10 %
    actor._ends[:] = 0.0
    actor._ends[2] = 0.5  # apart from the lowest end

    def offered(shortfall: float, solves: int, hopeless: float = 0.02) -> bool:
        actor.problem = dataclasses.replace(actor.problem, multistart_hopeless=hopeless)
        actor._runner_up_shortfall, actor._episode_solves = shortfall, solves
        return actor._runner_up() is not None

    assert offered(0.0, 1) and offered(0.02, 1)  # never lost, or lost by no more than the share
    assert not offered(0.05, 1) and not offered(0.05, 2)  # lost by 5 %: skipped between refreshes
    assert offered(0.05, 3)  # a refresh's solve measures again
    assert offered(0.05, 1, hopeless=0.0)  # 0: never skipped


def learned_critic_actor(hopeless: float) -> StackedActor:
    """RL-QV+ at N = 12 with the full multistart (the defaults' margin, refresh, vertex search and
    Newton iterations), the runner-up skipped after a loss of more than ``hopeless``: the actor the
    benchmark's "learned" critic misleads (tools.bench.actor.learned_weights)."""
    return make_actor(
        "rlqv+",
        12,
        multistart=True,
        multistart_margin=0.1,
        multistart_refresh=3,
        multistart_hopeless=hopeless,
        multistart_flips=3,
        newton_iterations=6,
    )


def test_the_runner_up_shortfall_is_kept_per_robot_and_saves_polishes_on_a_critic_that_misleads() -> None:
    # The actor benchmark's "learned" critic (indefinite): its fresh ends keep looking within the
    # margin and polish to a minimum a few % worse. With multistart_hopeless the runner-up is then
    # polished at the refreshes only (0: at every offer, the negative control); the shortfall goes
    # with a robot's memory (swap_memory) and a reset forgets it.
    from common.config.settings import Settings
    from tools.bench.actor import learned_weights

    weights = learned_weights(Settings.load())
    counts = {}
    for hopeless in (0.0, 0.02):
        actor = learned_critic_actor(hopeless)
        state = np.array([2.0, 2.0, math.pi / 4])
        shortfalls = []
        for _ in range(40):
            step = actor.step(state, weights.q, weights.v)
            shortfalls.append(actor._runner_up_shortfall)
            state = exact_step(state, step.action, DELTA)
        counts[hopeless] = actor.counters.second_solves
        assert max(shortfalls) > 0.02, shortfalls  # the critic misleads: a polish lost by more
        if hopeless:
            held = actor.swap_memory(ActorMemory())
            assert held.runner_up_shortfall == shortfalls[-1] and actor._runner_up_shortfall == 0.0
            actor.swap_memory(held)
            assert actor._runner_up_shortfall == shortfalls[-1]
            actor.reset()
            assert actor._runner_up_shortfall == 0.0
    assert counts[0.0] >= 20 and counts[0.02] <= counts[0.0] - 5, counts


def test_a_step_whose_newton_iterations_fell_short_polishes_no_runner_up() -> None:
    # StackedActor.step: a polish that fell back to fatrop is the step's one interior-point
    # solve; no runner-up polish follows it. The benchmark's "learned" critic offers a runner-up
    # at most steps (multistart_hopeless 0). Every Newton end made to look short of stationary:
    # no step polishes again after a polish that fell back, while the same loop with the Newton
    # iterations as they are (the negative control) polishes a runner-up at 20 or more of 40
    # steps, and one whose first polish ran no Newton iterations still polishes its runner-up.
    from common.config.settings import Settings
    from tools.bench.actor import learned_weights

    weights = learned_weights(Settings.load())
    second = {}
    for short in (False, True):
        actor = learned_critic_actor(0.0)
        polishes: list[bool] = []  # this step's polishes: did each fall back to fatrop?
        if short:
            newton = actor._evaluate_newton

            def fall_short(newton: Callable[[], None] = newton, actor: StackedActor = actor) -> None:
                newton()
                actor._newton_stationarity[0] = 1.0

            actor._evaluate_newton = fall_short  # type: ignore[method-assign]
        polish = actor._polish

        def counted(
            warm: bool,
            polish: Callable[[bool], Any] = polish,
            actor: StackedActor = actor,
            polishes: list[bool] = polishes,
        ) -> Any:
            fallbacks = actor.counters.newton_fallbacks
            result = polish(warm)
            polishes.append(actor.counters.newton_fallbacks > fallbacks)
            return result

        actor._polish = counted  # type: ignore[method-assign]
        state = np.array([2.0, 2.0, math.pi / 4])
        after_fresh = 0
        for _ in range(40):
            polishes.clear()
            step = actor.step(state, weights.q, weights.v)
            assert step.success
            if short:
                assert len(polishes) == 1 or not polishes[0], polishes
                after_fresh += len(polishes) > 1
            state = exact_step(state, step.action, DELTA)
        second[short] = actor.counters.second_solves
    assert second[False] >= 20, second
    assert 0 < second[True] == after_fresh, (second, after_fresh)


def test_same_basin_follows_the_merit_along_the_segment() -> None:
    # The second polish is skipped when the objective falls monotonically from the runner-up's
    # end to the first solution (one basin), taken when it rises on the way (a ridge).
    actor = make_actor("mpc", 4, multistart=True)
    state = np.array([1.0, 0.5, 0.3])
    result = actor.step(state, np.zeros(15), np.zeros(6))
    solution = actor._previous_x.copy()
    start = np.zeros_like(solution)  # standing still: the convex MPC objective falls towards its minimum
    assert actor._same_basin(state, start, solution)
    values = iter([1.0, 0.9, 1.2, 0.8, 0.7])  # a ridge between start (1.0) and solution (0.7)
    actor._merit_of = lambda x: next(values)  # type: ignore[method-assign]
    assert not actor._same_basin(state, start, solution)
    assert result.success


def test_an_episode_does_not_depend_on_what_the_actor_solved_before() -> None:
    # The experiment's workers reuse one actor for many runs: after reset() the global phase
    # (its refresh's phase included) must act as on a fresh actor, step for step.
    rng = np.random.default_rng(3)  # weights whose starts end apart: refreshes polish twice
    w, v_w = 3 * rng.normal(size=15), 3 * rng.normal(size=6)
    used = make_actor("rlqv", 5, multistart=True, multistart_margin=0.0, multistart_refresh=3)
    for _ in range(7):  # an earlier episode of 7 solves: not a multiple of the refresh period
        used.step(rng.uniform(-1, 1, size=3), w, v_w)
    used.reset()
    fresh = make_actor("rlqv", 5, multistart=True, multistart_margin=0.0, multistart_refresh=3)
    for actor in (used, fresh):  # every refresh then polishes twice: its phase shows
        actor._same_basin = lambda *args: False  # type: ignore[method-assign]
    state_used = state_fresh = np.array([1.2, -0.8, 2.0])
    polished_twice: dict[str, list[int]] = {"used": [], "fresh": []}
    for _ in range(12):
        counts = (used.counters.second_solves, fresh.counters.second_solves)
        a, b = used.step(state_used, w, v_w), fresh.step(state_fresh, w, v_w)
        polished_twice["used"].append(used.counters.second_solves - counts[0])
        polished_twice["fresh"].append(fresh.counters.second_solves - counts[1])
        np.testing.assert_array_equal(a.plan, b.plan)
        state_used, state_fresh = exact_step(state_used, a.action, DELTA), exact_step(state_fresh, b.action, DELTA)
    assert polished_twice["used"] == polished_twice["fresh"] and sum(polished_twice["fresh"]) >= 1, polished_twice


def test_vertex_search_finds_the_lower_vertex_that_the_polish_cannot_see() -> None:
    # Random indefinite critics make the objective concave along some action entries: the
    # polished minimum then sits on one bound of such an entry while the other bound may be
    # lower. The vertex search (multistart_flips) moves entries to either bound while that lowers
    # the objective and polishes the result. Oracle: brute force over the 2^6 vertices of the
    # action box (N = 4). Negative control: the same actor without the search, on the same
    # problems, stays above the lowest vertex where the search reaches it.
    import itertools

    horizon = 4
    plain = make_actor("rlq", horizon, multistart=True)
    search = make_actor("rlq", horizon, multistart=True, multistart_flips=3)
    vertices = [
        [(np.float64(p[2 * i]), np.float64(p[2 * i + 1])) for i in range(horizon - 1)]
        for p in itertools.product((-V_MAX, V_MAX), (-OMEGA_MAX, OMEGA_MAX), repeat=horizon - 1)
    ]
    found = []
    for w, v_w, state in indefinite_problems(0, 30):
        plain.reset()
        search.reset()
        before, after = plain.step(state, w, v_w), search.step(state, w, v_w)
        assert before.success and after.success
        assert after.objective <= before.objective + 1e-9 * (1 + abs(before.objective))  # never worse
        plan = [(np.float64(a), np.float64(b)) for a, b in after.plan]
        assert after.objective == pytest.approx(float(hand_objective("rlq", state, plan, w, v_w)), rel=1e-6, abs=1e-9)
        lowest_vertex = min(float(hand_objective("rlq", state, p, w, v_w)) for p in vertices)
        tolerance = 1e-6 * (1 + abs(lowest_vertex))
        if after.objective <= lowest_vertex + tolerance < before.objective - 1e-3 * (1 + abs(lowest_vertex)):
            found.append((before.objective, after.objective, lowest_vertex))
    assert found, "no problem where the search reached a lower vertex than the polish alone"
    assert search.counters.flip_solves >= len(found) and plain.counters.flip_solves == 0


def test_a_hurried_step_is_one_warm_polish_and_skips_the_extras() -> None:
    # services/actor/host.py hurries a tick served late (docs/fleets.md): the runner-up polish and the
    # vertex search are skipped and, once the robot has a plan, the global phase too: one fatrop
    # polish of the warm start. Oracles: with no plan yet (a cold step) an actor built without
    # the extras (margin and refresh off, flips off) gives the same actions; with a plan, an
    # actor built without the global phase (multistart off) given the same plans does. Negative
    # controls: the unhurried actor uses its extras, and its global phase moves some plans.
    hurried = make_actor("rlq", 6, multistart=True, multistart_flips=3)
    bare = make_actor("rlq", 6, multistart=True, multistart_flips=0, multistart_margin=0.0, multistart_refresh=0)
    full = make_actor("rlq", 6, multistart=True, multistart_flips=3)
    warm_only = make_actor("rlq", 6, multistart=False)
    moved = 0
    for w, v_w, state in indefinite_problems(4, 12):
        for actor in (hurried, bare, full, warm_only):
            actor.reset()
        fast = hurried.step(state, w, v_w, hurry=True)
        assert fast.success
        np.testing.assert_allclose(fast.plan, bare.step(state, w, v_w).plan, atol=1e-9)
        full.step(state, w, v_w)
        plans = hurried.swap_memory(ActorMemory())
        hurried.swap_memory(plans)
        warm_only.swap_memory(ActorMemory(plans.previous_x.copy(), None))  # type: ignore[union-attr]
        after = exact_step(state, fast.action, 0.1)
        second = hurried.step(after, w, v_w, hurry=True)
        assert second.success
        np.testing.assert_allclose(second.plan, warm_only.step(after, w, v_w).plan, atol=1e-9)
        bare.swap_memory(ActorMemory(plans.previous_x.copy(), None))  # type: ignore[union-attr]
        moved += not np.allclose(bare.step(after, w, v_w).plan, second.plan, atol=1e-6)
    assert hurried.counters.hurried_solves == 24
    assert hurried.counters.second_solves == 0 and hurried.counters.flip_solves == 0
    assert full.counters.hurried_solves == 0
    assert full.counters.second_solves + full.counters.flip_solves > 0  # the extras a hurry skips
    assert moved > 0  # the global phase a hurry skips does change plans here


def test_a_descending_hurry_descends_the_warm_start_without_the_solver() -> None:
    # ActorProblem.hurry "descend" (an actor host over its CPU budget or late, docs/fleets.md): once
    # the robot has a plan, a hurried step is the warm start descended by the global phase's
    # compiled projected gradient, and the solver does not run. Oracles: the step's objective is
    # the hand-written objective of its plan, never above the warm start's (the shifted previous
    # plan: the descent takes only steps that lower the objective), and the solver's polish count
    # stands still. Negative control: "polish" runs the solver on the same steps.
    descend = make_actor("rlq", 6, multistart=True, multistart_flips=3, hurry="descend")
    polish = make_actor("rlq", 6, multistart=True, multistart_flips=3, hurry="polish")
    lowered = 0
    for w, v_w, state in indefinite_problems(4, 12):
        for actor in (descend, polish):
            actor.reset()
        first = descend.step(state, w, v_w, hurry=True)  # no plan yet: the global phase and the solver
        assert first.success and first.status == "success"
        polish.step(state, w, v_w, hurry=True)
        after = exact_step(state, first.action, 0.1)
        shifted = [*first.plan[1:], first.plan[-1]]  # the warm start: the plan shifted, last action held
        warm = float(hand_objective("rlq", after, shifted, w, v_w))
        polished = descend.counters.phase_counts["polish"], polish.counters.phase_counts["polish"]
        second = descend.step(after, w, v_w, hurry=True)
        polish.step(after, w, v_w, hurry=True)
        assert second.success and second.status == "descended"
        assert descend.counters.phase_counts["polish"] == polished[0]
        assert polish.counters.phase_counts["polish"] == polished[1] + 1
        plan = [(np.float64(a), np.float64(b)) for a, b in second.plan]
        assert second.objective == pytest.approx(float(hand_objective("rlq", after, plan, w, v_w)), rel=1e-6, abs=1e-9)
        assert second.objective <= warm + 1e-9 * (1 + abs(warm))
        assert np.all(np.abs(second.plan) <= [V_MAX, OMEGA_MAX])
        lowered += second.objective < warm - 1e-6 * (1 + abs(warm))
    assert lowered > 0  # the descent moves plans: not the warm start handed back
    assert descend.counters.hurried_solves == polish.counters.hurried_solves == 24


def test_an_unknown_hurry_is_refused() -> None:
    with pytest.raises(ValueError, match="unknown hurry 'sprint'"):
        make_actor("rlq", 6, hurry="sprint")


def test_global_every_k_runs_the_global_phase_every_kth_solve_and_the_vertex_search_every_solve() -> None:
    # ActorProblem.global_every (an actor host's): the global phase, and the runner-up polish that
    # picks among its ends, at solves 0, k, 2k ... of a robot and at any solve without a plan; the
    # vertex search at every solve. Negative control: k = 1 (one robot's actor) runs it every solve.
    every = make_actor("rlq", 6, multistart=True, multistart_flips=3, global_every=3)
    always = make_actor("rlq", 6, multistart=True, multistart_flips=3)
    w, v_w, start = next(indefinite_problems(5, 1))
    for actor in (every, always):
        state = start
        for _ in range(7):
            step = actor.step(state, w, v_w)
            assert step.success and np.all(np.abs(step.action) <= [V_MAX, OMEGA_MAX])
            state = exact_step(state, step.action, DELTA)
    assert every.counters.phase_counts["global"] == 3  # solves 0, 3 and 6
    assert always.counters.phase_counts["global"] == 7
    assert every.counters.phase_counts["flip_search"] == 7 == always.counters.phase_counts["flip_search"]
    assert every.counters.phase_counts["runner_up"] <= 3
    every.reset()  # a new episode: no plan, so its first solve runs the global phase again
    every.step(start, w, v_w)
    every.step(exact_step(start, np.zeros(2), DELTA), w, v_w)
    assert every.counters.phase_counts["global"] == 4
    with pytest.raises(ValueError, match="global_every"):
        make_actor("rlq", 6, multistart=True, global_every=0)


def test_the_newton_polish_reaches_the_solvers_minimum_and_leaves_the_rest_to_the_solver() -> None:
    # ActorProblem.newton_iterations: a warm start's polish is the compiled projected Newton
    # iterations, the solver only where they end short of stationary; a fresh start's is the
    # solver's. Oracles: fatrop alone (newton_iterations 0) polishing the same start (the global
    # phase's lowest end) on random indefinite critics; the hand-written objective of the plan;
    # the start's merit (the iterations only descend). Negative control: one iteration from a
    # vertex of the box (full speed ahead, turning) leaves many starts to the solver, and counts them.
    newton = make_actor("rlqv", 6, multistart=True, newton_iterations=6)
    solver = make_actor("rlqv", 6, multistart=True)
    short = make_actor("rlqv", 6, multistart=True, newton_iterations=1)
    stationary = agree = 0
    for w, v_w, state in indefinite_problems(7, 20):
        for actor in (newton, solver, short):
            actor._params[:15], actor._params[15:] = w, v_w
            actor.reset()
            actor._global_guess(state)
            actor._lbx_np[:3] = state
            actor._ubx_np[:3] = state
        newton._merit_state[:] = state
        start = newton._merit_of(newton._x0)
        before = newton.counters.newton_fallbacks
        (success, _, x, value), reference = newton._polish(warm=True), solver._polish(warm=True)
        assert success and reference[0]
        assert value == pytest.approx(float(hand_objective("rlqv", state, _actions_of(x), w, v_w)), rel=1e-9)
        assert value <= start + 1e-9 * (1 + abs(start))
        assert np.all(np.abs(np.array(_actions_of(x))) <= np.array([V_MAX, OMEGA_MAX]) + 1e-9)
        if newton.counters.newton_fallbacks == before:
            stationary += 1
            agree += value == pytest.approx(reference[3], rel=1e-6, abs=1e-9)
        else:  # the solver from the start itself: fatrop's answer
            np.testing.assert_array_equal(x, reference[2])
        fresh = newton._polish(warm=False)  # a fresh start: the solver's, bit for bit
        np.testing.assert_array_equal(fresh[2], reference[2])
        short._x0[:-3].reshape(-1, 5)[:, 3:] = [V_MAX, OMEGA_MAX]
        short._polish(warm=True)
    assert newton.counters.newton_fallbacks == 20 - stationary  # the fresh polishes count none
    assert solver.counters.newton_fallbacks == 0  # no Newton iterations: nothing to fall back from
    assert stationary >= 15 and agree >= stationary - 1, (stationary, agree)
    assert short.counters.newton_fallbacks >= 5  # 9 of these 20


@pytest.mark.parametrize("iterations", [-1, 51])
def test_bad_newton_iterations_raise(iterations: int) -> None:
    with pytest.raises(ValueError, match="newton_iterations"):
        ActorProblem("rlqv", 4, DELTA, tuple(R_DIAG), V_MAX, OMEGA_MAX, newton_iterations=iterations)
