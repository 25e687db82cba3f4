"""The TurtleBot3 actuator and odometry model (common/math/turtlebot.py) against independent oracles:
the exact unicycle, the first-order step response, hand-computed wheel speeds and slip."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from common.math.dynamics import exact_step
from common.math.turtlebot import RobotPlant, TurtleBot, TurtleBotParams, body_velocity, firmware_velocity, wheel_speeds

R, B = 0.033, 0.160


def params(**changes: object) -> TurtleBotParams:
    return dataclasses.replace(TurtleBotParams.ideal(), **changes)  # type: ignore[arg-type]


def test_everything_off_is_the_exact_unicycle() -> None:
    rng = np.random.default_rng(7)
    robot = TurtleBot(TurtleBotParams.ideal(), np.array([1.0, -0.5, 0.3]))
    oracle = np.array([1.0, -0.5, 0.3])
    for _ in range(200):
        action = rng.uniform([-0.3, -3.0], [0.3, 3.0])
        duration = float(rng.uniform(0.01, 0.2))
        reported = robot.step(action, duration)
        oracle = exact_step(oracle, action, duration)
        assert np.allclose(robot.true_pose, oracle, atol=1e-9, rtol=0)
        assert np.allclose(reported, oracle, atol=1e-9, rtol=0)
    assert robot.saturated_commands == 0


def test_wheel_kinematics_by_hand() -> None:
    # (v -/+ omega b/2) / r: v = 0.1, omega = 1 -> (0.1 -/+ 0.08) / 0.033
    assert np.allclose(wheel_speeds(0.1, 1.0, R, B), [0.02 / R, 0.18 / R])
    assert np.allclose(body_velocity(np.array([0.02 / R, 0.18 / R]), R, B), [0.1, 1.0])


def test_the_lag_step_response_is_one_minus_exp() -> None:
    tau, v = 0.1, 0.15
    robot = TurtleBot(params(lag=tau, substep=0.001), np.zeros(3))
    robot.command(v, 0.0)
    t = 0.0
    for _ in range(30):
        robot.advance(0.01)
        t += 0.01
        expected_wheel = v / R * (1.0 - math.exp(-t / tau))
        assert robot.wheels == pytest.approx([expected_wheel, expected_wheel], rel=1e-9)
        # distance: the integral of v (1 - exp(-t/tau))
        assert robot.true_pose[0] == pytest.approx(v * (t - tau * (1.0 - math.exp(-t / tau))), rel=1e-9)
    assert robot.true_pose[1:] == pytest.approx([0.0, 0.0], abs=1e-12)


def test_a_gain_below_one_falls_short_at_steady_state() -> None:
    robot = TurtleBot(params(lag=0.1, gain=0.8), np.zeros(3))
    robot.step(np.array([0.2, 0.0]), 2.0)  # 20 time constants
    assert robot.velocity[0] == pytest.approx(0.8 * 0.2, rel=1e-6)


def test_a_wheel_at_rest_does_not_start_below_the_deadband() -> None:
    robot = TurtleBot(params(deadband=1.0, lag=0.05), np.zeros(3))
    below, above = 0.9 * R, 1.1 * R  # wheel speeds 0.9 and 1.1 rad/s going straight
    robot.step(np.array([below, 0.0]), 1.0)
    assert np.array_equal(robot.wheels, [0.0, 0.0]) and np.array_equal(robot.true_pose, [0.0, 0.0, 0.0])
    robot.step(np.array([above, 0.0]), 1.0)
    assert robot.wheels == pytest.approx([1.1, 1.1], rel=1e-6)
    assert robot.true_pose[0] > 0.02
    # a turning wheel commanded below the deadband slows below it and is held: it stops
    robot.step(np.array([below, 0.0]), 1.0)
    assert np.all(np.abs(robot.wheels) < 1e-6)


def test_per_wheel_saturation_clamps_each_wheel_at_its_limit() -> None:
    limit = 0.22 / R
    robot = TurtleBot(params(wheel_speed_max=limit), np.zeros(3))
    robot.step(np.array([0.22, 2.84]), 0.1)  # right wheel (0.22 + 2.84 * 0.08) / 0.033 = 13.55 rad/s
    left = (0.22 - 2.84 * 0.08) / R
    assert robot.wheel_command == pytest.approx([left, limit])
    assert robot.saturated_commands == 1
    v, omega = body_velocity(np.array([left, limit]), R, B)
    assert robot.true_pose == pytest.approx(exact_step(np.zeros(3), np.array([v, omega]), 0.1), abs=1e-12)
    robot.step(np.array([0.1, 0.5]), 0.1)  # both wheels within the limit: not counted
    assert robot.saturated_commands == 1 and robot.commands == 2
    assert np.all(np.abs(robot.wheel_command) <= limit)


def test_the_firmware_path_quantizes_and_limits_and_never_passes_nan() -> None:
    robot = TurtleBot(params(quantize=True, v_max=0.22, omega_max=2.84), np.zeros(3))
    assert robot.command(0.1239, -0.0099) == (firmware_velocity(0.1239, 0.22), 0.0)
    assert robot.applied[0] == pytest.approx(0.12, abs=1e-7)
    assert robot.command(5.0, -9.0) == (0.22, -2.84)
    assert robot.command(float("nan"), float("inf")) == (0.0, 0.0)
    unquantized = TurtleBot(params(v_max=0.22, omega_max=2.84), np.zeros(3))
    assert unquantized.command(float("nan"), -9.0) == (0.0, -2.84)


def test_odometry_is_the_truth_without_slip_whatever_the_wheels_do() -> None:
    p = params(lag=0.1, deadband=1.0, quantize=True, v_max=0.22, omega_max=2.84, wheel_speed_max=6.67)
    robot = TurtleBot(p, np.array([-1.0, 2.0, 0.5]))
    rng = np.random.default_rng(3)
    for _ in range(300):
        robot.step(rng.uniform([-0.22, -2.84], [0.22, 2.84]), 0.1)
    assert robot.odometry == pytest.approx(robot.true_pose, abs=1e-9)


def test_slip_makes_the_odometry_overestimate_a_straight_line_by_the_slip() -> None:
    slip = 0.1
    robot = TurtleBot(params(slip=slip, slip_std=0.0), np.zeros(3))
    for _ in range(50):
        robot.step(np.array([0.2, 0.0]), 0.1)  # 1 m of wheel travel
    assert robot.odometry == pytest.approx([1.0, 0.0, 0.0], abs=1e-9)
    assert robot.true_pose == pytest.approx([(1 - slip) * 1.0, 0.0, 0.0], abs=1e-9)


def test_the_imu_heading_follows_the_true_heading_under_uneven_slip() -> None:
    def drive(imu: bool) -> TurtleBot:
        robot = TurtleBot(params(slip=0.05, slip_std=0.05, imu_heading=imu, seed=11), np.zeros(3))
        for _ in range(100):
            robot.step(np.array([0.2, 0.5]), 0.1)
        return robot

    encoders, imu = drive(False), drive(True)
    assert np.array_equal(encoders.true_pose, imu.true_pose)  # the same seeded slip
    assert abs(encoders.odometry[2] - encoders.true_pose[2]) > 0.05  # uneven slip: heading drift
    assert imu.odometry[2] == pytest.approx(imu.true_pose[2], abs=1e-9)
    assert np.hypot(*(imu.odometry[:2] - imu.true_pose[:2])) > 0.01  # the position still drifts


def test_the_heading_stays_continuous_through_many_turns() -> None:
    robot = TurtleBot(params(lag=0.1, quantize=True, v_max=0.22, omega_max=2.84), np.zeros(3))
    headings = [0.0]
    for _ in range(200):
        robot.step(np.array([0.05, 2.84]), 0.1)
        headings.append(float(robot.true_pose[2]))
    steps = np.diff(headings)
    assert np.all(steps >= -1e-12) and np.all(steps <= 2.84 * 0.1 + 1e-9)
    assert headings[-1] > 6 * math.pi  # three turns and more, never wrapped


def test_the_slip_is_seeded() -> None:
    def final(seed: int) -> np.ndarray:
        robot = TurtleBot(params(slip=0.02, slip_std=0.01, seed=seed), np.zeros(3))
        for _ in range(20):
            robot.step(np.array([0.2, 0.3]), 0.1)
        return robot.true_pose

    assert np.array_equal(final(1), final(1))
    assert not np.array_equal(final(1), final(2))


def test_a_reset_robot_is_a_new_robot() -> None:
    """The in-process plant's episodes (``RobotPlant.reset``) each see the slip a new robot would."""
    plant = RobotPlant(TurtleBot(params(slip=0.02, slip_std=0.01, seed=5), np.zeros(3)))

    def episode() -> tuple[np.ndarray, np.ndarray]:
        reported = plant.reset(np.array([1.0, -0.5, 0.3]))
        for _ in range(20):
            reported = plant.apply(np.array([0.2, 0.3]), 0.1)
        return reported, plant.true_state

    first, second = episode(), episode()
    assert np.array_equal(first[0], second[0]) and np.array_equal(first[1], second[1])
    assert not np.allclose(first[0], first[1], atol=1e-6)  # the slip is there: odometry is not the truth


def test_plant_sim_lockstep_reports_the_odometry_and_the_truth_of_the_model() -> None:
    from common.config.settings import Settings
    from common.contracts.messages import ResetRequest, StepRequest
    from services.plant_sim.service import SimulatedPlant

    settings = Settings.load(plant={"model": "actuator"}, actuator={"slip": 0.1, "imu_heading": False})
    plant = SimulatedPlant(settings)
    oracle = TurtleBot(settings.turtlebot_params(), np.array([1.0, -1.0, 0.2]))
    reply = plant.reset(ResetRequest(robot="tb3_0", episode=3, state=(1.0, -1.0, 0.2)))
    assert reply.state == reply.true_state == (1.0, -1.0, 0.2)
    rng = np.random.default_rng(5)
    for k in range(30):
        action = rng.uniform([-0.22, -2.84], [0.22, 2.84])
        reply = plant.step(StepRequest(robot="tb3_0", episode=3, step=k, action=tuple(action), duration=0.1))
        oracle.step(action, 0.1)
    assert reply.state == pytest.approx(tuple(oracle.odometry), abs=1e-12)
    assert reply.true_state == pytest.approx(tuple(oracle.true_pose), abs=1e-12)
    assert reply.saturated_commands == oracle.saturated_commands > 0
    assert np.hypot(reply.state[0] - reply.true_state[0], reply.state[1] - reply.true_state[1]) > 1e-3
