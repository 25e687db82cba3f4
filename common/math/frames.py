"""Planar frames and command limits for a real robot (pure math, no I/O).

The robot reports its pose in its own odometry frame (``odom``); the actor works in the goal
frame (docs/concepts.md: the goal pose is the origin with heading 0). A goal pose
``g = (g_x, g_y, g_theta)`` given in the odom frame fixes the transform:

    x     =  cos(g_theta) (p_x - g_x) + sin(g_theta) (p_y - g_y)
    y     = -sin(g_theta) (p_x - g_x) + cos(g_theta) (p_y - g_y)
    alpha =  p_theta - g_theta

and its inverse (:func:`from_goal_frame`). The action ``(v, omega)`` is a body-frame velocity,
the same in every frame, so commands need no transform.
"""

from __future__ import annotations

import math
from typing import NamedTuple


class Pose2D(NamedTuple):
    x: float
    y: float
    theta: float


def yaw_from_quaternion(x: float, y: float, z: float, w: float) -> float:
    """Yaw (rotation about z) of a quaternion, in ``(-pi, pi]``.

    ``atan2(2 (w z + x y), w^2 + x^2 - y^2 - z^2)``: the ZYX Euler yaw. Written with the
    squared norm terms instead of ``1 - 2 (y^2 + z^2)`` so that a quaternion that is not
    exactly unit length (float32 odometry, rounding) gives the same yaw. Raises
    ``ValueError`` for a non-finite or (near-)zero quaternion, which has no orientation.
    """
    if not all(math.isfinite(c) for c in (x, y, z, w)):
        raise ValueError(f"quaternion ({x}, {y}, {z}, {w}) is not finite")
    norm2 = x * x + y * y + z * z + w * w
    if norm2 < 1e-12:
        raise ValueError("quaternion of zero length has no orientation")
    return math.atan2(2.0 * (w * z + x * y), w * w + x * x - y * y - z * z)


def quaternion_from_yaw(theta: float) -> tuple[float, float, float, float]:
    """``(x, y, z, w)`` of a rotation by ``theta`` about z."""
    return (0.0, 0.0, math.sin(theta / 2.0), math.cos(theta / 2.0))


def wrap_angle(angle: float) -> float:
    """The representative of ``angle`` in ``[-pi, pi)``."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def to_goal_frame(pose: Pose2D, goal: Pose2D) -> Pose2D:
    """A pose given in the odom frame, expressed in the goal frame (heading not wrapped)."""
    dx, dy = pose.x - goal.x, pose.y - goal.y
    c, s = math.cos(goal.theta), math.sin(goal.theta)
    return Pose2D(c * dx + s * dy, -s * dx + c * dy, pose.theta - goal.theta)


def from_goal_frame(state: Pose2D, goal: Pose2D) -> Pose2D:
    """Inverse of :func:`to_goal_frame`: a goal-frame state expressed in the odom frame."""
    c, s = math.cos(goal.theta), math.sin(goal.theta)
    return Pose2D(goal.x + c * state.x - s * state.y, goal.y + s * state.x + c * state.y, state.theta + goal.theta)


def clamp_command(v: float, omega: float, v_max: float, omega_max: float) -> tuple[float, float]:
    """Clip ``(v, omega)`` to ``|v| <= v_max``, ``|omega| <= omega_max``.

    A non-finite component is not a command: ``ValueError`` (callers answer it with zero).
    """
    if not (math.isfinite(v) and math.isfinite(omega)):
        raise ValueError(f"command ({v}, {omega}) is not finite")
    return (min(max(v, -v_max), v_max), min(max(omega, -omega_max), omega_max))
