"""A localized pose from odometry and a localization source (pure math, no I/O).

REP 105 (https://www.ros.org/reps/rep-0105.html) chains the frames ``map -> odom -> base``: odometry
gives ``odom -> base`` (smooth, drifting), a localization gives ``map -> base`` or ``map -> odom``
(discrete jumps, no drift). The localized pose is the composition

    pose_map = C (+) pose_odom,      C = fix_map (+) inverse(pose_odom at the fix's stamp)

with ``(+)`` the planar pose composition (:func:`compose`). ``C`` is the ``map -> odom`` transform
AMCL and SLAM publish on ``/tf`` (nav2_amcl's ``sendMapToOdomTransform`` computes it the same way
from its pose estimate and the odometry at the scan's stamp). Between sparse fixes the pose moves
with the odometry; a new fix changes ``C``.

**No jump.** A new ``C`` is not applied at once: :class:`CorrectionBlend` moves the applied
correction from its current value to the new one linearly over ``blend_time`` seconds (heading by
the shorter arc), so the actor's state changes by at most ``|dC| * dt / blend_time`` per sample
on top of the robot's own motion. The first fix (nothing published before it) is taken at once.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from common.math.dynamics import Plant
from common.math.frames import Pose2D, from_goal_frame, to_goal_frame, wrap_angle

IDENTITY = Pose2D(0.0, 0.0, 0.0)


def compose(a: Pose2D, b: Pose2D) -> Pose2D:
    """``a (+) b``: pose ``b`` given in frame ``a``, expressed in ``a``'s parent frame."""
    return from_goal_frame(b, a)


def inverse(a: Pose2D) -> Pose2D:
    """``a^-1``, so that ``compose(a, inverse(a))`` is the identity."""
    return to_goal_frame(IDENTITY, a)


def correction(fix: Pose2D, odom: Pose2D) -> Pose2D:
    """The ``map -> odom`` transform of a fix ``map -> base`` taken where odometry read ``odom``."""
    c = compose(fix, inverse(odom))
    return Pose2D(c.x, c.y, wrap_angle(c.theta))


def motion(a: Pose2D, b: Pose2D) -> tuple[float, float]:
    """Distance [m] and absolute heading change [rad] from ``a`` to ``b``."""
    return math.hypot(b.x - a.x, b.y - a.y), abs(wrap_angle(b.theta - a.theta))


def interpolate(a: Pose2D, b: Pose2D, s: float) -> Pose2D:
    """The pose a fraction ``s`` in [0, 1] of the way from ``a`` to ``b`` (heading by the shorter arc)."""
    s = min(max(s, 0.0), 1.0)
    return Pose2D(a.x + s * (b.x - a.x), a.y + s * (b.y - a.y), a.theta + s * wrap_angle(b.theta - a.theta))


class OdomHistory:
    """The last ``size`` odometry poses by stamp: where odometry read at a fix's stamp.

    A fix is stamped when its sensor data was taken (AMCL: the laser scan's stamp), which is
    earlier than its arrival; composing it with the odometry at that stamp, not the newest one,
    keeps the robot's motion during the localization's latency out of the correction."""

    def __init__(self, size: int = 100) -> None:
        self.stamps: deque[int] = deque(maxlen=size)
        self.poses: deque[Pose2D] = deque(maxlen=size)

    def add(self, stamp_ns: int, pose: Pose2D) -> None:
        if self.stamps and stamp_ns <= self.stamps[-1]:  # the robot's clock went back: start over
            self.stamps.clear()
            self.poses.clear()
        self.stamps.append(stamp_ns)
        self.poses.append(pose)

    def latest(self) -> Pose2D | None:
        return self.poses[-1] if self.poses else None

    def at(self, stamp_ns: int) -> Pose2D | None:
        """Odometry at ``stamp_ns``: interpolated between the samples around it, the first or last
        sample outside them; None before any sample."""
        if not self.stamps:
            return None
        stamps = list(self.stamps)
        i = bisect.bisect_left(stamps, stamp_ns)
        if i == 0:
            return self.poses[0]
        if i == len(stamps):
            return self.poses[-1]
        t0, t1 = stamps[i - 1], stamps[i]
        return interpolate(self.poses[i - 1], self.poses[i], (stamp_ns - t0) / (t1 - t0))


class CorrectionBlend:
    """The applied ``map -> odom`` correction, moved to each new one over ``blend_time`` seconds."""

    def __init__(self, blend_time: float) -> None:
        if not (math.isfinite(blend_time) and blend_time >= 0.0):
            raise ValueError(f"blend_time must be finite and >= 0, got {blend_time}")
        self.blend_time = blend_time
        self.start: Pose2D | None = None
        self.target: Pose2D | None = None
        self.t0 = 0.0

    def set(self, target: Pose2D, now: float, snap: bool = False) -> None:
        """A new correction at time ``now``: blended from the applied one, or taken at once with
        ``snap`` (or when there is none yet)."""
        current = None if snap else self.value(now)
        self.start = target if current is None else current
        self.target = target
        self.t0 = now

    def value(self, now: float) -> Pose2D | None:
        if self.start is None or self.target is None:
            return None
        if self.blend_time <= 0.0:
            return self.target
        return interpolate(self.start, self.target, (now - self.t0) / self.blend_time)

    def apply(self, odom: Pose2D, now: float) -> Pose2D | None:
        """The localized pose of odometry pose ``odom`` at ``now``; None before the first fix."""
        c = self.value(now)
        return None if c is None else compose(c, odom)


# -- a localization source for srl's simulated plants ------------------------------------------
# The sources a simulated robot can be given (``srl bench parking --localization``): AMCL-like
# sparse fixes, or motion capture streaming at a rate.
SIM_SOURCES = ("amcl", "mocap")
# Their error, one standard deviation of each fix (x, y [m]; heading [rad]): an assumption of a
# well-mapped room (AMCL) and of a motion-capture lab (docs/turtlebot-parking.md).
SIM_NOISE = {"amcl": (0.01, 0.01), "mocap": (0.001, 0.002)}


@dataclass(frozen=True)
class SimLocalization:
    """A simulated localization source: the true pose with seeded Gaussian noise, by a rule.

    ``amcl``: a fix at start, then whenever the true pose moved ``update`` (distance [m] or
    angle [rad]) since the last fix, as nav2_amcl's ``update_min_d`` 0.25 m / ``update_min_a``
    0.2 rad (turtlebot3_navigation2 ``param/burger.yaml``); ``mocap``: a fix every ``1 / rate``
    seconds. ``blend_time`` is the robot bridge's ``bridge.pose_blend_time``."""

    source: str
    noise: tuple[float, float] = (0.0, 0.0)  # [m, rad] standard deviations of a fix
    update: tuple[float, float] = (0.25, 0.2)  # [m, rad] amcl: a fix after this much motion
    rate: float = 10.0  # [Hz] mocap
    blend_time: float = 1.0  # [s]
    seed: int = 0

    def __post_init__(self) -> None:
        if self.source not in SIM_SOURCES:
            raise ValueError(f"a simulated localization is {' or '.join(SIM_SOURCES)}, got {self.source!r}")
        values = (*self.noise, *self.update, self.rate, self.blend_time)
        if not all(math.isfinite(v) and v >= 0 for v in values) or self.rate <= 0 or min(self.update) <= 0:
            raise ValueError(f"localization noise, update, rate and blend time must be finite, >= 0, got {values}")


class LocalizedPlant:
    """A simulated robot whose reported state is its odometry corrected by a localization, fused
    by the robot bridge's own rule (:func:`correction`, :class:`CorrectionBlend`): the first fix
    taken at once, every later one blended in over ``blend_time``. Fixes come from the true pose
    (:class:`SimLocalization`), stamped when they are taken (no latency, so the odometry at the
    fix's stamp is the current one). A :class:`common.math.dynamics.Plant`; ``corrections`` counts fixes."""

    def __init__(self, plant: Plant, localization: SimLocalization) -> None:
        self.plant, self.localization = plant, localization
        self._reset_clock()

    def _reset_clock(self) -> None:
        self.now = 0.0
        self.rng = np.random.default_rng(self.localization.seed)
        self.blend = CorrectionBlend(self.localization.blend_time)
        self.last_fix_pose: Pose2D | None = None
        self.last_fix_at = 0.0
        self.fixes = 0

    def _due(self, truth: Pose2D) -> bool:
        if self.last_fix_pose is None:
            return True
        if self.localization.source == "amcl":
            distance, angle = motion(self.last_fix_pose, truth)
            return distance >= self.localization.update[0] or angle >= self.localization.update[1]
        return self.now - self.last_fix_at >= 1.0 / self.localization.rate - 1e-9

    def _report(self, odometry: np.ndarray) -> np.ndarray:
        odom = Pose2D(*(float(c) for c in odometry))
        true = self.plant.true_state
        if true is None:
            raise ValueError("a localized plant needs a plant that knows its true pose")
        truth = Pose2D(*(float(c) for c in true))
        if self._due(truth):
            sigma_xy, sigma_theta = self.localization.noise
            noise = self.rng.normal(0.0, 1.0, 3) * np.array([sigma_xy, sigma_xy, sigma_theta])
            fix = Pose2D(truth.x + noise[0], truth.y + noise[1], truth.theta + noise[2])
            self.blend.set(correction(fix, odom), self.now, snap=self.last_fix_pose is None)
            self.last_fix_pose, self.last_fix_at = truth, self.now
            self.fixes += 1
        pose = self.blend.apply(odom, self.now)
        assert pose is not None  # a fix was taken at reset
        return np.array(pose, dtype=float)

    def reset(self, state: np.ndarray) -> np.ndarray:
        self._reset_clock()
        return self._report(self.plant.reset(state))

    def apply(self, action: np.ndarray, duration: float) -> np.ndarray:
        odometry = self.plant.apply(action, duration)
        self.now += duration
        return self._report(odometry)

    @property
    def true_state(self) -> np.ndarray | None:
        return self.plant.true_state

    @property
    def saturated_commands(self) -> int | None:
        return self.plant.saturated_commands
