"""A TurtleBot3 Burger's actuators and odometry, as pure math.

The ideal unicycle (:func:`common.math.dynamics.exact_step`) turns a command into that motion at
once and reports the true pose. A real Burger does neither. :class:`TurtleBot` models, from the
command to the two poses (docs/turtlebot-models.md cites the source of every default):

1. **The OpenCR command path** (:func:`firmware_velocity`): turtlebot3_node writes
   ``int32(v * 100)``, the firmware multiplies by ``0.01f`` and constrains ``v`` and ``omega``
   to their limits (0.01 m/s and 0.01 rad/s resolution).
2. **Wheel kinematics**: wheel speeds ``(v -/+ omega * b/2) / r`` (left, right) [rad/s].
3. **Per-wheel saturation**: each wheel's command is clamped to ``wheel_speed_max`` on its own
   (the motor's velocity limit), which bends the path when one wheel saturates. Steps 1-3 are
   :func:`cmd_vel_to_wheels`, the command of every :class:`Burger` (this one and the MuJoCo
   one, common/math/physics.py).
4. **Deadband** (static friction): a wheel slower than ``deadband`` whose command is below
   ``deadband`` is driven to rest: a wheel at rest does not start below it.
5. **First-order lag and gain**: each wheel speed follows ``gain * command`` with time
   constant ``lag``; integrated exactly per sub-step.
6. **Slip**: each wheel's ground speed is ``(1 - slip) * r * w``, the slip of each wheel drawn
   per command from a seeded normal ``N(slip, slip_std)`` clipped to ``[0, 0.95]``.
7. **Odometry**: dead reckoning from the wheel encoders (which turn with the wheel, so slip is
   invisible to them), as turtlebot3_node does; with ``imu_heading`` the heading comes from the
   IMU (ROBOTIS's default ``use_imu``): the true heading (gyro drift neglected).

The true pose moves with the ground speeds, exactly (unicycle closed form) per sub-step of
``substep`` seconds with the sub-step's mean wheel speed. With ``lag = 0, deadband = 0, slip =
0``, no quantization and no saturation the model is :func:`common.math.dynamics.exact_step`.
Headings are continuous (never wrapped).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import NamedTuple, Protocol

import numpy as np

from common.math.dynamics import FloatArray, exact_step

INT32_MIN, INT32_MAX = -(2**31), 2**31 - 1
MAX_SLIP = 0.95  # a wheel never loses all traction (a slip of 1 would stop its ground speed)


def firmware_velocity(value: float, limit: float) -> float:
    """One velocity component as the TurtleBot3 applies it.

    turtlebot3_node: ``static_cast<int32_t>(value * 100)`` (toward zero; ARM's conversion
    saturates and maps NaN to 0); OpenCR firmware: ``data * 0.01f`` in float32, then
    ``constrain(-limit, limit)``.
    """
    scaled = value * 100.0
    if math.isnan(scaled):
        ticks = 0
    elif scaled >= INT32_MAX:
        ticks = INT32_MAX
    elif scaled <= INT32_MIN:
        ticks = INT32_MIN
    else:
        ticks = math.trunc(scaled)
    applied = float(np.float32(ticks) * np.float32(0.01))
    return min(max(applied, -limit), limit)


@dataclass(frozen=True)
class TurtleBotParams:
    """The model's constants (defaults: ``[actuator]`` in common/config/srl.toml; sources in
    docs/turtlebot-models.md)."""

    v_max: float  # [m/s] the firmware's limit on v
    omega_max: float  # [rad/s] the firmware's limit on omega
    wheel_radius: float  # r [m]
    wheel_separation: float  # b [m]
    wheel_speed_max: float  # [rad/s] per wheel (0 or inf: no saturation)
    lag: float  # [s] first-order time constant of each wheel (0: none)
    gain: float  # steady-state wheel speed / command
    deadband: float  # [rad/s] a wheel at rest does not start below it (0: none)
    slip: float  # mean slip of each wheel's ground speed, 0 .. 0.95
    slip_std: float  # its standard deviation, drawn per command (seeded)
    quantize: bool  # the OpenCR command path (int32(v * 100) * 0.01f); false: the limits only
    imu_heading: bool  # odometry heading from the IMU (true heading) instead of the encoders
    substep: float  # [s] internal integration step
    seed: int

    @classmethod
    def ideal(cls, v_max: float = math.inf, omega_max: float = math.inf, substep: float = 0.002) -> TurtleBotParams:
        """Everything off: the model is the exact unicycle (the oracle of the tests)."""
        return cls(v_max, omega_max, 0.033, 0.160, math.inf, 0.0, 1.0, 0.0, 0.0, 0.0, False, False, substep, 0)

    def __post_init__(self) -> None:
        values = (self.wheel_radius, self.wheel_separation, self.gain, self.substep)
        if not all(math.isfinite(v) and v > 0 for v in values):
            raise ValueError(f"wheel radius, separation, gain and substep must be finite and > 0, got {values}")
        if not all(v >= 0 for v in (self.lag, self.deadband, self.slip_std, self.wheel_speed_max)):
            raise ValueError("lag, deadband, slip_std and wheel_speed_max must be >= 0")
        if not 0.0 <= self.slip <= MAX_SLIP:
            raise ValueError(f"slip must be in [0, {MAX_SLIP}], got {self.slip}")


class WheelCommand(NamedTuple):
    """A cmd_vel after the robot's conversion: see :func:`cmd_vel_to_wheels`."""

    applied: tuple[float, float]  # (v, omega) after the firmware
    wheels: FloatArray  # [rad/s] each wheel's command (left, right), clamped to wheel_speed_max
    saturated: bool  # a wheel's command was beyond wheel_speed_max


def cmd_vel_to_wheels(params: TurtleBotParams, v: float, omega: float, gain: float = 1.0) -> WheelCommand:
    """What a Burger makes of a cmd_vel, up to the wheels' commands: a non-finite component is
    0 (never NaN to a wheel); the OpenCR command path (:func:`firmware_velocity`, ``quantize``)
    or the limits only; the wheels' speeds (:func:`wheel_speeds`) times ``gain``, each clamped
    to ``wheel_speed_max`` (0: no clamp). The actuator model applies its gain as the wheels
    follow (``gain`` 1 here), the physics plant's servos take ``gain`` times the speed."""
    p = params
    v, omega = (c if math.isfinite(c) else 0.0 for c in (v, omega))
    if p.quantize:
        applied = (firmware_velocity(v, p.v_max), firmware_velocity(omega, p.omega_max))
    else:
        applied = (min(max(v, -p.v_max), p.v_max), min(max(omega, -p.omega_max), p.omega_max))
    wheels = gain * wheel_speeds(applied[0], applied[1], p.wheel_radius, p.wheel_separation)
    saturated = p.wheel_speed_max > 0 and float(np.max(np.abs(wheels))) > p.wheel_speed_max
    if saturated:
        wheels = np.clip(wheels, -p.wheel_speed_max, p.wheel_speed_max)
    return WheelCommand(applied, wheels, saturated)


def wheel_speeds(v: float, omega: float, radius: float, separation: float) -> FloatArray:
    """Differential drive: ``(v - omega b/2) / r, (v + omega b/2) / r`` (left, right) [rad/s]."""
    return np.array([(v - omega * separation / 2.0) / radius, (v + omega * separation / 2.0) / radius])


def body_velocity(wheels: FloatArray, radius: float, separation: float) -> FloatArray:
    """The inverse: ``v = r (wl + wr) / 2``, ``omega = r (wr - wl) / b``."""
    left, right = float(wheels[0]), float(wheels[1])
    return np.array([radius * (left + right) / 2.0, radius * (right - left) / separation])


class Burger(ABC):
    """What every simulated Burger shares: :meth:`command` takes a cmd_vel as the robot converts
    it (:func:`cmd_vel_to_wheels`) and hands the wheels' commands to :meth:`_drive`;
    :meth:`advance` integrates the held command for a duration; :meth:`step` is both, and
    :attr:`velocity` the encoders' twist. ``odometry`` is what the robot reports."""

    params: TurtleBotParams
    odometry: FloatArray
    applied: tuple[float, float]  # (v, omega) after the firmware
    wheel_command: FloatArray  # [rad/s] each wheel's command (left, right), after saturation
    commands: int
    saturated_commands: int  # commands with at least one wheel beyond wheel_speed_max
    slip: FloatArray  # each wheel's slip under the current command

    @property
    @abstractmethod
    def wheels(self) -> FloatArray:
        """The wheels' speeds now [rad/s] (left, right)."""

    @abstractmethod
    def advance(self, duration: float) -> None:
        """Hold the current command for ``duration`` seconds."""

    @abstractmethod
    def _drive(self) -> None:
        """Hand :attr:`wheel_command` (just set by :meth:`command`) to the wheels."""

    def _command_gain(self) -> float:
        """The factor on the wheels' commands before their clamp: 1, the gain applied as the
        wheels follow (the actuator model)."""
        return 1.0

    def _forget_commands(self) -> None:
        """No command yet (a reset)."""
        self.wheel_command = np.zeros(2)
        self.slip = np.zeros(2)
        self.applied = (0.0, 0.0)
        self.commands = 0
        self.saturated_commands = 0

    def command(self, v: float, omega: float) -> tuple[float, float]:
        """A new cmd_vel: the firmware's conversion and the wheels' commands, then driven."""
        converted = cmd_vel_to_wheels(self.params, v, omega, gain=self._command_gain())
        self.applied = converted.applied
        self.commands += 1
        self.saturated_commands += int(converted.saturated)
        self.wheel_command = converted.wheels
        self._drive()
        return converted.applied

    def step(self, action: FloatArray, duration: float) -> FloatArray:
        """Command ``action`` and hold it for ``duration``; the odometry pose (what the robot reports)."""
        self.command(float(action[0]), float(action[1]))
        self.advance(duration)
        return self.odometry.copy()

    @property
    def velocity(self) -> tuple[float, float]:
        """The encoders' (v, omega) now: what turtlebot3_node reports in odometry's twist."""
        v, omega = body_velocity(self.wheels, self.params.wheel_radius, self.params.wheel_separation)
        return float(v), float(omega)


class TurtleBot(Burger):
    """The actuator model: a Burger's state (true pose, wheel speeds, odometry pose) and its
    transition, as formulas (module docstring). ``true_pose`` is where the robot is."""

    def __init__(self, params: TurtleBotParams, pose: FloatArray) -> None:
        self.params = params
        self.reset(pose)

    def reset(self, pose: FloatArray) -> None:
        """At rest at ``pose``; the odometry starts at the same pose (its frame is the goal's). The
        slip is re-seeded: a reset robot is a new robot, and every episode sees the same slip."""
        self.rng = np.random.default_rng(self.params.seed)
        self.true_pose = np.asarray(pose, dtype=float).copy()
        self.odometry = self.true_pose.copy()
        self._wheels = np.zeros(2)  # [rad/s] left, right
        self._forget_commands()

    @property
    def wheels(self) -> FloatArray:
        return self._wheels

    def _drive(self) -> None:
        """This command's slip (the wheels follow the command as :meth:`advance` integrates)."""
        p = self.params
        if p.slip > 0 or p.slip_std > 0:
            self.slip = np.clip(p.slip + p.slip_std * self.rng.standard_normal(2), 0.0, MAX_SLIP)

    def _targets(self) -> FloatArray:
        """What each wheel's speed tends to: ``gain * command``, zero for a wheel held by static friction."""
        p = self.params
        targets = p.gain * self.wheel_command
        if p.deadband > 0:
            held = (np.abs(self.wheel_command) < p.deadband) & (np.abs(self._wheels) < p.deadband)
            targets = np.where(held, 0.0, targets)
        return targets

    def advance(self, duration: float) -> None:
        """Hold the current command for ``duration`` seconds (sub-steps of at most ``substep``)."""
        if duration <= 0:
            return
        p = self.params
        n = max(1, math.ceil(duration / p.substep - 1e-9))
        h = duration / n
        decay = math.exp(-h / p.lag) if p.lag > 0 else 0.0
        # mean of target + (w0 - target) exp(-t/lag) over [0, h]: the fraction of (w0 - target) kept
        mean_kept = p.lag / h * (1.0 - decay) if p.lag > 0 else 0.0
        for _ in range(n):
            targets = self._targets()
            mean_wheels = targets + (self._wheels - targets) * mean_kept
            self._wheels = targets + (self._wheels - targets) * decay
            ground = body_velocity((1.0 - self.slip) * mean_wheels, p.wheel_radius, p.wheel_separation)
            encoders = body_velocity(mean_wheels, p.wheel_radius, p.wheel_separation)
            heading_before = float(self.true_pose[2])
            self.true_pose = exact_step(self.true_pose, ground, h)
            if p.imu_heading:  # the IMU's yaw increment replaces the encoders'
                encoders[1] = (float(self.true_pose[2]) - heading_before) / h
            self.odometry = exact_step(self.odometry, encoders, h)


class SimulatedRobot(Protocol):
    """A simulated robot, what every consumer calls (a plant model's row builds one,
    common/math/plant_models.py): :class:`TurtleBot` (the actuator model),
    :class:`common.math.physics.PhysicsBot` (the MuJoCo one), or a user's model. plant_sim and
    the in-process plant command it and let it run (:meth:`command`, :meth:`advance`, or both:
    :meth:`step`); the emulator also reads :attr:`params` (the firmware's conversion),
    :attr:`applied` and :attr:`velocity` (its odometry's twist)."""

    @property
    def params(self) -> TurtleBotParams:
        """The constants it was built with (the emulator converts a cmd_vel with them)."""
        ...

    @property
    def odometry(self) -> FloatArray:
        """[x m, y m, theta rad]: the pose it reports."""
        ...

    @property
    def true_pose(self) -> FloatArray:
        """[x m, y m, theta rad]: where it is."""
        ...

    @property
    def applied(self) -> tuple[float, float]:
        """(v, omega) of the newest command, as the robot took it (after its firmware)."""
        ...

    @property
    def velocity(self) -> tuple[float, float]:
        """(v, omega) it moves at now, as its encoders measure it."""
        ...

    @property
    def saturated_commands(self) -> int:
        """Commands it could not follow (a wheel beyond its speed limit)."""
        ...

    def reset(self, pose: FloatArray) -> None:
        """At rest at ``pose``, its odometry from there."""
        ...

    def command(self, v: float, omega: float) -> tuple[float, float]:
        """A new cmd_vel, held until the next; the (v, omega) it takes of it."""
        ...

    def advance(self, duration: float) -> None:
        """Hold the current command for ``duration`` seconds."""
        ...

    def step(self, action: FloatArray, duration: float) -> FloatArray:
        """:meth:`command` ``action``, :meth:`advance` ``duration``; the odometry after."""
        ...


class RobotPlant:
    """A simulated TurtleBot3 in process, a :class:`common.math.dynamics.Plant`: it reports the robot's
    odometry and keeps the true pose beside it. A reset puts the robot at rest at the start (the
    actuator model's slip re-seeded: every episode of the same settings sees the same slip)."""

    def __init__(self, robot: SimulatedRobot) -> None:
        self.robot = robot

    def reset(self, state: np.ndarray) -> np.ndarray:
        self.robot.reset(np.asarray(state, dtype=float))
        return self.robot.odometry.copy()

    def apply(self, action: np.ndarray, duration: float) -> np.ndarray:
        return self.robot.step(action, duration)

    @property
    def true_state(self) -> np.ndarray:
        return self.robot.true_pose.copy()

    @property
    def saturated_commands(self) -> int:
        return self.robot.saturated_commands
