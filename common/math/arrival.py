"""The arrival rule: a goal checker with hysteresis (like Nav2's ``SimpleGoalChecker``).

The paper's actors never stop: near the target a short-horizon optimum can be a parking
shuffle (no smooth time-invariant feedback brings a unicycle to rest at a point, Brockett),
and the learned critics make it a full-speed period-2 limit cycle (docs/experiment.md). A
running robot stops instead once it is close enough: inside the inner tolerances (distance to
the target <= ``position`` AND wrapped heading error <= ``heading``) the actor commands exactly
zero and says "arrived"; it resumes only when the robot leaves the outer tolerances
(``hysteresis`` times the inner ones), so noise on the measured pose near a boundary never
toggles it back and forth.

Pure: the state is one boolean, kept by :class:`ArrivalRule` and updated by
:func:`arrival_update` (state in, state out). The state is in the goal frame (the target is
the origin with heading 0), as everywhere in the actor.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ArrivalTolerances:
    """Inner tolerances and the hysteresis factor (outer = ``hysteresis`` x inner)."""

    position: float  # [m] distance to the target
    heading: float  # [rad] |heading error|, wrapped to [-pi, pi]
    hysteresis: float  # >= 1: leave "arrived" only beyond hysteresis x (position, heading)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.position) and self.position > 0):
            raise ValueError(f"arrival position tolerance must be a positive number [m], got {self.position}")
        if not (math.isfinite(self.heading) and 0 < self.heading <= math.pi):
            raise ValueError(f"arrival heading tolerance must be in (0, pi] rad, got {self.heading}")
        if not (math.isfinite(self.hysteresis) and self.hysteresis >= 1):
            raise ValueError(f"arrival hysteresis must be a number >= 1, got {self.hysteresis}")


def heading_error(alpha: float) -> float:
    """The heading relative to the target's (0), wrapped to [-pi, pi] (the actor's is unwrapped)."""
    return math.remainder(alpha, 2.0 * math.pi)


def arrival_update(arrived: bool, state: np.ndarray, tolerances: ArrivalTolerances) -> bool:
    """The next "arrived" flag from the current one and the measured state ``(x, y, alpha)``.

    Not arrived: arrive when inside both inner tolerances. Arrived: stay until outside
    either outer tolerance. A non-finite state is never "arrived" (the actor refuses it)."""
    x, y, alpha = (float(c) for c in state)
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(alpha)):
        return False
    distance, heading = math.hypot(x, y), abs(heading_error(alpha))
    scale = tolerances.hysteresis if arrived else 1.0
    return distance <= scale * tolerances.position and heading <= scale * tolerances.heading


class ArrivalRule:
    """The goal checker's state across steps. :meth:`update` every step; :meth:`reset` for a
    new episode (not arrived)."""

    def __init__(self, tolerances: ArrivalTolerances, deadband: WheelDeadband | None = None) -> None:
        self.tolerances = tolerances
        self.deadband = deadband  # None or breakaway 0: commands are sent as solved
        self.arrived = False
        self.arrivals = 0  # times it went from moving to arrived (a count that grows = dithering)

    def reset(self) -> None:
        self.arrived = False

    def update(self, state: np.ndarray) -> bool:
        arrived = arrival_update(self.arrived, state, self.tolerances)
        if arrived and not self.arrived:
            self.arrivals += 1
        self.arrived = arrived
        return arrived

    def last_word(self, action: np.ndarray, state: np.ndarray) -> np.ndarray:
        """The command to send for the solved ``action`` at ``state`` (:func:`deadband_action`)."""
        if self.deadband is None:
            return action
        return deadband_action(action, state, self.deadband, self.tolerances)


@dataclass(frozen=True)
class WheelDeadband:
    """The wheels' breakaway: a wheel at rest does not start for a command below ``breakaway``
    [rad/s] held one sampling interval (for the physics plant :func:`common.math.physics.breakaway_speed`
    with the hold = delta; docs/turtlebot.md "The deadband at the actor's output")."""

    breakaway: float  # [rad/s] per wheel; 0 = off
    wheel_radius: float  # [m]
    wheel_separation: float  # [m]

    def __post_init__(self) -> None:
        if not (math.isfinite(self.breakaway) and self.breakaway >= 0):
            raise ValueError(f"wheel breakaway speed must be a number >= 0 [rad/s], got {self.breakaway}")
        if not (self.wheel_radius > 0 and self.wheel_separation > 0):
            raise ValueError(
                f"wheel radius and separation must be > 0, got {self.wheel_radius}, {self.wheel_separation}"
            )

    def wheels(self, action: np.ndarray) -> tuple[float, float]:
        """The wheel speeds [rad/s] (left, right) of ``(v, omega)`` (turtlebot3_node's kinematics)."""
        v, omega = float(action[0]), float(action[1])
        half = omega * self.wheel_separation / 2.0
        return (v - half) / self.wheel_radius, (v + half) / self.wheel_radius


def deadband_action(
    action: np.ndarray, state: np.ndarray, deadband: WheelDeadband, tolerances: ArrivalTolerances
) -> np.ndarray:
    """The command actually sent: one that cannot move a wheel is never the last word.

    A command whose wheels are all below the breakaway speed (and not both exactly zero) is
    replaced by exactly zero when the robot is inside the outer arrival tolerances (where the
    arrival rule would hold it anyway: it is as parked as it can be told), else scaled up in its
    own direction (the same curvature) until its faster wheel runs at the breakaway speed. Any
    other command, and every command with ``breakaway`` 0, is returned as it is."""
    if deadband.breakaway <= 0.0:
        return action
    peak = max(abs(w) for w in deadband.wheels(action))
    if peak == 0.0 or peak >= deadband.breakaway:
        return action
    x, y, alpha = (float(c) for c in state)
    outer = tolerances.hysteresis
    if math.hypot(x, y) <= outer * tolerances.position and abs(heading_error(alpha)) <= outer * tolerances.heading:
        return np.zeros_like(action)
    raised: np.ndarray = np.asarray(action, dtype=float) * (deadband.breakaway / peak)
    return raised
