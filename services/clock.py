"""Absolute-time ticks on the monotonic clock: no drift, missed deadlines counted."""

from __future__ import annotations

import threading
import time


class Ticker:
    """Tick ``k`` is due at ``t0 + k * period``; sleeping to it never accumulates drift.

    A tick whose due time has already passed when the loop comes to wait for it is a missed
    deadline (the previous iteration overran). Ticks more than a period late are skipped,
    counted as missed too, and the schedule moves on: no burst of catch-up ticks.
    """

    def __init__(self, period: float, stop: threading.Event | None = None) -> None:
        if period <= 0:
            raise ValueError("period must be > 0")
        self.period = period
        self.stop = stop or threading.Event()
        self.start = time.monotonic()
        self.index = 0
        self.missed = 0
        self.last_tick = self.start

    def wait(self) -> float | None:
        """Sleep until the next tick; its actual time, or None when asked to stop."""
        self.index += 1
        due = self.start + self.index * self.period
        now = time.monotonic()
        if now > due:
            skipped = int((now - due) // self.period)
            self.missed += skipped + 1
            self.index += skipped
            due = self.start + self.index * self.period
        if self.stop.wait(max(0.0, due - time.monotonic())):
            return None
        self.last_tick = time.monotonic()
        return self.last_tick
