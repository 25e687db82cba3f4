"""Figures of ``srl experiment paper`` (matplotlib, headless).

* ``ratio_N<N>.png``: the paper's figures 3-4, one panel per RL agent: contours of
  ``J_agent / J_mpc * 100 %`` over the start position (interpolated between the starts on a
  Delaunay triangulation, as the paper interpolates between its grid ticks), the 100 % line
  drawn heavy, every start marked with its value. Blue is better than MPC, red worse.
* ``trajectories.png``: every run's path, one panel per (N, agent).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import TwoSlopeNorm
from matplotlib.tri import Triangulation

from common.math.agents import AGENT_ROWS
from common.math.systems import UNICYCLE, System
from tools.experiment.marks import TIE_PERCENT

# the learning agents, in the table's order (the plots are of J / J_MPC)
TITLES = {name: row.title for name, row in AGENT_ROWS.items() if row.learns}


def plane(system: System, extent: float) -> tuple[tuple[str, str], tuple[float, float]]:
    """The figures' plane: the state's first two entries' names and half-widths (the robot's
    ``x [m]``, ``y [m]`` over ``extent``; another system's over its start box)."""
    if system.wheeled:
        return ("x [m]", "y [m]"), (extent, extent)
    box = system.box_of_starts
    names = (*system.states[:2], "")[:2]
    widths = (float(box[0]) or 1.0, float(box[1]) if len(box) > 1 and box[1] > 0 else 1.0)
    return (names[0], names[1]), widths


def _triangulation(x: np.ndarray, y: np.ndarray) -> Triangulation | None:
    """``None`` when the starts span no area (fewer than 3, or all on a line)."""
    if x.size < 3:
        return None
    try:
        tri = Triangulation(x, y)
    except (ValueError, RuntimeError):  # qhull: collinear or duplicate points
        return None
    return tri if len(tri.triangles) else None


def plot_ratio_contours(
    ratios: Sequence[dict[str, Any]], horizon: int, extent: float, path: Path, system: System = UNICYCLE
) -> bool:
    """One figure for one horizon, over the start's first two entries (the robot's position;
    another system's start box); returns False (and writes nothing) without any ratio."""
    (x_name, y_name), (x_limit, y_limit) = plane(system, extent)
    agents = [a for a in TITLES if any(t["agent"] == a for t in ratios)]
    if not agents:
        return False
    values = np.array([t["ratio_percent"] for t in ratios if np.isfinite(t["ratio_percent"])])
    if values.size == 0:
        return False
    # Diverging colours centred on 100 %, one scale for every panel of the figure.
    low, high = min(float(values.min()), 99.0), max(float(values.max()), 101.0)
    norm = TwoSlopeNorm(vmin=low, vcenter=100.0, vmax=high)
    levels = np.unique(np.concatenate([np.linspace(low, 100.0, 8), np.linspace(100.0, high, 8)]))
    fig, axes = plt.subplots(1, len(agents), figsize=(5.6 * len(agents), 5.0), squeeze=False)
    mappable = None
    for ax, agent in zip(axes[0], agents, strict=True):
        marks = [t for t in ratios if t["agent"] == agent and np.isfinite(t["ratio_percent"])]
        x = np.array([t["start_x"] for t in marks])
        y = np.array([t["start_y"] for t in marks])
        z = np.array([t["ratio_percent"] for t in marks])
        tri = _triangulation(x, y)
        if tri is not None:
            mappable = ax.tricontourf(tri, z, levels=levels, cmap="RdBu_r", norm=norm, extend="neither")
            if z.min() < 100.0 < z.max():
                lines = ax.tricontour(tri, z, levels=[100.0], colors="k", linewidths=2.6)
                ax.clabel(lines, fmt="100 %%", fontsize=8)
        scatter = ax.scatter(x, y, c=z, cmap="RdBu_r", norm=norm, s=36, edgecolors="k", linewidths=0.8, zorder=3)
        mappable = mappable or scatter
        for xi, yi, zi in zip(x, y, z, strict=True):
            ax.annotate(
                f"{zi:.0f}", (xi, yi), textcoords="offset points", xytext=(0, 6), ha="center", fontsize=7, zorder=4
            )
        ax.plot(0, 0, "*", ms=14, color="gold", markeredgecolor="k", zorder=5)
        ax.set_xlim(-x_limit * 1.08, x_limit * 1.08)
        ax.set_ylim(-y_limit * 1.08, y_limit * 1.08)
        if system.wheeled:
            ax.set_aspect("equal")
        ax.set_xlabel("x0 [m]" if system.wheeled else f"{x_name} at the start")
        ax.set_ylabel("y0 [m]" if system.wheeled else f"{y_name} at the start")
        beat = int(np.sum(z < 100.0 - TIE_PERCENT))
        ax.set_title(
            f"J_{TITLES[agent]} / J_MPC x 100 %, N = {horizon}\n"
            f"median {np.median(z):.1f} %, better than MPC from {beat}/{z.size} starts",
            fontsize=10,
        )
    assert mappable is not None
    bar = fig.colorbar(mappable, ax=axes[0].tolist(), shrink=0.9)
    bar.set_label("J_agent / J_MPC [%]  (below 100: better than MPC)")
    bar.ax.axhline(100.0, color="k", linewidth=2.0)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return True


def plot_trajectory_overview(
    rows: Sequence[dict[str, Any]],
    arrays: dict[str, dict[str, np.ndarray]],
    agents: Sequence[str],
    horizons: Sequence[int],
    extent: float,
    path: Path,
    tolerance: float = 0.25,
    system: System = UNICYCLE,
) -> None:
    """Every run's path over the state's first two entries, one panel per (N, agent); a robot's
    with its start heading, within ``tolerance`` of the goal blue (parked, or stabilized), else red."""
    (x_name, y_name), (x_limit, y_limit) = plane(system, extent)
    fig, axes = plt.subplots(
        len(horizons),
        len(agents),
        figsize=(4.2 * len(agents), 4.2 * len(horizons)),
        squeeze=False,
        sharex=True,
        sharey=True,
    )
    for i, horizon in enumerate(horizons):
        for j, agent in enumerate(agents):
            ax = axes[i][j]
            runs = [r for r in rows if r["agent"] == agent and r["horizon"] == horizon and r["run_id"] in arrays]
            for r in runs:
                states = arrays[r["run_id"]]["states"]
                parked = r["final_distance"] <= tolerance
                ys = states[:, 1] if states.shape[1] > 1 else np.zeros(len(states))
                ax.plot(states[:, 0], ys, lw=0.9, alpha=0.8, color="tab:blue" if parked else "tab:red")
                ax.plot(states[0, 0], ys[0], "o", ms=3, color="tab:green")
                if not system.wheeled:
                    continue
                ax.arrow(
                    states[0, 0],
                    states[0, 1],
                    0.18 * np.cos(states[0, 2]),
                    0.18 * np.sin(states[0, 2]),
                    width=0.01,
                    color="tab:green",
                    length_includes_head=True,
                )
            ax.plot(0, 0, "*", ms=12, color="gold", markeredgecolor="k", zorder=5)
            box = plt.Rectangle((-x_limit, -y_limit), 2 * x_limit, 2 * y_limit, fill=False, ls=":", color="gray")
            ax.add_patch(box)
            if system.wheeled:
                ax.set_xlim(-x_limit * 1.25, x_limit * 1.25)
                ax.set_ylim(-y_limit * 1.25, y_limit * 1.25)
                ax.set_aspect("equal")
            ax.grid(True, alpha=0.3)
            parked = sum(r["final_distance"] <= tolerance for r in runs)
            word = "parked" if system.wheeled else "stabilized"
            ax.set_title(f"{agent}, N = {horizon}: {word} {parked}/{len(runs)}", fontsize=10)
            if i == len(horizons) - 1:
                ax.set_xlabel(x_name)
            if j == 0:
                ax.set_ylabel(y_name)
    fig.suptitle(
        f"Trajectories (green: start and heading; blue: parked within {tolerance:g} m, red: not)"
        if system.wheeled
        else f"Trajectories (green: start; blue: stabilized within {tolerance:g}, red: not)",
        fontsize=11,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
