"""The physics plant's wheels as the XL430-W250 runs them (common/math/physics.py): its velocity PI
at the control table's gains, the stall torque as the PWM limit, the joint's breakaway friction.

A probe: each test drives a :class:`PhysicsBot` through a step (wheel speeds sampled every 5 ms)
and prints its response (``pytest -s``), then holds it against the datasheet: a running wheel
reaches its command (the integral term), the robot reaches the Burger's 0.22 m/s, the step is no
faster than the stall torque allows and settles within the actuator model's time (4 x
``[actuator] lag``), and a command below breakaway leaves the wheel at rest for as long as the PI
needs to break it away -- and no longer: only zero holds a robot at rest.

Sources: ROBOTIS e-Manual, XL430-W250 (https://emanual.robotis.com/docs/en/dxl/x/xl430-w250/):
control table (Velocity I Gain(76) 1000, Velocity P Gain(78) 100, PWM Limit(36) 885, velocity
unit 0.229 rev/min), "Velocity PI Gain(76, 78)" (K_VP = P / 128, K_VI = I / 65536), stall torque
1.4 N m at 11.1 V; TurtleBot3 Burger specification 0.22 m/s, 2.84 rad/s (ROBOTIS e-Manual).
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import numpy as np
import pytest

from common.config.settings import Settings
from common.math import physics
from common.math.physics import PhysicsBot, breakaway_speed, effective_wheel_inertia, velocity_gains

physics.load_mujoco()  # the extra srl[physics]: ./srl and CI install it, so it is never skipped
SAMPLE = 0.005  # [s] the probe's sampling period
TICK = 2.0 * math.pi / 4096  # [rad] one encoder tick of the XL430


class StepResponse(NamedTuple):
    command: float  # [rad/s] the wheel's command (after the firmware's conversion and clamp)
    final: float  # [rad/s] mean over the last 0.5 s
    rise: float  # [s] 10 % -> 90 % of the command
    overshoot: float  # peak beyond the command, share of the command
    settle: float  # [s] last time outside +/- 2 % of the command
    peak_torque: float  # [N m] the largest torque the motor applied

    @property
    def error(self) -> float:
        """The steady-state error, share of the command."""
        return (self.final - self.command) / self.command


@pytest.fixture(scope="module")
def settings() -> Settings:
    return Settings.load()


def bot(settings: Settings, **physics_changes: object) -> PhysicsBot:
    constants = dataclasses.replace(settings.physics_params(), **physics_changes)  # type: ignore[arg-type]
    return PhysicsBot(settings.turtlebot_params(), constants, np.zeros(3))


def step_response(robot: PhysicsBot, v: float, omega: float, duration: float = 1.5) -> StepResponse:
    """Command ``(v, omega)`` from rest; the response of the faster wheel (the right one on a tie)."""
    robot.command(v, omega)
    wheel = int(np.argmax(np.abs(robot.wheel_command) + np.array([0.0, 1e-12])))
    command = float(robot.wheel_command[wheel])
    speeds, torque = [], 0.0
    for _ in range(round(duration / SAMPLE)):
        robot.advance(SAMPLE)
        speeds.append(float(robot.wheels[wheel]))
        torque = max(torque, float(np.max(np.abs(robot.data.qfrc_actuator[robot.wheel_dof]))))
    w = np.array(speeds) / command  # the response as a share of the command
    t = SAMPLE * np.arange(1, len(w) + 1)
    rise = crossing(t, w, 0.9) - crossing(t, w, 0.1)
    outside = np.flatnonzero(np.abs(w - 1.0) > 0.02)
    settle = float(t[outside[-1]]) if outside.size else 0.0
    final = command * float(np.mean(w[-round(0.5 / SAMPLE) :]))
    response = StepResponse(command, final, rise, float(np.max(w) - 1.0), settle, torque)
    print(
        f"\nstep v={v:g} m/s omega={omega:g} rad/s: wheel {command:+.3f} rad/s -> {final:+.4f} "
        f"(error {100 * response.error:+.3f} %), rise {1000 * rise:.0f} ms, overshoot "
        f"{100 * response.overshoot:.1f} %, settles (2 %) in {1000 * settle:.0f} ms, peak torque {torque:.3f} N m"
    )
    return response


def crossing(t: np.ndarray, w: np.ndarray, level: float) -> float:
    """When ``w`` (0 at t = 0) first reaches ``level``, interpolated between samples [s]."""
    i = int(np.argmax(w >= level))
    t0, w0 = (float(t[i - 1]), float(w[i - 1])) if i > 0 else (0.0, 0.0)
    return t0 + (float(t[i]) - t0) * (level - w0) / (float(w[i]) - w0)


def fastest_rise(settings: Settings, command: float) -> float:
    """10 % -> 90 % of ``command`` at the stall torque with nothing resisting: the datasheet's bound."""
    return effective_wheel_inertia(settings.turtlebot_params()) * 0.8 * abs(command) / settings.physics.torque_max


def test_a_running_wheel_reaches_its_command(settings: Settings) -> None:
    response = step_response(bot(settings), 0.2, 0.0)
    assert response.command == pytest.approx(0.2 / 0.033, rel=1e-6)
    assert abs(response.error) < 0.02  # the integral term holds the load: no shortfall
    assert fastest_rise(settings, response.command) <= response.rise  # no faster than the stall torque allows
    assert response.settle <= 4.0 * settings.actuator.lag  # a first-order lag's 2 % time
    assert response.overshoot < 0.25
    assert response.peak_torque <= settings.physics.torque_max + 1e-9


def test_the_robot_reaches_the_burgers_top_speed(settings: Settings) -> None:
    robot = bot(settings)
    response = step_response(robot, 0.22, 0.0, duration=2.0)
    assert abs(response.error) < 0.02
    before = robot.true_pose.copy()
    robot.advance(1.0)
    true_speed = float(np.hypot(*(robot.true_pose[:2] - before[:2])))
    print(f"true speed {true_speed:.4f} m/s, the encoders' {robot.velocity[0]:.4f} m/s")
    assert true_speed == pytest.approx(0.22, rel=0.02)  # the specification, on the floor (the tyres slip a little)
    assert robot.velocity[0] == pytest.approx(0.22, rel=0.02)


def test_turning_at_the_burgers_top_rate_saturates_each_wheel_and_reaches_it(settings: Settings) -> None:
    robot = bot(settings)
    response = step_response(robot, 0.0, 2.84)
    p = settings.turtlebot_params()
    assert response.command == pytest.approx(p.wheel_speed_max)  # 2.84 * 0.08 / 0.033 = 6.88 rad/s: clamped
    assert abs(response.error) < 0.02
    assert response.settle <= 4.0 * settings.actuator.lag
    assert np.allclose(robot.wheels, [-p.wheel_speed_max, p.wheel_speed_max], rtol=0.02)
    before = robot.true_pose[2]
    robot.advance(1.0)
    rate = float(robot.true_pose[2] - before)
    clamped = 2.0 * p.wheel_radius * p.wheel_speed_max / p.wheel_separation  # 2.75 rad/s
    print(f"turn rate {rate:.3f} rad/s true, {robot.velocity[1]:.3f} the encoders', {clamped:.3f} the clamped command")
    assert robot.velocity[1] == pytest.approx(clamped, rel=0.02)
    assert rate == pytest.approx(clamped, rel=0.05)  # the tyres scrub turning in place


def test_the_torque_limit_bounds_a_stiffly_tuned_wheel_without_windup(settings: Settings) -> None:
    # a Velocity P Gain of 3000 asks ~2 N m for a 6 rad/s step: the PWM limit (stall torque) caps it
    robot = bot(settings, velocity_p_gain=3000)
    kp, _ = velocity_gains(robot.physics)
    assert kp * 0.2 / 0.033 > settings.physics.torque_max
    response = step_response(robot, 0.2, 0.0)
    assert response.peak_torque == pytest.approx(settings.physics.torque_max, rel=1e-6)
    assert fastest_rise(settings, response.command) <= response.rise
    assert abs(response.error) < 0.02 and response.overshoot < 0.25  # the anti-windup: no overshoot from the limit


def test_a_command_below_breakaway_leaves_the_wheel_at_rest_for_its_hold_and_no_longer(settings: Settings) -> None:
    hold = settings.plant.sampling_time  # one actor period: what one command is held for
    threshold = breakaway_speed(settings.physics_params(), hold)
    p = settings.turtlebot_params()
    print(f"\nbreakaway: a wheel command below {threshold:.3f} rad/s stays at rest for {hold:g} s")
    assert threshold > 0.0

    def turn(omega: float, duration: float) -> tuple[float, PhysicsBot]:
        robot = bot(settings)
        robot.command(0.0, omega)
        start = robot.encoders.copy()
        robot.advance(duration)
        return float(np.max(np.abs(robot.encoders - start))), robot

    # turning in place at omega puts omega * b/2 / r on each wheel (after the firmware's 0.01 rad/s)
    below = math.floor(0.8 * threshold * p.wheel_radius / (p.wheel_separation / 2.0) * 100) / 100
    above = math.ceil(2.0 * threshold * p.wheel_radius / (p.wheel_separation / 2.0) * 100) / 100
    still, _ = turn(below, hold)
    moved, _ = turn(above, hold)
    print(f"omega {below:g} rad/s: {still / TICK:.0f} ticks in {hold:g} s; omega {above:g}: {moved / TICK:.0f} ticks")
    assert still <= TICK  # at most one encoder tick: at rest as turtlebot3_node sees it
    assert moved >= 3 * TICK
    # held, the PI's integral breaks any command away: a robot is at rest only when told zero
    _, crept = turn(below, 3.0)
    print(f"omega {below:g} rad/s held 3 s: turned {crept.true_pose[2]:.4f} rad of {3 * below:.4f}")
    assert crept.true_pose[2] >= 0.5 * 3.0 * below


def test_zero_holds_a_robot_at_rest_after_it_ran(settings: Settings) -> None:
    robot = bot(settings)
    robot.step(np.array([0.2, 0.5]), 2.0)
    robot.command(0.0, 0.0)
    robot.advance(0.5)
    assert np.all(np.abs(robot.wheels) < 0.05)  # 1.7 mm/s at the rim
    resting = robot.true_pose.copy()
    robot.advance(5.0)
    assert robot.true_pose == pytest.approx(resting, abs=1e-3)  # the integral unwinds, friction holds


def test_the_ball_caster_rolls_under_the_robot(settings: Settings) -> None:
    robot = bot(settings)
    robot.step(np.array([0.2, 0.0]), 2.0)
    caster = robot.model.joint("caster_ball")
    spin = float(np.linalg.norm(robot.data.qvel[caster.dofadr[0] : caster.dofadr[0] + 3]))
    print(f"\ncaster ball: {spin:.1f} rad/s at 0.2 m/s (rolling: {0.2 / physics.CASTER_RADIUS:.1f})")
    assert spin == pytest.approx(0.2 / physics.CASTER_RADIUS, rel=0.05)  # it rolls, it does not slide
