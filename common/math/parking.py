"""Did the robot park, and does it rest there? Pure functions over a run's states
and actions, shared by ``srl bench parking`` and the experiment.

"Parked" (within a distance of the target) is not enough: near the target a short-horizon
controller can shuffle back and forth (a limit cycle, or chatter: ``v`` flipping sign every
step), which the ideal unicycle forgives and motors with lag and deadband do not. Over the
last ``window`` seconds a run is **at rest** when its position spans at most ``span_m`` and
``v`` changes sign at most ``max_sign_changes`` times (only speeds ``|v| >= min_speed`` count:
a robot stopped at 0.001 m/s is not chattering).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

# what a robot at the target must meet (docs/concepts.md, "Parked, at rest, at target")
FINAL_DISTANCE_M = 0.05  # true final distance to the target [m]
SPAN_M = 0.05  # span of the true position over the last window [m]
MAX_SIGN_CHANGES = 5  # sign changes of v over the last window
WINDOW_S = 10.0  # [s]
MIN_SPEED = 0.01  # [m/s] slower commands are not counted as a sign


def last_window(rows: ArrayLike, seconds: float, sampling_time: float) -> np.ndarray:
    """The last ``round(seconds / delta)`` rows (all of them if there are fewer)."""
    array = np.asarray(rows, dtype=float)
    count = max(1, round(seconds / sampling_time))
    return array[-count:]


def position_span(positions: ArrayLike) -> float:
    """The diameter of a set of positions: the largest distance between two of them [m]."""
    xy = np.asarray(positions, dtype=float)[:, :2]
    if len(xy) < 2:
        return 0.0
    differences = xy[:, None, :] - xy[None, :, :]
    return float(np.sqrt(np.max(np.sum(differences**2, axis=-1))))


def sign_changes(speeds: ArrayLike, min_speed: float = MIN_SPEED) -> int:
    """How often ``v`` changes sign, counting only ``|v| >= min_speed`` (smaller ones are skipped)."""
    values = np.asarray(speeds, dtype=float)
    signs = np.sign(values[np.abs(values) >= min_speed])
    return int(np.count_nonzero(signs[1:] != signs[:-1]))


def distance_to_target(state: ArrayLike) -> float:
    """Distance of a goal-frame state's position from the target at the origin [m]."""
    s = np.asarray(state, dtype=float)
    return float(math.hypot(s[0], s[1]))


@dataclass(frozen=True)
class Parking:
    """The parking metrics of one run (positions: true states where known)."""

    final_distance: float  # [m]
    span: float  # [m] over the last window
    sign_changes: int  # of v over the last window
    median_speed: float  # median |v| over the last window [m/s]: a shuffle at speed or a buzz

    @property
    def at_rest(self) -> bool:
        return self.span <= SPAN_M and self.sign_changes <= MAX_SIGN_CHANGES

    @property
    def at_target(self) -> bool:
        """Within ``FINAL_DISTANCE_M`` of the target and at rest: "at target" of docs/concepts.md
        ("parked" is the looser 0.25 m of the experiment's tables)."""
        return self.final_distance <= FINAL_DISTANCE_M and self.at_rest


def parking(states: ArrayLike, actions: ArrayLike, sampling_time: float, window: float = WINDOW_S) -> Parking:
    """The metrics of a run: ``states`` has one row more than ``actions`` (the start)."""
    state_rows = np.asarray(states, dtype=float)
    action_rows = np.asarray(actions, dtype=float).reshape(-1, 2)
    speeds = last_window(action_rows[:, 0], window, sampling_time) if len(action_rows) else np.zeros(0)
    return Parking(
        final_distance=distance_to_target(state_rows[-1]),
        # the window's positions: the states at its steps and the one after the last
        span=position_span(last_window(state_rows, window + sampling_time, sampling_time)),
        sign_changes=sign_changes(speeds),
        median_speed=float(np.median(np.abs(speeds))) if len(speeds) else 0.0,
    )
