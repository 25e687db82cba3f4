"""Recordings and the live view: srl's messages as ROS 2 messages, into an MCAP file or to Foxglove.

One mapping (:class:`RosMapping`, :class:`Recorder`) from srl's messages to ROS 2 topics, and the
sinks that take its CDR samples (:mod:`tools.recording.sinks`: an MCAP file in the rosbag2 layout,
profile ``ros2``, ``ros2msg`` schemas, ``cdr`` messages, the ``rosbag2`` metadata record that
``ros2 bag info`` reads; in :mod:`tools.recording.view`, the Foxglove WebSocket server). Per robot:

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
(its Humble typestore, srl's types registered in a private copy); the MCAP container is written
by foxglove-sdk (:mod:`tools.recording.sinks`) and read by the ``mcap`` library. The messages
written at every step and state of every robot (odometry, ``/tf``, ``cmd_vel``, transitions,
critic weights, the path) are packed by :mod:`tools.recording.cdr` instead, byte for byte what rosbags writes for them
(tests/test_record_tf.py compares the two), at a fraction of its CPU: a recorder beside a fleet
writes thousands of them a second.

Time: a step ``k`` of a robot's episode is placed at ``origin + k delta`` (``origin``: the
recording's start for ``srl run`` and the experiment; for a recorder over Zenoh, the arrival of the
episode's first transition minus its steps), so actions and transitions are exactly ``delta``
apart. States arrive at their own rate: stamped on arrival (``clock = "wall"``, real time) or, in
lockstep, one step each (``clock = "steps"``).
"""

from __future__ import annotations

import functools
import json
import logging
import math
import operator
import os
import re
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from common.contracts.columns import Columns
from common.contracts.pose_sources import ODOMETRY_ONLY
from common.math.frames import Pose2D, from_goal_frame, to_goal_frame
from common.math.loop import Episode
from tools.recording.cdr import (
    Vector,
    odometry_cdr,
    odometry_rows,
    path_rows,
    planar,
    planar_rows,
    sin_cos,
    tf_message,
    transform_template,
    transition_cdr,
    transition_rows,
    twist_stamped_cdr,
    twist_stamped_rows,
    weights_cdr,
)
from tools.recording.sinks import McapSink, RecordingError, RowWriteError, Sink, SplitSink

log = logging.getLogger(__name__)

Clock = Literal["wall", "steps"]
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
LATCHED_TOPICS = frozenset({TARGET_TOPIC})  # written once: again at the start of each file of a split recording
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


class _Definitions(dict[str, str]):
    """ROS 2 types' ``ros2msg`` definitions, each generated by ``store`` when first asked for."""

    def __init__(self, store: Any) -> None:
        super().__init__()
        self.store = store

    def __missing__(self, ros_type: str) -> str:
        definition: str = self.store.generate_msgdef(ros_type, ros_version=2)[0]
        self[ros_type] = definition
        return definition


class RosMapping:
    """ROS 2 types: their CDR (``rosbags``) and their ``ros2msg`` definitions, srl's own included."""

    def __init__(self) -> None:
        self.store: Any = get_typestore(Stores.ROS2_HUMBLE)
        for name, text in SRL_MSGS.items():
            self.store.register(get_types_from_msg(text, name))
        self.types: dict[str, Any] = self.store.types
        self.definitions = _Definitions(self.store)  # ros_type -> its definition, generated once

    def definition(self, ros_type: str) -> str:
        return self.definitions[ros_type]

    def cdr(self, message: Any, ros_type: str) -> bytes:
        return bytes(self.store.serialize_cdr(message, ros_type, little_endian=True))

    def path_cdr(self, t_ns: int, frame: str, stamps: np.ndarray, table: np.ndarray, frames: Sequence[str]) -> bytes:
        """``nav_msgs/Path`` of the poses ``table`` (rows x, y, alpha), stamped ``stamps`` [ns] in
        ``frames`` (one each), the path stamped ``t_ns`` in ``frame``, as CDR (:meth:`path_poses_cdr`)."""
        table = np.asarray(table, dtype=float).reshape(-1, 3)
        return self.path_poses_cdr(t_ns, frame, stamps, planar_rows(table[:, 0], table[:, 1], table[:, 2]), frames)

    def path_poses_cdr(
        self, t_ns: int, frame: str, stamps: np.ndarray, poses: np.ndarray, frames: Sequence[str]
    ) -> bytes:
        """``nav_msgs/Path`` of ``poses`` (rows of :func:`tools.recording.cdr.planar_rows`) as CDR:
        the bytes :meth:`cdr` gives for the same message, packed with numpy
        (:func:`tools.recording.cdr.path_rows`: a path of :data:`PATH_POSES` poses every second per
        robot would be most of a recorder's CPU through rosbags' per-field serializer). Poses in
        more than one frame go through :meth:`cdr`."""
        distinct = set(frames)
        if len(distinct) > 1:
            t = self.types
            message = t[PATH](
                header=self.header(t_ns, frame),
                poses=[
                    t[POSE_STAMPED](
                        header=self.header(int(stamp), f),
                        pose=t["geometry_msgs/msg/Pose"](
                            position=t["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]), z=float(p[2])),
                            orientation=t["geometry_msgs/msg/Quaternion"](*(float(q) for q in p[3:7])),
                        ),
                    )
                    for stamp, p, f in zip(stamps, poses, frames, strict=True)
                ],
            )
            return self.cdr(message, PATH)
        own = distinct.pop() if distinct else ""
        count = len(stamps)
        return path_rows(
            np.array([t_ns]), frame, own, np.reshape(stamps, (1, count)), np.reshape(poses, (1, count, 7))
        )[0]

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


@functools.lru_cache(maxsize=4096)  # a fleet's ids, bounded whatever names arrive
def ros_name(robot: str) -> str:
    """A robot id as a ROS 2 name chunk (letters, digits, underscores): ``rlqv+-N12-s000`` ->
    ``rlqvplus_N12_s000``; srl's usual ids (``tb3_0``) stay as they are."""
    return re.sub(r"[^A-Za-z0-9_]", "_", robot.replace("+", "plus"))


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


POSE_FRAMES = (ODOM_FRAME, GOAL_FRAME)  # the pose frames (PoseFrames.pose_frame) by their code in Tracks


@dataclass(frozen=True)
class FrameRows:
    """The :class:`PoseFrames` of a batch's states, one row each: the goal ``g`` (x, y, theta),
    whether the robot is localized, and its ``map -> odom`` correction (NaN where none is known)."""

    goal: np.ndarray
    localized: np.ndarray
    map_to_odom: np.ndarray

    def take(self, rows: slice | np.ndarray) -> FrameRows:
        return FrameRows(self.goal[rows], self.localized[rows], self.map_to_odom[rows])


class Tracks:
    """What the recorder remembers of each robot, in arrays of a row (slot) per robot heard, so a
    batch of many robots reads and updates them with a few array operations: bounded by the robots
    (a path's last :data:`PATH_POSES` poses, one episode's steps and cost), the arrays doubled as
    robots come. With each robot its topics and its base's ``/tf`` templates, made once.

    The actor's episode (transitions) and the plant's (states) are counted apart: a robot bridge
    numbers its states in its own episodes, whatever the actor's are."""

    def __init__(self) -> None:
        self.slots: dict[str, int] = {}
        self.topics: list[tuple[str, str, str, str]] = []  # /<robot>/odom, cmd_vel, srl/transition, path
        self.base_frames: list[str] = []  # <robot>/base_footprint
        self.base_ids: list[tuple[int, int]] = []  # bases' rows, as Python numbers (one robot's state)
        # every transform template (tools.recording.cdr.transform_template) a pending /tf refers to by index:
        # odom -> goal, map -> goal, map -> odom, then each robot's base from odom and from map
        self.templates = [transform_template(parent, child) for parent, child in TF_FIXED]
        self.size = 0
        self._allocate(16)

    def _allocate(self, capacity: int) -> None:
        def grown(old: np.ndarray | None, fill: float | int, dtype: Any, *shape: int) -> np.ndarray:
            new = np.full((capacity, *shape), fill, dtype=dtype)
            if old is not None:
                new[: self.size] = old[: self.size]
            return new

        get = self.__dict__.get
        self.episode = grown(get("episode"), -1, np.int64)  # of the newest transition
        self.last_step = grown(get("last_step"), -1, np.int64)
        self.accumulated = grown(get("accumulated"), 0.0, float)  # J of the episode's steps written
        self.action = grown(get("action"), 0.0, float, 2)  # the newest step's (odometry's twist)
        self.state_episode = grown(get("state_episode"), -1, np.int64)  # of the newest state
        self.states_seen = grown(get("states_seen"), 0, np.int64)  # of that episode (clock "steps")
        self.tf_sent = grown(get("tf_sent"), 0, np.int64)  # states on /tf (the goal every GOAL_EVERY)
        self.pose_frame = grown(get("pose_frame"), 0, np.int8)  # of the newest state (POSE_FRAMES)
        self.bases = grown(get("bases"), 0, np.int64, 2)  # its base's templates: from odom, from map
        # the path: every PATH_STRIDE-th step's pose (planar_rows), stamp and frame, a ring per robot
        self.path_count = grown(get("path_count"), 0, np.int64)  # poses appended in the episode
        self.path_stamps = grown(get("path_stamps"), 0, np.int64, PATH_POSES)
        self.path_poses = grown(get("path_poses"), 0.0, float, PATH_POSES, 7)
        self.path_frames = grown(get("path_frames"), 0, np.int8, PATH_POSES)

    def slot(self, robot: str) -> int:
        """The robot's slot, a new one if it is heard first."""
        slot = self.slots.get(robot)
        if slot is None:
            self._add(robot)
            slot = self.slots[robot]
        return slot

    def renew(self, slots: int | np.ndarray, episodes: int | np.ndarray) -> None:
        """The robots (``slots``) begin transition episodes ``episodes``: no step, cost or path yet."""
        self.episode[slots], self.last_step[slots] = episodes, -1
        self.accumulated[slots], self.action[slots], self.path_count[slots] = 0.0, 0.0, 0

    def of(self, robots: Sequence[str]) -> np.ndarray:
        """The robots' slots, a new one for each robot heard first."""
        found = list(map(self.slots.get, robots))
        if None in found:
            for robot in robots:
                if robot not in self.slots:
                    self._add(robot)
            found = list(map(self.slots.get, robots))
        return np.array(found, dtype=np.intp)

    def _add(self, robot: str) -> None:
        name, base = ros_name(robot), base_frame(robot)  # first: a robot that cannot be named gets no slot
        bases = [transform_template(parent, base) for parent in (ODOM_FRAME, MAP_FRAME)]
        if self.size == len(self.episode):
            self._allocate(2 * self.size)
        slot = self.size
        ids = (len(self.templates), len(self.templates) + 1)
        self.bases[slot] = ids
        self.base_ids.append(ids)
        self.base_frames.append(base)
        self.templates += bases
        self.topics.append((f"/{name}/odom", f"/{name}/cmd_vel", f"/{name}/srl/transition", f"/{name}/path"))
        self.slots[robot] = slot
        self.size += 1


# the transforms every robot's /tf may carry besides its base (Tracks.templates, first)
TF_FIXED = ((ODOM_FRAME, GOAL_FRAME), (MAP_FRAME, GOAL_FRAME), (MAP_FRAME, ODOM_FRAME))
ODOM_GOAL, MAP_GOAL, MAP_ODOM = range(3)

# (robot, episode) origins remembered per robot heard (Recorder.step_time): every robot of a fleet
# keeps its own, and they stay bounded however many episodes pass
ORIGINS_PER_ROBOT = 4

Failed = Callable[[Exception], None]  # told each row a batch could not write, and why


def _raise(error: Exception) -> None:
    raise error


def _part(column: Any, rows: slice) -> Any:
    """A batch's column (an array, FrameRows or None) at ``rows``."""
    if column is None:
        return None
    return column.take(rows) if isinstance(column, FrameRows) else column[rows]


def runs(robots: Sequence[str]) -> list[slice]:
    """``robots``' rows in consecutive runs in which no robot comes twice: a robot's row is
    written after its rows before it (its step, its path), so each run is written whole, in order."""
    if len(set(robots)) == len(robots):
        return [slice(0, len(robots))]
    cuts, start = [], 0
    seen: set[str] = set()
    for row, robot in enumerate(robots):
        if robot in seen:
            cuts.append(slice(start, row))
            seen, start = set(), row
        seen.add(robot)
    return [*cuts, slice(start, len(robots))]


def groups(*codes: np.ndarray) -> list[tuple[tuple[int, ...], np.ndarray | slice]]:
    """The rows of each combination of ``codes``' values (frames, lengths): all rows (a slice)
    when they agree, as they mostly do."""
    if len(codes[0]) <= 1 or all((column == column[0]).all() for column in codes):
        return [(tuple(int(column[0]) if len(column) else 0 for column in codes), slice(None))]
    distinct, inverse = np.unique(np.stack(codes, axis=1).astype(np.int64), axis=0, return_inverse=True)
    return [(tuple(d), np.flatnonzero(inverse.reshape(-1) == k)) for k, d in enumerate(distinct.tolist())]


def in_rows(count: int, parts: Sequence[tuple[np.ndarray | slice, list[bytes]]]) -> list[bytes]:
    """The messages of :func:`groups`' parts (rows, their messages) back in their rows' order."""
    if len(parts) == 1 and len(parts[0][1]) == count:  # every row (each row is in one part)
        return parts[0][1]
    out = [b""] * count
    for rows, messages in parts:
        for row, message in zip(np.arange(count)[rows].tolist(), messages, strict=True):
            out[row] = message
    return out


@dataclass
class _StatePlan:
    """What a run of states writes, worked out before anything changes (Recorder.states)."""

    slots: np.ndarray
    episodes: np.ndarray
    seen: np.ndarray  # each row's count of states before it in its episode
    t_ns: np.ndarray
    origins: dict[tuple[str, int], int]  # fixed by these rows
    codes: np.ndarray  # pose frames
    odometry: list[bytes]
    transforms: np.ndarray  # rows x 3: which of (map -> odom, base, goal) the state puts on /tf
    ids: np.ndarray  # rows x 3: their templates (Tracks.templates)
    poses: np.ndarray  # rows x 3 x 7: their poses (planar_rows)


@dataclass
class _StepPlan:
    """What a run of transitions writes, worked out before anything changes (Recorder.transitions)."""

    slots: np.ndarray
    episodes: np.ndarray
    steps: np.ndarray
    t_ns: np.ndarray
    origins: dict[tuple[str, int], int]
    new: np.ndarray  # rows that begin an episode of their robot
    kept: np.ndarray  # the rows written (the others come at or after a step written: late)
    accumulated: np.ndarray  # J after each kept row
    actions: np.ndarray
    codes: np.ndarray  # the kept rows' pose frames
    commands: list[bytes]
    samples: list[bytes]
    path_poses: np.ndarray  # the kept rows' poses (planar_rows)


class Recorder:
    """srl's messages -> ROS 2 messages on a :class:`Sink`; what it remembers per robot in :class:`Tracks`.

    States and steps are written in batches of many robots (:meth:`states`, :meth:`transitions`:
    srl record's writer hands them a fleet's samples as they came, columns and all), their
    messages packed with numpy (:mod:`tools.recording.cdr`), so what is left per message is the
    sink's write. One state or step (:meth:`state`, :meth:`transition`: srl run's recording) is
    written by the same rules without arrays, whose cost would be most of a single row's;
    tests/test_record.py checks the two write the same samples.

    Not thread-safe: one thread calls it (:class:`tools.recording.record.Feed`'s writer, or ``srl run``)."""

    def __init__(self, sink: Sink, sampling_time: float, clock: Clock = "wall") -> None:
        self.sink = sink
        self.ros = RosMapping()
        self.delta_ns = round(sampling_time * 1e9)
        self.clock = clock
        self.tracks = Tracks()
        self.origins: dict[tuple[str, int], int] = {}
        self.target_sent = False
        self.late = 0  # transitions that came at or before a step written (dropped, Recorder.transitions)
        self.tf_gathered = 1  # transforms per /tf message at most (gather_tf)
        # transforms waiting for /tf, oldest first: (stamp [ns], template (Tracks.templates), pose (planar))
        self.tf_pending: list[tuple[int, int, Sequence[float]]] = []

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
            stamps, ids, poses = zip(*pending, strict=True)
            templates = self.tracks.templates
            data = tf_message(stamps, [templates[i] for i in ids], poses)
            self._write_cdr(TF_TOPIC, TF_MESSAGE, data, max(stamps))

    def _write(self, topic: str, ros_type: str, message: Any, t_ns: int) -> None:
        self.sink.write(topic, ros_type, self.ros.definition(ros_type), self.ros.cdr(message, ros_type), t_ns)

    def _write_cdr(self, topic: str, ros_type: str, data: bytes, t_ns: int) -> None:
        self.sink.write(topic, ros_type, self.ros.definition(ros_type), data, t_ns)

    def _write_rows(
        self,
        topics: list[str],
        ros_types: list[str],
        datas: list[bytes],
        stamps: list[int],
        failed: Failed,
        start: int = 0,
        width: int = 1,
    ) -> list[int]:
        """The samples from ``start`` on, ``width`` a row (a row's samples in order), through the
        sink's :meth:`~Sink.write_rows`: a row whose sample fails is handed to ``failed`` with why
        and the rest of its samples skipped, the rows after it written all the same, as a
        ``write`` per sample would have it. The rows refused, in order."""
        refused: list[int] = []
        write_rows, definitions = self.sink.write_rows, self.ros.definitions
        while start < len(topics):
            try:
                write_rows(topics[start:], ros_types[start:], datas[start:], stamps[start:], definitions)
                break
            except RowWriteError as failure:
                row = (start + failure.row) // width
                refused.append(row)
                failed(failure.error)
                start = (row + 1) * width
        return refused

    def begin(self, robot: str, episode: int, origin_ns: int) -> None:
        """Place step 0 of the robot's episode at ``origin_ns`` (an episode that ran in process)."""
        self.origins[(robot, episode)] = origin_ns

    def step_time(self, robot: str, episode: int, step: int, now_ns: int) -> int:
        """``origin + step delta`` of the robot's episode; the origin fixed by its first message."""
        key = (robot, episode)
        origin = self.origins.get(key)
        if origin is None:
            origin = now_ns - step * self.delta_ns
            self._remember({key: origin})
        return origin + step * self.delta_ns

    def _origins(
        self, robots: Sequence[str], episodes: np.ndarray, steps: np.ndarray, now_ns: np.ndarray
    ) -> tuple[np.ndarray, dict[tuple[str, int], int]]:
        """Each row's origin (:meth:`step_time`), and those its row fixes (not yet remembered)."""
        keys = list(zip(robots, episodes.tolist(), strict=True))
        found = list(map(self.origins.get, keys))
        fixed: dict[tuple[str, int], int] = {}
        if None in found:
            for row, (key, origin) in enumerate(zip(keys, found, strict=True)):
                if origin is None:
                    found[row] = fixed[key] = int(now_ns[row]) - int(steps[row]) * self.delta_ns
        return np.array(found, dtype=np.int64), fixed

    def _remember(self, origins: dict[tuple[str, int], int]) -> None:
        """Keep ``origins``, forgetting the oldest beyond :data:`ORIGINS_PER_ROBOT` per robot heard."""
        for key, origin in origins.items():
            if len(self.origins) >= ORIGINS_PER_ROBOT * max(1, self.tracks.size):
                del self.origins[next(iter(self.origins))]
            self.origins[key] = origin

    def target(self, t_ns: int, frame: str = ODOM_FRAME) -> None:
        """The target pose: the origin of the goal frame (once), in ``frame`` (the goal frame's name)."""
        if not self.target_sent:
            self.target_sent = True
            message = self.ros.types[POSE_STAMPED](header=self.ros.header(t_ns, frame), pose=self.ros.pose(IDENTITY))
            self._write(TARGET_TOPIC, POSE_STAMPED, message, t_ns)

    def _in_runs(
        self,
        plan: Callable[..., Any],
        write: Callable[[Any, Failed], int],
        failed: Failed,
        robots: list[str],
        *columns: Any,
    ) -> int:
        """``write(plan(...))`` of each :func:`runs` of the rows, in order; the rows taken (written,
        or dropped as late). A run that cannot be planned (a value its message cannot hold) is
        written row by row, so a bad row costs only itself: handed to ``failed`` with why, as is
        every row the sink refuses. ``plan`` changes nothing (but the robots' slots); ``write``
        hands its failures to ``failed``."""
        taken = 0
        for run in runs(robots):
            try:
                planned = plan(robots[run], *(_part(column, run) for column in columns))
            except Exception as error:
                if run.stop - run.start == 1:
                    failed(error)
                    continue
                for row in range(run.start, run.stop):
                    one = slice(row, row + 1)
                    taken += self._in_runs(plan, write, failed, robots[one], *(_part(c, one) for c in columns))
                continue
            taken += write(planned, failed)
        return taken

    # -- states -----------------------------------------------------------------------
    def state(self, robot: str, episode: int, state: Vector, now_ns: int, frames: PoseFrames = SIMULATED) -> None:
        """A state the robot reported, as :meth:`states` writes a row of them (one robot: no
        arrays, whose cost would be most of a row's)."""
        tracks = self.tracks
        slot = tracks.slot(robot)
        seen = tracks.states_seen.item(slot) if tracks.state_episode.item(slot) == episode else 0
        t_ns = self.step_time(robot, episode, seen, now_ns) if self.clock == "steps" else now_ns
        tracks.state_episode[slot], tracks.states_seen[slot] = episode, seen + 1
        frame = frames.pose_frame
        tracks.pose_frame[slot] = POSE_FRAMES.index(frame)
        self.target(t_ns, frame)
        action = (tracks.action.item(slot, 0), tracks.action.item(slot, 1))
        self._write_cdr(tracks.topics[slot][0], ODOMETRY, odometry_cdr(t_ns, frame, BASE_FRAME, state, action), t_ns)
        base, bases, pending = tracks.base_frames[slot], tracks.base_ids[slot], self.tf_pending
        for parent, child, pose in frames.transforms(state, base):
            template = bases[parent == MAP_FRAME] if child == base else TF_FIXED.index((parent, child))
            pending.append((t_ns, template, planar(pose.x, pose.y, pose.theta)))
        sent = tracks.tf_sent.item(slot)
        if sent % GOAL_EVERY == 0:
            goal = frames.goal
            pending.append((t_ns, TF_FIXED.index((frames.root, GOAL_FRAME)), planar(goal.x, goal.y, goal.theta)))
        tracks.tf_sent[slot] = sent + 1
        if len(pending) >= self.tf_gathered:  # without gather_tf: at once, one message per state
            self.flush_tf()

    def states(
        self,
        robots: Sequence[str],
        episodes: np.ndarray,
        states: np.ndarray,
        now_ns: int | np.ndarray,
        frames: FrameRows | None = None,
        failed: Failed = _raise,
    ) -> int:
        """States the robots reported, a row each (goal-frame x, y, alpha), arrived at ``now_ns``
        (one for all, or one each): ``/<robot>/odom`` (twist: the action it holds) and ``/tf``
        (``<robot>/base_footprint`` and ``map -> odom``: :meth:`PoseFrames.transforms`; ``<root> ->
        goal`` in the robot's first and every :data:`GOAL_EVERY`-th, so a live view that joins
        late sees the target within a second); ``frames`` None: simulated plants'. Stamped on
        arrival, or (clock "steps") the robot's n-th state of an episode at ``origin + n delta``.
        Returns the rows written (the others were handed to ``failed``, :meth:`_in_runs`)."""
        arrived = np.broadcast_to(np.asarray(now_ns, dtype=np.int64), (len(robots),))
        numbers = (np.asarray(episodes, dtype=np.int64), np.asarray(states, dtype=float), arrived)
        return self._in_runs(self._plan_states, self._write_states, failed, list(robots), *numbers, frames)

    def _plan_states(
        self, robots: list[str], episodes: np.ndarray, states: np.ndarray, now_ns: np.ndarray, frames: FrameRows | None
    ) -> _StatePlan:
        tracks, count = self.tracks, len(robots)
        slots = tracks.of(robots)
        seen = np.where(tracks.state_episode[slots] == episodes, tracks.states_seen[slots], 0)
        origins: dict[tuple[str, int], int] = {}
        t_ns = now_ns.copy()
        if self.clock == "steps":
            starts, origins = self._origins(robots, episodes, seen, now_ns)
            t_ns = starts + seen * self.delta_ns
        poses = planar_rows(states[:, 0], states[:, 1], states[:, 2])
        transforms = np.zeros((count, 3), dtype=bool)  # map -> odom, base, goal
        transforms[:, 1] = True
        transforms[:, 2] = tracks.tf_sent[slots] % GOAL_EVERY == 0
        ids = np.empty((count, 3), dtype=np.int64)
        moves = np.zeros((count, 3, 7))
        moves[:, 1] = poses
        moves[:, 2, 6] = 1.0  # the goal: the identity, unless a robot's (below)
        ids[:, 0], ids[:, 2] = MAP_ODOM, ODOM_GOAL
        ids[:, 1] = tracks.bases[slots, 0]
        codes = np.zeros(count, dtype=np.int8)
        if frames is not None:
            codes = self._frames(frames, states, slots, transforms, ids, moves)
        action = tracks.action[slots]
        parts = [
            (rows, odometry_rows(t_ns[rows], POSE_FRAMES[code], BASE_FRAME, poses[rows], action[rows]))
            for (code,), rows in groups(codes)
        ]
        odometry = in_rows(count, parts)
        return _StatePlan(slots, episodes, seen, t_ns, origins, codes, odometry, transforms, ids, moves)

    def _frames(
        self,
        frames: FrameRows,
        states: np.ndarray,
        slots: np.ndarray,
        transforms: np.ndarray,
        ids: np.ndarray,
        moves: np.ndarray,
    ) -> np.ndarray:
        """The transforms of states whose goal frame is not their odom frame (:class:`PoseFrames`)
        into ``transforms``, ``ids`` and ``moves``; their pose frames' codes."""
        goal, localized = frames.goal, frames.localized
        identity = (goal == 0.0).all(axis=1)
        corrected = localized & np.isfinite(frames.map_to_odom).all(axis=1)
        pose = states.copy()
        placed = ~identity  # g (+) s
        if placed.any():
            g, s = goal[placed], states[placed]
            sin, cos = sin_cos(g[:, 2])
            pose[placed] = np.column_stack(
                (g[:, 0] + cos * s[:, 0] - sin * s[:, 1], g[:, 1] + sin * s[:, 0] + cos * s[:, 1], s[:, 2] + g[:, 2])
            )
        if corrected.any():  # the base in odom: to_goal_frame(pose, C)
            c, p = frames.map_to_odom[corrected], pose[corrected]
            sin, cos = sin_cos(c[:, 2])
            dx, dy = p[:, 0] - c[:, 0], p[:, 1] - c[:, 1]
            pose[corrected] = np.column_stack((cos * dx + sin * dy, -sin * dx + cos * dy, p[:, 2] - c[:, 2]))
            moves[corrected, 0] = planar_rows(c[:, 0], c[:, 1], c[:, 2])
            transforms[:, 0] = corrected
        moved = placed | corrected
        if moved.any():
            p = pose[moved]
            moves[moved, 1] = planar_rows(p[:, 0], p[:, 1], p[:, 2])
        ids[:, 1] = self.tracks.bases[slots, (localized & ~corrected).astype(np.intp)]  # from map: no odom
        ids[:, 2] = np.where(localized, MAP_GOAL, ODOM_GOAL)
        goals = transforms[:, 2]
        moves[goals, 2] = planar_rows(goal[goals, 0], goal[goals, 1], goal[goals, 2])
        return np.where(localized | ~identity, 1, 0).astype(np.int8)  # goal, else odom

    def _target_first(self, t_ns: int, code: int, failed: Failed) -> list[int]:
        """The target before a batch's first row, once a recording (:meth:`target`): ``[0]`` when
        it could not be written (that row is refused with it, ``failed`` told why), else ``[]``."""
        if self.target_sent:
            return []
        try:
            self.target(t_ns, POSE_FRAMES[code])
        except Exception as error:
            failed(error)
            return [0]
        return []

    def _write_states(self, plan: _StatePlan, failed: Failed) -> int:
        tracks = self.tracks
        slots, count = plan.slots, len(plan.slots)
        tracks.state_episode[slots] = plan.episodes
        tracks.states_seen[slots] = plan.seen + 1
        tracks.pose_frame[slots] = plan.codes
        self._remember(plan.origins)
        stamps = plan.t_ns.tolist()
        refused = self._target_first(stamps[0], plan.codes[0], failed)
        topics = tracks.topics
        odometry = [topics[slot][0] for slot in slots.tolist()]
        refused += self._write_rows(odometry, [ODOMETRY] * count, plan.odometry, stamps, failed, len(refused))
        transforms = plan.transforms
        if refused:
            transforms = transforms.copy()
            transforms[refused] = False
            slots = np.delete(slots, refused)
        tracks.tf_sent[slots] += 1
        self._gather(transforms, np.broadcast_to(plan.t_ns[:, None], transforms.shape), plan.ids, plan.poses, failed)
        return count - len(refused)

    def _gather(
        self, transforms: np.ndarray, stamps: np.ndarray, ids: np.ndarray, poses: np.ndarray, failed: Failed
    ) -> None:
        """The states' ``transforms`` (rows x 3, in their rows' order) onto the pending ``/tf``,
        a message written whenever :attr:`tf_gathered` are pending at the end of a state."""
        ends = np.cumsum(transforms.sum(axis=1))  # each state's last transform, counted from 1
        moves = list(
            zip(stamps[transforms].tolist(), ids[transforms].tolist(), poses[transforms].tolist(), strict=True)
        )
        start = 0
        while start < len(moves):
            row = int(np.searchsorted(ends, max(start + 1, start + self.tf_gathered - len(self.tf_pending))))
            end = int(ends[row]) if row < len(ends) else len(moves)
            self.tf_pending += moves[start:end]
            start = end
            if row < len(ends):
                try:
                    self.flush_tf()
                except Exception as error:
                    failed(error)

    # -- steps ------------------------------------------------------------------------
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
        """One step, as :meth:`transitions` writes a row of them (one robot: no arrays); False
        (nothing written) for a step at or before one written."""
        tracks = self.tracks
        slot = tracks.slot(robot)
        t_ns = self.step_time(robot, episode, step, now_ns)
        if tracks.episode.item(slot) != episode:  # a new episode: its own steps, cost and path
            tracks.renew(slot, episode)
        if step <= tracks.last_step.item(slot):
            self.late += 1
            return False
        accumulated = tracks.accumulated.item(slot) + float(cost)
        v, omega = float(action[0]), float(action[1])
        tracks.last_step[slot], tracks.accumulated[slot], tracks.action[slot] = step, accumulated, (v, omega)
        code = tracks.pose_frame.item(slot)
        self.target(t_ns, POSE_FRAMES[code])
        topics = tracks.topics[slot]
        self._write_cdr(topics[1], TWIST_STAMPED, twist_stamped_cdr(t_ns, BASE_FRAME, v, omega), t_ns)
        x, y, alpha = float(state[0]), float(state[1]), float(state[2])
        values = (x, y, alpha, v, omega, float(cost), accumulated)
        sample = transition_cdr(t_ns, POSE_FRAMES[code], episode, step, values)
        self._write_cdr(topics[2], TRANSITION, sample, t_ns)
        if step % PATH_STRIDE == 0:
            at = tracks.path_count.item(slot) % PATH_POSES
            tracks.path_stamps[slot, at], tracks.path_poses[slot, at] = t_ns, planar(x, y, alpha)
            tracks.path_frames[slot, at], tracks.path_count[slot] = code, tracks.path_count.item(slot) + 1
        if step % PATH_EVERY == 0:
            self.path(robot, t_ns)
        return True

    def transitions(
        self,
        robots: Sequence[str],
        episodes: np.ndarray,
        steps: np.ndarray,
        states: np.ndarray,
        actions: np.ndarray,
        costs: np.ndarray,
        now_ns: int | np.ndarray,
        failed: Failed = _raise,
    ) -> int:
        """Steps, a row each (s_k, u_k, c_k), arrived at ``now_ns`` (one for all, or one each) and
        stamped ``origin + k delta``: ``/<robot>/cmd_vel`` and ``/<robot>/srl/transition``; the
        path every :data:`PATH_EVERY` steps. A robot's rows are written in their order, a step at
        or before one written dropped (counted in :attr:`late`). Returns the rows taken (written,
        or dropped as late; the others were handed to ``failed``, :meth:`_in_runs`)."""
        arrived = np.broadcast_to(np.asarray(now_ns, dtype=np.int64), (len(robots),))
        numbers = [np.asarray(column, dtype=np.int64) for column in (episodes, steps)]
        numbers += [np.asarray(column, dtype=float) for column in (states, actions, costs)]
        return self._in_runs(self._plan_steps, self._write_steps, failed, list(robots), *numbers, arrived)

    def _plan_steps(
        self,
        robots: list[str],
        episodes: np.ndarray,
        steps: np.ndarray,
        states: np.ndarray,
        actions: np.ndarray,
        costs: np.ndarray,
        now_ns: np.ndarray,
    ) -> _StepPlan:
        tracks = self.tracks
        slots = tracks.of(robots)
        starts, origins = self._origins(robots, episodes, steps, now_ns)
        t_ns = starts + steps * self.delta_ns
        new = tracks.episode[slots] != episodes
        kept = np.flatnonzero(steps > np.where(new, -1, tracks.last_step[slots]))
        accumulated = np.where(new, 0.0, tracks.accumulated[slots])[kept] + costs[kept]
        codes = tracks.pose_frame[slots[kept]]
        stamps, state, action = t_ns[kept], states[kept, :3], actions[kept, :2]
        values = np.column_stack((state, action, costs[kept], accumulated))
        commands = twist_stamped_rows(stamps, BASE_FRAME, action)
        parts = [
            (
                rows,
                transition_rows(stamps[rows], POSE_FRAMES[code], episodes[kept][rows], steps[kept][rows], values[rows]),
            )
            for (code,), rows in groups(codes)
        ]
        samples = in_rows(len(kept), parts)
        strided = steps[kept] % PATH_STRIDE == 0
        path_poses = planar_rows(state[strided, 0], state[strided, 1], state[strided, 2])
        plan = (slots, episodes, steps, t_ns, origins, new, kept, accumulated, action, codes, commands, samples)
        return _StepPlan(*plan, path_poses)

    def _write_steps(self, plan: _StepPlan, failed: Failed) -> int:
        tracks, kept = self.tracks, plan.kept
        self._remember(plan.origins)
        self.late += len(plan.slots) - len(kept)
        if plan.new.any():  # a new episode: its own steps, cost and path
            tracks.renew(plan.slots[plan.new], plan.episodes[plan.new])
        slots, steps, t_ns = plan.slots[kept], plan.steps[kept], plan.t_ns[kept]
        tracks.last_step[slots] = steps
        tracks.accumulated[slots] = plan.accumulated
        tracks.action[slots] = plan.actions
        if not len(kept):
            return len(plan.slots)
        stamps = t_ns.tolist()
        refused = self._target_first(stamps[0], plan.codes[0], failed)
        topics = tracks.topics
        # a row's command, then its transition (a command refused: not its transition)
        names = [topic for slot in slots.tolist() for topic in topics[slot][1:3]]
        datas = [data for pair in zip(plan.commands, plan.samples, strict=True) for data in pair]
        twice = [stamp for stamp in stamps for _ in range(2)]
        kinds = [TWIST_STAMPED, TRANSITION] * len(stamps)
        refused += self._write_rows(names, kinds, datas, twice, failed, 2 * len(refused), width=2)
        strided = np.flatnonzero(steps % PATH_STRIDE == 0)
        written = np.ones(len(kept), dtype=bool)
        written[refused] = False
        appended = strided[written[strided]]
        if len(appended):  # onto the robots' rings
            ring = slots[appended]
            at = tracks.path_count[ring] % PATH_POSES
            tracks.path_stamps[ring, at] = t_ns[appended]
            tracks.path_poses[ring, at] = plan.path_poses[written[strided]]
            tracks.path_frames[ring, at] = plan.codes[appended]
            tracks.path_count[ring] += 1
        due = np.flatnonzero(written & (steps % PATH_EVERY == 0))
        if len(due):
            refused += self._write_paths(slots[due], t_ns[due], due, failed)
        return len(plan.slots) - len(set(refused))

    # -- the path ---------------------------------------------------------------------
    def path(self, robot: str, t_ns: int) -> None:
        """``/<robot>/path``: its newest poses, stamped ``t_ns`` (nothing before its first)."""
        slot = self.tracks.slots.get(robot)
        if slot is not None and self.tracks.path_count[slot]:
            self._write_paths(np.array([slot]), np.array([t_ns]), np.zeros(1, dtype=np.intp), _raise)

    def _write_paths(self, slots: np.ndarray, t_ns: np.ndarray, rows: np.ndarray, failed: Failed) -> list[int]:
        """Each robot's path (``slots``, each with poses), stamped ``t_ns``; the ``rows`` of those
        that were not written (handed to ``failed``)."""
        try:
            messages = self._paths(slots, t_ns)
        except Exception as error:
            for _ in rows:
                failed(error)
            return rows.tolist()
        topics = self.tracks.topics
        paths = [topics[slot][3] for slot in slots.tolist()]
        refused = self._write_rows(paths, [PATH] * len(paths), messages, t_ns.tolist(), failed)
        return rows[refused].tolist()

    def _paths(self, slots: np.ndarray, t_ns: np.ndarray) -> list[bytes]:
        """The robots' paths as CDR, those of the same length and frames packed together
        (:func:`tools.recording.cdr.path_rows`); a path whose poses are in more than one frame (a
        robot localized mid-path) through rosbags (:meth:`RosMapping.path_poses_cdr`)."""
        tracks = self.tracks
        counts = tracks.path_count[slots]
        lengths = np.minimum(counts, PATH_POSES)
        parts = []
        for (length,), alike in groups(lengths):
            ring = slots[alike][:, None]
            at = (counts[alike][:, None] - length + np.arange(length)) % PATH_POSES  # oldest first
            stamps, poses, frames = (
                tracks.path_stamps[ring, at],
                tracks.path_poses[ring, at],
                tracks.path_frames[ring, at],
            )
            own = np.where((frames == frames[:, :1]).all(axis=1), frames[:, 0], -1)  # -1: in more than one
            heads = tracks.pose_frame[slots[alike]]
            times = t_ns[alike]
            for (head, mine), rows in groups(heads, own):
                if mine >= 0:
                    packed = path_rows(times[rows], POSE_FRAMES[head], POSE_FRAMES[mine], stamps[rows], poses[rows])
                else:
                    packed = [
                        self.ros.path_poses_cdr(int(t), POSE_FRAMES[head], s, p, [POSE_FRAMES[f] for f in f_row])
                        for t, s, p, f_row in zip(
                            times[rows], stamps[rows], poses[rows], frames[rows].tolist(), strict=True
                        )
                    ]
                parts.append((np.arange(len(slots))[alike][rows], packed))
        return in_rows(len(slots), parts)

    # -- the critic and the actor ---------------------------------------------------------
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
        slot = self.tracks.slots.get(robot)
        t_ns = now_ns
        if self.clock == "steps" and slot is not None and self.tracks.last_step.item(slot) >= 0:
            episode, step = self.tracks.episode.item(slot), self.tracks.last_step.item(slot)
            t_ns = self.step_time(robot, episode, step, now_ns)

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
# On Ctrl-C the recorder keeps receiving until nothing has come for this long (at most the second):
# srl up stops it after the services, whose last messages may still be on their way through the router.
SETTLE_QUIET_S = 0.25
SETTLE_LONGEST_S = 1.0
UNRECEIVED_NOTE = "; {count} steps never received (before a robot's first, not in the actors' caches)"
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


def robot_frame_rows(bridge: Any, robot: np.ndarray, corrections: np.ndarray) -> FrameRows:
    """:func:`robot_frames` of a batch's states, one row each: ``robot`` says which came from a
    robot bridge, ``corrections`` their ``map_to_odom`` (rows of NaN where none)."""
    goal = np.zeros((len(robot), 3))
    goal[robot] = [float(c) for c in bridge.goal]
    localized = robot & (getattr(bridge, "pose_source", ODOMETRY_ONLY) != ODOMETRY_ONLY)
    known = robot & np.isfinite(corrections).all(axis=1)
    return FrameRows(goal, localized, np.where(known[:, None], corrections, math.nan))


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
        self.unreceived = 0  # steps before a held robot's first that neither came nor were recovered
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
        """``write(*args)`` (one row of ``kind``, or the batch's /tf); True if it was written, else
        :meth:`_failed`. Nothing is built per row but the call."""
        try:
            write(*args)
            return True
        except Exception as error:
            self._failed(kind, error)
        return False

    def _failed(self, kind: str, error: Exception) -> None:
        """A row of ``kind`` not written: counted in ``errors``, and the recording goes on. A bad row
        is logged with its traceback, a file that cannot be written (:class:`RecordingError`, a
        full disk) once per reason, not once per row."""
        self.errors += 1
        if isinstance(error, RecordingError):
            if str(error) != self.failure:
                self.failure = str(error)
                log.error("recorder: %s", error)
        else:
            log.error("recorder: cannot record a %s sample", kind, exc_info=error)

    def _rows(self, kind: str, write: Callable[..., object], *columns: Sequence[Any]) -> None:
        """``write`` of each row (the i-th of every column), guarded row by row."""
        guarded = self._guarded
        self.received += sum(guarded(kind, write, *row) for row in zip(*columns, strict=True))

    def _states(self, columns: Columns[Any], now_ns: int) -> None:
        """A batch's states, written at once (Recorder.states)."""
        from common.contracts.columns import choice_code
        from common.contracts.messages import PlantState

        robot = columns.field("source") == choice_code(PlantState, "source", "robot")
        frames = robot_frame_rows(self.bridge, robot, columns.field("map_to_odom")) if robot.any() else None
        episodes, states = columns.field("episode"), columns.field("state")
        failed = functools.partial(self._failed, "state")
        self.received += self.recorder.states(columns.robots, episodes, states, now_ns, frames, failed)

    def _transitions(self, columns: Columns[Any], now_ns: int) -> None:
        """A batch's transitions, written at once (Recorder.transitions), in step order per robot: a
        robot's first transition of an episode after step 0 (the subscription's history came too
        late, or not at all) holds its robot's rows while the actors' caches are asked for the
        steps before it (:meth:`_release`)."""
        robots, episodes = columns.robots, columns.field("episode")
        if self.held or any(map(operator.ne, map(self.started.get, robots), episodes.tolist())):
            fields = [columns.field(name).tolist() for name in ("episode", "step", "state", "action", "cost")]
            rows = zip(robots, *fields, [now_ns] * len(columns), strict=True)
            columns = columns.take([row for row, values in enumerate(rows) if not self._hold(values)])
        if len(columns):
            steps = [columns.field(name) for name in ("episode", "step", "state", "action", "cost")]
            self._write_steps(columns.robots, steps, now_ns)

    def _write_steps(self, robots: Sequence[str], columns: Sequence[Any], now_ns: int | np.ndarray) -> None:
        """Recorder.transitions of ``columns`` (episodes, steps, states, actions, costs)."""
        episodes, steps, states, actions, costs = columns
        failed = functools.partial(self._failed, "transition")
        self.received += self.recorder.transitions(robots, episodes, steps, states, actions, costs, now_ns, failed)

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
        rows: list[tuple[Any, ...]] = []
        for robot in done:
            firsts = {row[2]: row for row in reversed(self.held.pop(robot))}  # the first of each step
            missing = max(firsts) + 1 - len(firsts)  # of steps 0 .. the newest held
            if missing:  # said, never silently left out: srl record's summary line counts them
                self.unreceived += missing
                log.warning(
                    "recorder: %s: %d of its first %d steps never came and were not recovered",
                    robot,
                    missing,
                    max(firsts) + 1,
                )
            rows += sorted(firsts.values(), key=lambda row: row[2])
        if rows:
            robots, *columns, arrivals = zip(*rows, strict=True)
            self._write_steps(robots, [np.array(column) for column in columns], np.array(arrivals))

    def _weights(self, columns: Columns[Any], now_ns: int) -> None:
        def write(m: Any) -> None:
            residuals = (m.q_residual, m.v_residual)
            fit = (m.version, m.trained_step, m.q_weights, m.v_weights, residuals, m.pairs)
            self.recorder.weights(m.robot, m.episode, *fit, now_ns)

        self._rows("weights", write, list(columns.items()))

    def _status(self, message: Any, now_ns: int) -> None:
        self._rows("status", self.recorder.status, [message.robot], [dict(message.counters)], [now_ns])

    def close(self) -> None:
        """Take what is still coming (:data:`SETTLE_QUIET_S` without a sample, at most
        :data:`SETTLE_LONGEST_S`), stop receiving, write what is queued, close the sink (the file
        is complete after this)."""
        self.inbox.settle(SETTLE_QUIET_S, SETTLE_LONGEST_S)
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
            latched=LATCHED_TOPICS,
        )
    except RecordingError as error:
        raise UsageError(str(error)) from None
    recorder = Recorder(sink, settings.plant.sampling_time, clock=args.clock)
    ready = f"srl record: recording srl/* (every robot) from {settings.transport.router} to {sink.path}; Ctrl-C ends it"
    feed = Feed.run(settings, recorder, "record", args, lambda: ready)
    late = recorder.late
    extra = DROPPED_NOTE.format(count=feed.dropped) if feed.dropped else ""
    extra += f"; {late} late transitions skipped" if late else ""
    extra += UNRECEIVED_NOTE.format(count=feed.unreceived) if feed.unreceived else ""
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
