"""The arrival rule (common/math/arrival.py) against its definition, written out here by hand:
inside both inner tolerances -> arrived; arrived stays until outside either outer tolerance."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from common.math.arrival import (
    ArrivalRule,
    ArrivalTolerances,
    Docking,
    TurnFirst,
    approach_heading,
    arrival_update,
    dock_action,
    heading_error,
    line_of_travel_error,
)

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


# -- turn first and docking (the robot's settings: srl.toml [actor] turn_first_threshold, docking_*) --

RATE, DELTA = 2.75, 0.1
TURN_FIRST = TurnFirst(threshold=0.785, tolerance=0.1, rate=RATE, sampling_time=DELTA, min_distance=0.045)
DOCKING = Docking(radius=1.0, reversals=3, speed=0.22, rate=RATE, sampling_time=DELTA, half_track=0.08)


def unicycle(state: np.ndarray, action: np.ndarray, delta: float = DELTA) -> np.ndarray:
    """The ideal unicycle over one held interval (Euler in 10 substeps)."""
    x, y, alpha = state
    for _ in range(10):
        x += delta / 10 * action[0] * math.cos(alpha)
        y += delta / 10 * action[0] * math.sin(alpha)
        alpha += delta / 10 * action[1]
    return np.array([x, y, alpha])


def test_line_of_travel_ahead_or_back_and_the_approach_heading() -> None:
    assert line_of_travel_error(2.0, 2.0, math.atan2(2.0, 2.0)) == pytest.approx(0.0)  # backing straight in
    assert line_of_travel_error(2.0, 0.0, math.pi) == pytest.approx(0.0)  # facing it
    assert line_of_travel_error(2.0, 0.0, math.pi / 2) == pytest.approx(math.pi / 2)  # across
    assert line_of_travel_error(-1.0, 0.0, 0.3) == pytest.approx(0.3)
    # from x < 0 ahead (heading towards +x), from x > 0 backing (heading towards +x as well)
    assert approach_heading(-1.0, -1.0) == pytest.approx(math.pi / 4)
    assert approach_heading(1.0, 1.0) == pytest.approx(math.pi / 4)
    assert approach_heading(1.0, -1.0) == pytest.approx(-math.pi / 4)
    assert approach_heading(0.0, -1.0) == pytest.approx(math.pi / 2)


def test_turn_first_turns_in_place_to_the_approach_heading_then_hands_over_for_good() -> None:
    rule = ArrivalRule(TOL, turn_first=TURN_FIRST)
    solved = np.array([0.2, 0.0])
    state = np.array([1.18, 2.51, -1.11])  # line of travel 0.9 rad off the target
    commands = []
    for _ in range(30):
        command = rule.last_word(solved, state)
        if command[0] != 0.0:
            break
        commands.append(command)
        state = unicycle(state, command)
    assert 3 <= len(commands) < 30 and all(c[0] == 0.0 and c[1] > 0 for c in commands)  # turned left, in place
    assert abs(state[2] - approach_heading(1.18, 2.51)) <= 0.1  # backing in, through heading 0
    assert np.array_equal(command, solved)  # then the actor's command ...
    assert np.array_equal(rule.last_word(solved, np.array([1.18, 2.51, -1.11])), solved)  # ... for this goal
    assert rule.turn_first_steps == len(commands)
    rule.reset()  # a new goal decides again
    assert rule.last_word(solved, np.array([1.18, 2.51, -1.11]))[0] == 0.0


def test_turn_first_turns_through_the_actors_zero_not_round_the_other_way() -> None:
    """Facing away from 0 (-2.89) at (0.91, 1.85): the approach heading 1.11 (backing in) is 4.0
    rad up through 0, not 2.28 down to -5.17, which the actor's unwrapped heading cost would undo."""
    rule = ArrivalRule(TOL, turn_first=TURN_FIRST)
    state = np.array([0.91, 1.85, -2.89])
    for _ in range(40):
        command = rule.last_word(np.array([0.2, 0.0]), state)
        if command[0] != 0.0:
            break
        assert command[1] > 0
        state = unicycle(state, command)
    assert abs(state[2] - approach_heading(0.91, 1.85)) <= 0.1 and state[2] > 0


@pytest.mark.parametrize("start", [(2.0, 2.0, math.atan2(2.0, 2.0)), (-2.0, 0.0, 0.5), (0.02, 0.02, 2.0)])
def test_turn_first_leaves_a_start_on_its_line_or_at_the_target_to_the_actor(start: tuple[float, ...]) -> None:
    """The paper's starts (turned away from the target: backing straight in), a line of travel
    within the threshold, and a start inside the outer position tolerance: the solved command."""
    rule = ArrivalRule(TOL, turn_first=TURN_FIRST)
    solved = np.array([-0.2, 0.1])
    assert np.array_equal(rule.last_word(solved, np.array(start)), solved)
    assert rule.turn_first_steps == 0


def test_dock_action_legs() -> None:
    # inside the position tolerance: turn in place to the target's heading
    v, omega = dock_action(np.array([0.01, 0.0, 0.5]), DOCKING, TOL)
    assert v == 0.0 and omega < 0
    # sideways offset, heading 0: turn in place first (driving on would miss)
    v, omega = dock_action(np.array([0.0, 0.08, 0.0]), DOCKING, TOL)
    assert v == 0.0 and omega != 0.0
    # on the line: drive to it, ahead when facing it, back when facing away
    v, _ = dock_action(np.array([0.2, 0.0, math.pi]), DOCKING, TOL)
    assert v > 0
    v, omega = dock_action(np.array([0.5, 0.01, 0.0]), DOCKING, TOL)
    assert v < 0 and abs(v) + abs(omega) * DOCKING.half_track <= DOCKING.speed + 1e-12  # in the wheel box


@pytest.mark.parametrize("start", [(0.0, 0.08, 0.0), (0.06, -0.05, 0.05), (0.6, 0.3, -0.4), (-0.04, 0.03, 3.0)])
def test_docking_parks_a_sideways_offset_that_a_shuffle_cannot(start: tuple[float, ...]) -> None:
    """The manoeuvre alone, on the ideal unicycle, brings the robot inside both inner tolerances
    (the arrival rule's) within a few seconds from where the actor shuffles."""
    rule = ArrivalRule(TOL)
    state = np.array(start)
    for _ in range(60):
        if rule.update(state):
            break
        state = unicycle(state, dock_action(state, DOCKING, TOL))
    assert rule.arrived, state


def test_docking_takes_over_after_the_actors_reversals_within_its_radius_until_arrival() -> None:
    rule = ArrivalRule(TOL, docking=DOCKING)
    state = np.array([0.02, 0.07, 0.0])
    shuffle = [np.array([0.2, 0.1]), np.array([-0.2, -0.1])]
    sent = [rule.last_word(shuffle[k % 2], state) for k in range(3)]
    assert all(np.array_equal(s, shuffle[k % 2]) for k, s in enumerate(sent))  # two reversals: the actor's
    assert np.array_equal(rule.last_word(shuffle[1], state), shuffle[1])  # the third reversal is sent ...
    assert not np.array_equal(rule.last_word(shuffle[0], state), shuffle[0])  # ... then docking
    assert rule.docked and rule.docking_steps == 1
    assert rule.update(np.array([0.0, 0.0, 0.0]))  # arrived: the next approach starts with the actor
    assert not rule.docked
    far = ArrivalRule(TOL, docking=DOCKING)  # beyond the radius reversals do not count
    for k in range(6):
        far.last_word(shuffle[k % 2], np.array([1.5, 0.0, 0.0]))
    assert not far.docked


def test_bad_turn_first_and_docking_are_refused() -> None:
    with pytest.raises(ValueError):
        TurnFirst(threshold=2.0, tolerance=0.1, rate=RATE, sampling_time=DELTA)
    with pytest.raises(ValueError):
        TurnFirst(threshold=0.5, tolerance=0.1, rate=float("nan"), sampling_time=DELTA)
    with pytest.raises(ValueError):
        Docking(radius=-1.0, reversals=3, speed=0.22, rate=RATE, sampling_time=DELTA)
    with pytest.raises(ValueError):
        Docking(radius=1.0, reversals=0, speed=0.22, rate=RATE, sampling_time=DELTA)
