"""``srl view``: a running system, live, in Foxglove (the Foxglove WebSocket protocol, ``foxglove-sdk``).

The same mapping as the recordings (:mod:`tools.record`: every robot's ``/<robot>/odom``,
``path``, ``cmd_vel``, ``srl/transition``, ``srl/critic_weights``, ``srl/actor_status`` and
``/target``, ROS 2 messages in CDR with their ``ros2msg`` definitions) fed by the same Zenoh
subscriber (:class:`tools.record.Feed`); only the sink differs: :class:`FoxgloveSink` logs each
sample on a foxglove-sdk channel of its own context, served by a WebSocket server bound to
loopback (127.0.0.1) unless ``--host`` says otherwise. ``docs/foxglove-layout.json`` opens the
view (3D scene, plots). From another host: an SSH tunnel (README), never an open port.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys

import foxglove

from common.arguments import COMMAND_SETTINGS, add_settings_arguments, settings_from_args
from common.lifeline import die_with_parent
from common.runtime import UsageError, connect_with_retry, stop_on_signals
from tools.record import Feed, Recorder

log = logging.getLogger(__name__)
DEFAULT_PORT = 8765


class FoxgloveSink:
    """CDR samples onto foxglove-sdk channels (one per topic, ``ros2msg`` schema, ``cdr``),
    served live by a WebSocket server of its own context."""

    def __init__(self, host: str, port: int) -> None:
        self.context = foxglove.Context()
        self.server = foxglove.start_server(name="srl", host=host, port=port, context=self.context)
        self.channels: dict[str, foxglove.Channel] = {}
        self.messages = 0

    @property
    def port(self) -> int:
        return int(self.server.port)

    def write(self, topic: str, ros_type: str, definition: str, data: bytes, t_ns: int) -> None:
        channel = self.channels.get(topic)
        if channel is None:
            schema = foxglove.Schema(name=ros_type, encoding="ros2msg", data=definition.encode())
            channel = self.channels[topic] = foxglove.Channel(
                topic, schema=schema, message_encoding="cdr", context=self.context
            )
        channel.log(data, log_time=t_ns)
        self.messages += 1

    def close(self) -> None:
        self.server.stop()


def add_view_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, COMMAND_SETTINGS["view"])
    parser.add_argument(
        "--port", type=int, default=DEFAULT_PORT, help=f"WebSocket port (0: any free one) (default: {DEFAULT_PORT})"
    )
    parser.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to bind; keep loopback and reach it from elsewhere by an SSH tunnel (README) "
        "(default: 127.0.0.1)",
    )
    parser.add_argument("--seconds", type=float, help="stop after this long (default: until Ctrl-C)")
    parser.add_argument(
        "--connect-timeout", type=float, default=30.0, help="[s] wait this long for the router (default: 30)"
    )


def cmd_view(args: argparse.Namespace) -> int:
    settings = settings_from_args(args)
    if not 0 <= args.port <= 65535:
        raise UsageError(f"--port must be 0..65535, got {args.port}")
    if args.seconds is not None and not (math.isfinite(args.seconds) and args.seconds > 0):
        raise UsageError(f"--seconds must be a positive number, got {args.seconds}")
    try:
        sink = FoxgloveSink(args.host, args.port)
    except RuntimeError as error:  # foxglove-sdk: the port is taken, the address is not ours
        raise UsageError(f"view: cannot serve on {args.host}:{args.port}: {error}") from None
    recorder = Recorder(sink, settings.plant.sampling_time, clock="wall")
    with stop_on_signals() as stop:
        die_with_parent(stop)
        try:
            feed = connect_with_retry(lambda: Feed(settings, recorder), settings, "view", args.connect_timeout, stop)
        except BaseException:
            sink.close()
            raise
        # the readiness line (srl up and the tests wait for it): where to point Foxglove
        print(
            f"srl view: serving every robot of {settings.transport.router} on ws://{args.host}:{sink.port} "
            "(Foxglove: Open connection -> Foxglove WebSocket; layout docs/foxglove-layout.json); Ctrl-C ends it",
            file=sys.stderr,
            flush=True,
        )
        stop.wait(args.seconds)
        feed.close()
    print(json.dumps({"view": f"ws://{args.host}:{sink.port}", "messages": sink.messages}), flush=True)
    return 0
