"""Parking metrics (common/math/parking.py) against hand-computed examples, and ``srl bench parking``."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from common.math.parking import last_window, parking, position_span, sign_changes
from tools.bench.parking import ParkingResult
from tools.cli import main


def test_sign_changes_by_hand() -> None:
    assert sign_changes([0.1, -0.1, 0.1, -0.1]) == 3
    assert sign_changes([0.1, 0.005, -0.005, 0.2]) == 0  # |v| < 0.01 does not count as a sign
    assert sign_changes([0.1, 0.0, -0.1]) == 1  # a stop between two directions is one change
    assert sign_changes([-0.22, -0.01, 0.01, 0.22, -0.009]) == 1
    assert sign_changes([]) == 0 and sign_changes([0.0, 0.0]) == 0


def test_position_span_is_the_largest_distance_between_two_positions() -> None:
    assert position_span([[0, 0, 0]]) == 0.0
    assert position_span([[0, 0, 1], [3, 4, 2], [1, 1, 0]]) == pytest.approx(5.0)
    square = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]
    assert position_span(square) == pytest.approx(math.sqrt(2))


def test_last_window_keeps_round_seconds_over_delta_rows() -> None:
    rows = np.arange(350)
    assert list(last_window(rows, 10.0, 0.1)) == list(range(250, 350))
    assert list(last_window(rows[:5], 10.0, 0.1)) == list(range(5))


def test_a_shuffle_near_the_target_is_not_at_rest() -> None:
    delta = 0.1
    # 35 s: drive in, then shuttle +/- 0.12 m/s every step around x = 0.02 for the last 15 s
    actions = [[0.2, 0.0]] * 200 + [[0.12 * (-1) ** k, 0.0] for k in range(150)]
    states = [[-1.0 + 0.02 * k, 0.0, 0.0] for k in range(201)]
    states += [[0.02 + (0.012 if k % 2 == 0 else 0.0), 0.0, 0.0] for k in range(150)]
    metrics = parking(states, actions, delta)
    assert metrics.sign_changes == 99  # 100 actions of alternating sign in the last 10 s
    assert metrics.span == pytest.approx(0.012)
    assert metrics.median_speed == pytest.approx(0.12)
    assert not metrics.at_rest and not metrics.at_target
    resting = parking(states[:201] + [[0.02, 0.0, 0.0]] * 150, actions[:200] + [[0.0, 0.0]] * 150, delta)
    assert resting.sign_changes == 0 and resting.span == 0.0 and resting.at_rest and resting.at_target
    assert resting.final_distance == pytest.approx(0.02)


@pytest.mark.integration
def test_bench_parking_runs_one_row_and_prints_the_typed_row(capsys: pytest.CaptureFixture[str]) -> None:
    code = main(
        [
            "bench", "parking", "--agents", "mpc", "--plants", "actuator", "--starts", "1,-1",
            "--parking-seconds", "12", "--no-jit", "--json",
        ]
    )  # fmt: skip
    assert code == 0
    out = capsys.readouterr().out.strip().splitlines()
    result = ParkingResult.model_validate(json.loads(out[-1]))
    assert result.total == 2 and len(result.rows) == 2  # the paper's method and the robot's, side by side
    paper, robot = result.rows
    for row in (paper, robot):
        assert (row.plant, row.agent, row.horizon, row.steps) == ("actuator", "mpc", 12, 120)
        assert row.start == pytest.approx((1.0, -1.0, math.atan2(-1.0, 1.0)))
        assert row.passed == (row.final_ok and row.span_ok and row.sign_changes_ok and row.arrival_ok)
        assert row.final_ok == (row.true_final_distance <= 0.05)
    assert (paper.method, robot.method) == ("paper", "robot")
    # the paper's actor boxes v and omega separately: a wheel is asked beyond its limit; the wheel
    # box of the robot's settings never does
    assert paper.saturated_commands > 0
    assert robot.saturated_commands == 0
    assert any(line.lstrip().startswith("paper  actuator mpc") for line in out)
    assert any(line.lstrip().startswith("robot  actuator mpc") for line in out)
    assert main(["bench", "parking", "--plants", "gazebo"]) == 2
