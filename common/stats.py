"""Summary statistics used by every report (one definition of median / p99)."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np


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
