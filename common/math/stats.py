"""Summary statistics used by every report (one definition of median / p99), a fixed-size
window for long-running services (bounded memory, whatever the run length), and the finite
check of a small vector on a per-tick path."""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

WINDOW = 4096
"""Values a :class:`Window` keeps: 6.8 min at delta = 0.1 s. A 30 s run (300 ticks) is summarized
exactly as from the full list; a run of days keeps 32 KB per statistic."""


def all_finite(values: np.ndarray) -> bool:
    """Every element of the 1-D array ``values`` is finite. For the few numbers of a state or a
    weight vector, checked once per tick: a Python loop over them costs a quarter of
    ``np.all(np.isfinite(values))`` (numpy's per-call overhead dominates below ~50 elements)."""
    return all(map(math.isfinite, values.tolist()))


def summarize(values: Iterable[float], scale: float = 1.0) -> dict[str, float]:
    """``{"median", "p99", "max"}`` of ``values * scale``; NaN for an empty input."""
    data = np.asarray(list(values), dtype=float) * scale
    if data.size == 0:
        return {"median": float("nan"), "p99": float("nan"), "max": float("nan")}
    return {
        "median": float(np.median(data)),
        "p99": float(np.percentile(data, 99)),
        "max": float(np.max(data)),
    }


class Window:
    """The newest ``size`` values in a ring buffer (a fixed numpy array), plus the count and the
    maximum of every value ever added: median and p99 over the window, max over the whole run.
    Non-finite values are not added (a statistic of durations has none that mean anything)."""

    def __init__(self, size: int = WINDOW) -> None:
        if size < 1:
            raise ValueError("a window holds at least one value")
        # written through at once: the window's memory is resident from the start, so a long
        # run's RSS does not creep up as windows fill (a soak would read that as a leak)
        self._data = np.full(size, math.nan)
        self._size = size
        self._next = 0
        self.count = 0
        self.maximum = -math.inf
        self.last = math.nan

    def append(self, value: float) -> None:
        # on every robot's every tick, several times: plain comparisons, no calls but the check
        if not math.isfinite(value):
            return
        value = float(value)
        slot = self._next
        self._data[slot] = value
        slot += 1
        self._next = 0 if slot == self._size else slot
        self.count += 1
        if value > self.maximum:
            self.maximum = value
        self.last = value

    def __len__(self) -> int:
        return min(self.count, self._data.size)

    def values(self) -> np.ndarray:
        """The values in the window, oldest first (a copy)."""
        if self.count < self._data.size:
            return self._data[: self.count].copy()
        return np.concatenate((self._data[self._next :], self._data[: self._next]))

    def summary(self, scale: float = 1.0) -> dict[str, float]:
        """As :func:`summarize` of the window, but ``max`` of the whole run."""
        result = summarize(self.values(), scale)
        if self.count:
            result["max"] = self.maximum * scale
        return result
