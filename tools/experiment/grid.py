"""The paper's grid of starts and the runs planned on it (pure: no processes, no transport).

A start is turned away from the target (``alpha_0 = atan2(y_0, x_0)``, ``pi`` at the centre);
a run is one (start, agent, horizon); its settings are the base settings with those three set.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.config.settings import Settings
from common.math.dynamics import heading_away_from_target

STARTS = ("paper", "held-out")  # the paper's grid, or random starts it never saw


# -- the grid of starts -----------------------------------------------------------------
@dataclass(frozen=True)
class Start:
    index: int
    x: float
    y: float
    alpha: float  # turned away from the target: atan2(y, x), pi at the centre


def _start(index: int, x: float, y: float) -> Start:
    x, y = float(x), float(y)
    return Start(index, x, y, heading_away_from_target(x, y))


def grid_starts(k: int, extent: float) -> list[Start]:
    """The paper's grid: ``k x k`` lattice over ``[-extent, extent]^2``, corners included.

    Row-major from the bottom-left: ``index = row * k + column``. ``k = 1`` is the centre.
    """
    if k < 1 or not (math.isfinite(extent) and extent > 0):
        raise ValueError(f"a grid needs k >= 1 and a positive extent, got k = {k}, extent = {extent}")
    ticks = np.linspace(-extent, extent, k) if k > 1 else np.zeros(1)
    ticks = np.where(np.abs(ticks) < 1e-12 * extent, 0.0, ticks)  # the centre exactly, not 1e-17
    return [_start(row * k + col, x, y) for row, y in enumerate(ticks) for col, x in enumerate(ticks)]


def held_out_starts(k: int, extent: float, seed: int) -> list[Start]:
    """The held-out grid: the square cut into ``k x k`` equal cells, one start drawn
    uniformly inside each cell (stratified jitter, ``numpy.random.default_rng(seed)``).

    Same count and coverage as the paper's grid, but generic positions (off the axes and
    the diagonals, where the paper's lattice has its symmetric starts), so a setting chosen
    on one grid is checked on starts it never saw.
    """
    if k < 1 or not (math.isfinite(extent) and extent > 0):
        raise ValueError(f"a grid needs k >= 1 and a positive extent, got k = {k}, extent = {extent}")
    rng = np.random.default_rng(seed)
    edges = np.linspace(-extent, extent, k + 1)
    starts = []
    for row in range(k):
        for col in range(k):
            x = rng.uniform(edges[col], edges[col + 1])
            y = rng.uniform(edges[row], edges[row + 1])
            starts.append(_start(row * k + col, x, y))
    return starts


def make_starts(kind: str, k: int, extent: float, seed: int) -> list[Start]:
    if kind == "paper":
        return grid_starts(k, extent)
    if kind == "held-out":
        return held_out_starts(k, extent, seed)
    raise ValueError(f"unknown set of starts {kind!r}; choose one of {', '.join(STARTS)}")


# -- the runs ---------------------------------------------------------------------------
@dataclass(frozen=True)
class RunSpec:
    run_id: str
    agent: str
    horizon: int
    start: Start

    @property
    def group(self) -> tuple[str, int]:
        return (self.agent, self.horizon)


def plan_runs(starts: Sequence[Start], agents: Sequence[str], horizons: Sequence[int]) -> list[RunSpec]:
    return [
        RunSpec(f"{agent}-N{horizon}-s{start.index:03d}", agent, horizon, start)
        for agent in agents
        for horizon in horizons
        for start in starts
    ]


def run_settings(base: dict[str, Any], spec: RunSpec) -> Settings:
    """The settings of one run: the resolved base with this run's agent, horizon and start."""
    data = json.loads(json.dumps(base))  # a deep copy of plain JSON data
    data["actor"].update(agent=spec.agent, horizon=spec.horizon)
    data["episode"]["start"] = [spec.start.x, spec.start.y, spec.start.alpha]
    return Settings.model_validate(data)
