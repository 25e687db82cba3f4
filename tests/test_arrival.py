"""The arrival rule (common/math/arrival.py) against its definition, written out here by hand:
inside both inner tolerances -> arrived; arrived stays until outside either outer tolerance."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from common.math.arrival import ArrivalRule, ArrivalTolerances, arrival_update, heading_error

TOL = ArrivalTolerances(position=0.03, heading=0.1, hysteresis=1.5)


def test_arrives_inside_both_inner_tolerances_only() -> None:
    assert arrival_update(False, np.array([0.02, 0.02, 0.05]), TOL)  # 0.028 m, 0.05 rad
    assert not arrival_update(False, np.array([0.03, 0.01, 0.0]), TOL)  # 0.0316 m
    assert not arrival_update(False, np.array([0.0, 0.0, 0.11]), TOL)  # heading off
    assert not arrival_update(False, np.array([0.0, 0.0, math.pi]), TOL)  # facing away


def test_heading_is_wrapped_the_actor_keeps_it_unwrapped() -> None:
    assert arrival_update(False, np.array([0.0, 0.0, 2 * math.pi + 0.05]), TOL)
    assert arrival_update(False, np.array([0.0, 0.0, -4 * math.pi - 0.05]), TOL)
    assert heading_error(2 * math.pi - 0.1) == pytest.approx(-0.1)


def test_hysteresis_stays_until_the_outer_tolerance() -> None:
    rule = ArrivalRule(TOL)
    path = [0.05, 0.029, 0.035, 0.044, 0.046, 0.035, 0.029]  # distance along x, heading 0
    flags = [rule.update(np.array([d, 0.0, 0.0])) for d in path]
    #        outside, arrive, stay (< 0.045), stay, leave (> 0.045), not yet back (> 0.03), arrive
    assert flags == [False, True, True, True, False, False, True]
    assert rule.arrivals == 2
    rule.reset()
    assert not rule.arrived


def test_no_chatter_on_a_noisy_boundary() -> None:
    """A pose jittering +-5 mm around the inner tolerance toggles at most once: once arrived,
    the noise is far inside the outer tolerance."""
    rng = np.random.default_rng(0)
    rule = ArrivalRule(TOL)
    flags = [rule.update(np.array([0.03 + rng.uniform(-0.005, 0.005), 0.0, 0.0])) for _ in range(1000)]
    assert sum(a != b for a, b in itertools.pairwise(flags)) == 1
    assert flags[-1] and rule.arrivals == 1


@given(
    st.booleans(),
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(allow_nan=True, allow_infinity=True),
)
def test_any_state_decides_and_non_finite_is_never_arrived(arrived: bool, x: float, y: float, a: float) -> None:
    result = arrival_update(arrived, np.array([x, y, a]), TOL)
    assert isinstance(result, bool)
    if not all(math.isfinite(c) for c in (x, y, a)):
        assert not result


@pytest.mark.parametrize(
    "position, heading, hysteresis",
    [(0.0, 0.1, 1.5), (0.03, 0.0, 1.5), (0.03, 4.0, 1.5), (0.03, 0.1, 0.9), (float("nan"), 0.1, 1.5)],
)
def test_bad_tolerances_are_refused(position: float, heading: float, hysteresis: float) -> None:
    with pytest.raises(ValueError):
        ArrivalTolerances(position, heading, hysteresis)
