"""Recordings and the live view: srl's messages as ROS 2 messages, into an MCAP file or to Foxglove.

One mapping (:class:`RosMapping`, :class:`Recorder`) from srl's messages to ROS 2 topics, and two
sinks that take its CDR samples: :class:`McapSink` (an MCAP file in the rosbag2 layout: profile
``ros2``, ``ros2msg`` schemas, ``cdr`` messages, the ``rosbag2`` metadata record that
``ros2 bag info`` reads) and, in :mod:`tools.recording.view`, the Foxglove WebSocket server. Per robot:

==========================  ==============================  =========================================
topic                       type                            what
==========================  ==============================  =========================================
``/<robot>/odom``           ``nav_msgs/msg/Odometry``       the state the robot reports (goal-frame
                                                            pose, frame :attr:`PoseFrames.pose_frame`,
                                                            child ``base_footprint``)
``/<robot>/path``           ``nav_msgs/msg/Path``           the last :data:`PATH_POSES` poses of every
                                                            :data:`PATH_STRIDE`-th step, every
                                                            :data:`PATH_EVERY` steps
``/<robot>/cmd_vel``        ``geometry_msgs/msg/TwistStamped``  the action u_k, one per step
``/<robot>/srl/transition`` ``srl_msgs/msg/Transition``     s_k, u_k, c_k and J, one per step
``/<robot>/srl/critic_weights`` ``srl_msgs/msg/CriticWeights``  version, trained step, w, v, residuals
``/<robot>/srl/actor_status``   ``srl_msgs/msg/ActorStatus``    solve time, staleness, tick jitter (1 Hz)
``/target``                 ``geometry_msgs/msg/PoseStamped``  the target: the origin of the goal frame
``/tf``                     ``tf2_msgs/msg/TFMessage``      ``odom -> <robot>/base_footprint`` per state,
                                                            ``odom -> goal``, ``map -> odom`` when localized
==========================  ==============================  =========================================

The frames (REP 105, https://www.ros.org/reps/rep-0105.html; docs/recordings.md "Frames"): srl's
states are in the goal frame (docs/concepts.md "Frames: the goal frame"); :class:`PoseFrames` says
where that frame sits: the goal pose ``g`` in the pose frame (``odom``, or ``map`` when localized)
and, when the robot bridge reports it, the ``map -> odom`` correction. ``/tf`` carries
``odom -> <robot>/base_footprint`` (the robot's pose in its odometry frame), ``odom -> goal`` (the
target as a frame) and ``map -> odom``; a simulated plant's goal frame is its odom frame (``g`` the
identity).

srl's own types are ROS 2 message definitions too (``srl_msgs/msg/*``, :data:`SRL_MSGS`), so every
channel of a recording is CDR with its full ``ros2msg`` definition in the schema: Foxglove decodes
and plots them, ``ros2 bag info`` lists them. The CDR and the definitions come from ``rosbags``
(its Humble typestore, srl's types registered in a private copy); the MCAP container is written by
foxglove-sdk (:class:`McapSink`) and read by the ``mcap`` library. The messages written at every
step and state of every robot (odometry, ``/tf``, ``cmd_vel``, transitions, critic weights, the
path) are packed by :mod:`tools.recording.cdr` instead, byte for byte what rosbags writes for them
(tests/test_record_tf.py compares the two), at a fraction of its CPU: a recorder beside a fleet
writes thousands of them a second.

Time: a step ``k`` of a robot's episode is placed at ``origin + k delta`` (``origin``: the
recording's start for ``srl run`` and the experiment; for a recorder over Zenoh, the arrival of the
episode's first transition minus its steps), so actions and transitions are exactly ``delta``
apart. States arrive at their own rate: stamped on arrival (``clock = "wall"``, real time) or, in
lockstep, one step each (``clock = "steps"``).
"""

from __future__ import annotations

import contextlib
import functools
import glob
import json
import logging
import math
import os
import re
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Literal, Protocol

import foxglove
import numpy as np
from foxglove.mcap import MCAPCompression, MCAPWriteOptions
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from common.contracts.columns import Columns
from common.contracts.pose_sources import ODOMETRY_ONLY
from common.math.frames import Pose2D, from_goal_frame, to_goal_frame
from common.math.loop import Episode
from tools.recording.cdr import Vector, odometry_cdr, tf_cdr, transition_cdr, twist_stamped_cdr, weights_cdr

log = logging.getLogger(__name__)

Clock = Literal["wall", "steps"]
DISTRO = "humble"  # the message definitions of the recording (the same in Jazzy for these types)
ODOM_FRAME = "odom"  # REP 105's odometry frame: a simulated plant's goal frame (the target is its origin)
MAP_FRAME = "map"  # REP 105's localization frame: the pose frame of a localized robot
GOAL_FRAME = "goal"  # the actor's frame: the target pose, heading 0 (docs/concepts.md)
BASE_FRAME = "base_footprint"
IDENTITY = Pose2D(0.0, 0.0, 0.0)
TF_TOPIC = "/tf"
TF_MESSAGE, TRANSFORM_STAMPED = "tf2_msgs/msg/TFMessage", "geometry_msgs/msg/TransformStamped"
PATH_STRIDE = 5  # the path holds every 5th step's pose (2 a second at delta = 0.1 s; /odom has every one)
PATH_POSES = 120  # the path keeps the last 60 s of them: bounded, however long the recording
PATH_EVERY = 10  # a path message every 10 steps (1 Hz), ending at that step: re-sent whole each time
TARGET_TOPIC = "/target"
ODOMETRY, PATH, TWIST_STAMPED = "nav_msgs/msg/Odometry", "nav_msgs/msg/Path", "geometry_msgs/msg/TwistStamped"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TRANSITION, WEIGHTS, STATUS = "srl_msgs/msg/Transition", "srl_msgs/msg/CriticWeights", "srl_msgs/msg/ActorStatus"
# srl's own message types, ROS 2 message definitions (units in the comments, as in common/contracts/messages.py)
SRL_MSGS = {
    TRANSITION: """\
# One replay sample (s_k, u_k, c_k) of the paper's Algorithm 1; header.stamp = origin + k delta.
std_msgs/Header header
uint64 episode
uint32 step            # k
float64 x              # s_k [m], goal frame
float64 y              # [m]
float64 alpha          # [rad], unwrapped
float64 v              # u_k [m/s]
float64 omega          # [rad/s]
float64 stage_cost     # c_k = delta r(s_k, u_k)
float64 accumulated_cost  # J up to and including c_k
""",
    WEIGHTS: """\
# The critic's weights (common/contracts/messages.py CriticWeights).
std_msgs/Header header
uint64 episode
uint64 version        # strictly increasing (the critic service: a time-based base)
int32 trained_step     # the last transition step the fit used (-1: initial weights)
float64[15] q_weights  # w of Qhat(s, u; w) = <w, phi_Q(s, u)>
float64[6] v_weights   # v of Jhat(s; v) = <v, phi_V(s)>
float64 q_residual     # TD residual of the fit (NaN: no fit)
float64 v_residual
uint32 pairs           # TD pairs in the fit
""",
    STATUS: """\
# The actor's health (its 1 Hz status; per step in srl run's recordings).
std_msgs/Header header
uint32 step
float64 solve_ms           # the newest solve [ms] (NaN: no solve, e.g. held by the arrival rule)
float64 staleness_steps    # how many steps old the weights the actor used were
float64 jitter_ms          # the newest tick's distance from its deadline [ms] (NaN: not real time)
float64 missed_deadlines
float64 solver_failures
float64 weights_version
""",
}
# rosbag2's QoS of a recorded topic (reliable, volatile, keep last 10), as rosbag2_storage_mcap
# writes it into each channel's metadata
QOS_YAML = (
    "- history: 1\n  depth: 10\n  reliability: 1\n  durability: 2\n"
    "  deadline:\n    sec: 2147483647\n    nsec: 4294967295\n"
    "  lifespan:\n    sec: 2147483647\n    nsec: 4294967295\n  liveliness: 1\n"
    "  liveliness_lease_duration:\n    sec: 2147483647\n    nsec: 4294967295\n"
    "  avoid_ros_namespace_conventions: false\n"
)


class RecordingError(RuntimeError):
    """The recording cannot be written (a bad path, a full disk): one line that says why."""


class RosMapping:
    """ROS 2 types: their CDR (``rosbags``) and their ``ros2msg`` definitions, srl's own included."""

    def __init__(self) -> None:
        self.store: Any = get_typestore(Stores.ROS2_HUMBLE)
        for name, text in SRL_MSGS.items():
            self.store.register(get_types_from_msg(text, name))
        self.types: dict[str, Any] = self.store.types
        self._definitions: dict[str, str] = {}

    def definition(self, ros_type: str) -> str:
        if ros_type not in self._definitions:
            self._definitions[ros_type] = self.store.generate_msgdef(ros_type, ros_version=2)[0]
        return self._definitions[ros_type]

    def cdr(self, message: Any, ros_type: str) -> bytes:
        return bytes(self.store.serialize_cdr(message, ros_type, little_endian=True))

    def path_cdr(self, t_ns: int, frame: str, stamps: np.ndarray, table: np.ndarray, frames: Sequence[str]) -> bytes:
        """``nav_msgs/Path`` of the poses ``table`` (rows x, y, alpha), stamped ``stamps`` [ns] in
        ``frames`` (one each), the path stamped ``t_ns`` in ``frame``, as CDR: the bytes :meth:`cdr`
        gives for the same message, written with numpy (a path of :data:`PATH_POSES` poses every
        second per robot would be most of a recorder's CPU through rosbags' per-field serializer). The layout is
        :class:`tools.recording.cdr.CdrLayout`'s. Poses in more than one frame go through :meth:`cdr`."""
        distinct = set(frames)
        if len(distinct) > 1:
            message = self.types[PATH](
                header=self.header(t_ns, frame),
                poses=[
                    self.types[POSE_STAMPED](header=self.header(int(stamp), f), pose=self.pose(pose))
                    for stamp, pose, f in zip(stamps, table, frames, strict=True)
                ],
            )
            return self.cdr(message, PATH)
        own = distinct.pop().encode() + b"\0" if distinct else b"\0"
        head = frame.encode() + b"\0"
        count = len(table)
        alpha = table[:, 2]
        values = np.column_stack(
            (
                table[:, 0],
                table[:, 1],
                np.zeros(count),
                np.zeros(count),
                np.zeros(count),
                np.sin(alpha / 2),
                np.cos(alpha / 2),
            )
        )
        string = len(own)

        def align(offset: int, size: int) -> int:
            return -(-offset // size) * size

        start = align(12 + len(head), 4) + 4  # after the header and the sequence's length
        # a pose's doubles end 8-aligned, so every pose after the first starts 8-aligned: the
        # first may be padded differently (by where the header left it), the others alike
        first_doubles = align(start + 12 + string, 8) - start
        rest_doubles = align(12 + string, 8)
        sizes = ([first_doubles + 56] + [rest_doubles + 56] * (count - 1)) if count else []
        out = np.zeros(4 + start + sum(sizes), dtype=np.uint8)
        out[:4] = (0, 1, 0, 0)  # CDR_LE encapsulation
        payload = out[4:]
        sec, nanosec = divmod(int(t_ns), 1_000_000_000)
        payload[:12] = np.frombuffer(np.array([sec, nanosec, len(head)], dtype="<u4").tobytes(), np.uint8)
        payload[12 : 12 + len(head)] = np.frombuffer(head, np.uint8)
        payload[start - 4 : start] = np.frombuffer(np.uint32(count).astype("<u4").tobytes(), np.uint8)

        def fill(block: np.ndarray, rows: slice, doubles_at: int) -> None:
            secs, nanos = np.divmod(stamps[rows], 1_000_000_000)
            fields = np.column_stack((secs, nanos, np.full(len(secs), string))).astype("<u4")
            block[:, :12] = fields.view(np.uint8).reshape(-1, 12)
            block[:, 12 : 12 + string] = np.frombuffer(own, np.uint8)
            block[:, doubles_at:] = np.ascontiguousarray(values[rows], dtype="<f8").view(np.uint8).reshape(-1, 56)

        if count:
            fill(payload[start : start + sizes[0]].reshape(1, -1), slice(0, 1), first_doubles)
            if count > 1:
                rest = payload[start + sizes[0] :].reshape(count - 1, rest_doubles + 56)
                fill(rest, slice(1, None), rest_doubles)
        return out.tobytes()

    def deserialize(self, data: bytes, ros_type: str) -> Any:
        return self.store.deserialize_cdr(data, ros_type)

    # -- builders ---------------------------------------------------------------------
    def header(self, t_ns: int, frame: str = ODOM_FRAME) -> Any:
        sec, nanosec = divmod(int(t_ns), 1_000_000_000)
        return self.types["std_msgs/msg/Header"](
            stamp=self.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame
        )

    def transform(self, t_ns: int, parent: str, child: str, pose: Pose2D) -> Any:
        """``geometry_msgs/TransformStamped``: the planar ``pose`` of ``child`` in ``parent``."""
        t = self.types
        return t[TRANSFORM_STAMPED](
            header=self.header(t_ns, parent),
            child_frame_id=child,
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](x=float(pose.x), y=float(pose.y), z=0.0),
                rotation=self.pose(pose).orientation,
            ),
        )

    def pose(self, state: Vector) -> Any:
        t = self.types
        x, y, alpha = (float(c) for c in state[:3])
        return t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
            orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(alpha / 2), w=math.cos(alpha / 2)),
        )

    def twist(self, v: float, omega: float) -> Any:
        vector = self.types["geometry_msgs/msg/Vector3"]
        return self.types["geometry_msgs/msg/Twist"](
            linear=vector(x=float(v), y=0.0, z=0.0), angular=vector(x=0.0, y=0.0, z=float(omega))
        )


class Sink(Protocol):
    """Where CDR samples go: an MCAP file (:class:`McapSink`) or a live server (tools/recording/view.py)."""

    def write(self, topic: str, ros_type: str, definition: str, data: bytes, t_ns: int) -> None: ...
    def close(self) -> None: ...


class MemorySink:
    """A :class:`Sink` that keeps every sample in memory, ``(t_ns, ros_type, data)`` per topic: for
    a short episode only (tests, the live view's figure in tools/docs/live_view.py)."""

    def __init__(self) -> None:
        self.samples: dict[str, list[tuple[int, str, bytes]]] = {}

    def write(self, topic: str, ros_type: str, definition: str, data: bytes, t_ns: int) -> None:
        self.samples.setdefault(topic, []).append((t_ns, ros_type, data))

    def close(self) -> None:
        pass


@functools.lru_cache(maxsize=4096)  # a fleet's ids, bounded whatever names arrive
def ros_name(robot: str) -> str:
    """A robot id as a ROS 2 name chunk (letters, digits, underscores): ``rlqv+-N12-s000`` ->
    ``rlqvplus_N12_s000``; srl's usual ids (``tb3_0``) stay as they are."""
    return re.sub(r"[^A-Za-z0-9_]", "_", robot.replace("+", "plus"))


def open_for_writing(path: Path) -> IO[bytes]:
    """The file, created (or truncated) now: a bad or unwritable path fails before any run starts."""
    path = Path(path).expanduser()
    if path.suffix != ".mcap":
        raise RecordingError(f"a recording is an MCAP file: {path} does not end in .mcap")
    if path.is_dir():
        raise RecordingError(f"cannot record to {path}: it is a directory")
    if not path.parent.is_dir():
        raise RecordingError(f"cannot record to {path}: no directory {path.parent}")
    try:
        return path.open("wb")
    except OSError as error:
        raise RecordingError(f"cannot record to {path}: {error.strerror}") from None


class _Disk:
    """The file as an MCAP writer sees it (foxglove's ``McapWritable``: write, seek, flush),
    keeping the first error any of them met (a buffered file's seek writes its buffer too):
    :class:`McapSink` raises it at its next write instead of handing the writer more messages,
    each of which it would refuse with a log line of its own."""

    def __init__(self, file: IO[bytes]) -> None:
        self.file = file
        self.error: OSError | None = None

    def _kept(self, call: Callable[..., Any], *args: Any) -> Any:
        try:
            return call(*args)
        except OSError as error:
            self.error = self.error or error
            raise

    def write(self, data: bytes | bytearray) -> int:
        return int(self._kept(self.file.write, data))

    def flush(self) -> None:
        self._kept(self.file.flush)

    def seek(self, offset: int, whence: int = 0) -> int:
        return int(self._kept(self.file.seek, offset, whence))


class McapSink:
    """An MCAP file in the rosbag2 layout, streamed: a chunk goes to the disk when it holds
    :data:`CHUNK_BYTES` or is :data:`CHUNK_SECONDS` old, whichever comes first, so a recorder killed
    outright loses at most that much; :meth:`close` adds the ``rosbag2`` metadata and the summary.

    The writer is foxglove-sdk's (Rust's ``mcap`` crate behind a Python channel per topic: ~1 us a
    message against ~4 us for the pure-Python ``mcap`` writer, which srl keeps for reading). Each
    sink has a ``foxglove.Context`` of its own, so its channels reach this file only (not a live
    view's server in the same process). The writer numbers each channel's messages from 1 and
    stamps their publish time with their log time, as the rosbag2 layout has them.

    The writer keeps one index entry per chunk, naming every channel in it, for the summary it
    writes at the end: a recording's memory grows with its chunks (100 robots, 600 channels: ~24 KB
    a chunk). Big chunks keep that growth small (at 100 robots ~0.7 MB a minute, not 12.5 with
    256 KiB chunks) and cost less to write; the age bound keeps a recording of one robot, a few KB
    a second, on the disk within seconds.

    A write that fails (a full disk) is known when the writer writes a chunk (full, or at its
    age): from the next :meth:`write` on, every one raises :class:`RecordingError` saying why and
    nothing more goes to the writer (which logs one line for the message whose chunk failed)."""

    CHUNK_BYTES = 4 * 1024 * 1024
    CHUNK_SECONDS = 2.0

    def __init__(self, path: Path, extra_metadata: dict[str, str] | None = None) -> None:
        self.path = Path(path).expanduser()
        self.file = open_for_writing(self.path)
        self.context = foxglove.Context()
        options = MCAPWriteOptions(
            profile="ros2",
            chunk_size=self.CHUNK_BYTES,
            compression=MCAPCompression.Zstd,
            compression_threads=0,  # compress on the writer's own thread (the recorder's niceness)
            # a chunk goes to the file whole, never a header to be filled in later: a file cut
            # short (a recorder killed) ends at a record's end and reads up to it
            disable_seeking=True,
        )
        self.disk = _Disk(self.file)
        self.writer = foxglove.open_mcap(self.disk, context=self.context, writer_options=options)
        self.schemas: dict[str, foxglove.Schema] = {}
        self.channels: dict[str, foxglove.Channel] = {}
        self.counts: dict[str, int] = {}
        self.types: dict[str, str] = {}
        self.first_ns: int | None = None
        self.last_ns = 0
        self.extra_metadata = extra_metadata or {}
        self.closed = False
        self.failure: str | None = None
        self.chunk_started = time.monotonic()

    def write(self, topic: str, ros_type: str, definition: str, data: bytes, t_ns: int) -> None:
        if self.failure is None and self.disk.error is not None:  # a chunk the last write completed
            self.failure = f"cannot write {self.path}: {self.disk.error}"
        if self.failure is not None:
            raise RecordingError(self.failure)
        channel = self.channels.get(topic)
        if channel is None:
            schema = self.schemas.get(ros_type)
            if schema is None:
                schema = self.schemas[ros_type] = foxglove.Schema(
                    name=ros_type, encoding="ros2msg", data=definition.encode()
                )
            channel = self.channels[topic] = foxglove.Channel(
                topic,
                schema=schema,
                message_encoding="cdr",
                context=self.context,
                metadata={"offered_qos_profiles": QOS_YAML},
            )
            self.counts[topic], self.types[topic] = 0, ros_type
        self.counts[topic] += 1
        self.first_ns = t_ns if self.first_ns is None else min(self.first_ns, t_ns)
        self.last_ns = max(self.last_ns, t_ns)
        channel.log(data, log_time=t_ns)
        now = time.monotonic()
        if now - self.chunk_started >= self.CHUNK_SECONDS:
            self.chunk_started = now
            self._written(self.writer.flush)  # the chunk in progress to the disk, full or not

    def _written(self, action: Callable[[], None]) -> None:
        """Run one of the writer's calls that reach the disk; a failure becomes the sink's."""
        try:
            action()
        except (RuntimeError, OSError) as error:  # foxglove-sdk: FoxgloveError (a RuntimeError)
            self.failure = f"cannot write {self.path}: {error}"
            raise RecordingError(self.failure) from None

    @property
    def messages(self) -> int:
        return sum(self.counts.values())

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            if self.failure is None:
                self.writer.write_metadata("rosbag2", {"serialized_metadata": self.rosbag2_metadata()})
                if self.extra_metadata:
                    self.writer.write_metadata("srl", self.extra_metadata)
                self._written(self.writer.close)
            else:  # already said by write(): the writer is let go, the file closed
                with contextlib.suppress(RuntimeError, OSError):
                    self.writer.close()
        finally:
            self.channels.clear()
            try:
                self.file.close()  # closed even when its last flush fails
            except OSError as error:
                if self.failure is None:  # else already said
                    self.failure = f"cannot write {self.path}: {error}"
                    raise RecordingError(self.failure) from None

    def rosbag2_metadata(self) -> str:
        """What rosbag2_storage_mcap stores in the ``rosbag2`` metadata record (YAML; this is its
        JSON subset): the bag's topics, counts and time range."""
        start = self.first_ns or 0
        duration = max(0, self.last_ns - start)
        topics = [
            {
                "topic_metadata": {
                    "name": topic,
                    "type": self.types[topic],
                    "serialization_format": "cdr",
                    "offered_qos_profiles": QOS_YAML,
                },
                "message_count": count,
            }
            for topic, count in self.counts.items()
        ]
        info = {
            "version": 5,
            "storage_identifier": "mcap",
            "duration": {"nanoseconds": duration},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": self.messages,
            "topics_with_message_count": topics,
            "compression_format": "",
            "compression_mode": "",
            "relative_file_paths": [self.path.name],
            "files": [
                {
                    "path": self.path.name,
                    "starting_time": {"nanoseconds_since_epoch": start},
                    "duration": {"nanoseconds": duration},
                    "message_count": self.messages,
                }
            ],
            "custom_data": {},
            "ros_distro": DISTRO,
        }
        return json.dumps({"rosbag2_bagfile_information": info}, indent=1)


def part_path(path: Path, part: int) -> Path:
    """The ``part``-th file of a recording split in parts: the first is ``path`` itself, the next
    ``<stem>_1.mcap``, ``<stem>_2.mcap``, ... beside it."""
    return path if part == 0 else path.with_name(f"{path.stem}_{part}{path.suffix}")


class SplitSink:
    """A recording in consecutive MCAP files (:class:`McapSink`), a new one when the current file's
    messages span ``split_seconds`` (by their own stamps): what a file's writer keeps in memory for
    its summary (an index entry per chunk) is bounded by one file's length, not the recording's.
    A closed file's writer is let go; what stays per file is its path.

    A recording replaces the one of the same name, its parts too (``<stem>_<n>.mcap``). Each file is
    a complete recording of its span, readable alone: the messages written once (the
    target pose, :data:`LATCHED_TOPICS`) are written again at the start of every file, with the
    new file's first stamp; ``/tf`` carries the goal frame every second anyway. ``split_seconds``
    0: one file, as :class:`McapSink` alone."""

    LATCHED_TOPICS = frozenset({TARGET_TOPIC})

    def __init__(self, path: Path, extra_metadata: dict[str, str] | None = None, split_seconds: float = 0.0) -> None:
        if not (math.isfinite(split_seconds) and split_seconds >= 0):
            raise RecordingError(f"a recording's part must span a positive time (0: one file), got {split_seconds}")
        self.split_ns = round(split_seconds * 1e9)
        self.extra_metadata = extra_metadata or {}
        self.current = McapSink(path, self.extra_metadata)
        self.path = self.current.path  # the first file's: the name the recording was asked for
        self.paths = [self.path]
        for old in self.path.parent.glob(f"{glob.escape(self.path.stem)}_*{self.path.suffix}"):
            if old.stem[len(self.path.stem) + 1 :].isdigit():  # a part of the recording this one replaces
                old.unlink(missing_ok=True)
        self.counts: dict[str, int] = {}  # messages per topic as they came (not the latched ones written again)
        self.latched: dict[str, tuple[str, str, bytes]] = {}
        self.file_first_ns: int | None = None

    @property
    def messages(self) -> int:
        return sum(self.counts.values())

    def write(self, topic: str, ros_type: str, definition: str, data: bytes, t_ns: int) -> None:
        if self.file_first_ns is None:
            self.file_first_ns = t_ns
        elif self.split_ns and t_ns - self.file_first_ns >= self.split_ns:
            self._next_file(t_ns)
        if topic in self.LATCHED_TOPICS:
            self.latched[topic] = (ros_type, definition, data)
        self.counts[topic] = self.counts.get(topic, 0) + 1
        self.current.write(topic, ros_type, definition, data, t_ns)

    def _next_file(self, t_ns: int) -> None:
        """Close the current file (its summary and metadata written), open the next one and write
        the latched messages into it first."""
        self.current.close()
        self.paths.append(part_path(self.path, len(self.paths)))
        self.current = McapSink(self.paths[-1], self.extra_metadata)
        self.file_first_ns = t_ns
        for topic, (ros_type, definition, data) in self.latched.items():
            self.current.write(topic, ros_type, definition, data, t_ns)

    def close(self) -> None:
        self.current.close()


@dataclass(frozen=True)
class PoseFrames:
    """Where a robot's goal-frame state sits in REP 105's frames (docs/recordings.md "Frames").

    The state ``s`` is the pose of the robot in the goal frame, and the goal ``g`` is a pose in
    the pose frame (``odom``; ``map`` when localized: ``bridge.goal``), so the robot's pose in the
    pose frame is ``g (+) s`` (:func:`common.math.frames.from_goal_frame`). Localized with the
    ``map -> odom`` correction ``C`` known, the odometry pose is ``C^-1 (+) g (+) s`` and ``/tf``
    chains ``map -> odom -> base_footprint``; without ``C`` the base hangs from ``map``, the frame
    its pose is known in. The default (``g`` the identity, not localized) is a simulated plant's:
    its goal frame is its odom frame."""

    goal: Pose2D = IDENTITY
    localized: bool = False
    map_to_odom: Pose2D | None = None

    @property
    def root(self) -> str:
        """The pose frame: the parent of ``goal``."""
        return MAP_FRAME if self.localized else ODOM_FRAME

    @property
    def pose_frame(self) -> str:
        """The frame srl's goal-frame poses (odometry, path, target) are stamped in: ``odom`` where
        the goal frame is the odom frame (a simulated plant; a robot with ``bridge.goal`` zero and
        odometry only), else ``goal``. ``/tf`` joins either to the rest."""
        return ODOM_FRAME if not self.localized and self.goal == IDENTITY else GOAL_FRAME

    def transforms(self, state: Vector, base: str) -> list[tuple[str, str, Pose2D]]:
        """``(parent, child, pose)`` of ``base`` for the goal-frame state ``state``, and ``map ->
        odom`` when known."""
        s = Pose2D(float(state[0]), float(state[1]), float(state[2]))
        pose = s if self.goal == IDENTITY else from_goal_frame(s, self.goal)  # g (+) s
        if not self.localized:
            return [(ODOM_FRAME, base, pose)]
        if self.map_to_odom is None:
            return [(MAP_FRAME, base, pose)]
        return [(MAP_FRAME, ODOM_FRAME, self.map_to_odom), (ODOM_FRAME, base, to_goal_frame(pose, self.map_to_odom))]


SIMULATED = PoseFrames()
GOAL_EVERY = PATH_EVERY  # states of a robot between two ``goal`` transforms on /tf (and with the first)
# A recorder that gathers /tf (Recorder.gather_tf: srl record and srl view, whose writer takes a
# fleet's states many at a time) writes at most this many transforms in one TFMessage.
TF_GATHERED = 256


def base_frame(robot: str) -> str:
    """The robot's base frame on ``/tf``: ``<robot>/base_footprint``, one per robot of a fleet (a
    frame-name prefix per robot, as ROS's tf_prefix gave), the same for one robot and for many."""
    return f"{ros_name(robot)}/{BASE_FRAME}"


class PathBuffer:
    """A path's newest ``size`` poses, oldest first: stamps [ns] and ``(x, y, alpha)`` in
    preallocated arrays used as a ring (bounded, and no list of tuples to convert per path),
    and the frame of each."""

    def __init__(self, size: int) -> None:
        self.size = size
        self.stamps = np.zeros(size, dtype=np.int64)
        self.table = np.zeros((size, 3))
        self.frames: deque[str] = deque(maxlen=size)
        self.count = 0  # poses ever appended

    def __len__(self) -> int:
        return min(self.count, self.size)

    def append(self, t_ns: int, state: Vector, frame: str) -> None:
        slot = self.count % self.size
        self.stamps[slot] = t_ns
        self.table[slot] = state[:3]
        self.frames.append(frame)
        self.count += 1

    def ordered(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps, poses) of the kept poses, oldest first."""
        if self.count <= self.size:
            return self.stamps[: self.count], self.table[: self.count]
        order = np.roll(np.arange(self.size), -(self.count % self.size))
        return self.stamps[order], self.table[order]


@dataclass
class _Track:
    """What the mapping remembers of one robot: bounded (the path's last poses, one episode).

    The actor's episode (transitions) and the plant's (states) are counted apart: a robot bridge
    numbers its states in its own episodes, whatever the actor's are."""

    episode: int = -1  # of the newest transition
    last_step: int = -1
    accumulated_cost: float = 0.0
    action: tuple[float, float] = (0.0, 0.0)
    # the path's poses: (t_ns, x, y, alpha) and their frame (RosMapping.path_cdr serializes them at once)
    path: PathBuffer = field(default_factory=lambda: PathBuffer(PATH_POSES))
    late: int = 0  # transitions that came after a later step (dropped: one per step, in order)
    state_episode: int = -1  # of the newest state
    states_seen: int = 0  # states of that episode (clock "steps": state n at origin + n delta)
    tf_sent: int = 0  # /tf messages of this robot (the goal transform every GOAL_EVERY)
    pose_frame: str = ODOM_FRAME  # of the newest state (PoseFrames.pose_frame)


# (robot, episode) origins remembered per robot heard (Recorder.step_time): every robot of a fleet
# keeps its own, and they stay bounded however many episodes pass
ORIGINS_PER_ROBOT = 4


class Recorder:
    """srl's messages -> ROS 2 messages on a :class:`Sink`; one :class:`_Track` per robot.

    Not thread-safe: one thread calls it (:class:`tools.recording.record.Feed`'s writer, or ``srl run``)."""

    def __init__(self, sink: Sink, sampling_time: float, clock: Clock = "wall") -> None:
        self.sink = sink
        self.ros = RosMapping()
        self.delta_ns = round(sampling_time * 1e9)
        self.clock = clock
        self.tracks: dict[str, _Track] = {}
        self.origins: dict[tuple[str, int], int] = {}
        self.target_sent = False
        self.tf_gathered = 1  # transforms per /tf message at most (gather_tf)
        self.tf_pending: list[tuple[int, str, str, Pose2D]] = []

    def gather_tf(self, limit: int = TF_GATHERED) -> None:
        """From now on the transforms of many states go out as one ``/tf`` message (each with its
        own stamp, as a ROS tf broadcaster of many frames sends them): when ``limit`` are pending
        and at :meth:`flush_tf`, which the caller calls when it has written what it had (srl
        record's writer: at the end of each batch, Feed). One TFMessage per state is a fifth of a
        fleet recorder's messages and of its writing CPU."""
        self.flush_tf()
        self.tf_gathered = max(1, limit)

    def flush_tf(self) -> None:
        """The pending transforms as one ``/tf`` message, logged at the newest of their stamps."""
        if self.tf_pending:
            pending, self.tf_pending = self.tf_pending, []
            t_ns = max(stamp for stamp, _, _, _ in pending)
            self._write_cdr(TF_TOPIC, TF_MESSAGE, tf_cdr(pending), t_ns)

    def _write(self, topic: str, ros_type: str, message: Any, t_ns: int) -> None:
        self.sink.write(topic, ros_type, self.ros.definition(ros_type), self.ros.cdr(message, ros_type), t_ns)

    def _write_cdr(self, topic: str, ros_type: str, data: bytes, t_ns: int) -> None:
        self.sink.write(topic, ros_type, self.ros.definition(ros_type), data, t_ns)

    def _robot(self, robot: str) -> _Track:
        """The robot's track, made at its first message (not one per call, as setdefault would)."""
        track = self.tracks.get(robot)
        if track is None:
            track = self.tracks[robot] = _Track()
        return track

    def _track(self, robot: str, episode: int) -> _Track:
        """The robot's step stream, reset by a new episode of its transitions."""
        track = self._robot(robot)
        if episode != track.episode:  # a new episode: its own cost and path
            self.tracks[robot] = track = _Track(
                episode=episode,
                state_episode=track.state_episode,
                states_seen=track.states_seen,
                tf_sent=track.tf_sent,
                pose_frame=track.pose_frame,
            )
        return track

    def begin(self, robot: str, episode: int, origin_ns: int) -> None:
        """Place step 0 of the robot's episode at ``origin_ns`` (an episode that ran in process)."""
        self.origins[(robot, episode)] = origin_ns

    def step_time(self, robot: str, episode: int, step: int, now_ns: int) -> int:
        """``origin + step delta`` of the robot's episode; the origin fixed by its first message."""
        key = (robot, episode)
        if key not in self.origins:
            if len(self.origins) >= ORIGINS_PER_ROBOT * max(1, len(self.tracks)):
                del self.origins[next(iter(self.origins))]
            self.origins[key] = now_ns - step * self.delta_ns
        return self.origins[key] + step * self.delta_ns

    def target(self, t_ns: int, frame: str = ODOM_FRAME) -> None:
        """The target pose: the origin of the goal frame (once), in ``frame`` (the goal frame's name)."""
        if not self.target_sent:
            self.target_sent = True
            message = self.ros.types[POSE_STAMPED](header=self.ros.header(t_ns, frame), pose=self.ros.pose(IDENTITY))
            self._write(TARGET_TOPIC, POSE_STAMPED, message, t_ns)

    def state(self, robot: str, episode: int, state: Vector, now_ns: int, frames: PoseFrames = SIMULATED) -> None:
        """A state the robot reported: ``/<robot>/odom`` (twist: the action it holds) and ``/tf``
        (:meth:`tf`)."""
        track = self._robot(robot)
        if episode != track.state_episode:
            track.state_episode, track.states_seen = episode, 0
        t_ns = self.step_time(robot, episode, track.states_seen, now_ns) if self.clock == "steps" else now_ns
        track.states_seen += 1
        track.pose_frame = frames.pose_frame
        self.target(t_ns, track.pose_frame)
        odometry = odometry_cdr(t_ns, track.pose_frame, BASE_FRAME, state, track.action)
        self._write_cdr(f"/{ros_name(robot)}/odom", ODOMETRY, odometry, t_ns)
        self.tf(robot, track, state, frames, t_ns)

    def tf(self, robot: str, track: _Track, state: Vector, frames: PoseFrames, t_ns: int) -> None:
        """``/tf`` of one state: the robot's base (and ``map -> odom``, :meth:`PoseFrames.transforms`),
        with ``<root> -> goal`` in the first and every :data:`GOAL_EVERY`-th message of the robot, so
        a live view that joins late sees the target within a second."""
        moves = frames.transforms(state, base_frame(robot))
        if track.tf_sent % GOAL_EVERY == 0:
            moves.append((frames.root, GOAL_FRAME, frames.goal))
        track.tf_sent += 1
        self.tf_pending += [(t_ns, *move) for move in moves]
        if len(self.tf_pending) >= self.tf_gathered:  # without gather_tf: at once, one message per state
            self.flush_tf()

    def transition(
        self,
        robot: str,
        episode: int,
        step: int,
        state: Vector,
        action: Vector,
        cost: float,
        now_ns: int,
    ) -> bool:
        """One step: ``/<robot>/cmd_vel`` and ``/<robot>/srl/transition``; the path every
        :data:`PATH_EVERY` steps. False (nothing written) for a step at or before one written."""
        t_ns = self.step_time(robot, episode, step, now_ns)
        track = self._track(robot, episode)
        if step <= track.last_step:
            track.late += 1
            return False
        track.last_step = step
        track.accumulated_cost += float(cost)
        track.action = (float(action[0]), float(action[1]))
        self.target(t_ns, track.pose_frame)
        name = ros_name(robot)
        command = twist_stamped_cdr(t_ns, BASE_FRAME, *track.action)
        self._write_cdr(f"/{name}/cmd_vel", TWIST_STAMPED, command, t_ns)
        values = (*(float(c) for c in state[:3]), *track.action, float(cost), track.accumulated_cost)
        sample = transition_cdr(t_ns, track.pose_frame, episode, step, values)
        self._write_cdr(f"/{name}/srl/transition", TRANSITION, sample, t_ns)
        if step % PATH_STRIDE == 0:
            track.path.append(t_ns, state, track.pose_frame)
        if step % PATH_EVERY == 0:
            self.path(robot, t_ns)
        return True

    def path(self, robot: str, t_ns: int) -> None:
        track = self.tracks.get(robot)
        if track is not None and len(track.path):
            stamps, table = track.path.ordered()
            data = self.ros.path_cdr(t_ns, track.pose_frame, stamps, table, track.path.frames)
            self._write_cdr(f"/{ros_name(robot)}/path", PATH, data, t_ns)

    def weights(
        self,
        robot: str,
        episode: int,
        version: int,
        trained_step: int,
        q_weights: Sequence[float],
        v_weights: Sequence[float],
        residuals: tuple[float, float],
        pairs: int,
        now_ns: int,
    ) -> None:
        """``/<robot>/srl/critic_weights``: at arrival, or (clock "steps") at the step after the
        last one the fit used, where the actor can use them first."""
        t_ns = self.step_time(robot, episode, trained_step + 1, now_ns) if self.clock == "steps" else now_ns
        data = weights_cdr(t_ns, ODOM_FRAME, episode, version, trained_step, q_weights, v_weights, residuals, pairs)
        self._write_cdr(f"/{ros_name(robot)}/srl/critic_weights", WEIGHTS, data, t_ns)

    def status(self, robot: str, counters: dict[str, float], now_ns: int) -> None:
        """``/<robot>/srl/actor_status`` from the actor's status counters (NaN where absent)."""
        track = self.tracks.get(robot)
        t_ns = now_ns
        if self.clock == "steps" and track is not None and track.last_step >= 0:
            t_ns = self.step_time(robot, track.episode, track.last_step, now_ns)

        def value(name: str) -> float:
            return float(counters.get(name, math.nan))

        message = self.ros.types[STATUS](
            header=self.ros.header(t_ns),
            step=max(0, int(counters.get("steps", 0))),
            solve_ms=value("solve_ms_last"),
            staleness_steps=value("staleness_steps"),
            jitter_ms=value("jitter_ms_last"),
            missed_deadlines=value("missed_deadlines"),
            solver_failures=value("solver_failures"),
            weights_version=value("weights_version"),
        )
        self._write(f"/{ros_name(robot)}/srl/actor_status", STATUS, message, t_ns)

    def close(self) -> None:
        self.flush_tf()
        self.sink.close()


# -- an episode that ran in this process (srl run, the experiment) ----------------------
def record_episode(recorder: Recorder, episode: Episode, robot: str, origin_ns: int, episode_id: int = 0) -> None:
    """Everything of one in-process episode: state s_k and step k at ``origin + k delta``, the
    initial weights and those of every fit (version counted from 1; the residuals of the fit after
    step k travel with the weights it produced, at step k + 1), the solve time of every step."""
    delta = recorder.delta_ns
    recorder.begin(robot, episode_id, origin_ns)
    recorder.target(origin_ns)
    version, previous = 0, None
    # step k's solve time, where it solved (a step the arrival rule held has none)
    held = episode.held if len(episode.held) == episode.steps else [False] * episode.steps
    solves: list[float | None] = [None] * episode.steps
    if len(episode.solve_seconds) == held.count(False):
        times = iter(episode.solve_seconds)
        solves = [None if rest else next(times) for rest in held]
    for k in range(episode.steps):
        t_ns = origin_ns + k * delta
        recorder.state(robot, episode_id, episode.states[k], t_ns)  # clock "steps": state k at origin + k delta
        if k < len(episode.q_weights):
            weights = (tuple(episode.q_weights[k]), tuple(episode.v_weights[k]))
            residuals = episode.td_residuals[k - 1] if 0 < k <= len(episode.td_residuals) else (math.nan, math.nan)
            if weights != previous or not math.isnan(residuals[0]):  # the initial weights, then every fit
                version += 1
                previous = weights
                recorder.weights(robot, episode_id, version, k - 1, *weights, residuals, 0, t_ns)
        recorder.transition(robot, episode_id, k, episode.states[k], episode.actions[k], episode.costs[k], t_ns)
        counters = {"steps": float(k), "weights_version": float(version)}
        solve = solves[k]
        if solve is not None:
            counters["solve_ms_last"] = solve * 1e3
        if version:
            counters["staleness_steps"] = 0.0  # in process the critic is synchronous
        recorder.status(robot, counters, t_ns)
    end_ns = origin_ns + episode.steps * delta
    recorder.state(robot, episode_id, episode.final_state, end_ns)
    recorder.path(robot, end_ns)


def episode_recorder(path: Path, sampling_time: float, metadata: dict[str, Any]) -> Recorder:
    """A recorder onto a new MCAP file (created now: a bad path fails before the run) whose
    ``srl`` metadata record holds ``metadata`` (agent, horizon, delta: what ``srl plot`` needs)."""
    sink = McapSink(path, {k: json.dumps(v) for k, v in {"sampling_time": sampling_time, **metadata}.items()})
    return Recorder(sink, sampling_time, clock="steps")


def wall_ns() -> int:
    return time.time_ns()


NAMED_ROBOTS = 8  # the robots a recording's summary line names (a fleet's: the first of them, then "...")


def describe(sink: McapSink | SplitSink) -> str:
    """The one summary line of a closed recording (of a split one: its files and their total size)."""
    counts = sink.counts
    robots = sorted({t.split("/")[1] for t in counts if t.count("/") >= 2})
    paths = sink.paths if isinstance(sink, SplitSink) else [sink.path]
    size = sum(os.path.getsize(path) for path in paths if path.exists())
    files = (
        "" if len(paths) == 1 else f" and {len(paths) - 1} more file{'s' if len(paths) > 2 else ''} ({paths[-1].name})"
    )
    named = ", ".join(robots[:NAMED_ROBOTS]) + (", ..." if len(robots) > NAMED_ROBOTS else "")
    return (
        f"recorded {sum(counts.values())} messages on {len(counts)} topics "
        f"({len(robots)} robot{'s' if len(robots) != 1 else ''}: {named or 'none'}) "
        f"to {sink.path}{files} ({size / 1024:.1f} KiB)"
    )


# -- a running system, over Zenoh (srl record, srl view, srl up --record / --view) -------------
# Samples waiting for the writer; beyond it they are dropped and counted. A fleet of 300 robots
# gives a recorder ~400,000 messages in 30 s, and the writer, niced (OBSERVER_NICENESS), falls
# behind while the fleet drives and catches up while it rests: with 10,000 (under a second of
# them) 24 of 26 runs of 30 s lost samples (up to 179,079), with this many (15-20 s) none of 5. A
# waiting sample holds 1.3-2 KB (a decoded message; tests/test_record.py measures them): at most
# ~400 MB.
QUEUE_LIMIT = 200_000
DROPPED_NOTE = "; {count} dropped (writer behind)"  # in srl record's summary line (dropped_by_writer reads it)
# a robot's transitions held while its missing first steps are asked for (Feed): ~100 s at delta
# 0.1 s, far beyond the history query's 10 s bound; past it they are written as they are
HOLD_LIMIT = 1000
BATCH_SECONDS = 0.2  # the writer's pause between batches (a real-time system: ~10 states + 2 steps each)
OBSERVER_NICENESS = 10  # srl record / srl view yield the CPU to the loop they watch


def dropped_by_writer(summary_line: str | None) -> int:
    """The samples an ``srl record`` summary line says it dropped with its writer behind (0: none)."""
    pattern = re.escape(DROPPED_NOTE).replace(re.escape("{count}"), r"(\d+)")
    match = re.search(pattern, summary_line or "")
    return int(match.group(1)) if match else 0


def yield_cpu_to_the_loop() -> None:
    """Lower this process's CPU priority (nice +10, common.process.runtime.lower_priority) before Zenoh's
    threads start, so they and the writer run niced too, and on a busy machine the actor's tick
    comes first (srl bench loop --record holds the cost to the loop's jitter). Refused: a warning, and it
    records anyway."""
    from common.process.runtime import lower_priority

    lower_priority(OBSERVER_NICENESS, "the recorder")


def robot_frames(bridge: Any, source: str, correction: Sequence[float] | None) -> PoseFrames:
    """The frames of a state (:class:`PoseFrames`) from its ``source`` and its ``map_to_odom``
    ``correction`` (x [m], y [m], theta [rad]; None, or NaN, when it carries none): a robot
    bridge's (``source`` "robot") goal is ``bridge.goal`` of these settings (``srl up`` hands the
    recorder the bridge's), in ``map`` when ``bridge.pose_source`` localizes, with the
    ``map -> odom`` correction when the state carries one; a simulated plant's goal frame is its
    odom frame."""
    if source != "robot":
        return SIMULATED
    corrected = correction is not None and all(math.isfinite(c) for c in correction)
    return PoseFrames(
        goal=Pose2D(*(float(c) for c in bridge.goal)),
        localized=getattr(bridge, "pose_source", ODOMETRY_ONLY) != ODOMETRY_ONLY,
        map_to_odom=Pose2D(*(float(c) for c in correction)) if corrected and correction is not None else None,
    )


class Feed:
    """Subscribes to every robot's state, transitions, critic weights and actor status
    (``srl/*/...`` and srl's batches of them) and hands them, in arrival order, to a
    :class:`Recorder` on its own writer thread. Zenoh's threads only queue a sample's bytes
    (:class:`common.net.transport.Inbox`, at most :data:`QUEUE_LIMIT` rows): the writer decodes
    what waits a few times a second and writes a batch's rows from its columns, building no
    message per robot. A slow disk never holds up the system."""

    def __init__(self, settings: Any, recorder: Recorder) -> None:
        import threading

        from common.contracts.keys import STATE, STATUS, TRANSITION, WEIGHTS, every_robot
        from common.contracts.messages import CriticWeights, PlantState, ServiceStatus, Transition
        from common.net.history import HistoryRecovery
        from common.net.transport import Bus

        self.recorder = recorder
        recorder.gather_tf()  # the writer takes states many at a time: their /tf in few messages
        self.bridge = settings.bridge  # a robot's goal and pose source (robot_frames)
        self.closing = threading.Event()
        self.received = 0  # rows written
        self.errors = 0  # rows not written (a bad sample, a file that cannot be written)
        self.failure = ""  # the last reason the file could not be written (said once)
        self.writes: dict[type, Callable[[Any, int], None]] = {
            PlantState: self._states,
            Transition: self._transitions,
            CriticWeights: self._weights,
            ServiceStatus: self._status,
        }
        self.bus = Bus.open(settings.transport, "recorder")
        self.inbox = self.bus.inbox(QUEUE_LIMIT)
        self.inbox.subscribe(STATE, every_robot(STATE))
        # transitions from the actor's advanced publisher: a recorder that joins late still gets
        # its cached history (duplicates are dropped by step, Recorder.transition); a robot whose
        # stream still starts after step 0 is held while the caches are asked for the rest
        self.inbox.subscribe(TRANSITION, every_robot(TRANSITION), recover=True)
        self.started: dict[str, int] = {}  # robot -> the episode whose transitions it began
        self.held: dict[str, list[tuple[Any, ...]]] = {}  # robot -> rows waiting for their first steps
        self.recovered: deque[Transition] = deque()  # what the caches answered (Zenoh's threads)
        self.recovery = HistoryRecovery(self._ask, self.recovered.append, who="recorder")
        self.inbox.subscribe(WEIGHTS, every_robot(WEIGHTS))
        self.inbox.subscribe(STATUS, every_robot(STATUS, service="actor"))
        self.writer = threading.Thread(target=self._drain, name="recorder-writer", daemon=True)
        self.writer.start()

    @property
    def dropped(self) -> int:
        """Rows the writer was too far behind to take (counted, not written)."""
        return self.inbox.dropped

    def _drain(self) -> None:
        """Write in batches: everything waiting, then a pause of :data:`BATCH_SECONDS`, so the
        writer wakes a few times a second rather than once per sample beside the actor's tick;
        after :meth:`close`, what waits is written and the writer ends."""
        while True:
            closing = self.closing.is_set()  # before the batch: nothing put before close is left
            for taken, now_ns in self.inbox.take():
                schema = taken.schema if isinstance(taken, Columns) else type(taken)
                self.writes[schema](taken, now_ns)
            self._release(everything=closing)
            self._guarded("/tf", self.recorder.flush_tf)  # the batch's /tf out before the pause
            if closing:
                return
            self.closing.wait(BATCH_SECONDS)

    def _guarded(self, kind: str, write: Callable[..., object], *args: Any) -> bool:
        """``write(*args)`` (one row of ``kind``, or the batch's /tf); True if it was written.
        A failure is counted in ``errors`` and does not end the recording: a bad row is logged
        with its traceback, a file that cannot be written (:class:`RecordingError`, a full disk)
        once per reason, not once per row. Nothing is built per row but the call."""
        try:
            write(*args)
            return True
        except RecordingError as error:
            self.errors += 1
            if str(error) != self.failure:
                self.failure = str(error)
                log.error("recorder: %s", error)
        except Exception:
            self.errors += 1
            log.exception("recorder: cannot record a %s sample", kind)
        return False

    def _rows(self, kind: str, write: Callable[..., object], *columns: Sequence[Any]) -> None:
        """``write`` of each row (the i-th of every column), guarded row by row."""
        guarded = self._guarded
        self.received += sum(guarded(kind, write, *row) for row in zip(*columns, strict=True))

    def _states(self, columns: Columns[Any], now_ns: int) -> None:
        from common.contracts.columns import choice_code
        from common.contracts.messages import PlantState

        sources = columns.field("source").tolist()
        frames: Sequence[PoseFrames] = [SIMULATED] * len(columns)
        robot = choice_code(PlantState, "source", "robot")
        if robot in sources:
            corrections = columns.field("map_to_odom").tolist()
            frames = [
                robot_frames(self.bridge, "robot" if code == robot else "sim", correction)
                for code, correction in zip(sources, corrections, strict=True)
            ]
        episodes, states = columns.field("episode").tolist(), columns.field("state").tolist()
        self._rows("state", self.recorder.state, columns.robots, episodes, states, [now_ns] * len(columns), frames)

    def _transitions(self, columns: Columns[Any], now_ns: int) -> None:
        """A batch's transitions, written in step order per robot: a robot's first transition of an
        episode after step 0 (the subscription's history came too late, or not at all) holds its
        robot's rows while the actors' caches are asked for the steps before it (:meth:`_release`)."""
        fields = [columns.field(name).tolist() for name in ("episode", "step", "state", "action", "cost")]
        rows = list(zip(columns.robots, *fields, [now_ns] * len(columns), strict=True))
        if self.held or any(self.started.get(robot) != episode for robot, episode, *_ in rows):
            rows = [row for row in rows if not self._hold(row)]
        if rows:
            self._rows("transition", self.recorder.transition, *zip(*rows, strict=True))

    def _hold(self, row: tuple[Any, ...]) -> bool:
        """Whether ``row`` (robot, episode, step, state, action, cost, now_ns) waits for its robot's first steps."""
        robot, episode, step, *_, now_ns = row
        held = self.held.get(robot)
        if held is not None and held[0][1] == episode:
            held.append(row)
            return True
        if self.started.get(robot) == episode:
            return False
        self.started[robot] = episode
        if step <= 0:
            return False
        self.recorder.step_time(robot, episode, step, now_ns)  # its origin, as writing the row would fix it
        self.held[robot] = [row]
        self.recovery.need(robot, episode, range(step))
        return True

    def _ask(self, robots: list[str], answer: Callable[[Any], None], done: Callable[[], None]) -> None:
        from common.contracts.keys import TRANSITION

        try:
            self.bus.history(TRANSITION, [TRANSITION.key(robot) for robot in robots], answer, done)
        except Exception as error:  # a closed session: the query has ended (done was called)
            log.debug("recorder: history query not sent: %s", error)

    def _release(self, everything: bool = False) -> None:
        """Write the held robots whose first steps are no longer asked for (or that hold
        :data:`HOLD_LIMIT` rows; ``everything``: all of them, at close): what the caches answered
        and the live rows, in step order, each step once."""
        done = [
            robot
            for robot, rows in self.held.items()
            if everything or len(rows) >= HOLD_LIMIT or not self.recovery.pending(robot)
        ]  # decided before the answers are taken: those of a query that ended are all in
        while self.recovered:
            m = self.recovered.popleft()
            held = self.held.get(m.robot)
            if held is not None and held[0][1] == m.episode:
                held.append((m.robot, m.episode, m.step, m.state, m.action, m.cost, held[0][-1]))
        for robot in done:
            steps = {row[2]: row for row in reversed(self.held.pop(robot))}  # the first of each step
            rows = sorted(steps.values(), key=lambda row: row[2])
            self._rows("transition", self.recorder.transition, *zip(*rows, strict=True))

    def _weights(self, columns: Columns[Any], now_ns: int) -> None:
        def write(m: Any) -> None:
            residuals = (m.q_residual, m.v_residual)
            fit = (m.version, m.trained_step, m.q_weights, m.v_weights, residuals, m.pairs)
            self.recorder.weights(m.robot, m.episode, *fit, now_ns)

        self._rows("weights", write, list(columns.items()))

    def _status(self, message: Any, now_ns: int) -> None:
        self._rows("status", self.recorder.status, [message.robot], [dict(message.counters)], [now_ns])

    def close(self) -> None:
        """Stop receiving, write what is queued, close the sink (the file is complete after this)."""
        self.bus.close()
        self.closing.set()
        self.writer.join()
        self.recorder.close()

    @classmethod
    def run(cls, settings: Any, recorder: Recorder, who: str, args: Any, ready: Callable[[], str]) -> Feed:
        """What ``srl record`` and ``srl view`` do once their sink is open: join the system (retried
        for ``args.connect_timeout``), print the ``ready()`` line, feed the recorder until Ctrl-C,
        SIGTERM, the parent's death (started by srl up) or ``args.seconds``; closed on the way
        out whatever happens (a recording is complete after this)."""
        import sys

        from common.process.runtime import connect_with_retry, stop_on_signals
        from common.system.lifeline import die_with_parent

        with stop_on_signals() as stop:
            die_with_parent(stop)
            try:
                feed = connect_with_retry(lambda: cls(settings, recorder), settings, who, args.connect_timeout, stop)
            except BaseException:
                recorder.close()
                raise
            print(ready(), file=sys.stderr, flush=True)
            try:
                stop.wait(args.seconds)
            finally:
                feed.close()
        return feed


def positive_seconds(seconds: float | None) -> None:
    """``--seconds`` of srl record / srl view: None (until Ctrl-C) or a positive number."""
    from common.config.arguments import UsageError

    if seconds is not None and not (math.isfinite(seconds) and seconds > 0):
        raise UsageError(f"--seconds must be a positive number, got {seconds}")


def cmd_record(args: Any) -> int:
    """``srl record FILE.mcap``: join a running system and record every robot until Ctrl-C."""
    from common.config.arguments import UsageError, settings_from_args

    settings = settings_from_args(args)
    positive_seconds(args.seconds)
    yield_cpu_to_the_loop()
    if args.file is None:
        args.file = Path(time.strftime("srl-%Y%m%d-%H%M%S.mcap", time.gmtime()))
    try:
        sink = SplitSink(
            args.file,
            {"sampling_time": json.dumps(settings.plant.sampling_time), "source": '"zenoh"'},
            split_seconds=60.0 * args.split_minutes,
        )
    except RecordingError as error:
        raise UsageError(str(error)) from None
    recorder = Recorder(sink, settings.plant.sampling_time, clock=args.clock)
    ready = f"srl record: recording srl/* (every robot) from {settings.transport.router} to {sink.path}; Ctrl-C ends it"
    feed = Feed.run(settings, recorder, "record", args, lambda: ready)
    late = sum(t.late for t in recorder.tracks.values())
    extra = DROPPED_NOTE.format(count=feed.dropped) if feed.dropped else ""
    extra += f"; {late} late transitions skipped" if late else ""
    print(f"srl record: {describe(sink)}{extra}", flush=True)
    return 0


# -- reading a recording back (srl plot) ----------------------------------------------
def read_episodes(path: Path) -> tuple[dict[str, Episode], float]:
    """Every robot's (last) episode in a recording, as :class:`Episode` (what ``--plot`` draws),
    and the sampling time. States, actions and costs from ``/<robot>/srl/transition`` (the final
    state from the robot's last odometry), the weights the actor could use at step k (the newest
    at or before it) and each fit's residuals from ``/<robot>/srl/critic_weights``."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    path = Path(path).expanduser()
    if not path.is_file():
        raise RecordingError(f"no recording at {path}")
    ros = RosMapping()
    transitions: dict[str, list[tuple[int, Any]]] = {}
    weights: dict[str, list[tuple[int, Any]]] = {}
    odometry: dict[str, tuple[int, Any]] = {}
    meta: dict[str, Any] = {}
    try:
        with path.open("rb") as file:
            reader = make_reader(file)
            for record in reader.iter_metadata():
                if record.name == "srl":
                    meta = {k: json.loads(v) for k, v in record.metadata.items()}
            for schema, channel, message in reader.iter_messages(log_time_order=True):
                parts = channel.topic.split("/")
                if schema is None or len(parts) < 3:
                    continue
                robot, kind = parts[1], "/".join(parts[2:])
                if kind == "srl/transition":
                    decoded = ros.deserialize(message.data, TRANSITION)
                    transitions.setdefault(robot, []).append((message.log_time, decoded))
                elif kind == "srl/critic_weights":
                    weights.setdefault(robot, []).append((message.log_time, ros.deserialize(message.data, WEIGHTS)))
                elif kind == "odom":
                    odometry[robot] = (message.log_time, ros.deserialize(message.data, ODOMETRY))
    except (McapError, OSError, ValueError, KeyError, EOFError) as error:
        raise RecordingError(f"cannot read {path} as an MCAP recording of srl: {error}") from None
    sampling_time = float(meta.get("sampling_time", 0.1))
    episodes = {}
    for robot, samples in transitions.items():
        last_episode = samples[-1][1].episode
        steps = sorted((m for _, m in samples if m.episode == last_episode), key=lambda m: m.step)
        times = [t for t, m in samples if m.episode == last_episode]
        states = [np.array([m.x, m.y, m.alpha]) for m in steps]
        final = states[-1]
        if robot in odometry and odometry[robot][0] >= max(times):
            o = odometry[robot][1].pose.pose
            yaw = 2 * math.atan2(o.orientation.z, o.orientation.w)
            alpha = final[2] + math.remainder(yaw - final[2], 2 * math.pi)  # unwrapped, near the last step's
            final = np.array([o.position.x, o.position.y, alpha])
        episode = Episode(
            agent=str(meta.get("agent", robot)),
            horizon=int(meta.get("horizon", 0)),
            states=[*states, final],
            actions=[np.array([m.v, m.omega]) for m in steps],
            costs=[float(m.stage_cost) for m in steps],
        )
        fits = [(t, m) for t, m in weights.get(robot, []) if m.episode == last_episode]
        if fits:
            residual_of = {m.trained_step: (float(m.q_residual), float(m.v_residual)) for _, m in fits}
            for t_k, m in zip(sorted(times), steps, strict=True):
                used = [w for t, w in fits if t <= t_k]
                current = used[-1] if used else fits[0][1]
                episode.q_weights.append(np.asarray(current.q_weights, dtype=float))
                episode.v_weights.append(np.asarray(current.v_weights, dtype=float))
                episode.td_residuals.append(residual_of.get(m.step, (math.nan, math.nan)))
        episodes[robot] = episode
    return episodes, sampling_time
