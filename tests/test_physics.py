"""The MuJoCo TurtleBot3 (common/math/physics.py, plant.model = "physics"): the model is the URDF's,
its wheels behave as a real Burger's (the XL430's PI: lag, no shortfall, breakaway, saturation; the
step response against the datasheet is tests/test_wheels.py), its odometry is
dead reckoning with the IMU's heading, and it is the plant of srl run, plant_sim and the emulator.
Bounds are physical, measured once and kept generous (MuJoCo's contact solver decides the slip)."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys

import numpy as np
import pytest

from common.config.settings import Settings
from common.math import physics
from common.math.physics import PhysicsBot, burger_mjcf, velocity_gains
from common.math.plant_models import simulated_robot
from common.math.turtlebot import RobotPlant, TurtleBot

ROOT = __import__("pathlib").Path(__file__).resolve().parents[1]
mujoco = physics.load_mujoco()  # the extra srl[physics]: ./srl and CI install it, so it is never skipped


@pytest.fixture(scope="module")
def settings() -> Settings:
    return Settings.load()


def bot(settings: Settings, pose: tuple[float, float, float] = (0.0, 0.0, 0.0), **changes: object) -> PhysicsBot:
    params = dataclasses.replace(settings.turtlebot_params(), **changes)  # type: ignore[arg-type]
    return PhysicsBot(params, settings.physics_params(), np.array(pose))


def test_the_model_has_the_urdf_masses_and_wheel_geometry(settings: Settings) -> None:
    model = mujoco.MjModel.from_xml_string(burger_mjcf(settings.turtlebot_params(), settings.physics_params()))
    # turtlebot3_burger.urdf: base 0.8257 + wheels 2 x 0.0285 + caster 0.005 + LDS 0.114 kg
    assert float(np.sum(model.body_mass)) == pytest.approx(0.82573504 + 2 * 0.028498940 + 0.005 + 0.114, rel=1e-9)
    left, right = (model.body(f"wheel_{side}") for side in ("left", "right"))
    assert left.pos == pytest.approx([0.0, 0.08, 0.033]) and right.pos == pytest.approx([0.0, -0.08, 0.033])
    assert model.actuator_ctrlrange[0] == pytest.approx([-6.67, 6.67])  # the per-wheel limit


def test_at_rest_it_stays_where_it_was_put(settings: Settings) -> None:
    start = (0.5, -0.3, 0.4)
    robot = bot(settings, start)
    assert robot.true_pose == pytest.approx(start, abs=1e-9) and robot.odometry == pytest.approx(start, abs=1e-9)
    robot.command(0.0, 0.0)
    robot.advance(5.0)
    assert robot.true_pose == pytest.approx(start, abs=1e-4)
    assert robot.odometry == pytest.approx(start, abs=1e-4)


def test_the_wheels_lag_and_reach_their_command(settings: Settings) -> None:
    robot = bot(settings)
    robot.command(0.15, 0.0)
    speeds = []
    for _ in range(100):  # 1 s in 10 ms steps
        robot.advance(0.01)
        speeds.append(float(robot.wheels[0]))
    final = float(np.mean(speeds[-20:]))
    t63 = 0.01 * (1 + next(i for i, w in enumerate(speeds) if w >= (1 - math.exp(-1)) * final))
    assert 0.005 <= t63 <= settings.actuator.lag  # the PI against the wheel's and the robot's inertia: not instant
    # the PI's integral holds the tyres' rolling resistance and the joint's friction: no shortfall
    assert final == pytest.approx(0.15 / 0.033, rel=0.01)
    # the e-Manual's conversion: K_VP = 100 / 128 PWM units per 0.229 rev/min, 885 units = the stall torque
    kp, ki = velocity_gains(settings.physics_params())
    assert kp == pytest.approx(100 / 128 * 1.4 / 885 / (0.229 * 2 * math.pi / 60), rel=1e-9)
    assert ki == pytest.approx(1000 / 65536 * 1.4 / 885 / (0.229 * 2 * math.pi / 60) / 0.001, rel=1e-9)


def test_a_slow_command_from_rest_moves_it_at_its_speed_as_a_fast_one_does(settings: Settings) -> None:
    slow, fast = bot(settings), bot(settings)
    slow.step(np.array([0.02, 0.0]), 2.0)
    fast.step(np.array([0.10, 0.0]), 2.0)
    assert slow.true_pose[0] == pytest.approx(0.04, rel=0.1)  # the integral breaks the wheels away
    assert fast.true_pose[0] == pytest.approx(0.20, rel=0.05)


def test_each_wheel_saturates_at_its_limit_and_is_counted(settings: Settings) -> None:
    robot = bot(settings)
    robot.step(np.array([0.22, 2.84]), 0.1)  # (0.22 + 2.84 * 0.08) / 0.033 = 13.6 rad/s
    assert robot.saturated_commands == 1
    assert np.max(np.abs(robot.data.ctrl)) == pytest.approx(6.67)
    robot.step(np.array([0.1, 0.0]), 0.1)
    assert robot.saturated_commands == 1


def test_nan_never_reaches_a_wheel(settings: Settings) -> None:
    robot = bot(settings)
    assert robot.command(float("nan"), float("inf")) == (0.0, 0.0)
    assert np.all(np.isfinite(robot.data.ctrl)) and np.all(robot.data.ctrl == 0.0)


def test_odometry_dead_reckons_the_encoders_and_the_imu_gives_the_heading(settings: Settings) -> None:
    robot = bot(settings)
    for _ in range(30):
        robot.step(np.array([0.2, 0.0]), 0.1)
    driven = robot.true_pose[0]
    assert driven > 0.3
    # the encoders turn with the wheels: slip makes the odometry run ahead of the truth, a little
    assert 0.0 <= robot.odometry[0] - driven <= 0.05 * driven
    for _ in range(100):  # turning in place for 10 s: many turns, the heading stays continuous
        robot.step(np.array([0.0, 2.0]), 0.1)
    assert robot.true_pose[2] > 2 * math.pi
    assert robot.odometry[2] == pytest.approx(robot.true_pose[2], abs=1e-9)  # the IMU's yaw
    encoders_only = bot(settings, imu_heading=False)
    for _ in range(50):
        encoders_only.step(np.array([0.0, 2.0]), 0.1)
    assert abs(encoders_only.odometry[2] - encoders_only.true_pose[2]) > 1e-3  # the tyres scrub


def test_the_plant_reports_odometry_and_keeps_the_truth_beside_it(settings: Settings) -> None:
    plant = RobotPlant(PhysicsBot(settings.turtlebot_params(), settings.physics_params(), np.zeros(3)))
    reported = plant.reset(np.array([1.0, 1.0, 0.0]))
    assert reported == pytest.approx([1.0, 1.0, 0.0], abs=1e-9)
    for _ in range(20):
        reported = plant.apply(np.array([0.2, 0.5]), 0.1)
    assert np.all(np.isfinite(reported)) and np.all(np.isfinite(plant.true_state))
    assert not np.allclose(reported, plant.true_state, atol=1e-6)  # what the robot says is not the truth
    assert np.linalg.norm(reported[:2] - plant.true_state[:2]) < 0.05


def test_the_factory_makes_the_robot_of_each_model(settings: Settings) -> None:
    args = (settings.turtlebot_params(), settings.physics_params(), np.zeros(3))
    assert simulated_robot("ideal", *args) is None
    assert isinstance(simulated_robot("actuator", *args), TurtleBot)
    assert isinstance(simulated_robot("physics", *args), PhysicsBot)
    with pytest.raises(ValueError, match="unknown plant model 'gazebo'"):
        simulated_robot("gazebo", *args)


def test_without_mujoco_it_says_how_to_install_it(monkeypatch: pytest.MonkeyPatch) -> None:
    def missing(name: str) -> None:
        raise ImportError(f"No module named {name!r}")

    monkeypatch.setattr(physics.importlib, "import_module", missing)
    with pytest.raises(RuntimeError, match=r"pip install 'srl\[physics\]'"):
        physics.load_mujoco()


def test_plant_sim_runs_the_physics_robot_in_lockstep() -> None:
    from common.contracts.messages import ResetRequest, StepRequest
    from services.plant_sim.service import SimulatedPlant

    plant = SimulatedPlant(Settings.load(plant={"model": "physics"}))
    first = plant.reset(ResetRequest(robot="robot1", episode=1, state=(1.0, 0.0, math.pi)))
    assert first.state == pytest.approx((1.0, 0.0, math.pi), abs=1e-9)
    reply = first
    for k in range(10):
        reply = plant.step(StepRequest(robot="robot1", episode=1, step=k, action=(0.2, 0.0), duration=0.1))
    assert reply.true_state is not None
    assert reply.true_state[0] < 0.95  # it drove towards -x (heading pi)
    assert reply.state != reply.true_state  # odometry beside the truth


@pytest.mark.integration
def test_srl_run_parks_the_physics_robot_and_reports_the_truth() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "tools.cli", "run", "--agent", "rlqv", "--horizon", "12", "--start", "2,-1",
         "--duration", "35", "--json"],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
        env={**__import__("os").environ, "SRL_PLANT__MODEL": "physics"},
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-2000:]
    summary = __import__("json").loads(result.stdout.strip().splitlines()[-1])
    assert summary["plant_model"] == "physics"
    truth = summary["truth"]
    assert truth is not None and truth["final_distance"] <= 0.1
    assert truth["accumulated_cost"] != summary["accumulated_cost"]  # J on the true states beside the reported J


def test_the_emulated_turtlebot3_can_be_the_physics_robot(settings: Settings) -> None:
    from common.math.frames import Pose2D
    from services.tb3_emulator.service import Tb3Model

    model = Tb3Model(
        Pose2D(0.0, 0.0, 0.0), 0.22, 2.84, 0.0, 0.0, (0.0, 0.0), 0, 0.0,
        model="physics", params=settings.turtlebot_params(), physics=settings.physics_params(),
    )  # fmt: skip
    assert model.kind == "physics" and isinstance(model.robot, PhysicsBot)
    model.command(0.2, 0.0, now=0.0)
    pose, velocity = model.sample(1.0)
    assert 0.05 < pose[0] < 0.2  # lagging: short of 0.2 m after 1 s
    assert velocity[0] == pytest.approx(0.2, rel=0.02)  # the encoders' speed (turtlebot3_node's): the command
    assert model.state[0] == pytest.approx(pose[0], abs=0.02)
