"""A plant model of your own, in one file: a unicycle whose speeds lag behind the command.

Run it with any srl command by naming this file in ``SRL_PLUGINS`` (common/process/plugins.py)
and choosing the model::

    SRL_PLUGINS=examples/lagged_unicycle.py SRL_PLANT__MODEL=lagged_unicycle ./srl run --duration 20

The robot is any object with the methods of :class:`common.math.turtlebot.SimulatedRobot`; srl
calls :func:`register` once per process, which adds the row (docs/extending.md).
"""

from __future__ import annotations

import math

import numpy as np

from common.math.dynamics import FloatArray, exact_step
from common.math.physics import PhysicsParams
from common.math.plant_models import register_plant_model
from common.math.turtlebot import SimulatedRobot, TurtleBotParams

NAME = "lagged_unicycle"
LAG = 0.3  # [s] the speeds follow the command with this time constant
SUBSTEP = 0.005  # [s] integration step
ODOMETRY_SCALE = 1.05  # the odometry overstates the distance driven by 5 %


class LaggedUnicycle:
    """A unicycle whose (v, omega) follow the command with a first-order lag, the command clamped
    to the settings' speed limits (``[plant] v_max``, ``omega_max``), its odometry 5 % long."""

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
        v_max, omega_max = self.params.v_max, self.params.omega_max
        clamped = (min(max(v, -v_max), v_max), min(max(omega, -omega_max), omega_max))
        self.saturated_commands += clamped != (v, omega)
        self.applied = clamped
        return clamped

    def advance(self, duration: float) -> None:
        steps = max(1, math.ceil(duration / SUBSTEP - 1e-9))
        h = duration / steps
        keep = math.exp(-h / LAG)
        target = np.asarray(self.applied)
        for _ in range(steps):
            self.moving = target + (self.moving - target) * keep
            self.true_pose = exact_step(self.true_pose, self.moving, h)
            self.odometry = exact_step(self.odometry, self.moving * np.array([ODOMETRY_SCALE, 1.0]), h)

    def step(self, action: FloatArray, duration: float) -> FloatArray:
        self.command(float(action[0]), float(action[1]))
        self.advance(duration)
        return self.odometry.copy()


def build(params: TurtleBotParams, physics: PhysicsParams, pose: FloatArray) -> SimulatedRobot:
    """The row's robot: built from the ``[actuator]`` constants (their speed limits) at ``pose``."""
    return LaggedUnicycle(params, pose)


def register() -> None:
    register_plant_model(NAME, "a unicycle whose speeds lag 0.3 s behind the command (examples/)", build)
