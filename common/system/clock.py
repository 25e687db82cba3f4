"""Absolute-time ticks on the monotonic clock: no drift, missed deadlines counted."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

LATE_FRACTION = 0.25
"""A tick that wakes up more than this fraction of the period after its due time is a missed
deadline (25 ms at delta = 0.1 s): its action then
holds for less than three quarters of the interval the plan assumed, although the previous
iteration did not overrun (a preempted or oversleeping thread). Smaller delays are jitter (the
loop's jitter statistics show them): on a loaded 2-vCPU machine 10-20 ms wake-ups happen."""


class Ticker:
    """Tick ``k`` is due at ``t0 + k * period``; sleeping to it never accumulates drift.

    A tick is a missed deadline when its due time has already passed when the loop comes to
    wait for it (the previous iteration overran), or when the wake-up comes more than
    ``late_fraction * period`` after the due time (``late`` counts these). Ticks more than a
    period late are skipped, counted as missed too, and the schedule moves on: no burst of
    catch-up ticks.

    ``clock`` and ``sleep`` (``sleep(seconds) -> True`` to stop) are injectable for tests; by
    default the monotonic clock and ``stop.wait``.
    """

    def __init__(
        self,
        period: float,
        stop: threading.Event | None = None,
        *,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], bool] | None = None,
        late_fraction: float = LATE_FRACTION,
    ) -> None:
        if period <= 0:
            raise ValueError("period must be > 0")
        if not 0 < late_fraction <= 1:
            raise ValueError("late_fraction must be in (0, 1]")
        self.period = period
        self.stop = stop or threading.Event()
        self.clock = clock
        self.sleep = sleep or self.stop.wait
        self.late_threshold = late_fraction * period
        self.start = clock()
        self.index = 0
        self.missed = 0
        self.late = 0
        self.last_tick = self.start

    def wait(self) -> float | None:
        """Sleep until the next tick; its actual time, or None when asked to stop."""
        self.index += 1
        due = self.start + self.index * self.period
        now = self.clock()
        if now > due:
            skipped = int((now - due) // self.period)
            self.missed += skipped + 1
            self.index += skipped
            due = self.start + self.index * self.period
            overran = True
        else:
            overran = False
        if self.sleep(max(0.0, due - self.clock())):
            return None
        self.last_tick = self.clock()
        if not overran and self.last_tick - due > self.late_threshold:
            self.missed += 1  # woke up late: this tick's deadline is missed all the same
            self.late += 1
        return self.last_tick


STATE_SYNC_MARGIN_S = 0.005
"""A plant host that learned a robot's tick phase from its actions (services/plant_sim/host.py
``StateSync``) publishes the robot's state from one state period and this margin before the tick
it estimates, until the action comes. The estimate is late by the action's least delay, so the
margin keeps the last state before the real tick in the window; the window is then longer than a
state period, and a tick that falls within about the margin after a state tick gets two states a
period (:func:`tick_phase_offset` keeps an actor host's ticks out of there)."""


def tick_phase_offset(period: float, phases: int, state_period: float, margin: float = STATE_SYNC_MARGIN_S) -> float:
    """Where in a plant's state period [0, ``state_period``), after a state arrived, an actor
    host of ``phases`` tick phases ``period / phases`` apart best puts its first: as far as can
    be, for its nearest phase, from ``margin / 2`` after a state's arrival, the middle of the
    stretch where a tick gets two states a period (:data:`STATE_SYNC_MARGIN_S`). Phases one state
    period apart (the default: 5 of 0.1 s at 50 Hz) all land mid-way, ``(state_period + margin) / 2``.
    ``state_period`` 0 or not below ``period`` (states no faster than ticks): 0."""
    if not 0.0 < state_period < period or phases < 1:
        return 0.0
    spacing = period / phases
    centre = margin / 2.0
    candidates = 200

    def nearest(offset: float) -> float:
        gaps = [((offset + g * spacing - centre) % state_period) for g in range(phases)]
        return min(min(gap, state_period - gap) for gap in gaps)

    offsets = [i * state_period / candidates for i in range(candidates)]
    return max(offsets, key=lambda o: (round(nearest(o), 9), -o))


def aligned_start(now: float, newest_state: float | None, offset: float, state_period: float) -> float:
    """The first time at or after ``now`` that is ``offset`` after a state arrival on the grid of
    ``newest_state`` (its arrival time) and ``state_period``; ``now`` when no state has come."""
    if newest_state is None or state_period <= 0.0:
        return now
    first = newest_state + offset
    return first + -(-(now - first) // state_period) * state_period  # ceil: the first at or after now
