"""The paper's grid of starts and the runs planned on it (pure: no processes, no transport).

A robot's start is turned away from the target (``alpha_0 = atan2(y_0, x_0)``, ``pi`` at the
centre); another system's starts span its row's start box (common/math/systems.py) on its first two
state entries, the others zero (:func:`system_starts`). A run is one (start, agent, horizon); its
settings are the base settings with those three set.
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
from common.math.systems import UNICYCLE, System

STARTS = ("paper", "held-out")  # the paper's grid, or random starts it never saw


# -- the grid of starts -----------------------------------------------------------------
@dataclass(frozen=True)
class Start:
    """A robot's start ``(x, y, alpha)``; another system's whole start is :attr:`state`, and ``x``,
    ``y``, ``alpha`` are its first three entries (nan where it has fewer: runs.csv's columns)."""

    index: int
    x: float
    y: float
    alpha: float  # a robot's: turned away from the target, atan2(y, x), pi at the centre
    state: tuple[float, ...] = ()  # another system's start (the robot's: empty, (x, y, alpha))

    @property
    def values(self) -> tuple[float, ...]:
        """The start state: :attr:`state`, or the robot's ``(x, y, alpha)``."""
        return self.state or (self.x, self.y, self.alpha)


def system_start(index: int, state: Sequence[float]) -> Start:
    """Another system's start ``state`` as a :class:`Start`."""
    values = tuple(float(c) for c in state)
    first = [*values[:3], *[math.nan] * (3 - min(3, len(values)))]
    return Start(index, first[0], first[1], first[2], values)


def system_starts(system: System, kind: str, k: int, seed: int) -> list[Start]:
    """Another system's ``k x k`` starts over its start box's first two entries (the others zero):
    ``paper``, the lattice, corners included, but not its centre, the goal; ``held-out``, one
    seeded start in each cell, as for the robot. Where the box spans one of the two (a system of
    one state, or a start box of width 0 on the other): ``k * k`` starts along it."""
    if kind not in STARTS:
        raise ValueError(f"unknown set of starts {kind!r}; choose one of {', '.join(STARTS)}")
    box, n = system.box_of_starts, system.state_dim
    spanned = [i for i in range(min(2, n)) if box[i] > 0]  # the first two entries the box spans
    if not spanned:
        raise ValueError(f"system {system.what!r}: its start box spans neither of its first two entries")
    points = k * k if len(spanned) == 1 else k
    widths = [float(w) for w in box[spanned]]
    grid = lattice(points, widths) if kind == "paper" else jittered(points, widths, np.random.default_rng(seed))
    starts: list[Start] = []
    for point in grid:
        if any(point):  # the goal itself is no start: every agent's J is 0 there (the lattice's centre)
            state = [0.0] * n
            for axis, value in zip(spanned, point, strict=True):
                state[axis] = float(value)
            starts.append(system_start(len(starts), state))
    return starts


def lattice(points: int, widths: Sequence[float]) -> list[tuple[float, ...]]:
    """``points`` per axis over ``[-w, w]`` for each of one or two half-widths ``w``, corners
    included (one point: the centre), the first axis fastest; the centre exactly 0, not 1e-17."""
    ticks = [np.linspace(-w, w, points) if points > 1 else np.zeros(1) for w in widths]
    ticks = [np.where(np.abs(t) < 1e-12 * max(w, 1e-300), 0.0, t) for t, w in zip(ticks, widths, strict=True)]
    return [(float(t),) for t in ticks[0]] if len(ticks) == 1 else [(a, b) for b in ticks[1] for a in ticks[0]]


def jittered(points: int, widths: Sequence[float], rng: np.random.Generator) -> list[tuple[float, ...]]:
    """The box cut into ``points`` equal cells per axis, one point drawn uniformly in each
    (stratified jitter), in :func:`lattice`'s order, the first axis drawn first in each cell."""
    edges = [np.linspace(-w, w, points + 1) for w in widths]
    axes = range(len(widths))
    cells = (
        [(i,) for i in range(points)] if len(widths) == 1 else [(c, r) for r in range(points) for c in range(points)]
    )
    return [tuple(float(rng.uniform(edges[a][cell[a]], edges[a][cell[a] + 1])) for a in axes) for cell in cells]


def _start(index: int, x: float, y: float) -> Start:
    x, y = float(x), float(y)
    return Start(index, x, y, heading_away_from_target(x, y))


def grid_starts(k: int, extent: float) -> list[Start]:
    """The paper's grid: ``k x k`` lattice over ``[-extent, extent]^2``, corners included.

    Row-major from the bottom-left: ``index = row * k + column``. ``k = 1`` is the centre.
    """
    if k < 1 or not (math.isfinite(extent) and extent > 0):
        raise ValueError(f"a grid needs k >= 1 and a positive extent, got k = {k}, extent = {extent}")
    return [_start(index, x, y) for index, (x, y) in enumerate(lattice(k, (extent, extent)))]


def held_out_starts(k: int, extent: float, seed: int) -> list[Start]:
    """The held-out grid: the square cut into ``k x k`` equal cells, one start drawn
    uniformly inside each cell (stratified jitter, ``numpy.random.default_rng(seed)``).

    Same count and coverage as the paper's grid, but generic positions (off the axes and
    the diagonals, where the paper's lattice has its symmetric starts), so a setting chosen
    on one grid is checked on starts it never saw.
    """
    if k < 1 or not (math.isfinite(extent) and extent > 0):
        raise ValueError(f"a grid needs k >= 1 and a positive extent, got k = {k}, extent = {extent}")
    points = jittered(k, (extent, extent), np.random.default_rng(seed))
    return [_start(index, x, y) for index, (x, y) in enumerate(points)]


def make_starts(kind: str, k: int, extent: float, seed: int, system: System = UNICYCLE) -> list[Start]:
    """The starts of ``kind`` for ``system``: the robot's over ``[-extent, extent]^2``, another
    system's over its start box (:func:`system_starts`; ``extent`` is the robot's)."""
    if not system.wheeled:
        return system_starts(system, kind, k, seed)
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
    data["episode"]["start"] = list(spec.start.values)
    return Settings.model_validate(data)
