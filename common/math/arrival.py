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

from common.math.parking import MIN_SPEED


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


def arrival_masks(states: np.ndarray, tolerances: ArrivalTolerances) -> tuple[np.ndarray, np.ndarray]:
    """:func:`arrival_update`'s test for many states ``(G, 3)`` at once: inside the inner
    tolerances (arrive), and inside the outer ones (stay arrived); a non-finite state is in
    neither. The heading error is wrapped exactly as :func:`heading_error` (``math.remainder``):
    ``fmod`` is exact, and so is moving its result by one turn (Sterbenz)."""
    states = np.asarray(states, dtype=float)
    turn = 2.0 * math.pi
    with np.errstate(invalid="ignore"):  # NaN compares False
        wrapped = np.fmod(states[:, 2], turn)
        heading = np.abs(wrapped - turn * (wrapped > math.pi) + turn * (wrapped < -math.pi))
        distance = np.hypot(states[:, 0], states[:, 1])
        finite = np.isfinite(states).all(axis=1)
        inner, outer = (
            (distance <= scale * tolerances.position) & (heading <= scale * tolerances.heading) & finite
            for scale in (1.0, tolerances.hysteresis)
        )
    return inner, outer


class ArrivalRule:
    """The goal checker's state across steps. :meth:`update` every step; :meth:`reset` for a
    new episode (not arrived)."""

    def __init__(
        self,
        tolerances: ArrivalTolerances,
        deadband: WheelDeadband | None = None,
        turn_first: TurnFirst | None = None,
        docking: Docking | None = None,
    ) -> None:
        self.tolerances = tolerances
        self.deadband = deadband  # None or breakaway 0: commands are sent as solved
        self.turn_first = turn_first  # None or threshold 0: the solved command from the first step
        self.docking = docking  # None or radius 0: the solved command however long it hunts
        self.arrived = False
        self.arrivals = 0  # times it went from moving to arrived (a count that grows = dithering)
        self.turning: bool | None = None  # None: not decided yet for this goal; True: turning first
        self.turn_first_steps = 0  # commands replaced by the in-place turn
        self.docked = False  # the docking manoeuvre drives until arrival
        self.docking_steps = 0  # commands replaced by the docking manoeuvre
        self._heading_sign = 0  # the sign of the last v sent beyond the docking's speed floor ...
        self._reversals = 0  # ... and its changes since the robot came within the docking radius

    def reset(self) -> None:
        self.arrived = False
        self.turning = None
        self._forget_approach()

    def _forget_approach(self) -> None:
        self.docked = False
        self._heading_sign, self._reversals = 0, 0

    def update(self, state: np.ndarray) -> bool:
        arrived = arrival_update(self.arrived, state, self.tolerances)
        if arrived:
            self._arrive()
        self.arrived = arrived
        return arrived

    def _arrive(self) -> None:
        """The robot is (still) arrived: counted when it was not; a resumed approach starts with
        the actor again."""
        if not self.arrived:
            self.arrivals += 1
        self.arrived = True
        self._forget_approach()

    def last_word(self, action: np.ndarray, state: np.ndarray) -> np.ndarray:
        """The command to send for the solved ``action`` at ``state``: the in-place turn while the
        turn-first phase lasts (:meth:`turn_command`), the docking manoeuvre once the approach
        shuffles (:meth:`dock_command`), then through :func:`deadband_action`; a command the
        deadband makes zero inside the outer tolerances leaves the robot arrived."""
        turn = self.turn_command(state)
        if turn is not None:
            self.turn_first_steps += 1
            action = turn
        else:
            dock = self.dock_command(state)
            if dock is not None:
                self.docking_steps += 1
                action = dock
        if self.deadband is not None:
            solved, action = action, deadband_action(action, state, self.deadband, self.tolerances)
            # made zero inside the outer tolerances (a command that was not zero is now zero): as
            # parked as it can be told, so arrived (held at zero without a solve until it leaves
            # them), not solving a command it cannot follow
            if solved.any() and not action.any():
                self._arrive()
        self._count_reversal(action, state)
        return action

    def turn_command(self, state: np.ndarray) -> np.ndarray | None:
        """The turn-first phase of this goal (:class:`TurnFirst`): decided at the first command
        after :meth:`reset`, it turns in place until the line of travel is within the heading
        tolerance of the :func:`approach_heading` and then ends for good; None when it is not on."""
        rule = self.turn_first
        if rule is None or rule.threshold <= 0.0 or self.turning is False:
            return None
        x, y, alpha = (float(c) for c in state)
        error = approach_heading(x, y) - alpha  # unwrapped: the turn ends where the actor measures 0
        if self.turning is None:  # the first command for this goal decides
            self.turning = math.hypot(x, y) > rule.min_distance and line_of_travel_error(x, y, alpha) > rule.threshold
        elif abs(error) <= rule.tolerance:
            self.turning = False
        if not self.turning:
            return None
        return np.array([0.0, rule.turn_rate(error)])

    def _count_reversal(self, sent: np.ndarray, state: np.ndarray) -> None:
        """Count the reversals of the sent ``v`` within the docking radius (from 0 outside it)."""
        rule = self.docking
        if rule is None or self.docked:
            return
        if math.hypot(float(state[0]), float(state[1])) > rule.radius:
            self._heading_sign, self._reversals = 0, 0
            return
        v = float(sent[0])
        if abs(v) >= rule.speed_floor:
            sign = 1 if v > 0 else -1
            self._reversals += int(self._heading_sign != 0 and sign != self._heading_sign)
            self._heading_sign = sign

    def dock_command(self, state: np.ndarray) -> np.ndarray | None:
        """The docking manoeuvre (:class:`Docking`) once the commands sent within its radius have
        reversed their direction of travel ``reversals`` times, until arrival; None while the
        actor's command stands."""
        rule = self.docking
        if rule is None or rule.radius <= 0.0:
            return None
        if not self.docked:
            within = math.hypot(float(state[0]), float(state[1])) <= rule.radius
            self.docked = within and self._reversals >= rule.reversals
            if not self.docked:
                return None
        return dock_action(state, rule, self.tolerances)


def line_of_travel_error(x: float, y: float, alpha: float) -> float:
    """The smallest turn [rad] that puts the robot's line of travel (ahead or back: a differential
    drive runs both ways alike) through the target from ``(x, y)``, in [0, pi/2]."""
    error = abs(math.remainder(math.atan2(-y, -x) - alpha, 2.0 * math.pi))  # to face the target
    return min(error, math.pi - error)


def approach_heading(x: float, y: float) -> float:
    """The heading [rad] in [-pi/2, pi/2] whose line of travel runs from ``(x, y)`` through the
    target: ahead from x < 0, backing from x > 0. Of the headings along that line it is the one
    nearest the target's heading, 0, as the actor sees it: the running cost weighs the heading
    as it is, unwrapped, all the way (the paper's stage cost, docs/concepts.md), so the actor
    keeps to it where it would turn away from any other."""
    heading = math.atan2(-y, -x)
    if heading > math.pi / 2:
        heading -= math.pi
    elif heading < -math.pi / 2:
        heading += math.pi
    return heading


@dataclass(frozen=True)
class TurnFirst:
    """Turn in place first when a goal starts far off the line of travel, as Nav2's Rotation Shim
    Controller does before it hands a new path to its primary controller
    (https://docs.nav2.org/configuration/packages/configuring-rotation-shim-controller.html,
    ``angular_dist_threshold``): a short-horizon actor facing across the target drives on along
    its heading first and takes the long way round (docs/turtlebot-parking.md).

    Engaged at a goal's first command when the robot is farther than ``min_distance`` from the
    target and its line of travel (ahead or back) is more than ``threshold`` off the bearing to
    it (:func:`line_of_travel_error`); it then commands ``(0, omega)`` until its heading is within
    ``tolerance`` of the :func:`approach_heading`, turning through the actor's 0 and not round
    the other way (up to 3 pi / 2 from a heading in [-pi, pi]), ``omega`` the remaining error
    over ``settle`` sampling intervals, capped at ``rate``."""

    threshold: float  # [rad] 0 = off
    tolerance: float  # [rad]
    rate: float  # [rad/s] the top turning rate in place
    sampling_time: float  # [s]
    min_distance: float = 0.0  # [m]
    settle: float = 2.0  # sampling intervals to close the remaining error (a proportional turn)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.threshold) and 0.0 <= self.threshold <= math.pi / 2):
            raise ValueError(f"turn-first threshold must be in [0, pi/2] rad, got {self.threshold}")
        for name, value in (("tolerance", self.tolerance), ("rate", self.rate), ("sampling time", self.sampling_time)):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"turn-first {name} must be a positive number, got {value}")
        if not (math.isfinite(self.min_distance) and self.min_distance >= 0 and self.settle >= 1):
            raise ValueError(f"turn-first distance >= 0 and settle >= 1, got {self.min_distance}, {self.settle}")

    def turn_rate(self, error: float) -> float:
        """The in-place turning rate [rad/s] for the remaining ``error``."""
        return float(np.clip(error / (self.settle * self.sampling_time), -self.rate, self.rate))


@dataclass(frozen=True)
class Docking:
    """The last centimetres when the actor shuffles: within ``radius`` of the target, once the
    commands sent have reversed their direction of travel ``reversals`` times (ROS move_base's
    oscillation recovery, ``oscillation_timeout`` / ``oscillation_distance``:
    https://wiki.ros.org/move_base), the approach is finished by rotate, drive straight, rotate
    (:func:`dock_action`) until the arrival rule holds the robot. Near the target a unicycle
    cannot move sideways (Brockett): the short-horizon actor closes a sideways offset of a few
    centimetres by shuffling back and forth, which can last tens of seconds (docs/turtlebot-parking.md,
    "Parking"); a straight leg along the line through the target closes it at once."""

    radius: float  # [m] 0 = off
    reversals: int  # changes of the sign of v that make a shuffle
    speed: float  # [m/s] the straight leg's top speed
    rate: float  # [rad/s] the top turning rate in place
    sampling_time: float  # [s]
    half_track: float = 0.0  # [m] half the wheel separation: the straight leg's |v| + |omega| x this <= speed
    speed_floor: float = MIN_SPEED  # [m/s] a slower v sent has no direction (the parking metrics' floor)
    settle: float = 3.0  # sampling intervals to close the remaining error (proportional legs)

    def __post_init__(self) -> None:
        values = (self.radius, self.half_track, self.speed, self.rate, self.sampling_time, self.speed_floor)
        if not all(math.isfinite(v) for v in values) or min(values[:2]) < 0 or min(values[2:]) <= 0:
            raise ValueError(f"docking radius and track must be >= 0, its speeds and times > 0, got {values}")
        if self.reversals < 1:
            raise ValueError(f"docking reversals must be >= 1, got {self.reversals}")
        if not self.settle >= 1:
            raise ValueError(f"docking settle must be >= 1 sampling interval, got {self.settle}")


def dock_action(state: np.ndarray, docking: Docking, tolerances: ArrivalTolerances) -> np.ndarray:
    """One command of the docking manoeuvre at ``state`` (goal frame): inside the position
    tolerance, turn in place to the target's heading; else, while the line of travel (ahead or
    back, the nearer) is off the target by more than the heading tolerance and driving on would
    miss it by more than half the position tolerance, turn in place towards it; else drive to
    the target along that line, steering onto it. Each leg proportional (its error over
    ``settle`` sampling intervals), capped at the turning rate and, with the steering, at the top
    speed of the faster wheel (``half_track``)."""
    x, y, alpha = (float(c) for c in state)
    distance = math.hypot(x, y)
    horizon = docking.settle * docking.sampling_time

    def turn(error: float) -> float:
        return float(np.clip(error / horizon, -docking.rate, docking.rate))

    if distance <= tolerances.position:
        return np.array([0.0, turn(-heading_error(alpha))])
    facing = math.remainder(math.atan2(-y, -x) - alpha, 2.0 * math.pi)  # the turn to face the target
    ahead = abs(facing) <= math.pi / 2
    error = facing if ahead else math.remainder(facing + math.pi, 2.0 * math.pi)
    if abs(error) > tolerances.heading and distance * abs(math.sin(error)) > tolerances.position / 2:
        return np.array([0.0, turn(error)])
    omega = turn(error)
    speed = max(0.0, min(docking.speed - abs(omega) * docking.half_track, distance / horizon))
    return np.array([speed if ahead else -speed, omega])


@dataclass(frozen=True)
class WheelDeadband:
    """The wheels' breakaway: a wheel at rest does not start for a command below ``breakaway``
    [rad/s] held one sampling interval (for the physics plant :func:`common.math.physics.breakaway_speed`
    with the hold = delta; docs/turtlebot-parking.md "The deadband at the actor's output")."""

    breakaway: float  # [rad/s] per wheel; 0 = off
    wheel_radius: float  # [m]
    wheel_separation: float  # [m]
    # [m/s, rad/s] the robot truncates each component of a command towards zero to a multiple of
    # this (turtlebot3_node: int32(v * 100), 0.01; common/math/turtlebot.py firmware_velocity); 0 = none
    resolution: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.breakaway) and self.breakaway >= 0):
            raise ValueError(f"wheel breakaway speed must be a number >= 0 [rad/s], got {self.breakaway}")
        if not (math.isfinite(self.resolution) and self.resolution >= 0):
            raise ValueError(f"command resolution must be a number >= 0, got {self.resolution}")
        if not (self.wheel_radius > 0 and self.wheel_separation > 0):
            raise ValueError(
                f"wheel radius and separation must be > 0, got {self.wheel_radius}, {self.wheel_separation}"
            )

    def wheels(self, action: np.ndarray) -> tuple[float, float]:
        """The wheel speeds [rad/s] (left, right) of ``(v, omega)`` (turtlebot3_node's kinematics)."""
        v, omega = float(action[0]), float(action[1])
        half = omega * self.wheel_separation / 2.0
        return (v - half) / self.wheel_radius, (v + half) / self.wheel_radius

    def applied(self, action: np.ndarray) -> np.ndarray:
        """``action`` as the robot applies it: each component truncated towards zero to a
        multiple of ``resolution`` (as it is with 0)."""
        if self.resolution <= 0.0:
            return np.asarray(action, dtype=float)
        return np.array([math.trunc(float(c) / self.resolution) * self.resolution for c in action])

    def peak(self, action: np.ndarray) -> float:
        """The faster wheel's speed [rad/s] of ``action`` as the robot applies it."""
        return max(abs(w) for w in self.wheels(self.applied(action)))


def deadband_action(
    action: np.ndarray, state: np.ndarray, deadband: WheelDeadband, tolerances: ArrivalTolerances
) -> np.ndarray:
    """The command actually sent: one that cannot move a wheel is never the last word.

    A command (not both components exactly zero) whose wheels, as the robot applies it
    (:meth:`WheelDeadband.applied`: a component below the resolution is zero there), all run below
    the breakaway speed is replaced by exactly zero when the robot is inside the outer arrival
    tolerances (where the arrival rule would hold it anyway: it is as parked as it can be told),
    else scaled up in its own direction (the same curvature, up to the resolution) until its
    faster wheel, as applied, runs at the breakaway speed. Any other command, and every command
    with ``breakaway`` 0, is returned as it is."""
    if deadband.breakaway <= 0.0:
        return action
    action = np.asarray(action, dtype=float)
    peak = max(abs(w) for w in deadband.wheels(action))
    if peak == 0.0 or deadband.peak(action) >= deadband.breakaway:
        return action
    x, y, alpha = (float(c) for c in state)
    outer = tolerances.hysteresis
    if math.hypot(x, y) <= outer * tolerances.position and abs(heading_error(alpha)) <= outer * tolerances.heading:
        return np.zeros_like(action)
    scale = deadband.breakaway / peak
    if deadband.resolution > 0.0:  # the larger component at least one step (2 % over: rounding)
        scale = max(scale, 1.02 * deadband.resolution / float(np.max(np.abs(action))))
    raised: np.ndarray = action * scale
    for _ in range(32):  # the smaller component may still round to zero: more until the wheel turns
        if deadband.peak(raised) >= deadband.breakaway * (1.0 - 1e-9):  # at it, up to rounding
            break
        raised = raised * 1.25
    return raised
