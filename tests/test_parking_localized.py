"""Parking from every start (docs/turtlebot-parking.md): the arrival bound and time, the wheels'
deadband at the actor's output, the simulated localization fused as the robot bridge fuses it,
the start sets, and one short ``srl bench parking`` run on the localized physics plant."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from common.math.arrival import ArrivalRule, ArrivalTolerances, WheelDeadband, deadband_action
from common.math.localization import LocalizedPlant, SimLocalization
from common.math.turtlebot import firmware_velocity
from tools.bench.parking import (
    ODOMETRY_ONLY,
    ParkingResult,
    arrival_bound,
    arrival_time,
    deadband_commands,
    parse_starts,
)
from tools.cli import main

TOLERANCES = ArrivalTolerances(position=0.03, heading=0.1, hysteresis=1.5)  # outer: 0.045 m, 0.15 rad
DEADBAND = WheelDeadband(breakaway=0.132, wheel_radius=0.033, wheel_separation=0.160)
FAR = np.array([1.0, 0.5, 0.3])  # outside the outer tolerances


# -- item 3's criteria -----------------------------------------------------------------------


def test_arrival_bound_turns_to_the_target_drives_and_turns_to_its_heading() -> None:
    # facing the target: no turn, 2 m at 0.22 m/s
    assert arrival_bound((-2.0, 0.0, 0.0)) == pytest.approx(1.5 * (2.0 / 0.22) + 3.0)
    # facing away (the paper's starts): half a turn to face it, half a turn back to heading 0
    assert arrival_bound((2.0, 0.0, 0.0)) == pytest.approx(1.5 * (2.0 / 0.22 + 2.0 * math.pi / 2.84) + 3.0)
    # a corner of the grid facing away: turn pi, drive 2.83 m heading -3 pi / 4, turn 3 pi / 4 to 0
    corner = 1.5 * (math.hypot(2, 2) / 0.22 + (math.pi + 3 * math.pi / 4) / 2.84) + 3.0
    assert arrival_bound((2.0, 2.0, math.pi / 4)) == pytest.approx(corner)
    # at the target: only the heading
    assert arrival_bound((0.0, 0.0, -math.pi / 2)) == pytest.approx(1.5 * (math.pi / 2) / 2.84 + 3.0)
    # headings count wrapped: alpha and alpha + 2 pi are one start
    assert arrival_bound((1.0, -1.0, 0.5)) == pytest.approx(arrival_bound((1.0, -1.0, 0.5 + 2 * math.pi)))


def test_arrival_time_is_when_the_robot_came_within_the_radius_to_stay() -> None:
    d = [1.0, 0.5, 0.04, 0.06, 0.03, 0.02, 0.01]  # in, out again at 0.3 s, in for good from 0.4 s
    states = [[x, 0.0, 0.0] for x in d]
    assert arrival_time(states, 0.1) == pytest.approx(0.4)
    assert arrival_time([[0.0, 0.03, 1.0]] * 3, 0.1) == 0.0  # within from the start
    assert arrival_time([[0.0, 0.0, 0.0], [0.0, 0.06, 0.0]], 0.1) is None  # out at the end: never


def test_deadband_commands_counts_commands_that_move_no_wheel() -> None:
    actions = [
        [0.0, 0.0],  # zero: a stop, not a deadband command
        [0.002, 0.0],  # both wheels at 0.06 rad/s
        [0.0, 0.02],  # turning in place, wheels at 0.048 rad/s
        [0.1, 0.0],  # 3 rad/s: moves
        [0.002, 1.0],  # one wheel at 2.5 rad/s: moves
    ]
    assert deadband_commands(actions, 0.132, 0.033, 0.160) == 2
    assert deadband_commands(actions, 0.0, 0.033, 0.160) == 0


# -- the deadband rule at the actor's output --------------------------------------------------


def test_a_command_below_breakaway_is_zero_inside_the_outer_tolerances() -> None:
    creep = np.array([0.002, 0.01])  # both wheels below 0.132 rad/s
    assert max(abs(w) for w in DEADBAND.wheels(creep)) < DEADBAND.breakaway
    near = np.array([0.04, 0.0, 0.12])  # outside the inner tolerances, inside the outer ones
    np.testing.assert_array_equal(deadband_action(creep, near, DEADBAND, TOLERANCES), [0.0, 0.0])


def test_elsewhere_it_is_raised_to_breakaway_in_its_own_direction() -> None:
    creep = np.array([-0.002, 0.01])
    sent = deadband_action(creep, FAR, DEADBAND, TOLERANCES)
    assert max(abs(w) for w in DEADBAND.wheels(sent)) == pytest.approx(DEADBAND.breakaway)
    assert sent[0] / sent[1] == pytest.approx(creep[0] / creep[1])  # the same curvature and sense
    assert np.sign(sent[0]) == -1 and np.sign(sent[1]) == 1
    # heading outside the outer tolerance: raised too, however near
    sent = deadband_action(creep, np.array([0.0, 0.0, 0.2]), DEADBAND, TOLERANCES)
    assert max(abs(w) for w in DEADBAND.wheels(sent)) == pytest.approx(DEADBAND.breakaway)


def test_moving_commands_zero_and_breakaway_zero_pass_unchanged() -> None:
    near = np.array([0.01, 0.0, 0.0])
    for action in ([0.1, 0.0], [0.0, 0.5], [0.0, 0.0]):
        assert deadband_action(np.array(action), near, DEADBAND, TOLERANCES) is not None
        np.testing.assert_array_equal(deadband_action(np.array(action), near, DEADBAND, TOLERANCES), action)
    off = WheelDeadband(0.0, 0.033, 0.160)
    creep = np.array([0.002, 0.0])
    np.testing.assert_array_equal(deadband_action(creep, FAR, off, TOLERANCES), creep)
    with pytest.raises(ValueError, match="breakaway"):
        WheelDeadband(-1.0, 0.033, 0.160)
    with pytest.raises(ValueError, match="breakaway"):
        WheelDeadband(float("nan"), 0.033, 0.160)


def test_a_command_the_robot_truncates_to_zero_is_a_deadband_command() -> None:
    """turtlebot3_node sends int32(v * 100): (-0.009, -0.006) reaches the wheels as zero although
    its wheels would run at 0.26 rad/s, above breakaway (a robot held 0.07 m off for 20 s)."""
    hunt = np.array([-0.009, -0.006])
    robot = WheelDeadband(0.132, 0.033, 0.160, resolution=0.01)
    assert min(abs(w) for w in DEADBAND.wheels(hunt)) > DEADBAND.breakaway  # taken as sent: moves
    np.testing.assert_array_equal(deadband_action(hunt, FAR, DEADBAND, TOLERANCES), hunt)
    assert robot.peak(hunt) == 0.0
    sent = deadband_action(hunt, FAR, robot, TOLERANCES)
    applied = [firmware_velocity(float(c), 10.0) for c in sent]
    assert max(abs(w) for w in robot.wheels(np.array(applied))) >= robot.breakaway  # as the robot applies it
    assert np.sign(sent[0]) == -1 and np.sign(sent[1]) == -1 and abs(sent[0]) < 0.02  # its direction, slow
    np.testing.assert_array_equal(deadband_action(hunt, np.array([0.04, 0.0, 0.0]), robot, TOLERANCES), [0.0, 0.0])
    turn = np.array([0.0, 0.012])  # survives the truncation, but 0.01 rad/s moves no wheel: raised
    sent = deadband_action(turn, FAR, robot, TOLERANCES)
    assert sent[0] == 0.0 and robot.peak(sent) >= robot.breakaway
    assert deadband_commands([hunt, [0.1, 0.0]], 0.132, 0.033, 0.160, resolution=0.01) == 1
    assert deadband_commands([hunt, [0.1, 0.0]], 0.132, 0.033, 0.160) == 0
    with pytest.raises(ValueError, match="resolution"):
        WheelDeadband(0.132, 0.033, 0.160, resolution=-0.01)


def test_the_arrival_rule_applies_the_deadband_only_when_given_one() -> None:
    creep = np.array([0.002, 0.0])
    assert ArrivalRule(TOLERANCES).last_word(creep, FAR) is creep
    raised = ArrivalRule(TOLERANCES, DEADBAND).last_word(creep, FAR)
    assert raised[0] == pytest.approx(DEADBAND.breakaway * DEADBAND.wheel_radius)


def test_a_robot_the_deadband_holds_between_the_tolerances_has_arrived_and_solves_no_more() -> None:
    """Between the inner and the outer tolerances a command that moves no wheel is sent as zero
    (as parked as it can be told): the rule then says "arrived", so the actor holds zero without a
    solve until the robot leaves the outer tolerances, instead of solving every step a command it
    cannot follow (3 of 300 robots of a fleet stood so, 3.6 cm off, solving for 80 s). The negative
    controls: a command that moves a wheel, and one the deadband raises (outside the outer
    tolerances), leave the rule not arrived."""
    creep, near = np.array([0.002, 0.01]), np.array([0.035, 0.01, -0.02])  # 0.036 m: between
    rule = ArrivalRule(TOLERANCES, DEADBAND)
    assert not rule.update(near)  # not inside the inner tolerances: not arrived by position
    np.testing.assert_array_equal(rule.last_word(np.array([0.1, 0.0]), near), [0.1, 0.0])
    assert not rule.arrived  # a command that moves: still on its way
    rule.last_word(creep, FAR)
    assert not rule.arrived  # raised to breakaway out there: still on its way
    np.testing.assert_array_equal(rule.last_word(creep, near), [0.0, 0.0])
    assert rule.arrived and rule.arrivals == 1
    assert rule.update(near)  # held: the next step is "arrived", no solve
    assert not rule.update(np.array([0.05, 0.0, 0.0]))  # beyond the outer tolerance: on its way again


# -- the simulated localization ---------------------------------------------------------------


class SlippingPlant:
    """A fake robot on a line: it moves ``v * duration``, its odometry reads 25 % more."""

    def __init__(self) -> None:
        self.truth = np.zeros(3)
        self.odometry = np.zeros(3)

    def reset(self, state: np.ndarray) -> np.ndarray:
        self.truth = np.asarray(state, dtype=float).copy()
        self.odometry = self.truth.copy()
        return self.odometry.copy()

    def apply(self, action: np.ndarray, duration: float) -> np.ndarray:
        self.truth = self.truth + np.array([action[0] * duration, 0.0, action[1] * duration])
        self.odometry = self.odometry + np.array([1.25 * action[0] * duration, 0.0, action[1] * duration])
        return self.odometry.copy()

    @property
    def true_state(self) -> np.ndarray:
        return self.truth.copy()

    @property
    def saturated_commands(self) -> int:
        return 0


def test_amcl_fixes_after_a_quarter_metre_and_blends_the_correction_in() -> None:
    plant = LocalizedPlant(SlippingPlant(), SimLocalization("amcl", blend_time=1.0))
    np.testing.assert_allclose(plant.reset(np.array([-1.0, 0.0, 0.0])), [-1.0, 0.0, 0.0])  # the first fix
    assert plant.fixes == 1
    reported = [plant.apply(np.array([0.2, 0.0]), 0.1) for _ in range(12)]  # 0.02 m true per step
    assert plant.fixes == 1  # 0.24 m of true motion: no fix yet, the state is the odometry, 25 % long
    assert reported[11][0] == pytest.approx(-1.0 + 1.25 * 0.24)
    before = plant.apply(np.array([0.2, 0.0]), 0.1)
    assert plant.fixes == 2  # 0.26 m: a fix; its correction (-0.065 m) is blended in over 1 s
    steps = [plant.apply(np.array([0.0, 0.0]), 0.1) for _ in range(10)]
    assert abs(steps[0][0] - before[0]) < 0.01
    np.testing.assert_allclose(steps[-1], plant.true_state, atol=1e-9)
    assert plant.fixes == 2  # standing still: no fix


def test_mocap_streams_at_its_rate_with_seeded_noise() -> None:
    source = SimLocalization("mocap", noise=(0.01, 0.01), rate=10.0, blend_time=0.0, seed=3)
    runs = []
    for _ in range(2):
        plant = LocalizedPlant(SlippingPlant(), source)
        plant.reset(np.zeros(3))
        runs.append([plant.apply(np.array([0.1, 0.0]), 0.1) for _ in range(20)])
        assert plant.fixes == 21
        assert abs(runs[-1][-1][0] - plant.true_state[0]) < 0.05  # on the truth, up to the noise
    np.testing.assert_array_equal(runs[0], runs[1])  # seeded: the same noise each episode
    with pytest.raises(ValueError, match="amcl or mocap"):
        SimLocalization("gps")
    with pytest.raises(ValueError, match="finite"):
        SimLocalization("mocap", rate=0.0)


# -- the starts -------------------------------------------------------------------------------


def test_start_sets_grid_and_seeded_random() -> None:
    grid = parse_starts("grid")
    assert len(grid) == 25 and grid[0][:2] == (-2.0, -2.0) and grid[-1][:2] == (2.0, 2.0)
    assert grid[0][2] == pytest.approx(math.atan2(-2.0, -2.0))  # turned away from the target
    random = parse_starts("random:25:7")
    assert random == parse_starts("random:25:7") and random != parse_starts("random:25:8")
    assert len(random) == 25 and all(math.hypot(x, y) <= 3.0 and -math.pi <= a < math.pi for x, y, a in random)
    assert len(parse_starts("grid+random:3:1")) == 28
    assert parse_starts("1,2;3,4,0.5") == [(1.0, 2.0), (3.0, 4.0, 0.5)]
    for bad in ("random:x:1", "random:0:1", "1", "1,nan"):
        with pytest.raises(ValueError):
            parse_starts(bad)


# -- srl bench parking on the localized physics plant -----------------------------------------


@pytest.mark.integration  # the bench's JSON line carries the machine's info (tools/bench/meta.py)
def test_bench_parking_localized_physics_and_the_slipping_robot_odometry_only(
    capsys: pytest.CaptureFixture[str],
) -> None:
    code = main(
        [
            "bench", "parking", "--agents", "rlqv", "--methods", "robot", "--plants", "physics",
            "--localization", "amcl", "--starts", "-1,1", "--parking-seconds", "25", "--no-jit", "--json",
        ]
    )  # fmt: skip
    assert code == 0
    out = capsys.readouterr().out.strip().splitlines()
    (row,) = ParkingResult.model_validate(json.loads(out[-1])).rows
    assert (row.plant, row.localization, row.steps) == ("physics", "amcl", 250)
    assert row.arrival_bound == pytest.approx(arrival_bound(row.start))
    assert row.final_ok and row.span_ok and row.sign_changes_ok and row.arrival_ok and row.passed
    assert row.deadband_commands == 0
    assert not any("odometry only" in line for line in out[:-1])

    code = main(
        [
            "bench", "parking", "--agents", "mpc", "--methods", "robot", "--plants", "slipping",
            "--starts", "1,0", "--parking-seconds", "8", "--no-jit",
        ]
    )  # fmt: skip
    assert code == 0
    out = capsys.readouterr().out
    assert "slipping mpc    12 odom" in out and "pose: odometry only on slipping" in out
    assert ODOMETRY_ONLY == "odometry only"
    assert main(["bench", "parking", "--localization", "gps"]) == 2
