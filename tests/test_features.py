"""Features and stage cost against the paper's formula written out by hand.

phi(z) = concat_{k=0}^{n-1} concat_{i-j=k} (z z^T)_{ij}: the main diagonal of z z^T first,
then the first sub-diagonal, and so on, each in increasing row i.
"""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from common.math.features import (
    feature_count,
    feature_index_pairs,
    phi_q,
    phi_q_rows,
    phi_v,
    phi_v_rows,
    quadratic_features,
    quadratic_weights_for_diag,
    stage_cost,
)

# z = (s, u) = (2, 3, 5, 7, 11): distinct primes, so every product is identifiable.
S = np.array([2.0, 3.0, 5.0])
U = np.array([7.0, 11.0])
PHI_Q_EXPECTED = [
    # i - j = 0: z0^2, z1^2, z2^2, z3^2, z4^2
    2 * 2, 3 * 3, 5 * 5, 7 * 7, 11 * 11,
    # i - j = 1: z1 z0, z2 z1, z3 z2, z4 z3
    3 * 2, 5 * 3, 7 * 5, 11 * 7,
    # i - j = 2: z2 z0, z3 z1, z4 z2
    5 * 2, 7 * 3, 11 * 5,
    # i - j = 3: z3 z0, z4 z1
    7 * 2, 11 * 3,
    # i - j = 4: z4 z0
    11 * 2,
]  # fmt: skip
PHI_V_EXPECTED = [2 * 2, 3 * 3, 5 * 5, 3 * 2, 5 * 3, 5 * 2]
PAIRS_5 = [
    (0, 0), (1, 1), (2, 2), (3, 3), (4, 4),
    (1, 0), (2, 1), (3, 2), (4, 3),
    (2, 0), (3, 1), (4, 2),
    (3, 0), (4, 1),
    (4, 0),
]  # fmt: skip


def test_phi_q_order_and_count() -> None:
    got = phi_q(S, U)
    assert got.shape == (15,)
    assert got.tolist() == PHI_Q_EXPECTED


def test_phi_v_order_and_count() -> None:
    got = phi_v(S)
    assert got.shape == (6,)
    assert got.tolist() == PHI_V_EXPECTED


def test_row_features_equal_the_per_sample_ones_bit_for_bit() -> None:
    rng = np.random.default_rng(3)
    states, actions = rng.normal(size=(40, 3)) * 7, rng.normal(size=(40, 2))
    q_rows, v_rows = phi_q_rows(states, actions), phi_v_rows(states)
    assert q_rows.shape == (40, 15) and v_rows.shape == (40, 6)
    for k in range(40):  # exactly equal: the critic's fits must not change by vectorizing
        assert q_rows[k].tolist() == phi_q(states[k], actions[k]).tolist()
        assert v_rows[k].tolist() == phi_v(states[k]).tolist()
    assert phi_q_rows(S[None], U[None])[0].tolist() == PHI_Q_EXPECTED


def test_phi_q_accepts_lists() -> None:
    assert phi_q(list(S), list(U)).tolist() == PHI_Q_EXPECTED


def test_generic_quadratic_features_small_dims() -> None:
    assert quadratic_features(np.array([3.0])).tolist() == [9.0]
    assert quadratic_features(np.array([2.0, 3.0])).tolist() == [4.0, 9.0, 6.0]
    assert quadratic_features(np.array([2.0, 3.0, 5.0, 7.0])).tolist() == [
        4,
        9,
        25,
        49,
        6,
        15,
        35,
        10,
        21,
        14,
    ]


def test_feature_count_and_pairs() -> None:
    assert [feature_count(n) for n in (1, 2, 3, 5)] == [1, 3, 6, 15]
    assert feature_index_pairs(5) == PAIRS_5
    assert feature_index_pairs(3) == [(0, 0), (1, 1), (2, 2), (1, 0), (2, 1), (2, 0)]


def test_casadi_symbolic_path_matches() -> None:
    s = ca.SX.sym("s", 3)
    u = ca.SX.sym("u", 2)
    f_q = ca.Function("fq", [s, u], [phi_q(s, u)])
    f_v = ca.Function("fv", [s], [phi_v(s)])
    assert f_q.size1_out(0) == 15 and f_v.size1_out(0) == 6
    np.testing.assert_array_equal(np.asarray(f_q(S, U)).ravel(), PHI_Q_EXPECTED)
    np.testing.assert_array_equal(np.asarray(f_v(S)).ravel(), PHI_V_EXPECTED)


def test_casadi_mx_path_matches() -> None:
    s = ca.MX.sym("s", 3)
    u = ca.MX.sym("u", 2)
    f_q = ca.Function("fq", [s, u], [phi_q(s, u)])
    np.testing.assert_array_equal(np.asarray(f_q(S, U)).ravel(), PHI_Q_EXPECTED)


R_DIAG = (1.0, 10.0, 1.0, 0.01, 0.01)


def test_stage_cost_matches_chi_r_chi() -> None:
    rng = np.random.default_rng(3)
    for _ in range(50):
        s = rng.normal(size=3) * 3
        u = rng.normal(size=2)
        diag = rng.uniform(0, 5, size=5)
        chi = np.concatenate([s, u])
        expected = chi @ np.diag(diag) @ chi
        assert float(stage_cost(s, u, diag)) == pytest.approx(expected, rel=1e-13)


def test_stage_cost_by_hand() -> None:
    # 1*4 + 10*9 + 1*25 + 0.01*49 + 0.01*121
    assert float(stage_cost(S, U, R_DIAG)) == pytest.approx(4 + 90 + 25 + 0.49 + 1.21, rel=1e-14)


def test_stage_cost_symbolic() -> None:
    s = ca.SX.sym("s", 3)
    u = ca.SX.sym("u", 2)
    f = ca.Function("r", [s, u], [stage_cost(s, u, R_DIAG)])
    assert float(f(S, U)) == pytest.approx(4 + 90 + 25 + 0.49 + 1.21, rel=1e-14)


@pytest.mark.parametrize("dim", [3, 5])
def test_quadratic_weights_for_diag(dim: int) -> None:
    rng = np.random.default_rng(dim)
    diag = rng.uniform(0, 4, size=dim)
    weights = quadratic_weights_for_diag(diag)
    assert weights.shape == (dim * (dim + 1) // 2,)
    for _ in range(20):
        z = rng.normal(size=dim)
        assert weights @ quadratic_features(z) == pytest.approx(z @ np.diag(diag) @ z, rel=1e-12)
    # the main-diagonal features only, in order
    np.testing.assert_array_equal(weights[:dim], diag)
    np.testing.assert_array_equal(weights[dim:], 0.0)


def test_stage_cost_weights_reproduce_stage_cost() -> None:
    w = quadratic_weights_for_diag(R_DIAG)
    rng = np.random.default_rng(11)
    for _ in range(10):
        s, u = rng.normal(size=3), rng.normal(size=2)
        chi = np.concatenate([s, u])
        assert w @ phi_q(s, u) == pytest.approx(chi @ np.diag(R_DIAG) @ chi, rel=1e-12)
