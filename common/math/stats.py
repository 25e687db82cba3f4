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
        return _ring_values(self._data, self.count, self._next)

    def summary(self, scale: float = 1.0) -> dict[str, float]:
        """As :func:`summarize` of the window, but ``max`` of the whole run."""
        return _window_summary(self.values(), self.count, self.maximum, scale)


def _ring_values(data: np.ndarray, count: int, slot: int) -> np.ndarray:
    """A ring's values, oldest first (a copy): ``count`` written, the next at ``slot``."""
    if count < data.size:
        return data[:count].copy()
    return np.concatenate((data[slot:], data[:slot]))


def _window_summary(values: np.ndarray, count: int, maximum: float, scale: float) -> dict[str, float]:
    result = summarize(values, scale)
    if count:
        result["max"] = maximum * scale
    return result


class WindowRows:
    """``count`` windows (:class:`Window`) as the rows of one block, so that a host of many
    robots appends one value to each of many rows as one array operation
    (:meth:`append_rows`). :meth:`row` is one row with a :class:`Window`'s interface; a value
    appended either way is the same value in the same row, and a row's summary is a
    :class:`Window`'s of the same values, bit for bit. A row's next slot is its count modulo the
    size, and its last value the one before it: a value costs two array reads and three writes."""

    def __init__(self, count: int, size: int = WINDOW) -> None:
        if size < 1 or count < 1:
            raise ValueError("window rows hold at least one row of one value")
        self.data = np.full((count, size), math.nan)  # written through at once, as a Window's
        self.size = size
        self.count = np.zeros(count, dtype=np.int64)
        self.maximum = np.full(count, -math.inf)

    def row(self, i: int) -> WindowRow:
        return WindowRow(self, i)

    def append(self, i: int, value: float) -> None:
        """One value to row ``i`` (skipped when not finite), as :meth:`Window.append`."""
        if not math.isfinite(value):
            return
        value = float(value)
        count = self.count.item(i)
        self.data[i, count % self.size] = value
        self.count[i] = count + 1
        if value > self.maximum.item(i):
            self.maximum[i] = value

    def append_rows(self, rows: np.ndarray, values: np.ndarray) -> None:
        """``values[j]`` to row ``rows[j]``, the rows distinct; the values that are not finite are
        skipped, as :meth:`append` skips them."""
        finite = np.isfinite(values)
        if not finite.all():
            rows, values = rows[finite], values[finite]
        counts = self.count[rows]
        self.data[rows, counts % self.size] = values
        self.count[rows] = counts + 1
        self.maximum[rows] = np.maximum(self.maximum[rows], values)


class WindowRow:
    """Row ``i`` of a :class:`WindowRows`, read and appended as a :class:`Window`."""

    def __init__(self, rows: WindowRows, i: int) -> None:
        self.rows, self.i = rows, i

    def append(self, value: float) -> None:
        self.rows.append(self.i, value)

    @property
    def count(self) -> int:
        return int(self.rows.count[self.i])

    @property
    def maximum(self) -> float:
        return float(self.rows.maximum[self.i])

    @property
    def last(self) -> float:
        """The newest value (NaN: none yet)."""
        count = self.count
        return self.rows.data.item(self.i, (count - 1) % self.rows.size) if count else math.nan

    def __len__(self) -> int:
        return min(self.count, self.rows.size)

    def values(self) -> np.ndarray:
        """The values in the row's window, oldest first (a copy)."""
        count = self.count
        return _ring_values(self.rows.data[self.i], count, count % self.rows.size)

    def summary(self, scale: float = 1.0) -> dict[str, float]:
        """As :meth:`Window.summary`."""
        return _window_summary(self.values(), self.count, self.maximum, scale)
