"""TD least-squares fit, replay bookkeeping, and the double critic.

Oracles: the normal equations solved directly, scipy's L-BFGS-B on the bounded problem,
hand-written pair lists, and the exact Q-function of a linear-quadratic problem.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import scipy.optimize
from scipy.optimize import minimize

import common.math.critic
from common.math.critic import (
    DoubleCritic,
    Replay,
    Sample,
    append_each,
    bounded_lstsq,
    consecutive_pairs,
    newest_values,
    td_fit,
)
from common.math.features import quadratic_features


def _random_problem(rng: np.random.Generator, pairs: int, dim: int = 15):
    a = rng.normal(size=(pairs, dim))
    f_next = rng.normal(size=(pairs, dim))
    costs = rng.uniform(0, 2, size=pairs)
    w_prev = rng.normal(size=dim)
    return a, f_next, costs, w_prev


def _targets(costs, f_next, w_prev, beta):
    return costs + beta * (f_next @ w_prev)


def _objective(w, a, b, w_prev, lam):
    e = a @ w - b
    return 0.5 * e @ e + 0.5 * lam * (w - w_prev) @ (w - w_prev)


@pytest.mark.parametrize("lam", [0.0, 0.01, 3.0])
def test_td_fit_matches_normal_equations(lam: float) -> None:
    rng = np.random.default_rng(1)
    beta = 0.9
    a, f_next, costs, w_prev = _random_problem(rng, pairs=40)
    b = _targets(costs, f_next, w_prev, beta)
    expected = w_prev + np.linalg.solve(a.T @ a + lam * np.eye(15), a.T @ (b - a @ w_prev))
    fit = td_fit(a, f_next, costs, w_prev, beta, ridge=lam)
    np.testing.assert_allclose(fit.weights, expected, rtol=1e-9, atol=1e-10)
    e = a @ expected - b
    assert fit.residual == pytest.approx(0.5 * e @ e, rel=1e-9)
    assert fit.pairs == 40


def test_td_fit_without_ridge_is_plain_least_squares() -> None:
    rng = np.random.default_rng(2)
    a, f_next, costs, w_prev = _random_problem(rng, pairs=30, dim=6)
    b = _targets(costs, f_next, w_prev, 0.5)
    # independent of w_prev except through the targets: (A^T A)^{-1} A^T b
    expected = np.linalg.solve(a.T @ a, a.T @ b)
    fit = td_fit(a, f_next, costs, w_prev, 0.5)
    np.testing.assert_allclose(fit.weights, expected, rtol=1e-9, atol=1e-10)


def test_td_fit_exactly_consistent_data_has_zero_residual() -> None:
    rng = np.random.default_rng(5)
    a, f_next, _, w_prev = _random_problem(rng, pairs=25, dim=6)
    w_true = rng.normal(size=6)
    beta = 0.8
    costs = a @ w_true - beta * f_next @ w_prev  # targets equal a @ w_true exactly
    fit = td_fit(a, f_next, costs, w_prev, beta)
    np.testing.assert_allclose(fit.weights, w_true, rtol=1e-9, atol=1e-10)
    assert fit.residual == pytest.approx(0.0, abs=1e-18)


def test_td_fit_underdetermined_takes_minimum_norm_change() -> None:
    rng = np.random.default_rng(9)
    a, f_next, costs, w_prev = _random_problem(rng, pairs=5, dim=15)
    beta = 0.95
    b = _targets(costs, f_next, w_prev, beta)
    expected = w_prev + a.T @ np.linalg.solve(a @ a.T, b - a @ w_prev)
    fit = td_fit(a, f_next, costs, w_prev, beta)
    np.testing.assert_allclose(fit.weights, expected, rtol=1e-9, atol=1e-10)
    assert fit.residual == pytest.approx(0.0, abs=1e-18)


def test_td_fit_no_pairs_keeps_weights() -> None:
    w_prev = np.arange(6.0)
    fit = td_fit(np.empty((0, 0)), np.empty((0, 0)), np.empty(0), w_prev, 0.9)
    np.testing.assert_array_equal(fit.weights, w_prev)
    assert fit.pairs == 0 and fit.residual == 0.0
    assert fit.weights is not w_prev


@pytest.mark.parametrize(
    ("lam", "bounds", "prev_scale"),
    [(0.0, (-0.25, 0.25), 0.3), (0.1, (-0.2, 0.8), 0.3), (0.0, (-0.3, 0.3), 2.0), (0.5, (0.0, 1.0), 2.0)],
)
def test_td_fit_bounded_matches_lbfgsb(lam: float, bounds: tuple[float, float], prev_scale: float) -> None:
    rng = np.random.default_rng(17)
    a, f_next, costs, w_prev = _random_problem(rng, pairs=40, dim=6)
    w_prev = prev_scale * w_prev  # prev_scale 2: w_prev partly outside the bounds
    beta = 0.9
    b = _targets(costs, f_next, w_prev, beta)
    fit = td_fit(a, f_next, costs, w_prev, beta, ridge=lam, bounds=bounds)
    low, high = bounds
    assert np.all(fit.weights >= low) and np.all(fit.weights <= high)

    def fun(w):
        return _objective(w, a, b, w_prev, lam), a.T @ (a @ w - b) + lam * (w - w_prev)

    ref = minimize(
        fun, np.zeros(6) + (low + high) / 2, jac=True, method="L-BFGS-B",
        bounds=[bounds] * 6, options={"ftol": 1e-15, "gtol": 1e-12, "maxiter": 10_000},
    )  # fmt: skip
    unbounded = w_prev + np.linalg.solve(a.T @ a + lam * np.eye(6), a.T @ (b - a @ w_prev))
    assert np.any((unbounded < low) | (unbounded > high)), "bounds should be active in this case"
    assert _objective(fit.weights, a, b, w_prev, lam) <= ref.fun + 1e-9
    np.testing.assert_allclose(fit.weights, ref.x, atol=1e-5)
    e = a @ fit.weights - b
    assert fit.residual == pytest.approx(0.5 * e @ e, rel=1e-9)


def test_td_fit_wide_bounds_equal_unbounded() -> None:
    rng = np.random.default_rng(4)
    a, f_next, costs, w_prev = _random_problem(rng, pairs=40, dim=6)
    free = td_fit(a, f_next, costs, w_prev, 0.9, ridge=0.01)
    boxed = td_fit(a, f_next, costs, w_prev, 0.9, ridge=0.01, bounds=(-1e6, 1e6))
    np.testing.assert_allclose(boxed.weights, free.weights, rtol=1e-8, atol=1e-10)


def _boxed_problem(seed: int, dim: int = 15):
    """A strictly convex bounded least squares (ridge rows) whose unbounded minimum leaves the box."""
    rng = np.random.default_rng(seed)
    a = np.vstack([rng.normal(size=(29, dim)), np.eye(dim)])
    b = np.concatenate([rng.normal(scale=3.0, size=29), np.zeros(dim)])
    return a, b, np.full(dim, -0.5), np.full(dim, 0.5)


@pytest.mark.parametrize("seed", range(6))
def test_bounded_lstsq_with_the_right_guess_is_one_lstsq_and_the_same_minimum(seed: int, monkeypatch) -> None:
    a, b, low, high = _boxed_problem(seed)
    reference = scipy.optimize.lsq_linear(a, b, bounds=(low, high), method="bvls")
    x, on_bound = bounded_lstsq(a, b, low, high)  # no guess: BVLS, as before
    np.testing.assert_array_equal(x, reference.x)
    assert np.any(on_bound != 0), "the bounds should be active in this problem"

    calls = []
    monkeypatch.setattr(common.math.critic, "lsq_linear", lambda *args, **kw: calls.append(args) or reference)
    warm, warm_bound = bounded_lstsq(a, b, low, high, on_bound)
    assert calls == []  # the guess was optimal: no BVLS
    np.testing.assert_allclose(warm, reference.x, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(warm_bound, on_bound)


@pytest.mark.parametrize("seed", range(6))
def test_bounded_lstsq_refuses_a_wrong_guess_and_still_finds_the_minimum(seed: int) -> None:
    a, b, low, high = _boxed_problem(seed)
    reference = scipy.optimize.lsq_linear(a, b, bounds=(low, high), method="bvls")
    for guess in (np.zeros(15), -np.asarray(reference.active_mask, float), np.ones(15)):
        x, on_bound = bounded_lstsq(a, b, low, high, guess)
        np.testing.assert_allclose(x, reference.x, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(on_bound, reference.active_mask)


def test_a_critic_fitted_with_its_last_active_set_fits_as_one_fitted_afresh() -> None:
    """The warm guess changes what a fit costs, never its weights: a critic that keeps its last
    fit's active set and one that forgets it before every fit publish the same weights."""
    rng = np.random.default_rng(3)
    kept = DoubleCritic(np.full(15, 2.0), np.full(6, 2.0), 0.9, ridge=1.0, bounds=(0.0, 100.0))
    forgot = DoubleCritic(np.full(15, 2.0), np.full(6, 2.0), 0.9, ridge=1.0, bounds=(0.0, 100.0))
    replay = Replay(30)
    warm = 0
    for step in range(80):
        state = rng.normal(size=3) * np.exp(-step / 40)
        replay.add(Sample(step, state, rng.uniform(-0.2, 0.2, 2), 0.1 * float(state @ state)))
        warm += kept.q_on_bound is not None
        kept.update(replay)
        forgot.q_on_bound = forgot.v_on_bound = None
        forgot.update(replay)
        np.testing.assert_allclose(kept.q_weights, forgot.q_weights, rtol=0, atol=1e-12)
        np.testing.assert_allclose(kept.v_weights, forgot.v_weights, rtol=0, atol=1e-12)
    assert warm >= 70 and kept.q_on_bound is not None and np.any(kept.q_on_bound != 0)


# -- pairs and replay -------------------------------------------------------------------
def test_consecutive_pairs_by_hand() -> None:
    assert consecutive_pairs([0, 1, 2, 4, 5, 7]) == [(0, 1), (1, 2), (3, 4)]
    assert consecutive_pairs([3, 5, 7]) == []
    assert consecutive_pairs([10]) == []
    assert consecutive_pairs([]) == []
    assert consecutive_pairs([8, 9, 10, 11]) == [(0, 1), (1, 2), (2, 3)]


def _sample(step: int) -> Sample:
    # state encodes the step so that design rows can be checked by hand
    return Sample(step, np.array([float(step), 1.0, 0.0]), np.array([0.0, 0.0]), cost=100.0 + step)


def test_replay_design_never_joins_across_a_gap() -> None:
    replay = Replay(10)
    for step in (0, 1, 2, 4, 5, 8):
        replay.add(_sample(step))
    now, nxt, costs = replay.design(lambda states, _: states[:, :1])
    # pairs (0,1), (1,2), (4,5): never (2,4) nor (5,8)
    np.testing.assert_array_equal(now.ravel(), [0, 1, 4])
    np.testing.assert_array_equal(nxt.ravel(), [1, 2, 5])
    np.testing.assert_array_equal(costs, [100, 101, 104])


def test_replay_design_empty_when_no_pairs() -> None:
    replay = Replay(5)
    replay.add(_sample(0))
    replay.add(_sample(2))
    now, nxt, costs = replay.design(lambda states, _: states)
    assert now.shape[0] == 0 and nxt.shape[0] == 0 and costs.size == 0


def test_replay_keeps_only_the_last_m() -> None:
    replay = Replay(4)
    for step in range(10):
        replay.add(_sample(step))
    assert len(replay) == 4
    assert [s.step for s in replay.samples] == [6, 7, 8, 9]
    now, _, costs = replay.design(lambda states, _: states[:, :1])
    assert now.shape == (3, 1)  # M - 1 pairs
    np.testing.assert_array_equal(costs, [106, 107, 108])


def test_replay_out_of_order_insertion() -> None:
    replay = Replay(10)
    for step in (0, 1, 3, 2, 5, 4):
        replay.add(_sample(step))
    assert [s.step for s in replay.samples] == [0, 1, 2, 3, 4, 5]
    now, _, _ = replay.design(lambda states, _: states[:, :1])
    np.testing.assert_array_equal(now.ravel(), [0, 1, 2, 3, 4])


def test_replay_out_of_order_insertion_when_full() -> None:
    replay = Replay(3)
    for step in (0, 1, 3):
        replay.add(_sample(step))
    replay.add(_sample(2))
    assert [s.step for s in replay.samples] == [1, 2, 3]
    replay.add(_sample(0))  # older than everything kept: the oldest is trimmed again
    assert [s.step for s in replay.samples] == [1, 2, 3]
    replay.add(_sample(4))
    assert [s.step for s in replay.samples] == [2, 3, 4]


@pytest.mark.parametrize("duplicate", [0, 1, 2])
def test_replay_duplicate_step_raises(duplicate: int) -> None:
    replay = Replay(5)
    for step in (0, 1, 2):
        replay.add(_sample(step))
    with pytest.raises(ValueError):
        replay.add(_sample(duplicate))
    assert [s.step for s in replay.samples] == [0, 1, 2]


def test_replay_rejects_capacity_below_two() -> None:
    with pytest.raises(ValueError):
        Replay(1)


def test_replay_clear() -> None:
    replay = Replay(3)
    replay.add(_sample(0))
    replay.clear()
    assert len(replay) == 0
    replay.add(_sample(0))  # the same step is fine after a clear (new episode)


def test_append_each_is_add_of_each_and_refuses_a_step_add_would_insert() -> None:
    rng = np.random.default_rng(8)
    replays, alone = [Replay(4) for _ in range(5)], [Replay(4) for _ in range(5)]
    for step in range(9):
        values = rng.normal(size=(5, 5))
        costs = rng.uniform(0, 1, 5).tolist()
        append_each(replays, [step] * 5, costs, values)
        for i, replay in enumerate(alone):
            replay.add(Sample(step, values[i, :3], values[i, 3:], costs[i]))
        for mine, theirs in zip(replays, alone, strict=True):
            assert mine.table().tolist() == theirs.table().tolist()
            assert np.array_equal(mine.rows, theirs.rows) and (mine.start, len(mine)) == (theirs.start, len(theirs))
    steps, values = newest_values(replays)
    assert steps.tolist() == [8] * 5 and values.tolist() == [r.table()[-1, 1:6].tolist() for r in alone]
    with pytest.raises(ValueError, match="not after"):
        append_each(replays[:1], [8], [0.0], np.zeros((1, 5)))
    assert replays[0].last == 8 and replays[0].table().tolist() == alone[0].table().tolist()  # nothing written
    other = Replay(4)
    other.add(Sample(0, np.zeros(2), np.zeros(1), 0.0))  # another shape: a list of samples, no rows
    with pytest.raises(ValueError, match="one by one"):
        append_each([other], [1], [0.0], np.zeros((1, 5)))


# -- LQ oracle ----------------------------------------------------------------------------
def test_td_fit_recovers_exact_lq_q_function() -> None:
    A = np.array([[0.95, 0.2], [-0.1, 0.85]])
    B = np.array([[0.1], [0.5]])
    K = np.array([[-0.2, -0.4]])
    Qc = np.diag([1.0, 0.5])
    R = np.array([[0.3]])
    beta = 0.9
    A_cl = A + B @ K
    assert np.max(np.abs(np.linalg.eigvals(np.sqrt(beta) * A_cl))) < 1
    # P = Qc + K'RK + beta A_cl' P A_cl;  scipy solves X = a X a^H + q
    P = scipy.linalg.solve_discrete_lyapunov(np.sqrt(beta) * A_cl.T, Qc + K.T @ R @ K)
    np.testing.assert_allclose(P, Qc + K.T @ R @ K + beta * A_cl.T @ P @ A_cl, atol=1e-12)
    AB = np.hstack([A, B])
    H = scipy.linalg.block_diag(Qc, R) + beta * AB.T @ P @ AB  # Q(x, u) = z' H z, z = (x, u)
    # features of z = (x0, x1, u): z0^2, z1^2, z2^2, z1 z0, z2 z1, z2 z0 (off-diagonals: 2 H_ij)
    w_exact = np.array([H[0, 0], H[1, 1], H[2, 2], 2 * H[1, 0], 2 * H[2, 1], 2 * H[2, 0]])

    rng = np.random.default_rng(123)
    n = 60
    x = rng.normal(size=(n, 2))
    u = x @ K.T + 0.5 * rng.normal(size=(n, 1))
    x_next = x @ A.T + u @ B.T
    u_next = x_next @ K.T
    costs = np.einsum("ij,jk,ik->i", x, Qc, x) + np.einsum("ij,jk,ik->i", u, R, u)
    now = np.array([quadratic_features(np.concatenate([x[j], u[j]])) for j in range(n)])
    nxt = np.array([quadratic_features(np.concatenate([x_next[j], u_next[j]])) for j in range(n)])

    for ridge in (0.0, 1e-3):
        w = np.zeros(6)
        for _ in range(2000):
            fit = td_fit(now, nxt, costs, w, beta, ridge=ridge)
            change = np.max(np.abs(fit.weights - w))
            w = fit.weights
            if change < 1e-13:
                break
        np.testing.assert_allclose(w, w_exact, rtol=1e-7, atol=1e-9)
        # at the fixed point the TD errors vanish (exactly representable Q)
        assert fit.residual < 1e-16

    # spot-check the fitted Q against the closed form at a fresh point
    z = np.array([0.7, -1.3, 0.4])
    assert w @ quadratic_features(z) == pytest.approx(z @ H @ z, rel=1e-7)


# -- double critic ------------------------------------------------------------------------
GOOD_Q, GOOD_V = np.zeros(15), np.zeros(6)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"discount": -0.1},
        {"discount": 1.5},
        {"discount": 0.9, "ridge": -1.0},
        {"discount": 0.9, "bounds": (1.0, 0.0)},
        {"discount": 0.9, "bounds": (1.0, 1.0)},
        {"discount": 0.9, "q_weights": np.r_[np.zeros(14), np.nan]},
        {"discount": 0.9, "v_weights": np.r_[np.zeros(5), np.inf]},
    ],
)
def test_double_critic_rejects_bad_arguments(kwargs: dict) -> None:
    args = {"q_weights": GOOD_Q, "v_weights": GOOD_V, **kwargs}
    with pytest.raises(ValueError):
        DoubleCritic(**args)


def test_double_critic_accepts_edge_discounts() -> None:
    DoubleCritic(GOOD_Q, GOOD_V, 0.0)
    DoubleCritic(GOOD_Q, GOOD_V, 1.0, ridge=0.0, bounds=(-1.0, 1.0))


def test_double_critic_values_and_update() -> None:
    rng = np.random.default_rng(8)
    q0, v0 = rng.normal(size=15), rng.normal(size=6)
    critic = DoubleCritic(q0, v0, discount=0.9, ridge=0.01)
    q0[0] = 1e9  # the critic keeps its own copy
    assert critic.q_weights[0] != 1e9

    s, u = np.array([0.5, -1.0, 2.0]), np.array([0.1, -0.2])
    z = np.concatenate([s, u])
    pairs5 = [(0, 0), (1, 1), (2, 2), (3, 3), (4, 4), (1, 0), (2, 1), (3, 2), (4, 3),
              (2, 0), (3, 1), (4, 2), (3, 0), (4, 1), (4, 0)]  # fmt: skip
    pairs3 = [(0, 0), (1, 1), (2, 2), (1, 0), (2, 1), (2, 0)]
    q_hand = sum(critic.q_weights[k] * z[i] * z[j] for k, (i, j) in enumerate(pairs5))
    v_hand = sum(critic.v_weights[k] * s[i] * s[j] for k, (i, j) in enumerate(pairs3))
    assert critic.q_value(s, u) == pytest.approx(q_hand, rel=1e-12)
    assert critic.value(s) == pytest.approx(v_hand, rel=1e-12)

    replay = Replay(30)
    states = rng.normal(size=(31, 3))
    actions = rng.normal(size=(31, 2))
    for k in range(30):
        replay.add(Sample(k, states[k], actions[k], float(rng.uniform())))
    w_before, v_before = critic.q_weights.copy(), critic.v_weights.copy()
    update = critic.update(replay)
    assert update.q.pairs == 29 and update.v.pairs == 29
    # the same fit by the normal equations, features built by hand
    samples = replay.samples
    fq = np.array([[np.r_[s.state, s.action][i] * np.r_[s.state, s.action][j] for i, j in pairs5]
                   for s in samples])  # fmt: skip
    fv = np.array([[s.state[i] * s.state[j] for i, j in pairs3] for s in samples])
    c = np.array([s.cost for s in samples[:-1]])
    for feats, prev, got in ((fq, w_before, critic.q_weights), (fv, v_before, critic.v_weights)):
        a, nxt = feats[:-1], feats[1:]
        b = c + 0.9 * nxt @ prev
        n = prev.size
        expected = prev + np.linalg.solve(a.T @ a + 0.01 * np.eye(n), a.T @ (b - a @ prev))
        np.testing.assert_allclose(got, expected, rtol=1e-8, atol=1e-10)
