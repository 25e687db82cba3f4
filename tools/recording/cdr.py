"""CDR of the messages a recording writes at every state and step of every robot (odometry,
``/tf``, ``cmd_vel``, srl's transitions and critic weights), packed with one precompiled :mod:`struct` layout per
message shape: byte for byte what rosbags serializes for them (tests/test_record_tf.py compares the
two), at a fraction of its CPU, for a recorder beside a fleet writes thousands of them a second.
"""

from __future__ import annotations

import functools
import math
import struct
from collections.abc import Sequence

import numpy as np

from common.math.features import Q_FEATURES, V_FEATURES
from common.math.frames import Pose2D

Vector = Sequence[float] | np.ndarray  # a state (x, y, alpha) or an action (v, omega)


class CdrLayout:
    """The ``struct`` format of one CDR message as OMG DDS-XTypes' XCDR1 little endian lays it out
    (what ROS 2 and rosbags write): each field aligned to its own size counted from the end of the
    4-byte encapsulation header, a string as its uint32 length (with its NUL), its bytes and the NUL.
    Built once per message shape (its strings fixed), then one ``pack`` per message."""

    def __init__(self, offset: int | None = None) -> None:
        """A whole message (its encapsulation header first), or with ``offset`` a part of one that
        starts ``offset`` bytes after the encapsulation header (aligned as there)."""
        self.parts = ["<4s"] if offset is None else ["<"]  # the encapsulation header CDR_LE
        self.offset = offset or 0  # from the end of the encapsulation header

    def field(self, code: str, size: int, count: int = 1) -> CdrLayout:
        """``count`` values of the ``struct`` type ``code``, ``size`` bytes each, aligned to ``size``."""
        pad = -self.offset % size
        if pad:
            self.parts.append(f"{pad}x")
        self.parts.append(f"{count}{code}")
        self.offset += pad + size * count
        return self

    def uint32(self) -> CdrLayout:
        return self.field("I", 4)

    def uint64(self) -> CdrLayout:
        return self.field("Q", 8)

    def float64(self, count: int) -> CdrLayout:
        return self.field("d", 8, count)

    def zeros64(self, count: int) -> CdrLayout:
        """``count`` float64 zeros (a covariance nobody estimated): padding bytes, no value."""
        pad = -self.offset % 8
        self.parts.append(f"{pad + 8 * count}x")
        self.offset += pad + 8 * count
        return self

    def string(self, text: str) -> CdrLayout:
        """A fixed string: its length and bytes are in the format, not among the values."""
        self.uint32()
        size = len(text.encode()) + 1
        self.parts.append(f"{size}s")
        self.offset += size
        return self

    def header(self) -> CdrLayout:
        """``std_msgs/Header``'s stamp (int32 sec, uint32 nanosec); its frame_id follows (:meth:`string`)."""
        return self.field("i", 4).field("I", 4)

    def compile(self) -> struct.Struct:
        return struct.Struct("".join(self.parts))


CDR_LE = b"\x00\x01\x00\x00"


def _stamp(t_ns: int) -> tuple[int, int]:
    sec, nanosec = divmod(int(t_ns), 1_000_000_000)
    return sec, nanosec


def _text(text: str) -> tuple[int, bytes]:
    raw = text.encode() + b"\0"
    return len(raw), raw


def _planar(x: float, y: float, alpha: float) -> tuple[float, ...]:
    """A planar pose as ``geometry_msgs/Pose`` (or ``Transform``): position (x, y, 0), rotation about z."""
    return (x, y, 0.0, 0.0, 0.0, math.sin(alpha / 2), math.cos(alpha / 2))


@functools.cache
def _odometry_layout(frame: str, child: str) -> struct.Struct:
    layout = CdrLayout().header().string(frame).string(child).float64(7).zeros64(36).float64(6).zeros64(36)
    return layout.compile()


_TF_COUNT = struct.Struct("<4sI")  # a TFMessage's encapsulation header and its count of transforms


@functools.lru_cache(maxsize=4096)  # the frame pairs of a fleet's robots, bounded whatever ids come
def _transform_layout(parent: str, child: str, first: bool) -> struct.Struct:
    """One ``geometry_msgs/TransformStamped`` of a TFMessage: the first 4 bytes into the body
    (after the count), every other at a multiple of 8 (the one before ends with a float64)."""
    return CdrLayout(offset=4 if first else 0).header().string(parent).string(child).float64(7).compile()


@functools.cache
def _twist_stamped_layout(frame: str) -> struct.Struct:
    return CdrLayout().header().string(frame).float64(6).compile()


@functools.cache
def _transition_layout(frame: str) -> struct.Struct:
    return CdrLayout().header().string(frame).uint64().uint32().float64(7).compile()


@functools.cache
def _weights_layout(frame: str) -> struct.Struct:
    layout = CdrLayout().header().string(frame).uint64().uint64().field("i", 4)
    return layout.float64(Q_FEATURES).float64(V_FEATURES).float64(2).uint32().compile()


def odometry_cdr(t_ns: int, frame: str, child: str, state: Vector, action: tuple[float, float]) -> bytes:
    """``nav_msgs/Odometry`` of a planar ``state`` holding ``action``, covariances zero."""
    pose = _planar(float(state[0]), float(state[1]), float(state[2]))
    v, omega = action
    return _odometry_layout(frame, child).pack(
        CDR_LE, *_stamp(t_ns), *_text(frame), *_text(child), *pose, v, 0.0, 0.0, 0.0, 0.0, omega
    )


def tf_cdr(transforms: Sequence[tuple[int, str, str, Pose2D]]) -> bytes:
    """``tf2_msgs/TFMessage`` of planar ``(stamp [ns], parent, child, pose)`` transforms."""
    parts = [_TF_COUNT.pack(CDR_LE, len(transforms))]
    for i, (t_ns, parent, child, pose) in enumerate(transforms):
        planar = _planar(float(pose.x), float(pose.y), float(pose.theta))
        parts.append(
            _transform_layout(parent, child, i == 0).pack(*_stamp(t_ns), *_text(parent), *_text(child), *planar)
        )
    return b"".join(parts)


def twist_stamped_cdr(t_ns: int, frame: str, v: float, omega: float) -> bytes:
    """``geometry_msgs/TwistStamped``: linear (v, 0, 0), angular (0, 0, omega)."""
    return _twist_stamped_layout(frame).pack(CDR_LE, *_stamp(t_ns), *_text(frame), v, 0.0, 0.0, 0.0, 0.0, omega)


def transition_cdr(t_ns: int, frame: str, episode: int, step: int, values: Sequence[float]) -> bytes:
    """``srl_msgs/Transition`` (:data:`SRL_MSGS`): ``values`` = x, y, alpha, v, omega, stage_cost,
    accumulated_cost."""
    return _transition_layout(frame).pack(CDR_LE, *_stamp(t_ns), *_text(frame), episode, step, *values)


def weights_cdr(
    t_ns: int,
    frame: str,
    episode: int,
    version: int,
    trained_step: int,
    q_weights: Vector,
    v_weights: Vector,
    residuals: tuple[float, float],
    pairs: int,
) -> bytes:
    """``srl_msgs/CriticWeights`` (:data:`SRL_MSGS`): ``float64[15] q_weights``, ``float64[6] v_weights``."""
    if len(q_weights) != Q_FEATURES or len(v_weights) != V_FEATURES:
        raise ValueError(
            f"critic weights are {Q_FEATURES} + {V_FEATURES} numbers, got {len(q_weights)} + {len(v_weights)}"
        )
    return _weights_layout(frame).pack(
        CDR_LE,
        *_stamp(t_ns),
        *_text(frame),
        episode,
        version,
        trained_step,
        *(float(w) for w in q_weights),
        *(float(v) for v in v_weights),
        float(residuals[0]),
        float(residuals[1]),
        pairs,
    )
