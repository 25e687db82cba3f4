"""The guide's figures (docs/img/*.png), each drawn from this repository by one command.

    .venv/bin/python -m tools.docs.figures                 # every figure into docs/img/
    .venv/bin/python -m tools.docs.figures --out /tmp/img parking-path architecture

(``python -m``, not an ``srl`` subcommand: tools/cli.py's table of commands and the generated CLI
reference are not this module's to change.)

* ``parking-path.png``: one in-process episode, the README's ``srl run --agent rlqv --horizon 12
  --start 2,2 --duration 30``, in the goal frame: the path, the heading, the goal frame's axes and
  the 0.05 m ``srl bench parking`` asks of one robot (:data:`common.math.parking.FINAL_DISTANCE_M`)
  and the arrival rule's tolerance;
* ``fleet-scaling.png``: ``srl bench fleet`` (docs/benchmarks/data/fleet.json): CPU and missed
  deadlines against the fleet's size, one actor host against one actor process per robot;
* ``actor-solve-time.png``: ``srl bench actor`` (docs/benchmarks/data/actor.json): the actor's
  solve time at N = 12 per agent and weight set, median and p99, against the SLSQP baseline;
* ``live-view.png``: the Foxglove layout ``srl view`` ships, drawn with the messages it would
  serve for that same run (tools/docs/live_view.py);
* ``architecture.png``: the processes, the keys between them (read from
  :mod:`common.contracts.keys`, so a renamed key renames its arrow) and the floors of the code.

The style is fixed (matplotlib's defaults, the Agg backend, a fixed size and dpi, no software
version or date in the PNG's metadata), so a rerun on the same machine and matplotlib writes the
same bytes; the episode is deterministic and built without the JIT (the same numbers, no C build).
The live view alone differs from run to run: its actor panel plots the solve times as measured.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Circle, FancyArrowPatch, FancyBboxPatch, Rectangle
from matplotlib.ticker import FuncFormatter

from common.contracts import keys
from common.contracts.summaries import PARKED_WITHIN_M

ROOT = Path(__file__).resolve().parents[2]
IMAGES = Path("docs/img")
BENCHMARK_DATA = Path("docs/benchmarks/data")
DPI = 150
# no "Software: matplotlib x.y" (nor a date: PNG output has none): a rerun writes the same bytes
PNG_METADATA: dict[str, str | None] = {"Software": None}
STYLE: dict[str, Any] = {
    "font.size": 10,
    "axes.titlesize": 11,
    "axes.labelsize": 10,
    "legend.fontsize": 9,
    "xtick.labelsize": 9,
    "ytick.labelsize": 9,
    "figure.dpi": DPI,
    "savefig.dpi": DPI,
    "path.simplify": False,
    "svg.hashsalt": "srl",
}
FOOTNOTE: dict[str, Any] = {"fontsize": 7.5, "color": "0.35"}


class FigureDataError(ValueError):
    """A benchmark JSON that cannot be drawn (no rows, a missing field): which file, what is missing."""


def save(fig: Figure, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=DPI, metadata=PNG_METADATA)
    plt.close(fig)
    return path


# -- 1. the goal frame and a parked path ---------------------------------------------------------


@dataclass(frozen=True)
class EpisodeRun:
    """The README's first run: ``srl run --agent rlqv --horizon 12 --start 2,2 --duration 30``."""

    agent: str = "rlqv"
    horizon: int = 12
    start: tuple[float, float] = (2.0, 2.0)
    duration: float = 30.0

    def command(self) -> str:
        x, y = self.start
        return f"srl run --agent {self.agent} --horizon {self.horizon} --start {x:g},{y:g} --duration {self.duration:g}"


@dataclass(frozen=True)
class PathData:
    """What the path figure draws: the states (goal frame), the run and the tolerances it shows."""

    run: EpisodeRun
    states: np.ndarray  # (steps + 1, 3): x, y, alpha
    accumulated_cost: float
    sampling_time: float
    target_radius: float  # common.math.parking.FINAL_DISTANCE_M: srl bench parking's bound
    arrival_radius: float | None  # actor.arrival_position_tolerance (None: the arrival rule is off)
    at_target: bool  # common.math.parking.Parking.at_target: within target_radius and at rest

    @property
    def steps(self) -> int:
        return len(self.states) - 1

    @property
    def final_distance(self) -> float:
        return float(math.hypot(self.states[-1, 0], self.states[-1, 1]))


def run_path(run: EpisodeRun = EpisodeRun()) -> PathData:
    """One episode in this process (common.config.assembly.run_episode, what ``srl run`` calls),
    with the actor built without the JIT (``actor.jit = false``: the same numbers, no C build)."""
    from common.config.assembly import run_episode
    from common.config.settings import Settings
    from common.math.parking import FINAL_DISTANCE_M, parking

    settings = Settings.load(
        actor={"agent": run.agent, "horizon": run.horizon, "jit": False},
        episode={"start": run.start, "duration": run.duration},
    )
    episode = run_episode(settings)
    states = np.array(episode.true_states if episode.truth_known else episode.states, dtype=float)
    delta = settings.plant.sampling_time
    return PathData(
        run=run,
        states=states,
        accumulated_cost=episode.accumulated_cost,
        sampling_time=delta,
        target_radius=FINAL_DISTANCE_M,
        arrival_radius=settings.actor.arrival_position_tolerance if settings.actor.arrival else None,
        at_target=parking(states, np.array(episode.actions), delta).at_target,
    )


def heading_arrows(ax: Axes, states: np.ndarray, length: float, width: float, label: str | None = None) -> None:
    ax.quiver(
        states[:, 0],
        states[:, 1],
        length * np.cos(states[:, 2]),
        length * np.sin(states[:, 2]),
        angles="xy",
        scale_units="xy",
        scale=1,
        width=width,
        color="tab:orange",
        zorder=3,
        label=label,
    )


def goal_frame_axes(ax: Axes, length: float) -> None:
    """The goal frame: the target at the origin, x_g the heading the robot should park with."""
    for (dx, dy), name, color in (((length, 0.0), "$x_g$", "tab:red"), ((0.0, length), "$y_g$", "tab:green")):
        ax.annotate(
            "",
            xy=(dx, dy),
            xytext=(0.0, 0.0),
            arrowprops={"arrowstyle": "-|>", "color": color, "lw": 2.0, "mutation_scale": 14},
            zorder=4,
        )
        ax.text(dx * 1.08 + 0.02 * length, dy * 1.08 + 0.02 * length, name, color=color, fontsize=11, zorder=4)


def tolerance_circles(ax: Axes, data: PathData, labels: bool) -> None:
    ax.add_patch(
        Circle(
            (0.0, 0.0),
            data.target_radius,
            facecolor="gold",
            alpha=0.35,
            edgecolor="darkgoldenrod",
            lw=1.4,
            zorder=1,
            label=f"{data.target_radius:g} m: at target" if labels else None,
        )
    )
    if data.arrival_radius is not None:
        ax.add_patch(
            Circle(
                (0.0, 0.0),
                data.arrival_radius,
                fill=False,
                edgecolor="0.3",
                ls="--",
                lw=1.1,
                zorder=1,
                label=f"arrival rule: {data.arrival_radius:g} m" if labels else None,
            )
        )


def path_figure(data: PathData) -> Figure:
    states = data.states
    fig = plt.figure(figsize=(9.0, 6.2))
    ax = fig.add_axes((0.08, 0.17, 0.50, 0.73))
    zoom = fig.add_axes((0.65, 0.31, 0.33, 0.49))
    stride = max(1, round(1.0 / data.sampling_time))  # one heading arrow a second
    fine = max(1, stride // 5)
    for axes, length, every, width in ((ax, 0.16, stride, 0.005), (zoom, 0.03, fine, 0.007)):
        axes.plot(states[:, 0], states[:, 1], "-", lw=1.3, color="tab:blue", zorder=2, label="path")
        heading_arrows(axes, states[::every], length, width, f"heading (every {data.sampling_time * every:g} s)")
        axes.plot(*states[0, :2], "o", ms=9, color="tab:green", zorder=5, label="start")
        axes.plot(
            *states[-1, :2],
            "s",
            ms=10,
            markerfacecolor="none",
            markeredgewidth=2.0,
            color="tab:red",
            zorder=6,
            label="end",
        )
        axes.set_aspect("equal", adjustable="box")
        axes.grid(True, alpha=0.3)
    goal_frame_axes(ax, 0.5)
    tolerance_circles(ax, data, labels=False)
    tolerance_circles(zoom, data, labels=True)
    span = max(float(np.ptp(states[:, 0])), float(np.ptp(states[:, 1])), 0.5)
    margin = 0.12 * span
    ax.set_xlim(min(states[:, 0].min(), 0.0) - margin, max(states[:, 0].max(), 0.5) + margin)
    ax.set_ylim(min(states[:, 1].min(), 0.0) - margin, max(states[:, 1].max(), 0.5) + margin)
    ax.set_xlabel("$x$ [m] (goal frame)")
    ax.set_ylabel("$y$ [m] (goal frame)")
    ax.legend(loc="upper left", framealpha=0.9)
    near = states[np.hypot(states[:, 0], states[:, 1]) <= 0.2]
    reach = max(0.08, float(np.abs(near[:, :2]).max()) * 1.15 if len(near) else 0.08)
    zoom.set_xlim(-reach, reach)
    zoom.set_ylim(-reach, reach)
    ax.indicate_inset((-reach, -reach, 2 * reach, 2 * reach), inset_ax=zoom, edgecolor="0.4", alpha=0.5)
    zoom.set_title(f"at the target (\u00b1{reach * 100:.0f} cm)")
    zoom.set_xlabel("$x$ [m]")
    handles, labels = zoom.get_legend_handles_labels()
    keep = [i for i, label in enumerate(labels) if not label.startswith(("path", "start", "end"))]
    zoom.legend(
        [handles[i] for i in keep],
        [labels[i] for i in keep],
        loc="upper left",
        bbox_to_anchor=(0.0, -0.17),
        fontsize=8.5,
        frameon=False,
    )
    run = data.run
    fig.suptitle(
        f"{run.agent}, N = {run.horizon}, start ({run.start[0]:g}, {run.start[1]:g}): "
        f"J = {data.accumulated_cost:.2f} over {data.steps} steps ({data.steps * data.sampling_time:g} s)",
        fontsize=12,
    )
    verdict = "and at rest: within" if data.at_target else "and not at rest within"
    arrival = (
        f"The arrival rule stops it inside {data.arrival_radius:g} m (actor.arrival_position_tolerance)."
        if data.arrival_radius is not None
        else "The arrival rule is off."
    )
    fig.text(
        0.01,
        0.012,
        f"{run.command()}, in process (actor.jit = false). The robot starts facing away from the target "
        "and backs in.\n"
        f"It ends {data.final_distance * 100:.1f} cm from the target {verdict} the {data.target_radius:g} m "
        "srl bench parking asks of one robot (common/math/parking.py).\n"
        f"{arrival} Parked, on the guide's pages: within {PARKED_WITHIN_M:g} m (PARKED_WITHIN_M).",
        **FOOTNOTE,
    )
    return fig


# -- 2. a fleet's scaling ------------------------------------------------------------------------


@dataclass(frozen=True)
class FleetPoint:
    layout: str  # host: one actor host process for many robots; process: one actor process per robot
    robots: int
    cpu_percent: float  # of one CPU, the whole system
    cpu_ms_per_robot_tick: float
    missed_deadlines: int
    robot_ticks: int


def read_data(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise FigureDataError(f"{path}: no such file (run the benchmark with --json into it)")
    data = json.loads(path.read_text())
    if not isinstance(data, dict):
        raise FigureDataError(f"{path}: not a JSON object")
    return data


def rows_of(data: dict[str, Any], source: str) -> list[dict[str, Any]]:
    rows = data.get("rows")
    if not isinstance(rows, list) or not rows:
        raise FigureDataError(f"{source}: no rows to draw (the JSON of a run that measured nothing?)")
    return rows


def fleet_points(data: dict[str, Any], source: str = "fleet.json") -> list[FleetPoint]:
    """One point per row of ``srl bench fleet --json``, sorted by layout and size."""
    points = []
    for index, row in enumerate(rows_of(data, source)):
        try:
            fleet = row["fleet"]
            points.append(
                FleetPoint(
                    layout=str(row["layout"]),
                    robots=int(row["robots"]),
                    cpu_percent=float(row["cpu_percent"]),
                    cpu_ms_per_robot_tick=float(row["cpu_ms_per_robot_tick"]),
                    missed_deadlines=int(fleet["missed_deadlines"]),
                    robot_ticks=int(fleet["steps"]),
                )
            )
        except (KeyError, TypeError, ValueError) as error:
            raise FigureDataError(f"{source}: row {index} lacks a number the figure needs: {error!r}") from None
    return sorted(points, key=lambda p: (p.layout, p.robots))


def run_footnote(data: dict[str, Any], wrap: bool = False) -> str:
    """Where the numbers come from: command, commit, date, machine and load of the JSON's run (on
    two lines: ``wrap``)."""
    run = data.get("run") or {}
    if not run:
        return "This JSON carries no record of its run (command, commit, machine)."
    load = run.get("load_average") or []
    modified = " + uncommitted changes" if run.get("worktree_modified") else ""
    commit = str(run.get("commit") or "unknown")[:10]
    return (
        f"{run.get('command', '?')}:{chr(10) if wrap else ' '}commit {commit}{modified}, "
        f"{run.get('date', '?')}; {run.get('cpu_model', '?')}, {run.get('cpu_count', '?')} CPUs"
        + (f", load average {' / '.join(f'{x:.1f}' for x in load)} (1/5/15 min) at the end" if load else "")
    )


LAYOUTS = {
    "host": ("one actor host for many robots", "tab:blue", "o-"),
    "process": ("one actor process per robot", "tab:orange", "s--"),
}


def fleet_figure(data: dict[str, Any]) -> Figure:
    points = fleet_points(data)
    cpus = int(data.get("cpus") or (data.get("run") or {}).get("cpu_count") or 0)
    fig, (ax_cpu, ax_tick, ax_missed) = plt.subplots(1, 3, figsize=(10.0, 4.0))
    for layout in sorted({p.layout for p in points}):
        mine = [p for p in points if p.layout == layout]
        label, color, style = LAYOUTS.get(layout, (layout, "tab:gray", "^-"))
        robots = [p.robots for p in mine]
        kwargs: dict[str, Any] = {"color": color, "label": f"{layout}: {label}", "ms": 7, "lw": 1.6}
        ax_cpu.plot(robots, [p.cpu_percent for p in mine], style, **kwargs)
        ax_tick.plot(robots, [p.cpu_ms_per_robot_tick for p in mine], style, **kwargs)
        ax_missed.plot(robots, [100.0 * p.missed_deadlines / max(1, p.robot_ticks) for p in mine], style, **kwargs)
        for p in mine:
            if p.missed_deadlines:
                ax_missed.annotate(
                    f"{p.missed_deadlines} of\n{p.robot_ticks} ticks",
                    (p.robots, 100.0 * p.missed_deadlines / p.robot_ticks),
                    textcoords="offset points",
                    xytext=(-6, 8),  # above its point: below it would cover the smaller fleets' zeros
                    ha="right",
                    va="bottom",
                    fontsize=8,
                )
    if cpus:
        ax_cpu.axhline(100.0 * cpus, color="0.3", lw=1.0, ls=":")
        ax_cpu.text(
            ax_cpu.get_xlim()[0], 100.0 * cpus, f" the machine ({cpus} CPUs)", va="bottom", fontsize=8, color="0.3"
        )
        ax_cpu.set_ylim(0, 100.0 * cpus * 1.12)
    ax_cpu.set_title("CPU, all processes [% of one CPU]")
    ax_tick.set_title("CPU per robot tick [ms]")
    ax_tick.set_ylim(bottom=0)
    ax_missed.set_title("missed deadlines [% of robot ticks]")
    # from -1 so that a zero shows above the axis; to at least 1 % so that all zeros are not drawn on the top edge
    ax_missed.set_ylim(-1.0, max(1.0, ax_missed.get_ylim()[1]))
    sizes = sorted({p.robots for p in points})
    for ax in (ax_cpu, ax_tick, ax_missed):
        ax.set_xscale("log")
        ax.set_xticks(sizes, [str(s) for s in sizes])
        ax.minorticks_off()
        ax.set_xlabel("robots")
        ax.grid(True, alpha=0.3)
    handles, labels = ax_cpu.get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", ncol=2, frameon=False, bbox_to_anchor=(0.5, 0.94))
    agent = f"{data.get('agent', '?')}, N = {data.get('horizon', '?')}"
    fig.suptitle(f"A fleet on one machine ({agent}, {data.get('seconds', '?'):g} s a run, simulated plants)")
    fig.text(0.01, 0.012, run_footnote(data, wrap=True), **FOOTNOTE)
    fig.tight_layout(rect=(0, 0.07, 1, 0.91))
    return fig


# -- 3. the actor's solve time -------------------------------------------------------------------


@dataclass(frozen=True)
class SolveBar:
    label: str  # agent and weight set
    solver: str  # fatrop, ipopt, or the SLSQP baseline
    median_ms: float
    p99_ms: float


SOLVERS = {
    "fatrop": ("fatrop (actor.solver's default)", "tab:blue"),
    "ipopt": ("ipopt", "tab:orange"),
    "SLSQP baseline": ("SLSQP (rcognita-style baseline)", "tab:gray"),
}


def solve_bars(data: dict[str, Any], horizon: int = 12, source: str = "actor.json") -> list[SolveBar]:
    """The rows of ``srl bench actor --json`` at ``horizon``: per agent and weight set, each solver's
    median and p99 solve time, and the baseline's (once per agent and weight set)."""
    bars: list[SolveBar] = []
    for index, row in enumerate(rows_of(data, source)):
        try:
            if int(row["horizon"]) != horizon:
                continue
            weights = str(row["weights"])
            label = str(row["agent"]) + ("" if weights == "n/a" else f" {weights}")
            bars.append(SolveBar(label, str(row["solver"]), float(row["median_ms"]), float(row["p99_ms"])))
            baseline = SolveBar(
                label, "SLSQP baseline", float(row["baseline_median_ms"]), float(row["baseline_p99_ms"])
            )
        except (KeyError, TypeError, ValueError) as error:
            raise FigureDataError(f"{source}: row {index} lacks a number the figure needs: {error!r}") from None
        if not any(b.label == label and b.solver == baseline.solver for b in bars):
            bars.append(baseline)
    if not bars:
        raise FigureDataError(f"{source}: no row at N = {horizon}")
    return bars


def actor_figure(data: dict[str, Any], horizon: int = 12) -> Figure:
    bars = solve_bars(data, horizon)
    labels = list(dict.fromkeys(b.label for b in bars))
    solvers = [s for s in SOLVERS if any(b.solver == s for b in bars)]
    solvers += sorted({b.solver for b in bars} - set(solvers))
    fig, ax = plt.subplots(figsize=(9.0, 0.42 * len(labels) + 2.2))
    height = 0.8 / len(solvers)
    floor = 0.01  # [ms] the bars start here on the log axis
    for j, solver in enumerate(solvers):
        name, color = SOLVERS.get(solver, (solver, "tab:purple"))
        for i, label in enumerate(labels):
            found = [b for b in bars if b.label == label and b.solver == solver]
            if not found:
                continue
            bar = found[0]
            y = i + (j - (len(solvers) - 1) / 2) * height
            ax.barh(y, bar.p99_ms - floor, height * 0.92, left=floor, color=color, alpha=0.35, lw=0)
            ax.barh(y, bar.median_ms - floor, height * 0.92, left=floor, color=color)
        ax.barh(np.nan, 0, color=color, label=f"{name}: median (dark), p99 (light)")
    targets = data.get("targets") or {}
    for key, text, style in (("median_n12", "target: median", ":"), ("p99_n12", "target: p99", "--")):
        threshold = (targets.get(key) or {}).get("threshold")
        if threshold is not None and horizon == 12:
            ax.axvline(threshold, color="tab:blue", lw=1.1, ls=style, label=f"{text} <= {threshold:g} ms")
    delta = ((data.get("settings") or {}).get("plant") or {}).get("sampling_time")
    if delta:
        ax.axvline(1e3 * delta, color="tab:red", lw=1.4, label=f"the step, delta = {1e3 * delta:g} ms")
    ax.set_xscale("log")
    ax.set_xlim(floor, 200.0)
    ax.xaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
    ax.set_yticks(range(len(labels)), labels)
    ax.set_ylim(len(labels) - 0.5, -0.5)
    ax.set_xlabel("solve time of one actor step [ms] (log scale)")
    ax.grid(True, axis="x", which="both", alpha=0.25)
    ax.legend(loc="upper center", bbox_to_anchor=(0.42, -0.09), ncol=2, fontsize=8.5, frameon=False)
    ax.set_title(f"The actor's solve time at N = {horizon}, per agent and critic weights (srl bench actor)")
    fig.text(0.01, 0.012, run_footnote(data), **FOOTNOTE)
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    return fig


# -- 4. the architecture -------------------------------------------------------------------------


@dataclass(frozen=True)
class Process:
    """One box of the architecture: a process (or the robot), its floor, where it is drawn."""

    name: str
    floor: str  # tools, services, or robot (not srl's)
    label: str
    center: tuple[float, float]  # [in] on a 10 x 7.6 in figure
    size: tuple[float, float]


@dataclass(frozen=True)
class Link:
    """One arrow: ``keys`` are names in :mod:`common.contracts.keys` (their patterns label the
    arrow); a link of no key is not srl's wire (ROS 2 topics: ``text``)."""

    source: str
    target: str
    keys: tuple[str, ...] = ()
    text: str = ""  # the label of a link of no key
    every_robot: bool = False  # the key with a wildcard robot (keys.every_robot): a recorder's
    chunks: tuple[tuple[str, str], ...] = ()  # other chunks filled in: (("service", "actor"),)
    kind: str = "publish"  # publish, query (lockstep only), token (liveliness), ros
    path: tuple[tuple[float, float], tuple[float, float]] | None = None  # from, to [in]; None: centers
    bend: str = "arc3,rad=0"  # matplotlib's connectionstyle: straight, or "angle,...": a corner
    label_at: tuple[float, float] | None = None
    align: str = "center"


PROCESSES: tuple[Process, ...] = (
    Process(
        "router", "tools", "srl router\nthe Zenoh router: every\nsample passes through it", (1.75, 6.55), (2.3, 0.8)
    ),
    Process("recorder", "tools", "srl record / srl view\nMCAP file, Foxglove live", (5.0, 6.55), (2.4, 0.8)),
    Process("monitor", "tools", "srl status / srl health\nstatus line, readiness", (8.3, 6.55), (2.4, 0.8)),
    Process("plant_sim", "services", "plant_sim\nsimulated unicycle", (2.35, 4.45), (1.9, 0.62)),
    Process("robot_bridge", "services", "robot_bridge\nZenoh <-> ROS 2", (2.35, 3.35), (1.9, 0.62)),
    Process("robot", "robot", "the robot (ROS 2)\nTurtleBot3, emulator", (2.35, 1.95), (1.9, 0.55)),
    Process("actor", "services", "actor\nsolves its problem\nevery delta = 0.1 s", (5.6, 3.75), (1.45, 1.2)),
    Process("critic", "services", "critic\nTD fits,\noff-board", (9.05, 3.75), (1.3, 1.2)),
)

LINKS: tuple[Link, ...] = (
    Link("plant", "actor", ("STATE",), path=((3.4, 4.05), (4.875, 4.05)), label_at=(4.14, 4.1)),
    Link("actor", "plant", ("ACTION",), path=((4.875, 3.5), (3.4, 3.5)), label_at=(4.14, 3.55)),
    Link(
        "actor",
        "plant_sim",
        ("PLANT_STEP", "PLANT_RESET"),
        kind="query",
        path=((5.3, 4.35), (3.3, 4.55)),
        bend="angle,angleA=90,angleB=0,rad=0",
        label_at=(3.45, 4.6),
        align="left",
    ),
    Link("actor", "critic", ("TRANSITION",), path=((6.325, 4.05), (8.4, 4.05)), label_at=(7.36, 4.1)),
    Link("critic", "actor", ("WEIGHTS",), path=((8.4, 3.5), (6.325, 3.5)), label_at=(7.36, 3.55)),
    Link(
        "robot_bridge",
        "robot",
        text="cmd_vel",
        kind="ros",
        path=((2.0, 3.04), (2.0, 2.23)),
        label_at=(1.92, 2.63),
        align="right",
    ),
    Link(
        "robot",
        "robot_bridge",
        text="odom",
        kind="ros",
        path=((2.7, 2.23), (2.7, 3.04)),
        label_at=(2.78, 2.63),
        align="left",
    ),
    Link(
        "services",
        "recorder",
        ("STATE", "TRANSITION", "WEIGHTS", "STATUS"),
        every_robot=True,
        chunks=(("service", "actor"),),
        path=((5.0, 5.3), (5.0, 6.15)),
        label_at=(4.9, 5.72),
        align="right",
    ),
    Link(
        "services",
        "monitor",
        ("STATUS", "ALIVE"),
        kind="token",
        path=((8.3, 5.3), (8.3, 6.15)),
        label_at=(8.2, 5.72),
        align="right",
    ),
)
# the ends of a link that are not one process: the plant slot (either plant), every service
GROUPS = {"plant": ("plant_sim", "robot_bridge"), "services": ("plant_sim", "robot_bridge", "actor", "critic")}

FLOORS = (
    # name, bottom, top [in], the floor's own line
    ("tools/", 5.45, 7.3, "the srl command around the system: srl up starts the router and every service"),
    ("services/", 1.6, 5.3, "one folder per process of the system (a fleet: hosts of many robots)"),
    ("common/", 0.1, 1.45, ""),
)
COMMON_FLOORS = (  # tests/test_architecture.py's COMMON_FLOORS, from the ground up
    ("system", "OS: ticks, lifeline,\natomic files, JIT"),
    ("math", "dynamics, actor, critic,\nAlgorithm 1"),
    ("contracts", "keys, wire messages,\nsummaries"),
    ("config", "srl.toml, settings,\nflags"),
    ("net", "Zenoh transport\n(the only zenoh import)"),
    ("process", "signals, session,\nexit codes"),
)
ARCHITECTURE_SIZE = (10.0, 7.6)  # [in]


def key_pattern(name: str, every_robot: bool = False, chunks: tuple[tuple[str, str], ...] = ()) -> str:
    """The key expression of ``common.contracts.keys.<name>`` (a Topic, Service or pattern string),
    as the guide writes it: ``srl/<robot>/state`` (``srl/*/state``: every robot's; ``chunks``:
    other chunks filled in)."""
    value = getattr(keys, name, None)
    pattern = getattr(value, "pattern", value)
    if not isinstance(pattern, str) or not pattern.startswith("srl/"):
        raise FigureDataError(f"common.contracts.keys.{name} is not a key pattern of srl ({value!r})")
    if every_robot:
        pattern = pattern.replace("{robot}", "*")
    for chunk, filled in chunks:
        pattern = pattern.replace("{" + chunk + "}", filled)
    return pattern.replace("{", "<").replace("}", ">")


def link_label(link: Link) -> str:
    if not link.keys:
        return link.text
    patterns = [key_pattern(name, link.every_robot, link.chunks) for name in link.keys]
    if link.kind == "query":
        return "query " + ",\n".join(patterns) + " (lockstep only)"
    if link.kind == "token":
        return "\n".join([*patterns[:-1], patterns[-1] + " (token)"])
    return "\n".join(patterns)


def drawn_keys() -> set[str]:
    """The names in common.contracts.keys that the architecture figure draws."""
    return {name for link in LINKS for name in link.keys}


LINK_STYLE = {
    "publish": {"color": "black", "ls": "-"},
    "query": {"color": "tab:purple", "ls": "--"},
    "token": {"color": "0.35", "ls": "-"},
    "ros": {"color": "tab:brown", "ls": "-"},
}
FLOOR_COLOR = {"tools": "#e8f0fb", "services": "#e9f6ea", "robot": "#f3f3f3"}


def architecture_figure() -> Figure:
    width, height = ARCHITECTURE_SIZE
    fig = plt.figure(figsize=ARCHITECTURE_SIZE)
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.set_xlim(0, width)
    ax.set_ylim(0, height)
    ax.axis("off")
    for name, bottom, top, line in FLOORS:
        ax.add_patch(Rectangle((0.1, bottom), width - 0.2, top - bottom, facecolor="0.97", edgecolor="0.75", lw=1))
        ax.text(0.3, (bottom + top) / 2, name, rotation=90, ha="center", va="center", fontsize=12, weight="bold")
        if line:
            ax.text(0.55, top - 0.08, line, ha="left", va="top", fontsize=8.5, style="italic", color="0.35")
    ax.text(0.3, 7.45, "imports point down: tools/ -> services/ -> common/ (tests/test_architecture.py)", fontsize=8.5)
    cell = (width - 0.75) / len(COMMON_FLOORS)
    for i, (name, text) in enumerate(COMMON_FLOORS):
        left = 0.6 + i * cell
        ax.add_patch(
            FancyBboxPatch(
                (left + 0.04, 0.2),
                cell - 0.08,
                0.9,
                boxstyle="round,pad=0,rounding_size=0.06",
                facecolor="#fbf3e4",
                edgecolor="0.55",
            )
        )
        ax.text(left + cell / 2, 0.9, name + "/", ha="center", va="center", fontsize=10, weight="bold")
        ax.text(left + cell / 2, 0.5, text, ha="center", va="center", fontsize=8)
    ax.text(
        0.55,
        1.36,
        "from the ground up, left to right: a floor imports only its own and those to its left",
        fontsize=8.5,
        style="italic",
        color="0.35",
        va="top",
    )
    # the plant slot: a simulated plant or a real robot's bridge, the same keys either way
    ax.add_patch(Rectangle((1.3, 2.95), 2.1, 1.9, fill=False, edgecolor="0.45", ls=(0, (4, 3)), lw=1.0))
    ax.text(1.15, 3.9, "the plant: one of", rotation=90, ha="center", va="center", fontsize=8.5, color="0.3")
    ax.text(2.35, 3.9, "or", ha="center", va="center", fontsize=9, style="italic", color="0.3")
    for process in PROCESSES:
        (x, y), (w, h) = process.center, process.size
        ax.add_patch(
            FancyBboxPatch(
                (x - w / 2, y - h / 2),
                w,
                h,
                boxstyle="round,pad=0,rounding_size=0.08",
                facecolor=FLOOR_COLOR[process.floor],
                edgecolor="0.2" if process.floor != "robot" else "0.5",
                ls="-" if process.floor != "robot" else (0, (3, 2)),
                lw=1.3,
                zorder=2,
            )
        )
        first, _, rest = process.label.partition("\n")
        ax.text(x, y + (0.1 if rest else 0), first, ha="center", va="center", fontsize=10.5, weight="bold", zorder=3)
        if rest:
            ax.text(x, y - 0.05, rest, ha="center", va="top", fontsize=8.5, zorder=3, linespacing=1.15)
    for link in LINKS:
        style = LINK_STYLE[link.kind]
        start, end = link.path or (center_of(link.source), center_of(link.target))
        ax.add_patch(
            FancyArrowPatch(
                start,
                end,
                arrowstyle="-|>",
                connectionstyle=link.bend,
                mutation_scale=14,
                lw=1.5,
                color=style["color"],
                ls=style["ls"],
                zorder=4,
            )
        )
        lx, ly = link.label_at or ((start[0] + end[0]) / 2, (start[1] + end[1]) / 2)
        horizontal = abs(end[0] - start[0]) >= abs(end[1] - start[1])
        ax.text(
            lx,
            ly,
            link_label(link),
            ha=link.align if not horizontal or link.align != "center" else "center",
            va="bottom" if horizontal else "center",
            fontsize=8.8,
            family="monospace",
            color=style["color"],
            zorder=5,
            linespacing=1.1,
            bbox={"facecolor": "white", "edgecolor": "none", "alpha": 0.85, "pad": 0.5} if link.keys else None,
        )
    batch = key_pattern("STATE").replace("<robot>", keys.BATCH_CHUNK)
    ax.text(
        9.85,
        1.68,
        f"A fleet batches a round's messages of many robots: {batch} and the like. Every key: common/contracts/keys.py",
        ha="right",
        va="bottom",
        fontsize=7.5,
        color="0.35",
    )
    return fig


def center_of(name: str) -> tuple[float, float]:
    """Where the arrows of a link without a ``path`` meet ``name``: its box's center."""
    for process in PROCESSES:
        if process.name == name:
            return process.center
    raise FigureDataError(f"no process {name!r} in the architecture's table")


# -- the command ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class FigureSpec:
    name: str
    draw: Callable[[argparse.Namespace, Path], Figure]
    what: str


def _path(args: argparse.Namespace, root: Path) -> Figure:
    return path_figure(run_path(EpisodeRun(duration=args.duration)))


def _fleet(args: argparse.Namespace, root: Path) -> Figure:
    return fleet_figure(read_data(root / BENCHMARK_DATA / "fleet.json"))


def _actor(args: argparse.Namespace, root: Path) -> Figure:
    return actor_figure(read_data(root / BENCHMARK_DATA / "actor.json"))


def _architecture(args: argparse.Namespace, root: Path) -> Figure:
    return architecture_figure()


def _live_view(args: argparse.Namespace, root: Path) -> Figure:
    from tools.docs.live_view import draw

    return draw(args.duration)


FIGURES: tuple[FigureSpec, ...] = (
    FigureSpec("parking-path", _path, "the README's first run in the goal frame"),
    FigureSpec("fleet-scaling", _fleet, "srl bench fleet: CPU and missed deadlines against robots"),
    FigureSpec("actor-solve-time", _actor, "srl bench actor: solve time at N = 12"),
    FigureSpec("architecture", _architecture, "processes, keys and floors"),
    FigureSpec("live-view", _live_view, "srl view's Foxglove layout with the README's first run"),
)


def write_figures(
    out: Path, names: Sequence[str] = (), duration: float = EpisodeRun.duration, root: Path = ROOT
) -> list[Path]:
    """Draw the figures ``names`` (all: empty) into ``out``/NAME.png; the paths written."""
    known = {spec.name for spec in FIGURES}
    unknown = [name for name in names if name not in known]
    if unknown:
        raise FigureDataError(f"no figure {', '.join(unknown)}; choose from {', '.join(sorted(known))}")
    args = argparse.Namespace(duration=duration)
    written = []
    with plt.style.context(["default", STYLE]):  # matplotlib's defaults, not the user's matplotlibrc
        for spec in FIGURES:
            if not names or spec.name in names:
                written.append(save(spec.draw(args, root), out / f"{spec.name}.png"))
    return written


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m tools.docs.figures",
        description="Draw the guide's figures (docs/img/*.png) from this repository: "
        + "; ".join(f"{spec.name}: {spec.what}" for spec in FIGURES)
        + ".",
    )
    parser.add_argument("names", nargs="*", metavar="NAME", help="only these figures (default: every one)")
    parser.add_argument(
        "--out", type=Path, default=ROOT / IMAGES, help=f"the directory to write to (default: {IMAGES})"
    )
    parser.add_argument(
        "--duration",
        type=float,
        default=EpisodeRun.duration,
        help=f"the parking path's and the live view's episode [s] (default: {EpisodeRun.duration:g}, the README's)",
    )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        written = write_figures(args.out, args.names, args.duration)
    except FigureDataError as error:
        print(f"figures: {error}", file=sys.stderr)
        return 2
    for path in written:
        print(f"figures: wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
