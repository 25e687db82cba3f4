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
