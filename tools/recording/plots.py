"""Figures of a run (matplotlib, headless)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from common.math.agents import learns
from common.math.loop import Episode
from common.math.systems import UNICYCLE, System


def plot_episode(episode: Episode, sampling_time: float, path: Path, system: System = UNICYCLE) -> None:
    """One figure of a run: the robot's path in the goal frame (another system: its states over
    time) (left, full height); the controls and the costs (top); the critic's weights and TD
    residuals over time (bottom): the learning."""
    states = np.array(episode.states)
    times = np.arange(episode.steps) * sampling_time
    fig = plt.figure(figsize=(15, 8.5))
    grid = fig.add_gridspec(2, 3, width_ratios=(1.25, 1, 1))
    ax_xy = fig.add_subplot(grid[:, 0])
    if system.wheeled:
        plot_path(ax_xy, states)
        ax_xy.set_title(f"{episode.agent}, N = {episode.horizon}: path (goal frame)")
    else:
        for column, name in enumerate(system.states):
            ax_xy.plot(np.arange(len(states)) * sampling_time, states[:, column], lw=1.4, label=name)
        ax_xy.axhline(0.0, color="k", lw=0.6)
        ax_xy.set_xlabel("t [s]")
        ax_xy.legend(loc="best", fontsize=8)
        ax_xy.grid(True, alpha=0.3)
        ax_xy.set_title(f"{episode.agent}, N = {episode.horizon}: the state (goal: 0)")

    ax_u = fig.add_subplot(grid[0, 1])
    if episode.actions:
        actions = np.array(episode.actions)
        for column, name in enumerate(system.actions):
            ax_u.step(times, actions[:, column], where="post", lw=1.3, label=name)
    ax_u.axhline(0.0, color="k", lw=0.6)
    ax_u.set_xlabel("t [s]")
    ax_u.set_title("controls (held for delta)")
    ax_u.legend(loc="best", fontsize=8)
    ax_u.grid(True, alpha=0.3)

    ax_cost = fig.add_subplot(grid[0, 2])
    ax_cost.plot(times, episode.costs, lw=1.2, label="stage cost c_k = delta r(s_k, u_k)")
    ax_cost.set_xlabel("t [s]")
    ax_cost.set_ylabel("stage cost")
    ax_total = ax_cost.twinx()
    ax_total.plot(times, np.cumsum(episode.costs), color="tab:orange", lw=1.5, label="J accumulated")
    ax_total.set_ylabel("accumulated cost J")
    ax_cost.set_title(f"costs: J = {episode.accumulated_cost:.3f}")
    lines, labels = ax_cost.get_legend_handles_labels()
    lines_total, labels_total = ax_total.get_legend_handles_labels()
    ax_cost.legend(lines + lines_total, labels + labels_total, loc="center right", fontsize=8)
    ax_cost.grid(True, alpha=0.3)

    ax_w = fig.add_subplot(grid[1, 1])
    ax_res = fig.add_subplot(grid[1, 2])
    _plot_learning(ax_w, ax_res, episode, times)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_path(ax: plt.Axes, states: np.ndarray) -> None:
    ax.plot(states[:, 0], states[:, 1], "-", lw=1.5, color="tab:blue", label="path", zorder=2)
    # heading arrows of a fixed length in data units, so that the axis limits below contain them
    span = float(max(np.ptp(states[:, 0]), np.ptp(states[:, 1]), 0.2))
    length = 0.06 * span
    stride = max(1, len(states) // 25)
    shown = states[::stride]
    dx, dy = length * np.cos(shown[:, 2]), length * np.sin(shown[:, 2])
    ax.quiver(
        shown[:, 0],
        shown[:, 1],
        dx,
        dy,
        angles="xy",
        scale_units="xy",
        scale=1,
        width=0.004,
        color="tab:gray",
        zorder=3,
        label="heading",
    )
    # the target under everything; the end on top, hollow and larger, so both stay visible
    ax.plot(0, 0, "*", ms=16, color="gold", markeredgecolor="k", label="target", zorder=4)
    ax.plot(*states[0, :2], "o", ms=9, color="tab:green", label="start", zorder=5)
    ax.plot(
        *states[-1, :2],
        "s",
        ms=13,
        markerfacecolor="none",
        markeredgewidth=2.2,
        color="tab:red",
        label=f"end ({states[-1, 0]:+.2f}, {states[-1, 1]:+.2f})",
        zorder=6,
    )
    xs = np.concatenate([states[:, 0], shown[:, 0] + dx, [0.0]])
    ys = np.concatenate([states[:, 1], shown[:, 1] + dy, [0.0]])
    margin = 0.08 * span
    ax.set_xlim(xs.min() - margin, xs.max() + margin)
    ax.set_ylim(ys.min() - margin, ys.max() + margin)
    ax.set_aspect("equal", adjustable="box")  # the limits above hold
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)


def _plot_learning(ax_w: plt.Axes, ax_res: plt.Axes, episode: Episode, times: np.ndarray) -> None:
    if episode.q_weights and len(episode.q_weights) == len(times):
        q = np.array(episode.q_weights)
        v = np.array(episode.v_weights)
        ax_w.plot(times, q, lw=0.9, alpha=0.75)
        ax_w.plot(times, v, lw=1.4, ls="--", color="k", alpha=0.6)
        ax_w.plot([], [], lw=0.9, color="tab:blue", label=f"Q weights w ({q.shape[1]})")
        ax_w.plot([], [], lw=1.4, ls="--", color="k", label=f"V weights ({v.shape[1]})")
        ax_w.set_yscale("symlog", linthresh=1e-2)
        ax_w.legend(loc="best", fontsize=8)
    else:
        ax_w.text(0.5, 0.5, "weights not recorded", ha="center", va="center", transform=ax_w.transAxes)
    ax_w.set_xlabel("t [s]")
    ax_w.set_title("critic weights used by the actor")
    ax_w.grid(True, alpha=0.3)

    residuals = np.array(episode.td_residuals, dtype=float).reshape(-1, 2)
    residuals[~(residuals > 0)] = np.nan  # no fit yet (0 pairs), or none: not drawn on a log axis
    if residuals.size and np.isfinite(residuals).any():
        ax_res.semilogy(times[: len(residuals)], residuals[:, 0], lw=1.2, label="Q fit")
        ax_res.semilogy(times[: len(residuals)], residuals[:, 1], lw=1.2, label="V fit")
        ax_res.legend(loc="best", fontsize=8)
    else:
        text = f"no fits (agent {episode.agent})" if not learns(episode.agent) else "TD residuals not recorded"
        ax_res.text(0.5, 0.5, text, ha="center", va="center", transform=ax_res.transAxes)
    ax_res.set_xlabel("t [s]")
    ax_res.set_title("TD residual 1/2 sum e^2 of each fit")
    ax_res.grid(True, alpha=0.3)
