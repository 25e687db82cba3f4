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
