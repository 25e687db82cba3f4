"""A rigid-body TurtleBot3 Burger in MuJoCo: ``plant.model = "physics"`` (docs/turtlebot-models.md).

The actuator model (:mod:`common.math.turtlebot`) writes lag, deadband and slip down as formulas.
Here they arise from physics, as on a real Burger: a rigid body of ROBOTIS's published masses and
dimensions (turtlebot3_description ``turtlebot3_burger.urdf``; docs/turtlebot-models.md cites each) on
two wheels and a ball caster, with contact friction; each wheel driven by a Dynamixel XL430-W250
in velocity control mode, as the e-Manual draws its controller
(https://emanual.robotis.com/docs/en/dxl/x/xl430-w250/#velocity-pi-gain76-78): a PI loop on
the velocity error whose output is the motor's PWM, limited by the PWM limit (100 %: the stall
torque, ``torque_max``), against the joint's breakaway (dry) friction. So

* **steady state**: the integral term holds whatever torque the wheel's load needs (the
  tyres' rolling resistance, the joint's friction, a slope), so a running wheel reaches its
  command (:func:`velocity_gains`);
* **lag**: the PI's gains against the wheel's and the robot's inertia: the step response is the
  closed loop's, not a drawn time constant;
* **deadband**: a wheel at rest starts only when the servo's torque exceeds the breakaway
  friction ``motor_friction``; the integral term gets there after a while for any command, so a
  command below :func:`breakaway_speed` leaves a wheel at rest for its hold and starts it when
  held longer (a command that must leave the robot at rest is zero);
* **slip**: the tyres slide on the floor when the robot turns in place; nothing draws it, the
  contact solver does;
* **saturation**: each wheel's command is clamped to ``wheel_speed_max`` (the actuator's
  control range).

The P term is MuJoCo's ``velocity`` actuator (its damping is integrated implicitly, so a free
wheel of 2e-5 kg m^2 is stable at any gain); the I term a ``motor`` actuator whose torque
:class:`PhysicsBot` integrates every MuJoCo step with the e-Manual's anti-windup (the integral
stops growing while the output is at its limit); the joint's ``actuatorfrcrange`` limits the two
together to the stall torque.

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
from common.math.turtlebot import Burger, TurtleBotParams

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
# XL430-W250 control table (https://emanual.robotis.com/docs/en/dxl/x/xl430-w250/): Goal and
# Present Velocity in units of 0.229 rev/min; PWM in units of 0.113 %, PWM Limit(36) 885 = 100 %.
VELOCITY_UNIT = 0.229 * 2.0 * math.pi / 60.0  # [rad/s] per unit
PWM_FULL = 885
# Velocity PI Gain(76, 78): K_VP = KVP(TBL) / 128 and K_VI = KVI(TBL) / 65536 in PWM units per
# velocity unit (the integral's constant includes the sampling time, per control period).
P_GAIN_SCALE = 128
I_GAIN_SCALE = 65536


@dataclass(frozen=True)
class PhysicsParams:
    """The physics plant's own constants (``[physics]`` in common/config/srl.toml, docs/turtlebot-models.md)."""

    timestep: float  # [s] MuJoCo's integration step
    tire_friction: float  # sliding friction coefficient of the tyres on the floor
    caster_friction: float  # of the caster's ball on the floor
    torque_max: float  # [N m] each motor's torque at 100 % PWM (the XL430-W250's stall torque)
    motor_friction: float  # [N m] each wheel joint's breakaway (dry) friction
    odometry_period: float  # [s] how often the encoders are read and integrated
    encoder_ticks: int  # per wheel revolution (0: exact angles)
    velocity_p_gain: int  # Velocity P Gain(78), control table units
    velocity_i_gain: int  # Velocity I Gain(76), control table units
    velocity_loop_period: float  # [s] the XL430's control period (the I gain's time base)
    caster_socket_friction: float  # [N m] the caster ball's dry friction in its socket

    def __post_init__(self) -> None:
        values = (
            self.timestep, self.tire_friction, self.caster_friction, self.torque_max, self.odometry_period,
            self.velocity_loop_period,
        )  # fmt: skip
        if not all(math.isfinite(v) and v > 0 for v in values):
            raise ValueError(f"physics constants must be finite and > 0, got {values}")
        for name in ("motor_friction", "caster_socket_friction"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {value}")
        if self.encoder_ticks < 0:
            raise ValueError(f"encoder_ticks must be >= 0, got {self.encoder_ticks}")
        if not all(0 <= g <= 16383 for g in (self.velocity_p_gain, self.velocity_i_gain)):
            raise ValueError(
                f"velocity gains are control table values 0 .. 16383, got P {self.velocity_p_gain}, "
                f"I {self.velocity_i_gain}"
            )


def effective_wheel_inertia(params: TurtleBotParams) -> float:
    """What one wheel's motor accelerates when both drive straight: its own inertia about the
    axle plus half the robot's mass at the wheel radius [kg m^2]."""
    total = BASE_MASS + 2 * WHEEL_MASS + CASTER_MASS + SCAN_MASS
    return WHEEL_INERTIA[1] + total / 2.0 * params.wheel_radius**2


def velocity_gains(physics: PhysicsParams) -> tuple[float, float]:
    """The XL430's velocity PI in torque at the wheel: ``(kp [N m s/rad], ki [N m/rad])``.

    The e-Manual's controller turns the velocity error (units of 0.229 rev/min) into PWM (units
    of 1/885 of full) with ``KVP(TBL) / 128`` and, per control period, ``KVI(TBL) / 65536``; full
    PWM holds the stall torque ``torque_max`` at rest. The motor's back-EMF, which caps the
    datasheet's no-load speed (61 rev/min at 12 V, 6.39 rad/s, below the 6.67 rad/s of the
    Burger's 0.22 m/s), is not drawn: the robot's top speed is ``[actuator] wheel_speed_max``.
    """
    torque_per_unit = physics.torque_max / PWM_FULL / VELOCITY_UNIT  # [N m] per (rad/s) per gain
    kp = physics.velocity_p_gain / P_GAIN_SCALE * torque_per_unit
    ki = physics.velocity_i_gain / I_GAIN_SCALE * torque_per_unit / physics.velocity_loop_period
    return kp, ki


def breakaway_speed(physics: PhysicsParams, hold: float) -> float:
    """The largest wheel command [rad/s] that leaves a wheel at rest for ``hold`` seconds: the PI's
    torque ``(kp + ki t) e`` stays below the joint's breakaway friction until ``t = hold`` (the
    tyres' rolling resistance adds to it: a lower bound). Held longer, any command starts the
    wheel; 0 without friction."""
    kp, ki = velocity_gains(physics)
    return physics.motor_friction / (kp + ki * max(hold, 0.0))


def burger_mjcf(params: TurtleBotParams, physics: PhysicsParams) -> str:
    """The Burger as MJCF: one free body (base_footprint) with the base's, the LDS's masses, a
    ball caster, two hinged wheels, a floor; each wheel's XL430 as a P (velocity) and an I
    (motor) actuator, limited together to the stall torque by the joint."""
    r, half_b = params.wheel_radius, params.wheel_separation / 2.0
    kp, _ = velocity_gains(physics)
    friction = physics.motor_friction  # the joints' breakaway friction torque [N m]
    t_max = physics.torque_max
    w_max = params.wheel_speed_max if math.isfinite(params.wheel_speed_max) and params.wheel_speed_max > 0 else 0.0
    ctrl = f'ctrllimited="true" ctrlrange="{-w_max} {w_max}"' if w_max > 0 else 'ctrllimited="false"'
    # Dry friction as a hard constraint (MuJoCo's default is soft: a wheel below its breakaway
    # torque creeps at ~1/10 of its command): the stiffest time constant MuJoCo integrates stably
    # (2 steps) and an impedance near 1 (https://mujoco.readthedocs.io/en/stable/modeling.html#solver-parameters)
    stiction = f'solreffriction="{2 * physics.timestep} 1" solimpfriction="0.99 0.999 0.001"'
    ix, iy, iz = BASE_INERTIA
    wx, wy, wz = WHEEL_INERTIA
    sx, sy, sz = SCAN_POSITION
    wheels = "".join(
        f"""
      <body name="wheel_{side}" pos="0 {sign * half_b} {r}">
        <joint name="wheel_{side}" type="hinge" axis="0 1 0" frictionloss="{friction}" {stiction}
               actuatorfrclimited="true" actuatorfrcrange="{-t_max} {t_max}"/>
        <inertial pos="0 0 0" mass="{WHEEL_MASS}" diaginertia="{wx} {wy} {wz}"/>
        <geom type="sphere" size="{r}" friction="{physics.tire_friction} 0.005 0.0001"/>
      </body>"""
        for side, sign in (("left", 1), ("right", -1))
    )
    ball = 2.0 / 5.0 * CASTER_MASS * CASTER_RADIUS**2  # a solid sphere's inertia [kg m^2]
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
        <joint name="caster_ball" type="ball" frictionloss="{physics.caster_socket_friction}" {stiction}/>
        <inertial pos="0 0 0" mass="{CASTER_MASS}" diaginertia="{ball} {ball} {ball}"/>
        <geom type="sphere" size="{CASTER_RADIUS}" friction="{physics.caster_friction} 0.005 0.0001"/>
      </body>{wheels}
    </body>
  </worldbody>
  <actuator>
    <velocity name="left" joint="wheel_left" kv="{kp}" {ctrl}/>
    <velocity name="right" joint="wheel_right" kv="{kp}" {ctrl}/>
    <motor name="left_integral" joint="wheel_left" ctrllimited="true" ctrlrange="{-t_max} {t_max}"/>
    <motor name="right_integral" joint="wheel_right" ctrllimited="true" ctrlrange="{-t_max} {t_max}"/>
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
    wheels' commands go to their XL430s' velocity PI loops; ``true_pose`` is the body's pose."""

    SETTLE = 0.1  # [s] on the floor before a start: the contacts settle, then the pose is set again

    def __init__(self, params: TurtleBotParams, physics: PhysicsParams, pose: FloatArray) -> None:
        self.params = params
        self.physics = physics
        self.mujoco = load_mujoco()
        self.model = self.mujoco.MjModel.from_xml_string(burger_mjcf(params, physics))
        self.data = self.mujoco.MjData(self.model)
        self.wheel_qpos = [int(self.model.jnt_qposadr[self.model.joint(f"wheel_{s}").id]) for s in ("left", "right")]
        self.wheel_dof = [int(self.model.jnt_dofadr[self.model.joint(f"wheel_{s}").id]) for s in ("left", "right")]
        self.integral_actuators = [int(self.model.actuator(f"{s}_integral").id) for s in ("left", "right")]
        self.kp, self.ki = velocity_gains(physics)
        self._ki_dt = self.ki * physics.timestep
        self._loops = tuple(zip((0, 1), self.wheel_dof, self.integral_actuators, strict=True))  # goal, wheel, I
        self.odometry_steps = max(1, round(physics.odometry_period / physics.timestep))
        self.reset(pose)

    # -- state ------------------------------------------------------------------------------
    def reset(self, pose: FloatArray) -> None:
        """At rest at ``pose`` on the floor; the odometry starts at the same pose."""
        pose = np.asarray(pose, dtype=float)
        self.mujoco.mj_resetData(self.model, self.data)
        self._place(pose)
        self.data.ctrl[:] = 0.0  # goal velocities and the PI's integral terms
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
        """The goal velocities (Goal Velocity(104)); the integral terms carry on from their state."""
        self.data.ctrl[:2] = self.wheel_command

    @property
    def integral_torque(self) -> FloatArray:
        """Each wheel's PI integral term now [N m] (left, right)."""
        return np.array([float(self.data.ctrl[i]) for i in self.integral_actuators])

    def _integrate(self) -> None:
        """One MuJoCo step of the PI's integral term: ``ki * error * dt``, with the e-Manual's
        anti-windup (the integral does not grow while the output is at the torque limit in the
        error's direction) and bounded by the limit itself."""
        t_max, ctrl, qvel = self.physics.torque_max, self.data.ctrl, self.data.qvel
        for goal, dof, actuator in self._loops:
            error = ctrl[goal] - qvel[dof]
            integral = ctrl[actuator]
            output = self.kp * error + integral
            if -t_max < output < t_max or output * error < 0:
                integral = min(max(integral + self._ki_dt * error, -t_max), t_max)
                ctrl[actuator] = integral

    def advance(self, duration: float) -> None:
        """Hold the current command for ``duration`` seconds, the XL430's PI updated every MuJoCo
        step, reading the encoders every ``odometry_period`` (the last read at the end)."""
        steps = round(duration / self.physics.timestep)
        while steps > 0:
            n = min(steps, self.odometry_steps)
            yaw_before = _yaw(self.data.qpos[3:7])
            for _ in range(n):
                self._integrate()
                self.mujoco.mj_step(self.model, self.data)
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


__all__ = ["PhysicsBot", "PhysicsParams", "breakaway_speed", "burger_mjcf", "velocity_gains"]
