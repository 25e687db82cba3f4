"""``srl view``: a running system, live, in Foxglove (the Foxglove WebSocket protocol, ``foxglove-sdk``).

The same mapping as the recordings (:mod:`tools.recording.record`: every robot's ``/<robot>/odom``,
``path``, ``cmd_vel``, ``srl/transition``, ``srl/critic_weights``, ``srl/actor_status``, ``/target``
and ``/tf``, ROS 2 messages in CDR with their ``ros2msg`` definitions) fed by the same Zenoh
subscriber (:class:`tools.recording.record.Feed`); only the sink differs: :class:`FoxgloveSink` logs each
sample on a foxglove-sdk channel of its own context, served by a WebSocket server bound to
loopback (127.0.0.1) unless ``--host`` says otherwise. ``docs/foxglove-layout.json`` opens the
view (3D scene, plots). From another host: an SSH tunnel (docs/recordings.md), never an open port.
"""

from __future__ import annotations

import argparse
import json
import logging
from typing import Any

import foxglove

from common.config.arguments import UsageError, settings_from_args
from tools.recording.record import (
    ODOM_FRAME,
    Feed,
    Recorder,
    base_frame,
    positive_seconds,
    yield_cpu_to_the_loop,
)
from tools.recording.sinks import CdrChannels, RowsByOne

log = logging.getLogger(__name__)


class FoxgloveSink(RowsByOne):
    """CDR samples onto foxglove-sdk channels (one per topic, ``ros2msg`` schema, ``cdr``:
    :class:`~tools.recording.sinks.CdrChannels`), served live by a WebSocket server of its own
    context."""

    def __init__(self, host: str, port: int) -> None:
        self.context = foxglove.Context()
        self.server = foxglove.start_server(name="srl", host=host, port=port, context=self.context)
        self.channels = CdrChannels(self.context)
        self.messages = 0

    @property
    def port(self) -> int:
        return int(self.server.port)

    def write(self, topic: str, ros_type: str, definition: str, data: bytes, t_ns: int) -> None:
        self.channels.log_of(topic, ros_type, definition)(data, t_ns)
        self.messages += 1

    def close(self) -> None:
        self.server.stop()


def cmd_view(args: argparse.Namespace) -> int:
    settings = settings_from_args(args)
    if not 0 <= args.port <= 65535:
        raise UsageError(f"--port must be 0..65535, got {args.port}")
    positive_seconds(args.seconds)
    if args.host not in ("127.0.0.1", "localhost", "::1"):
        log.warning(
            "view: serving on %s without authentication: whoever reaches the port sees every robot "
            "(prefer the loopback default and an SSH tunnel, docs/recordings.md)",
            args.host,
        )
    yield_cpu_to_the_loop()
    try:
        sink = FoxgloveSink(args.host, args.port)
    except RuntimeError as error:  # foxglove-sdk: the port is taken, the address is not ours
        raise UsageError(f"view: cannot serve on {args.host}:{args.port}: {error}") from None
    recorder = Recorder(sink, settings.plant.sampling_time, clock="wall")
    url = f"ws://{args.host}:{sink.port}"  # the bound port (--port 0: the one the OS chose)
    # the readiness line (srl up and the tests wait for it): where to point Foxglove
    ready = (
        f"srl view: serving every robot of {settings.transport.router} on {url} "
        "(Foxglove: Open connection -> Foxglove WebSocket; layout docs/foxglove-layout.json); Ctrl-C ends it"
    )
    Feed.run(settings, recorder, "view", args, lambda: ready)
    print(json.dumps({"view": url, "messages": sink.messages}), flush=True)
    return 0


def foxglove_layout(robots: list[str]) -> str:
    """The Foxglove layout of docs/foxglove-layout.json (``foxglove.layouts``): the 3D scene first,
    fixed in ``odom`` and following the first robot's ``<robot>/base_footprint`` from ``/tf``
    (docs/recordings.md "Frames"), seen from above with every robot's odometry, path, base frame
    and the target (its pose and the ``goal`` frame), beside plots of the costs, the critic
    weights, the solve time, staleness and tick jitter (the first robot's; add series for more,
    the topics are ``/<robot>/...``)."""
    import foxglove.layouts as fl

    scene_topics: dict[str, Any] = {
        "/target": fl.BaseRendererPoseTopicSettings(visible=True, type="axis", axis_scale=0.3)
    }
    for robot in robots:
        scene_topics[f"/{robot}/odom"] = fl.BaseRendererPoseTopicSettings(visible=True, type="arrow")
        scene_topics[f"/{robot}/path"] = fl.BaseRendererPosesTopicSettings(visible=True, type="line", line_width=0.02)
    first = robots[0]

    def plot(title: str, *series: tuple[str, str]) -> Any:
        return fl.PlotPanel(
            title=title,
            config=fl.PlotConfig(paths=[fl.PlotSeries(value=value, label=label) for value, label in series]),
        )

    scene = fl.ThreeDeePanel(
        title=f"robots ({ODOM_FRAME} frame, following {base_frame(first)})",
        config=fl.ThreeDeeConfig(
            fixed_frame=ODOM_FRAME,
            follow_tf=base_frame(first),
            follow_mode="follow-position",
            scene=fl.BaseRendererSceneSettings(
                transforms=fl.BaseRendererTransforms(show_label=True, label_size=0.15, axis_size=0.25)
            ),
            topics=scene_topics,
            camera_state=fl.ThreeDeeCameraState(distance=8.0, perspective=False, phi=0.0, target=(0.0, 0.0, 0.0)),
        ),
    )
    plots = fl.SplitContainer(
        direction="column",
        items=[
            fl.SplitItem(
                content=plot(
                    "costs",
                    (f"/{first}/srl/transition.stage_cost", "stage cost c_k"),
                    (f"/{first}/srl/transition.accumulated_cost", "J"),
                )
            ),
            fl.SplitItem(
                content=plot(
                    "critic weights (version in the raw message)",
                    *((f"/{first}/srl/critic_weights.q_weights[{i}]", f"w{i}") for i in range(15)),
                    *((f"/{first}/srl/critic_weights.v_weights[{i}]", f"v{i}") for i in range(6)),
                )
            ),
            fl.SplitItem(
                content=plot(
                    "actor [ms, steps]",
                    (f"/{first}/srl/actor_status.solve_ms", "solve ms"),
                    (f"/{first}/srl/actor_status.jitter_ms", "tick jitter ms"),
                    (f"/{first}/srl/actor_status.staleness_steps", "staleness steps"),
                )
            ),
            fl.SplitItem(
                content=plot(
                    "action",
                    (f"/{first}/cmd_vel.twist.linear.x", "v [m/s]"),
                    (f"/{first}/cmd_vel.twist.angular.z", "omega [rad/s]"),
                )
            ),
        ],
    )
    layout = fl.Layout(
        content=fl.SplitContainer(
            direction="row",
            items=[fl.SplitItem(proportion=3, content=scene), fl.SplitItem(proportion=2, content=plots)],
        )
    )
    return json.dumps(json.loads(layout.to_json()), indent=1) + "\n"
