"""The stacked actors against brute-force grid search, plus bounds, validation and failures.

The oracle objective is written out here in numpy from the stacked objectives of docs/concepts.md
(Euler prediction, features from a hand-written pair list), evaluated on a grid of held actions.
"""

from __future__ import annotations

import contextlib
import math
import os
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
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
        action_max=(V_MAX, OMEGA_MAX),
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


def test_build_directories_of_processes_that_are_gone_are_removed_and_no_other(tmp_path) -> None:
    """A build killed with SIGKILL while CasADi wrote its C leaves srl-jit-PID-*: the next build
    and srl up's stop remove it; a running process's directory and other names stay."""
    from common.system.jit import remove_orphan_build_directories

    gone = int(Path("/proc/sys/kernel/pid_max").read_text())  # pids are below it: no process has it
    orphan = tmp_path / f"srl-jit-{gone}-abc123"
    running = tmp_path / f"srl-jit-{os.getpid()}-def456"
    others = [tmp_path / "srl-jit-abc", tmp_path / "srl-jit-12x-abc", tmp_path / "srl-secure-1-x"]
    for directory in [orphan, running, *others]:
        directory.mkdir()
        (directory / "srl_phase.c").write_text("int x;")
    assert remove_orphan_build_directories(str(tmp_path)) == 1
    assert not orphan.exists()
    assert running.exists() and all(d.exists() for d in others)
    assert remove_orphan_build_directories(str(tmp_path)) == 0


def test_a_build_directory_is_named_by_its_process(tmp_path, monkeypatch) -> None:
    from common.system.jit import jit_directory

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    with jit_directory() as compiler:
        assert os.path.basename(os.getcwd()).startswith(f"srl-jit-{os.getpid()}-")
        assert compiler.split()[0].startswith(os.getcwd())
    assert list(tmp_path.iterdir()) == []


def test_a_build_directory_written_to_while_it_is_removed_is_still_removed(tmp_path) -> None:
    """A compiler that a signal is stopping may create a file while its build directory is being
    removed: one pass of rmtree then leaves the directory (the control below), the removal used by
    the build and by srl up's stop tries again until it is gone."""
    import shutil
    import threading

    from common.system.jit import remove_build_directory

    def busy(directory: Path, stop: threading.Event) -> threading.Thread:
        directory.mkdir()
        for i in range(200):
            (directory / f"part{i}.c").write_text("int x;")

        def write() -> None:
            for i in range(400):
                if stop.is_set():
                    return
                with contextlib.suppress(OSError):  # the directory is gone: that writer is done
                    (directory / f"late{i}.o").write_text("x")
                time.sleep(0.0005)

        thread = threading.Thread(target=write)
        thread.start()
        return thread

    left = 0
    for attempt in range(10):  # the same race ten times for each removal
        stop = threading.Event()
        once, retried = tmp_path / f"once{attempt}", tmp_path / f"retried{attempt}"
        writers = [busy(once, stop), busy(retried, stop)]
        shutil.rmtree(once, ignore_errors=True)
        left += once.exists()
        assert remove_build_directory(str(retried)) and not retried.exists()
        stop.set()
        for writer in writers:
            writer.join()
    assert left > 0, "one pass never lost the race: the test cannot tell the removals apart"


def test_a_signal_during_the_build_setup_leaves_no_directory(tmp_path, monkeypatch) -> None:
    """KeyboardInterrupt (Ctrl-C) at the last step of jit_directory's setup, before the build
    starts: the directory, the working directory and the environment are as before."""
    import common.system.jit as jit

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    before, environment = os.getcwd(), dict(os.environ)

    def interrupted() -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(jit, "_SigintKeeper", interrupted)
    with pytest.raises(KeyboardInterrupt), jit.jit_directory():
        pass
    assert list(tmp_path.iterdir()) == []
    assert os.getcwd() == before and dict(os.environ) == environment


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
        {"action_max": (0.0, OMEGA_MAX)},
        {"action_max": (V_MAX, -1.0)},
        {"action_max": (V_MAX,)},
        {"action_max": (V_MAX, OMEGA_MAX, 1.0)},
        {"system": "no_such_system"},
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
        "action_max": (V_MAX, OMEGA_MAX), **changes,
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
        earlier, previous = actor.memory.earlier_x.copy(), actor.memory.previous_x.copy()
        actor._warm_guess(s_a)
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
    actor_settings = {"agent": agent, "horizon": 12, "jit": False, "multistart": False}
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
                actor.memory.earlier_x = None  # only the shifted previous solution is a candidate
            result = actor.step(state, weights.q, weights.v)
            assert result.success
            iterations[use_earlier] += int(actor._buffer.stats()["iter_count"])
            state = plant.apply(result.action, settings.plant.sampling_time)
    assert iterations[True] < 0.9 * iterations[False], iterations


# -- the argmin (common/math/actor_search.py) --------------------------------------------------------
def searching_actor(agent: str, horizon: int, **kwargs: Any) -> StackedActor:
    """The argmin's actor (multistart) with the packaged defaults, interpreted."""
    return make_actor(agent, horizon, multistart=True, **kwargs)


def scaled_plan(actor: StackedActor, plan: np.ndarray) -> np.ndarray:
    """A plan of held actions as the search's z (the decisions scaled to [-1, 1], u_1 first)."""
    return (plan / np.array([V_MAX, OMEGA_MAX])).ravel()


def test_the_ticks_answer_is_a_stationary_minimum_of_the_objective_it_reports() -> None:
    # Oracles: the hand-written objective of the returned plan; no small feasible perturbation of
    # the plan lowers it (a local minimum); the answer never above the warm start's objective
    # (the shifted previous plan: every phase only descends, and the warm polish starts there).
    rng = np.random.default_rng(41)
    actor = searching_actor("rlqv+", 5)
    bounds = np.array([V_MAX, OMEGA_MAX])
    for w, v_w, state in indefinite_problems(23, 8, spread=1.5):
        actor.reset()
        first = actor.step(state, w, v_w)
        after = exact_step(state, first.action, DELTA)
        shifted = [*first.plan[1:], first.plan[-1]]
        warm = float(hand_objective("rlqv+", after, shifted, w, v_w))
        second = actor.step(after, w, v_w)
        for result, at in ((first, state), (second, after)):
            assert result.success and result.status == "success"
            plan = [(np.float64(a), np.float64(b)) for a, b in result.plan]
            value = float(hand_objective("rlqv+", at, plan, w, v_w))
            assert result.objective == pytest.approx(value, rel=1e-9, abs=1e-12)
            kicks = rng.normal(size=(300, 4, 2)) * bounds * rng.choice([1e-4, 1e-3, 1e-2], size=(300, 1, 1))
            trial = np.clip(result.plan + kicks, -bounds, bounds)
            values = hand_objective("rlqv+", at, [(trial[:, i, 0], trial[:, i, 1]) for i in range(4)], w, v_w)
            assert values.min() >= value - 1e-7 * max(1.0, abs(value))
        assert second.objective <= warm + 1e-9 * (1 + abs(warm))
    assert actor.counters.phase_counts["solver"] == 0  # the Newton iterations converged every time


def test_the_alternatives_descent_only_descends_and_reports_the_objective_of_its_ends() -> None:
    # actor_search.descent_function: every start (a column) descends monotonically inside the box,
    # and the value reported for an end is the hand-written objective of its actions.
    from common.math.actor_search import search_graph

    problem = ActorProblem("rlqv+", 5, DELTA, tuple(R_DIAG), (V_MAX, OMEGA_MAX), multistart=True, jit=False)
    graph = search_graph(problem)
    bounds = np.array([V_MAX, OMEGA_MAX])
    rng = np.random.default_rng(8)
    for w, v_w, state in indefinite_problems(18, 4):
        starts = rng.uniform(-1, 1, size=(8, graph.starts))
        ends, values = (np.array(x) for x in graph.descent(starts, state, np.r_[w, v_w]))
        for column in range(graph.starts):
            start = [(np.float64(a), np.float64(b)) for a, b in starts[:, column].reshape(-1, 2) * bounds]
            end = [(np.float64(a), np.float64(b)) for a, b in ends[:, column].reshape(-1, 2) * bounds]
            assert np.all(np.abs(ends[:, column]) <= 1.0)
            assert values[0, column] == pytest.approx(float(hand_objective("rlqv+", state, end, w, v_w)), rel=1e-9)
            assert values[0, column] <= float(hand_objective("rlqv+", state, start, w, v_w)) + 1e-12


def test_the_polish_reaches_the_solvers_minimum_from_the_same_start() -> None:
    # actor_search's polish (projected Newton, damped where the Hessian is indefinite) against
    # fatrop from the same start on random indefinite critics: both stationary, and where they end
    # in the same minimum (the same plan) the same objective; the polish never rises above its start.
    from common.math.actor_search import NEWTON_TOLERANCE, search_graph

    actor = make_actor("rlqv", 6)  # fatrop: the oracle
    graph = search_graph(ActorProblem("rlqv", 6, DELTA, tuple(R_DIAG), (V_MAX, OMEGA_MAX), multistart=True, jit=False))
    rng = np.random.default_rng(9)
    stationary = same = 0
    for w, v_w, state in indefinite_problems(7, 20):
        weights = np.r_[w, v_w]
        z0 = rng.uniform(-0.5, 0.5, size=10)
        f0 = float(graph.value(z0, state, weights))
        z, f, stationarity, _ = (np.array(x).ravel() for x in graph.polish(z0, f0, state, weights))
        plan = [(np.float64(a), np.float64(b)) for a, b in z.reshape(-1, 2) * [V_MAX, OMEGA_MAX]]
        assert float(f[0]) == pytest.approx(float(hand_objective("rlqv", state, plan, w, v_w)), rel=1e-9)
        assert float(f[0]) <= f0 + 1e-12 * (1 + abs(f0))
        stationary += float(stationarity[0]) <= NEWTON_TOLERANCE
        actor._params[:15], actor._params[15:] = w, v_w
        actor._x0[:] = np.array(graph.decision_vector(z0, state)).ravel()
        solved = actor._solve()
        assert solved[0]
        if np.allclose(actor._decisions_of(solved[2]).ravel() / np.tile([V_MAX, OMEGA_MAX], 5), z, atol=1e-4):
            same += 1
            assert float(f[0]) == pytest.approx(solved[3], rel=1e-6, abs=1e-9)
    assert stationary >= 19 and same >= 12, (stationary, same)


def test_vertex_search_finds_the_lower_vertex_that_the_polish_cannot_see() -> None:
    # Random indefinite critics make the objective concave along some action entries: the
    # polished minimum then sits on one bound of such an entry while the other may be lower. The
    # vertex search (multistart_flips) moves entries to either bound while that lowers the
    # objective and polishes the result. Oracle: brute force over the 2^6 vertices of the action
    # box (N = 4). Negative control: the same actor without the search stays above the lowest
    # vertex where the search reaches it.
    import itertools

    horizon = 4
    plain = searching_actor("rlq", horizon, multistart_flips=0)
    search = searching_actor("rlq", horizon, multistart_flips=3)
    vertices = [
        [(np.float64(p[2 * i]), np.float64(p[2 * i + 1])) for i in range(horizon - 1)]
        for p in itertools.product((-V_MAX, V_MAX), (-OMEGA_MAX, OMEGA_MAX), repeat=horizon - 1)
    ]
    found = []
    for w, v_w, state in indefinite_problems(0, 40):
        plain.reset()
        search.reset()
        before, after = plain.step(state, w, v_w), search.step(state, w, v_w)
        assert before.success and after.success
        plan = [(np.float64(a), np.float64(b)) for a, b in after.plan]
        assert after.objective == pytest.approx(float(hand_objective("rlq", state, plan, w, v_w)), rel=1e-6, abs=1e-9)
        lowest_vertex = min(float(hand_objective("rlq", state, p, w, v_w)) for p in vertices)
        tolerance = 1e-6 * (1 + abs(lowest_vertex))
        if after.objective <= lowest_vertex + tolerance < before.objective - 1e-3 * (1 + abs(lowest_vertex)):
            found.append((before.objective, after.objective, lowest_vertex))
    assert found, "no problem where the search reached a lower vertex than the actor without it"
    assert search.counters.vertex_wins >= 1 and plain.counters.vertex_wins == 0
    assert plain.counters.phase_counts["vertex_search"] == 0 < search.counters.phase_counts["vertex_search"]


def test_a_hurried_step_is_the_warm_polish_alone() -> None:
    # services/actor/host.py hurries a tick served late (docs/fleets.md): once the robot has a
    # plan, neither the search nor the vertex search runs, and the answer is the warm start (the
    # cheaper of the shifted and the earlier plan) polished. Oracle: the search graph's own polish
    # from that warm start. Negative control: the unhurried step runs both and, here, moves plans.
    from common.math.actor_search import search_graph

    hurried = searching_actor("rlq", 6)
    full = searching_actor("rlq", 6)
    graph = search_graph(hurried.problem)
    moved = 0
    for w, v_w, state in indefinite_problems(4, 10):
        for actor in (hurried, full):
            actor.reset()
        first = hurried.step(state, w, v_w, hurry=True)  # no plan yet: a full step
        full.step(state, w, v_w)
        after = exact_step(state, first.action, DELTA)
        searches = hurried.counters.phase_counts["search"]
        shifted = np.r_[scaled_plan(hurried, first.plan)[2:], scaled_plan(hurried, first.plan)[-2:]]
        weights = np.r_[w, v_w]
        z, _, _, _ = graph.polish(shifted, float(graph.value(shifted, after, weights)), after, weights)
        second = hurried.step(after, w, v_w, hurry=True)
        assert second.success and hurried.counters.phase_counts["search"] == searches
        np.testing.assert_allclose(scaled_plan(hurried, second.plan), np.array(z).ravel(), atol=1e-9)
        moved += not np.allclose(full.step(after, w, v_w).plan, second.plan, atol=1e-6)
    assert hurried.counters.hurried_solves == 10 and full.counters.hurried_solves == 0
    assert hurried.counters.phase_counts["vertex_search"] == 10  # the first, unhurried steps only
    assert moved > 0  # what a hurry skips does change plans here


def test_an_episode_does_not_depend_on_what_the_actor_solved_before() -> None:
    # The experiment's workers reuse one actor for many runs: after reset() the search (its
    # alternatives, their ages and the fresh-start table's row) acts as on a fresh actor, step for step.
    rng = np.random.default_rng(3)
    w, v_w = 3 * rng.normal(size=15), 3 * rng.normal(size=6)
    used = searching_actor("rlqv", 5)
    for _ in range(7):
        used.step(rng.uniform(-1, 1, size=3), w, v_w)
    used.reset()
    fresh = searching_actor("rlqv", 5)
    state_used = state_fresh = np.array([1.2, -0.8, 2.0])
    for _ in range(12):
        a, b = used.step(state_used, w, v_w), fresh.step(state_fresh, w, v_w)
        np.testing.assert_array_equal(a.plan, b.plan)
        state_used, state_fresh = exact_step(state_used, a.action, DELTA), exact_step(state_fresh, b.action, DELTA)
    assert used.memory.fresh == fresh.memory.fresh
    np.testing.assert_array_equal(used.memory.alternatives, fresh.memory.alternatives)


def test_each_robots_memory_keeps_its_own_alternatives() -> None:
    # One built actor serves many robots (services/actor/host.py): two robots stepped in turn
    # through swap_memory get exactly what two actors of their own give them.
    rng = np.random.default_rng(5)
    w, v_w = 3 * rng.normal(size=15), 3 * rng.normal(size=6)
    shared, own = searching_actor("rlqv", 5), [searching_actor("rlqv", 5), searching_actor("rlqv", 5)]
    memories = [ActorMemory(), ActorMemory()]
    states = [np.array([1.2, -0.8, 2.0]), np.array([-0.5, 1.0, 0.3])]
    for _ in range(8):
        for robot in range(2):
            held = shared.swap_memory(memories[robot])
            got = shared.step(states[robot], w, v_w)
            memories[robot] = shared.swap_memory(held)
            expected = own[robot].step(states[robot], w, v_w)
            np.testing.assert_array_equal(got.plan, expected.plan)
            states[robot] = exact_step(states[robot], got.action, DELTA)
    for robot in range(2):
        np.testing.assert_array_equal(memories[robot].alternatives, own[robot].memory.alternatives)


def test_a_polish_that_ends_short_goes_on_and_then_falls_back_to_the_solver() -> None:
    # Where the tick's answer is not stationary, its Newton iterations go on once more from where
    # they ended (no search), and where that too ends short the solver (fatrop) takes it from there.
    # The tick's stationarity made to look short once, then always; the control leaves it as is.
    def short(actor: StackedActor, times: int) -> None:
        tick, left = actor._evaluate_tick, [times]

        def looks_short() -> None:
            tick()
            if left[0] != 0:
                left[0] -= 1
                actor._tick_stationarity[0] = 1.0

        actor._evaluate_tick = looks_short  # type: ignore[method-assign]

    w, v_w, state = next(indefinite_problems(6, 1, spread=1.0))
    for times, solver in ((0, 0), (1, 0), (-1, 1)):  # never, once, always short
        actor = searching_actor("rlqv", 5)
        actor.step(state, w, v_w)  # the plan (a cold start: its rounds are not made short)
        short(actor, times)
        result = actor.step(exact_step(state, np.zeros(2), DELTA), w, v_w)
        assert result.success
        assert actor.counters.repolished == (times != 0)
        assert actor.counters.phase_counts["solver"] == solver


@pytest.mark.parametrize(
    "changes",
    [
        {"multistart_iterations": 0},
        {"multistart_margin": -0.1},
        {"multistart_flips": -1},
        {"multistart_starts": 0},
        {"newton_iterations": 0},
        {"newton_iterations": 51},
    ],
)
def test_bad_multistart_settings_raise(changes: dict) -> None:
    with pytest.raises(ValueError):
        ActorProblem("rlqv", 4, DELTA, tuple(R_DIAG), (V_MAX, OMEGA_MAX), **changes)


@pytest.mark.parametrize(("agent", "horizon"), [("rlq", 6), ("rlqv+", 6), ("rlqv+", 12)])
def test_actor_in_the_loop_is_not_worse_than_a_cold_slsqp_solve(agent: str, horizon: int) -> None:
    # The minimizer the actor takes in the closed loop (warm-started from its own plans, the
    # benchmark's non-convex "learned" weights) is no worse than the paper framework's way, a
    # cold SLSQP solve from standing still at the same state (tools/bench/actor.py): the search
    # finds the minima the warm start alone misses.
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
