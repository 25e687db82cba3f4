"""Figures of a run (matplotlib, headless)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from common.loop import Episode


def plot_episode(episode: Episode, sampling_time: float, path: Path) -> None:
    """Trajectory in the goal frame (left) and stage / accumulated cost over time (right)."""
    states = np.array(episode.states)
    times = np.arange(episode.steps) * sampling_time
    fig, (ax_xy, ax_cost) = plt.subplots(1, 2, figsize=(11, 4.8))
    ax_xy.plot(states[:, 0], states[:, 1], "-", lw=1.5, label="trajectory")
    stride = max(1, len(states) // 25)
    ax_xy.quiver(
        states[::stride, 0], states[::stride, 1],
        np.cos(states[::stride, 2]), np.sin(states[::stride, 2]),
        angles="xy", scale=25, width=0.004, color="tab:gray",
    )
    ax_xy.plot(*states[0, :2], "o", color="tab:green", label="start")
    ax_xy.plot(*states[-1, :2], "s", color="tab:red", label="end")
    ax_xy.plot(0, 0, "*", ms=14, color="k", label="target")
    ax_xy.set_aspect("equal", adjustable="datalim")
    ax_xy.set_xlabel("x [m]")
    ax_xy.set_ylabel("y [m]")
    ax_xy.set_title(f"{episode.agent}, N = {episode.horizon}")
    ax_xy.grid(True, alpha=0.3)
    ax_xy.legend(loc="best", fontsize=8)

    ax_cost.plot(times, episode.costs, lw=1.2, label="c_k = delta r(s_k, u_k)")
    ax_cost.set_xlabel("t [s]")
    ax_cost.set_ylabel("stage cost")
    ax_total = ax_cost.twinx()
    ax_total.plot(times, np.cumsum(episode.costs), color="tab:orange", lw=1.5, label="J (accumulated)")
    ax_total.set_ylabel("accumulated cost J")
    ax_cost.set_title(f"J = {episode.accumulated_cost:.3f}")
    lines = ax_cost.get_legend_handles_labels()
    lines_total = ax_total.get_legend_handles_labels()
    ax_cost.legend(lines[0] + lines_total[0], lines[1] + lines_total[1], loc="center right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
