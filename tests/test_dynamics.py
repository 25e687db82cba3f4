"""The unicycle model: exact plant vs a high-accuracy ODE solver, the predictors, headings.

Oracles: ``scipy.integrate.solve_ivp`` (DOP853, tight tolerances) on a right-hand side
written out here, hand-computed Euler steps, and hand-derived heading values.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from common.math.dynamics import (
    euler_step,
    exact_step,
    heading_away_from_target,
    rk4_step,
    unicycle_rhs,
    unwrap_heading,
)


def _rhs(_t: float, s: np.ndarray, v: float, omega: float) -> list[float]:
    # The paper's eq. (3w-robot), written independently of common.math.dynamics.
    return [v * math.cos(s[2]), v * math.sin(s[2]), omega]


def _reference(state, action, duration: float) -> np.ndarray:
    sol = solve_ivp(
        _rhs,
        (0.0, duration),
        np.asarray(state, float),
        method="DOP853",
        rtol=1e-12,
        atol=1e-12,
        args=(float(action[0]), float(action[1])),
    )
    assert sol.success
    return sol.y[:, -1]


def _cases() -> list[tuple[np.ndarray, np.ndarray, float]]:
    rng = np.random.default_rng(20240611)
    cases = []
    for _ in range(44):
        state = np.array([rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(-60, 60)])
        action = np.array([rng.uniform(-1.0, 1.0), rng.uniform(-4.0, 4.0)])
        duration = float(rng.choice([0.1, rng.uniform(0.01, 2.0)]))
        cases.append((state, action, duration))
    # straight lines and (numerically) almost straight lines, with large headings too
    for omega in (0.0, 1e-12, -1e-12, 1e-9):
        cases.append((np.array([0.5, -1.0, 0.7]), np.array([0.22, omega]), 0.1))
    cases.append((np.array([1.0, 2.0, 123.4]), np.array([-0.3, 0.0]), 1.5))
    cases.append((np.array([-2.0, 0.0, -1000.0]), np.array([0.2, 1e-12]), 3.0))
    return cases


CASES = _cases()


def test_case_set_covers_the_edge_cases() -> None:
    omegas = [c[1][1] for c in CASES]
    assert len(CASES) >= 50
    assert 0.0 in omegas and 1e-12 in omegas
    assert max(abs(c[0][2]) for c in CASES) > 100


@pytest.mark.parametrize(("state", "action", "duration"), CASES)
def test_exact_step_matches_solve_ivp(state: np.ndarray, action: np.ndarray, duration: float) -> None:
    expected = _reference(state, action, duration)
    got = exact_step(state, action, duration)
    assert got.shape == (3,)
    np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-10)
    # the heading is never wrapped: exactly alpha + omega t
    assert got[2] == state[2] + action[1] * duration


def test_exact_step_straight_line_by_hand() -> None:
    got = exact_step(np.array([1.0, 2.0, math.pi / 2]), np.array([0.5, 0.0]), 2.0)
    np.testing.assert_allclose(got, [1.0, 3.0, math.pi / 2], atol=1e-15)


def test_exact_step_full_circle_returns_home() -> None:
    # omega t = 2 pi: back to the start position, heading advanced by exactly 2 pi (no wrap)
    omega = 2.0
    got = exact_step(np.array([0.3, -0.4, 0.2]), np.array([0.22, omega]), math.pi)
    np.testing.assert_allclose(got[:2], [0.3, -0.4], atol=1e-14)
    assert got[2] == pytest.approx(0.2 + 2 * math.pi, abs=1e-15)


def test_exact_step_does_not_modify_inputs() -> None:
    state, action = np.array([1.0, 2.0, 3.0]), np.array([0.1, 0.2])
    exact_step(state, action, 0.1)
    np.testing.assert_array_equal(state, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(action, [0.1, 0.2])


def test_rhs_by_hand() -> None:
    got = unicycle_rhs(np.array([5.0, 6.0, math.pi / 3]), np.array([2.0, -0.5]))
    np.testing.assert_allclose(got, [1.0, math.sqrt(3.0), -0.5], rtol=1e-15, atol=1e-15)


@pytest.mark.parametrize(("state", "action", "duration"), CASES[:20])
def test_euler_step_is_literally_s_plus_delta_f(state: np.ndarray, action: np.ndarray, duration: float) -> None:
    x, y, a = state
    v, w = action
    expected = np.array([x + duration * (v * math.cos(a)), y + duration * (v * math.sin(a)), a + duration * w])
    np.testing.assert_allclose(euler_step(state, action, duration), expected, rtol=1e-15, atol=1e-15)


@pytest.mark.parametrize(("state", "action", "duration"), CASES[:20])
def test_rk4_is_more_accurate_than_euler(state: np.ndarray, action: np.ndarray, duration: float) -> None:
    h = 0.05
    truth = _reference(state, action, h)
    err_rk4 = np.max(np.abs(rk4_step(state, action, h) - truth))
    err_euler = np.max(np.abs(euler_step(state, action, h) - truth))
    # local errors: Euler ~ |v| omega h^2 / 2, RK4 ~ |v| omega^4 h^5 / 120
    v, w = abs(action[0]), abs(action[1])
    assert err_rk4 <= v * w**4 * h**5 / 50 + 1e-11
    assert err_rk4 <= err_euler + 1e-12
    if v * w > 0.05:
        assert err_rk4 < 1e-3 * err_euler


def test_rk4_local_error_is_fifth_order() -> None:
    state, action = np.array([0.4, -0.2, 0.9]), np.array([1.0, 3.0])
    errors = []
    for h in (0.2, 0.1, 0.05):
        errors.append(np.max(np.abs(rk4_step(state, action, h) - _reference(state, action, h))))
    # halving h divides the local error by ~2^5 = 32
    for coarse, fine in itertools.pairwise(errors):
        assert 24 < coarse / fine < 40


def test_rk4_and_euler_exact_for_straight_line() -> None:
    state, action = np.array([0.4, -0.2, 0.9]), np.array([0.3, 0.0])
    truth = _reference(state, action, 0.5)
    np.testing.assert_allclose(rk4_step(state, action, 0.5), truth, atol=1e-12)
    np.testing.assert_allclose(euler_step(state, action, 0.5), truth, atol=1e-12)


@pytest.mark.parametrize(
    ("x", "y", "expected"),
    [
        (2.0, 2.0, math.pi / 4),
        (1.0, 0.0, 0.0),
        (-1.0, 0.0, math.pi),
        (0.0, -3.0, -math.pi / 2),
        (0.0, 3.0, math.pi / 2),
        (-1.0, -1.0, -3 * math.pi / 4),
        (0.0, 0.0, math.pi),
    ],
)
def test_heading_away_from_target(x: float, y: float, expected: float) -> None:
    heading = heading_away_from_target(x, y)
    assert isinstance(heading, float)
    assert heading == pytest.approx(expected, abs=1e-15)
    if (x, y) != (0.0, 0.0):
        # pointing away from the origin: the unit heading vector is the unit position vector
        r = math.hypot(x, y)
        assert math.cos(heading) == pytest.approx(x / r, abs=1e-15)
        assert math.sin(heading) == pytest.approx(y / r, abs=1e-15)


def test_unwrap_heading_by_hand() -> None:
    # measured in (-pi, pi], previous far out: the representative nearest previous
    assert unwrap_heading(10.0, 10.1 - 4 * math.pi) == pytest.approx(10.1, abs=1e-12)
    assert unwrap_heading(-7.0, -7.2 + 2 * math.pi) == pytest.approx(-7.2, abs=1e-12)
    assert unwrap_heading(0.0, 0.3) == pytest.approx(0.3, abs=1e-15)
    assert unwrap_heading(3.1, -3.1) == pytest.approx(2 * math.pi - 3.1, abs=1e-12)
    assert unwrap_heading(-3.1, 3.1) == pytest.approx(3.1 - 2 * math.pi, abs=1e-12)


def test_unwrap_heading_random() -> None:
    rng = np.random.default_rng(7)
    for _ in range(200):
        previous = rng.uniform(-100, 100)
        change = rng.uniform(-3.1, 3.1)
        turns = int(rng.integers(-20, 21))
        measured = previous + change + 2 * math.pi * turns
        assert unwrap_heading(previous, measured) == pytest.approx(previous + change, abs=1e-9)


def test_unwrap_heading_follows_a_spinning_robot() -> None:
    # a robot spinning at constant rate: wrapped measurements unwrap to the true heading
    true = np.linspace(-0.5, 40.0, 400)  # steps of ~0.1 rad, many turns
    measured = np.angle(np.exp(1j * true))
    heading = measured[0]
    for k in range(1, true.size):
        heading = unwrap_heading(heading, measured[k])
        assert heading == pytest.approx(true[k], abs=1e-9)
