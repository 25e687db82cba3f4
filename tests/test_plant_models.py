"""A plant model is one row (common/math/plant_models.py): a class that satisfies
:class:`common.math.turtlebot.SimulatedRobot`, registered, runs wherever a plant model runs --
the settings, the in-process episode (``srl run``, the experiment), plant_sim and the TurtleBot3
emulator -- with no change to srl's modules. The model here is defined in this file, as a user's
would be in theirs."""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import pytest
from pydantic import ValidationError

from common.config.settings import Settings
from common.math.dynamics import FloatArray, exact_step
from common.math.frames import Pose2D
from common.math.physics import PhysicsParams
from common.math.plant_models import (
    BUILT_IN_PLANT_MODELS,
    PLANT_MODELS,
    plant_model_row,
    register_plant_model,
    simulated_robot,
)
from common.math.turtlebot import SimulatedRobot, TurtleBotParams

NAME = "lagged_unicycle"
LAG = 0.3  # [s] the body velocity follows the command with this time constant
SUBSTEP = 0.005  # [s]
ODOMETRY_SCALE = 1.05  # its odometry overstates the distance by 5 %


class LaggedUnicycle:
    """A user's model: a unicycle whose (v, omega) follow the command with a first-order lag,
    clamped to the settings' speed limits, its odometry 5 % long."""

    def __init__(self, params: TurtleBotParams, pose: FloatArray) -> None:
        self.params = params
        self.saturated_commands = 0
        self.reset(pose)

    def reset(self, pose: FloatArray) -> None:
        self.true_pose = np.asarray(pose, dtype=float).copy()
        self.odometry = self.true_pose.copy()
        self.applied = (0.0, 0.0)
        self.moving = np.zeros(2)

    @property
    def velocity(self) -> tuple[float, float]:
        return float(self.moving[0]), float(self.moving[1])

    def command(self, v: float, omega: float) -> tuple[float, float]:
        limits = (self.params.v_max, self.params.omega_max)
        clamped = tuple(min(max(c, -m), m) for c, m in zip((v, omega), limits, strict=True))
        self.saturated_commands += clamped != (v, omega)
        self.applied = (clamped[0], clamped[1])
        return self.applied

    def advance(self, duration: float) -> None:
        steps = max(1, math.ceil(duration / SUBSTEP - 1e-9))
        h = duration / steps
        keep = math.exp(-h / LAG)
        for _ in range(steps):
            self.moving = np.asarray(self.applied) + (self.moving - np.asarray(self.applied)) * keep
            self.true_pose = exact_step(self.true_pose, self.moving, h)
            self.odometry = exact_step(self.odometry, self.moving * np.array([ODOMETRY_SCALE, 1.0]), h)

    def step(self, action: FloatArray, duration: float) -> FloatArray:
        self.command(float(action[0]), float(action[1]))
        self.advance(duration)
        return self.odometry.copy()


def build_lagged(params: TurtleBotParams, physics: PhysicsParams, pose: FloatArray) -> SimulatedRobot:
    return LaggedUnicycle(params, pose)


@pytest.fixture
def registered() -> Iterator[str]:
    register_plant_model(NAME, "a unicycle with a lag (tests/test_plant_models.py)", build_lagged)
    try:
        yield NAME
    finally:
        del PLANT_MODELS[NAME]  # other tests of this process see srl's rows only


def oracle(settings: Settings, start: FloatArray, actions: list[FloatArray], duration: float) -> list[FloatArray]:
    """The user's model alone, driven by ``actions``: its odometry after each."""
    robot = LaggedUnicycle(settings.turtlebot_params(), start)
    return [robot.step(action, duration) for action in actions]


def test_registering_a_model_makes_it_a_setting_and_a_choice_and_a_bad_one_is_refused(registered: str) -> None:
    from tools.cli import build_parser

    assert Settings.load(plant={"model": registered}).plant.model == registered
    assert plant_model_row(registered).build is build_lagged
    with pytest.raises(ValidationError, match=r"unknown plant model 'gazebo' \(ideal, actuator, physics, lagged"):
        Settings.load(plant={"model": "gazebo"})
    with pytest.raises(ValueError, match="exists already"):
        register_plant_model(registered, "again", build_lagged)
    with pytest.raises(ValueError, match="a-z 0-9 _"):
        register_plant_model("Bad Name", "a name no setting can hold", build_lagged)
    assert tuple(PLANT_MODELS)[: len(BUILT_IN_PLANT_MODELS)] == BUILT_IN_PLANT_MODELS
    model_choices = [
        list(action.choices)
        for sub in build_parser()._subparsers._group_actions[0].choices.values()  # type: ignore[union-attr]
        for action in sub._actions
        if "--model" in action.option_strings and action.choices is not None
    ]  # the parser is built after the registration: every --model offers the model
    assert model_choices and all(registered in choices for choices in model_choices)


def test_a_model_unregistered_is_refused_by_the_settings() -> None:
    assert NAME not in PLANT_MODELS  # the negative control of the test above: without the row, no setting
    with pytest.raises(ValidationError, match=f"unknown plant model '{NAME}'"):
        Settings.load(plant={"model": NAME})


@pytest.mark.slow
def test_the_in_process_episode_runs_the_users_model(registered: str) -> None:
    """``srl run``'s episode (common.config.assembly.run_episode) on the user's model: the actor
    saw its odometry, the truth is its true pose, and the model alone, driven by the episode's
    actions, gives the same states bit for bit."""
    from common.config.assembly import episode_summary, run_episode

    settings = Settings.load(
        plant={"model": registered},
        actor={"agent": "mpc", "horizon": 6, "jit": False},
        episode={"start": [1.0, 0.5], "duration": 3.0},
    )
    episode = run_episode(settings)
    start = settings.start_state()
    expected = oracle(settings, start, episode.actions, settings.plant.sampling_time)
    np.testing.assert_array_equal(np.array(episode.states[1:]), np.array(expected))
    assert episode.truth_known and not np.allclose(episode.true_states[-1], episode.states[-1])
    assert np.hypot(*episode.true_states[-1][:2]) < np.hypot(*start[:2])  # the MPC drove it towards the target
    summary = episode_summary(episode, settings)
    assert summary["plant_model"] == registered and summary["truth"] is not None


def test_plant_sim_runs_the_users_model_in_lockstep(registered: str) -> None:
    from common.contracts.messages import ResetRequest, StepRequest
    from services.plant_sim.service import SimulatedPlant

    settings = Settings.load(plant={"model": registered})
    plant = SimulatedPlant(settings)
    start = np.array([1.0, -0.5, 0.3])
    plant.reset(ResetRequest(robot="robot1", episode=1, state=(1.0, -0.5, 0.3)))
    actions = [np.array([0.2, 0.5]), np.array([0.22, -1.0]), np.array([0.0, 0.0])] * 3
    replies = [
        plant.step(StepRequest(robot="robot1", episode=1, step=k, action=(float(a[0]), float(a[1])), duration=0.1))
        for k, a in enumerate(actions)
    ]
    np.testing.assert_array_equal(np.array([r.state for r in replies]), np.array(oracle(settings, start, actions, 0.1)))
    assert all(r.true_state is not None and r.true_state != r.state for r in replies)


def test_the_emulator_runs_the_users_model_behind_its_latency(registered: str) -> None:
    from services.tb3_emulator.service import Tb3Model

    settings = Settings.load()
    model = Tb3Model(
        Pose2D(0.5, 0.0, 0.0), 0.22, 2.84, 0.0, 0.0, (0.0, 0.0), 0, 0.0,
        registered, settings.turtlebot_params(), settings.physics_params(),
    )  # fmt: skip
    assert model.kind == registered and isinstance(model.robot, LaggedUnicycle)
    assert model.robot.params.v_max == 0.22  # the emulated robot's limits, not the settings'
    model.command(0.5, 0.0, now=0.0)  # beyond its limit: clamped by the model
    pose, velocity = model.sample(1.0)
    robot = LaggedUnicycle(model.robot.params, np.array([0.5, 0.0, 0.0]))
    robot.command(0.5, 0.0)
    robot.advance(1.0)
    np.testing.assert_array_equal(pose, robot.odometry)
    assert velocity == robot.velocity and 0.0 < velocity[0] < 0.22  # the encoders' speed, still lagging
    assert model.robot.saturated_commands == 1


def test_the_built_in_rows_build_what_they_name() -> None:
    settings = Settings.load()
    args = (settings.turtlebot_params(), settings.physics_params(), np.zeros(3))
    assert simulated_robot("ideal", *args) is None  # the exact unicycle: no robot model
    assert type(simulated_robot("actuator", *args)).__name__ == "TurtleBot"
