"""The live view's figure (docs/img/live-view.png): the Foxglove layout ``srl view`` ships, drawn
with the messages ``srl view`` would serve for the README's first run.

Foxglove itself is an application this repository cannot run headless, so the figure is what it
would draw, computed from the same two sources: the layout is
:func:`tools.recording.view.foxglove_layout` (docs/foxglove-layout.json), read panel by panel (its
split proportions, titles, 3D topics and plot series); the messages are the ROS 2 CDR samples of
:class:`tools.recording.record.Recorder`, the mapping ``srl view`` and ``srl record`` share, fed by
:func:`tools.recording.record.record_episode` with one in-process episode and decoded back with
its own type store. A plot series the layout names (``/<robot>/srl/transition.stage_cost``,
``...q_weights[3]``) is read from the decoded messages by that path, so a series or topic the
mapping no longer has fails here instead of drawing an empty panel.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

ROBOT = "tb3_0"  # the layout's robot, as docs/foxglove-layout.json names it
_STEP = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)(?:\[(\d+)\])?")


class LiveViewError(ValueError):
    """The layout names a topic or field that the recorder's messages do not have."""


@dataclass(frozen=True)
class Panel:
    """One panel of the layout and where it sits (figure fractions: left, bottom, width, height)."""

    kind: str  # "ThreeDee" or "Plot"
    title: str
    config: dict[str, Any]
    box: tuple[float, float, float, float]


def panels(node: dict[str, Any], box: tuple[float, float, float, float] = (0.0, 0.0, 1.0, 1.0)) -> list[Panel]:
    """The layout's panels with their boxes: a split divides its box by its items' proportions
    (``row``: left to right, ``column``: top to bottom)."""
    if node.get("type") == "panel":
        return [Panel(node["panelType"], node.get("title", ""), node.get("config", {}), box)]
    if node.get("type") != "split":
        raise LiveViewError(f"a layout node of type {node.get('type')!r} (a panel or a split expected)")
    items = node["items"]
    total = sum(float(item.get("proportion", 1.0)) for item in items)
    left, bottom, width, height = box
    found: list[Panel] = []
    offset = 0.0
    for item in items:
        share = float(item.get("proportion", 1.0)) / total
        if node["direction"] == "row":
            part = (left + offset * width, bottom, share * width, height)
        else:  # column: the first item on top
            part = (left, bottom + (1.0 - offset - share) * height, width, share * height)
        found += panels(item["content"], part)
        offset += share
    return found


def field_value(message: Any, path: str) -> float:
    """``stage_cost``, ``q_weights[3]``, ``header.stamp.sec`` of a decoded message, as a float."""
    value = message
    for step in path.split("."):
        match = _STEP.fullmatch(step)
        if match is None or not hasattr(value, match.group(1)):
            raise LiveViewError(f"no field {path!r} in {type(value).__name__}")
        value = getattr(value, match.group(1))
        if match.group(2) is not None:
            value = value[int(match.group(2))]
    return float(value)


@dataclass
class ViewData:
    """The decoded messages per topic (time [s] from the first, message), and the run they show."""

    messages: dict[str, list[tuple[float, Any]]]
    title: str
    seconds: float  # the run's length: every plot's time axis

    def series(self, value: str) -> tuple[np.ndarray, np.ndarray]:
        """A plot series of the layout (``/topic.field``): its times [s] and values."""
        topic, _, path = value.partition(".")
        if topic not in self.messages:
            raise LiveViewError(f"the layout plots {value!r} but srl view serves no {topic}")
        rows = [(t, field_value(message, path)) for t, message in self.messages[topic]]
        return np.array([t for t, _ in rows]), np.array([v for _, v in rows])

    def last(self, topic: str) -> Any:
        if topic not in self.messages:
            raise LiveViewError(f"the layout shows {topic} but srl view serves no such topic")
        return self.messages[topic][-1][1]


def view_data(
    agent: str = "rlqv", horizon: int = 12, start: tuple[float, float] = (2.0, 2.0), duration: float = 30.0
) -> ViewData:
    """The README's first run in this process (no JIT: the same numbers), through the recorder's
    mapping into CDR, decoded back."""
    from common.config.assembly import run_episode
    from common.config.settings import Settings
    from tools.recording.record import Recorder, RosMapping, record_episode
    from tools.recording.sinks import MemorySink

    settings = Settings.load(
        actor={"agent": agent, "horizon": horizon, "jit": False}, episode={"start": start, "duration": duration}
    )
    episode = run_episode(settings)
    sink = MemorySink()
    recorder = Recorder(sink, settings.plant.sampling_time, clock="steps")
    record_episode(recorder, episode, ROBOT, origin_ns=0)
    ros = RosMapping()
    messages = {
        topic: [(t_ns * 1e-9, ros.store.deserialize_cdr(data, ros_type)) for t_ns, ros_type, data in samples]
        for topic, samples in sink.samples.items()
    }
    title = (
        "What srl view shows in Foxglove with docs/foxglove-layout.json, drawn from the messages it serves for\n"
        f"srl run --agent {agent} --horizon {horizon} --start {start[0]:g},{start[1]:g} --duration {duration:g} "
        f"(J = {episode.accumulated_cost:.4f}; in process: no tick jitter)"
    )
    return ViewData(messages, title, duration)


def _xy(pose: Any) -> tuple[float, float, float]:
    """A geometry_msgs/Pose's x, y and yaw (a planar quaternion)."""
    q = pose.orientation
    return float(pose.position.x), float(pose.position.y), 2.0 * float(np.arctan2(q.z, q.w))


def draw_scene(ax: Axes, panel: Panel, data: ViewData) -> None:
    """The 3D panel seen from above, as its camera is set (``phi = 0``, orthographic): each topic
    as the layout draws it (``line``: a path, ``arrow``: a pose, ``axis``: a frame's axes)."""
    for topic, settings in panel.config.get("topics", {}).items():
        kind = settings.get("type")
        message = data.last(topic)
        if kind == "line":
            xy = np.array([_xy(p.pose)[:2] for p in message.poses])
            ax.plot(xy[:, 0], xy[:, 1], color="tab:green", lw=1.5, label=topic)
        elif kind == "arrow":
            x, y, yaw = _xy(message.pose.pose)
            ax.annotate(
                "", (x + 0.3 * np.cos(yaw), y + 0.3 * np.sin(yaw)), (x, y), arrowprops={"arrowstyle": "->", "lw": 2}
            )
            ax.plot([], [], color="black", label=f"{topic} (arrow)")
        elif kind == "axis":
            x, y, yaw = _xy(message.pose)
            scale = float(settings.get("axisScale", 0.3))
            ax.plot([x, x + scale * np.cos(yaw)], [y, y + scale * np.sin(yaw)], color="red", lw=2, label=f"{topic} x")
            ax.plot([x, x - scale * np.sin(yaw)], [y, y + scale * np.cos(yaw)], color="green", lw=2)
        else:
            raise LiveViewError(f"a 3D topic drawn as {kind!r}: not one this figure knows")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, color="0.85")
    ax.set_xlabel(f"x [m] ({panel.config.get('fixedFrame', '')} frame)")
    ax.set_ylabel("y [m]")
    ax.legend(loc="lower right", fontsize=7.5)


LEGEND_SERIES = 6  # a panel of more series (the critic's 21 weights) names its first and last


def draw_plot(ax: Axes, panel: Panel, data: ViewData) -> None:
    paths = panel.config.get("paths", [])
    labels = [series.get("label", series["value"]) for series in paths]
    for series, label in zip(paths, labels, strict=True):
        times, values = data.series(series["value"])
        ax.plot(times, values, lw=1.2, label=label if len(paths) <= LEGEND_SERIES else None)
    ax.grid(True, color="0.85")
    if len(paths) <= LEGEND_SERIES:
        ax.legend(loc="upper right", fontsize=7, ncol=len(paths))
    else:
        ax.text(
            0.99,
            0.95,
            f"{len(paths)} series: {labels[0]} .. {labels[-1]}",
            transform=ax.transAxes,
            ha="right",
            va="top",
            fontsize=7,
        )
    ax.tick_params(labelsize=7.5)
    ax.set_xlim(0.0, data.seconds)


def live_view_figure(data: ViewData, layout: dict[str, Any]) -> Figure:
    """Every panel of ``layout`` (Foxglove's layout JSON) in its place, drawn from ``data``."""
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(11.0, 6.6))
    fig.suptitle(data.title, fontsize=9)
    drawers = {"ThreeDee": draw_scene, "Plot": draw_plot}
    for panel in panels(layout["content"]):
        if panel.kind not in drawers:
            raise LiveViewError(f"a {panel.kind} panel: not one this figure knows")
        left, bottom, width, height = panel.box
        # each panel's box inside the figure, below the title, with room for its title and ticks
        ax = fig.add_axes((0.06 + left * 0.92, 0.08 + bottom * 0.84, width * 0.92 - 0.06, height * 0.84 - 0.07))
        ax.set_title(panel.title, fontsize=8.5)
        drawers[panel.kind](ax, panel, data)
    return fig


def draw(duration: float = 30.0) -> Figure:
    from tools.recording.view import foxglove_layout

    return live_view_figure(view_data(duration=duration), json.loads(foxglove_layout([ROBOT])))
