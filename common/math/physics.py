"""A rigid-body TurtleBot3 Burger in MuJoCo: ``plant.model = "physics"`` (docs/turtlebot.md).

The actuator model (:mod:`common.math.turtlebot`) writes lag, deadband and slip down as formulas.
Here they arise from physics, as on a real Burger: a rigid body of ROBOTIS's published masses and
dimensions (turtlebot3_description ``turtlebot3_burger.urdf``; docs/turtlebot.md cites each) on
two wheels and a sliding caster, with contact friction; each wheel driven by a velocity servo
(the Dynamixel's velocity loop, MuJoCo's ``velocity`` actuator: torque ``kv (w_cmd - w)``,
limited to the motor's stall torque) against the joint's dry friction. So

* **lag**: the servo accelerates the wheel and the robot's share of its mass; its time constant
  is ``J_eff / kv``, and ``kv`` is chosen so that it equals ``[actuator] lag``;
* **deadband and shortfall**: the tyres' rolling resistance on the floor (MuJoCo's soft
  contact: ~0.008 N m per wheel) and the joints' dry friction (``motor_friction``)
  hold a wheel whose servo torque is below them, and leave a running wheel short of its
  command by ``resistance / kv`` (~1.5 rad/s, ~0.05 m/s, at ``lag = 0.1``) at any speed;
* **slip**: the tyres slide on the floor when the caster drags or the robot turns in place;
  nothing draws it, the contact solver does;
* **saturation**: each wheel's command is clamped to ``wheel_speed_max`` (the actuator's
  control range).

Before the wheels: the OpenCR command path and the clamp of
:func:`common.math.turtlebot.cmd_vel_to_wheels`. After them: the encoders (the wheel joints'
angles, quantized to the XL430's 4096 ticks per turn) integrated by dead reckoning every
``odometry_period`` as turtlebot3_node's ``odometry.cpp`` does, the heading from the IMU (the
body's true yaw) with ``imu_heading``. The true pose is the body's ``base_footprint`` frame.
Headings are continuous (never wrapped).

MuJoCo is an optional extra (``pip install 'srl[physics]'``, installed by ``./srl`` and CI);
it is imported when a :class:`PhysicsBot` is made, with a one-line error when missing.
"""

from __future__ import annotations

import importlib
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.math.dynamics import FloatArray
from common.math.turtlebot import Burger, TurtleBot, TurtleBotParams

# turtlebot3_description/urdf/turtlebot3_burger.urdf (ROBOTIS), in base_footprint's frame
BASE_HEIGHT = 0.010  # base_joint: base_link 0.010 m above base_footprint
BASE_MASS = 8.2573504e-01  # base_link inertial [kg], at base_link's origin
BASE_INERTIA = (2.2124416e-03, 2.1193702e-03, 2.0064271e-03)  # ixx, iyy, izz [kg m^2]
WHEEL_MASS = 2.8498940e-02  # each wheel [kg]
WHEEL_INERTIA = (1.1175580e-05, 2.0712558e-05, 1.1192413e-05)  # about x, the axle (y), z [kg m^2]
WHEEL_WIDTH = 0.018  # the wheel cylinder's length [m]
CASTER_X = -0.081  # caster_back_joint x [m]
CASTER_MASS = 0.005
CASTER_RADIUS = 0.005  # a sphere in the URDF's 0.030 x 0.009 x 0.020 box, touching the floor
SCAN_MASS = 0.114  # base_scan (the LDS) [kg], at (-0.032, 0, 0.172) of base_link
SCAN_POSITION = (-0.032, 0.0, 0.172 + BASE_HEIGHT)
ENCODER_TICKS = 4096  # per wheel revolution (XL430-W250, ROBOTIS e-manual; turtlebot3_node)


@dataclass(frozen=True)
class PhysicsParams:
    """The physics plant's own constants (``[physics]`` in common/config/srl.toml, docs/turtlebot.md)."""

    timestep: float  # [s] MuJoCo's integration step
    tire_friction: float  # sliding friction coefficient of the tyres on the floor
    caster_friction: float  # of the caster on the floor
    torque_max: float  # [N m] each motor's torque limit (the XL430-W250's stall torque)
    motor_friction: float  # [N m] each wheel joint's dry friction (0: the tyres' rolling resistance only)
    odometry_period: float  # [s] how often the encoders are read and integrated
    encoder_ticks: int  # per wheel revolution (0: exact angles)

    def __post_init__(self) -> None:
        values = (self.timestep, self.tire_friction, self.caster_friction, self.torque_max, self.odometry_period)
        if not all(math.isfinite(v) and v > 0 for v in values):
            raise ValueError(f"physics constants must be finite and > 0, got {values}")
        if not (math.isfinite(self.motor_friction) and self.motor_friction >= 0):
            raise ValueError(f"motor_friction must be finite and >= 0, got {self.motor_friction}")
        if self.encoder_ticks < 0:
            raise ValueError(f"encoder_ticks must be >= 0, got {self.encoder_ticks}")


def effective_wheel_inertia(params: TurtleBotParams) -> float:
    """What one wheel's servo accelerates when both drive straight: its own inertia about the
    axle plus half the robot's mass at the wheel radius [kg m^2]."""
    total = BASE_MASS + 2 * WHEEL_MASS + CASTER_MASS + SCAN_MASS
    return WHEEL_INERTIA[1] + total / 2.0 * params.wheel_radius**2


def servo_gain(params: TurtleBotParams) -> float:
    """``kv`` [N m s / rad] whose time constant ``J_eff / kv`` is ``params.lag`` (a stiff servo,
    10 ms, when the lag is 0)."""
    return effective_wheel_inertia(params) / (params.lag if params.lag > 0 else 0.01)


def burger_mjcf(params: TurtleBotParams, physics: PhysicsParams) -> str:
    """The Burger as MJCF: one free body (base_footprint) with the base's, the LDS's and the
    caster's masses, two hinged wheels, a floor; velocity servos on the wheels."""
    r, half_b = params.wheel_radius, params.wheel_separation / 2.0
    kv = servo_gain(params)
    friction = physics.motor_friction  # the joints' dry friction torque [N m]
    w_max = params.wheel_speed_max if math.isfinite(params.wheel_speed_max) and params.wheel_speed_max > 0 else 0.0
    ctrl = f'ctrllimited="true" ctrlrange="{-w_max} {w_max}"' if w_max > 0 else 'ctrllimited="false"'
    torque = f'forcelimited="true" forcerange="{-physics.torque_max} {physics.torque_max}"'
    ix, iy, iz = BASE_INERTIA
    wx, wy, wz = WHEEL_INERTIA
    sx, sy, sz = SCAN_POSITION
    wheels = "".join(
        f"""
      <body name="wheel_{side}" pos="0 {sign * half_b} {r}">
        <joint name="wheel_{side}" type="hinge" axis="0 1 0" frictionloss="{friction}"/>
        <inertial pos="0 0 0" mass="{WHEEL_MASS}" diaginertia="{wx} {wy} {wz}"/>
        <geom type="sphere" size="{r}" friction="{physics.tire_friction} 0.005 0.0001"/>
      </body>"""
        for side, sign in (("left", 1), ("right", -1))
    )
    return f"""<mujoco model="turtlebot3_burger">
  <option timestep="{physics.timestep}" integrator="implicitfast"/>
  <worldbody>
    <geom name="floor" type="plane" size="0 0 1" friction="1 0.005 0.0001"/>
    <body name="base_footprint" pos="0 0 0">
      <freejoint name="base"/>
      <inertial pos="0 0 {BASE_HEIGHT}" mass="{BASE_MASS}" diaginertia="{ix} {iy} {iz}"/>
      <body name="base_scan" pos="{sx} {sy} {sz}">
        <inertial pos="0 0 0" mass="{SCAN_MASS}" diaginertia="0.001 0.001 0.001"/>
      </body>
      <body name="caster_back" pos="{CASTER_X} 0 {CASTER_RADIUS}">
        <inertial pos="0 0 0" mass="{CASTER_MASS}" diaginertia="1e-6 1e-6 1e-6"/>
        <geom type="sphere" size="{CASTER_RADIUS}" friction="{physics.caster_friction} 0.005 0.0001"/>
      </body>{wheels}
    </body>
  </worldbody>
  <actuator>
    <velocity name="left" joint="wheel_left" kv="{kv}" {ctrl} {torque}/>
    <velocity name="right" joint="wheel_right" kv="{kv}" {ctrl} {torque}/>
  </actuator>
</mujoco>
"""


def load_mujoco() -> Any:
    """The ``mujoco`` module, or a one-line error saying how to install it."""
    try:
        return importlib.import_module("mujoco")
    except ImportError as error:
        raise RuntimeError(
            f"plant.model = 'physics' needs MuJoCo: pip install 'srl[physics]' (./srl installs it) ({error})"
        ) from None


def _yaw(quaternion: FloatArray) -> float:
    w, x, y, z = (float(c) for c in quaternion)
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


class PhysicsBot(Burger):
    """The MuJoCo Burger, a :class:`common.math.turtlebot.Burger` as the actuator model is: the
    wheels' commands go to their velocity servos; ``true_pose`` is the body's pose."""

    SETTLE = 0.1  # [s] on the floor before a start: the contacts settle, then the pose is set again

    def __init__(self, params: TurtleBotParams, physics: PhysicsParams, pose: FloatArray) -> None:
        self.params = params
        self.physics = physics
        self.mujoco = load_mujoco()
        self.model = self.mujoco.MjModel.from_xml_string(burger_mjcf(params, physics))
        self.data = self.mujoco.MjData(self.model)
        self.wheel_qpos = [int(self.model.jnt_qposadr[self.model.joint(f"wheel_{s}").id]) for s in ("left", "right")]
        self.wheel_dof = [int(self.model.jnt_dofadr[self.model.joint(f"wheel_{s}").id]) for s in ("left", "right")]
        self.odometry_steps = max(1, round(physics.odometry_period / physics.timestep))
        self.reset(pose)

    # -- state ------------------------------------------------------------------------------
    def reset(self, pose: FloatArray) -> None:
        """At rest at ``pose`` on the floor; the odometry starts at the same pose."""
        pose = np.asarray(pose, dtype=float)
        self.mujoco.mj_resetData(self.model, self.data)
        self._place(pose)
        self.data.ctrl[:] = 0.0
        self.mujoco.mj_step(self.model, self.data, nstep=max(1, round(self.SETTLE / self.physics.timestep)))
        self._place(pose)  # the settled heights and contacts, at exactly the start pose
        self.mujoco.mj_forward(self.model, self.data)
        self.heading = float(pose[2])  # the true heading, unwrapped
        self.odometry = pose.copy()
        self.encoders = self._encoders()
        self.imu_heading = self.heading
        self._forget_commands()  # slip stays zero: not drawn, physics decides

    def _place(self, pose: FloatArray) -> None:
        qpos = self.data.qpos
        qpos[0], qpos[1] = float(pose[0]), float(pose[1])
        if self.data.time == 0.0:
            qpos[2] = 0.0
        half = float(pose[2]) / 2.0
        qpos[3:7] = (math.cos(half), 0.0, 0.0, math.sin(half))
        self.data.qvel[:] = 0.0

    def _encoders(self) -> FloatArray:
        angles = np.array([float(self.data.qpos[i]) for i in self.wheel_qpos])
        if self.physics.encoder_ticks > 0:
            tick = 2.0 * math.pi / self.physics.encoder_ticks
            angles = np.round(angles / tick) * tick
        return angles

    @property
    def true_pose(self) -> FloatArray:
        return np.array([float(self.data.qpos[0]), float(self.data.qpos[1]), self.heading])

    @property
    def wheels(self) -> FloatArray:
        """The wheels' speeds [rad/s] (left, right)."""
        return np.array([float(self.data.qvel[i]) for i in self.wheel_dof])

    # -- transition -------------------------------------------------------------------------
    def _command_gain(self) -> float:
        """The servos take ``gain`` times the wheel speed as their target, clamped to their range."""
        return self.params.gain

    def _drive(self) -> None:
        self.data.ctrl[:] = self.wheel_command

    def advance(self, duration: float) -> None:
        """Hold the current command for ``duration`` seconds, reading the encoders every
        ``odometry_period`` (the last read at the end)."""
        steps = round(duration / self.physics.timestep)
        while steps > 0:
            n = min(steps, self.odometry_steps)
            yaw_before = _yaw(self.data.qpos[3:7])
            self.mujoco.mj_step(self.model, self.data, nstep=n)
            steps -= n
            turned = _yaw(self.data.qpos[3:7]) - yaw_before
            self.heading += math.remainder(turned, 2.0 * math.pi)
            self._dead_reckon()

    def _dead_reckon(self) -> None:
        """turtlebot3_node's odometry.cpp: ``delta_s`` from the encoders, ``delta_theta`` from
        the IMU (or the encoders), integrated at the mid heading."""
        p = self.params
        encoders = self._encoders()
        left, right = encoders - self.encoders
        self.encoders = encoders
        delta_s = p.wheel_radius * (left + right) / 2.0
        if p.imu_heading:
            delta_theta = self.heading - self.imu_heading
            self.imu_heading = self.heading
        else:
            delta_theta = p.wheel_radius * (right - left) / p.wheel_separation
        x, y, theta = (float(c) for c in self.odometry)
        mid = theta + delta_theta / 2.0
        self.odometry = np.array([x + delta_s * math.cos(mid), y + delta_s * math.sin(mid), theta + delta_theta])


def simulated_robot(
    model: str, params: TurtleBotParams, physics: PhysicsParams, pose: FloatArray
) -> TurtleBot | PhysicsBot | None:
    """The simulated TurtleBot3 of ``plant.model`` at rest at ``pose``: the actuator model
    (:class:`common.math.turtlebot.TurtleBot`), the MuJoCo one, or None for the ideal unicycle."""
    if model == "actuator":
        return TurtleBot(params, pose)
    if model == "physics":
        return PhysicsBot(params, physics, pose)
    if model != "ideal":
        raise ValueError(f"unknown plant model {model!r} (ideal, actuator or physics)")
    return None


__all__ = ["PhysicsBot", "PhysicsParams", "burger_mjcf", "servo_gain", "simulated_robot"]
