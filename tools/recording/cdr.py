"""CDR of the messages a recording writes at every state and step of every robot (odometry,
``/tf``, ``cmd_vel``, srl's transitions and critic weights, the path): byte for byte what rosbags
serializes for them (tests/test_record_tf.py compares the two), at a fraction of its CPU, for a
recorder beside a fleet writes thousands of them a second.

Each message shape (its strings fixed) is laid out once (:class:`CdrLayout`): the message with
every value 0, and where each value sits in it. A message is that template with its values
written in (:meth:`CdrMessage.one`, :mod:`struct`); many are packed at once with numpy
(:meth:`CdrMessage.rows`: the template once per row, each value field written in every row), so a
batch of a fleet's robots costs a few array operations, not a Python call per message.
"""

from __future__ import annotations

import functools
import math
import struct
from collections.abc import Sequence
from typing import Any

import numpy as np

from common.math.features import Q_FEATURES, V_FEATURES
from common.math.frames import Pose2D

Vector = Sequence[float] | np.ndarray  # a state (x, y, alpha) or an action (v, omega)
CDR_LE = b"\x00\x01\x00\x00"  # the encapsulation header: CDR, little endian
NS = 1_000_000_000
_DTYPES = {"i": "<i4", "I": "<u4", "Q": "<u8", "d": "<f8"}  # a struct code's numpy type
_TIME = np.dtype([("sec", "<i4"), ("nanosec", "<u4")])  # builtin_interfaces/Time


class CdrLayout:
    """One CDR message as OMG DDS-XTypes' XCDR1 little endian lays it out (what ROS 2 and rosbags
    write): each field aligned to its own size counted from the end of the 4-byte encapsulation
    header, a string as its uint32 length (with its NUL), its bytes and the NUL. Kept as the
    message with its strings and every value 0 (``template``) and where each value field sits in
    it (``values``: byte, ``struct`` code, count, in the order a message's values are given)."""

    def __init__(self, offset: int | None = None) -> None:
        """A whole message (its encapsulation header first), or with ``offset`` a part of one that
        starts ``offset`` bytes after the encapsulation header (aligned as there)."""
        self.template = bytearray(CDR_LE if offset is None else b"")
        self.offset = offset or 0  # from the end of the encapsulation header
        self.values: list[tuple[int, str, int]] = []

    def _pad(self, size: int) -> None:
        pad = -self.offset % size
        self.template += bytes(pad)
        self.offset += pad

    def field(self, code: str, size: int, count: int = 1) -> CdrLayout:
        """``count`` values of the ``struct`` type ``code``, ``size`` bytes each, aligned to ``size``."""
        self._pad(size)
        self.values.append((len(self.template), code, count))
        self.template += bytes(size * count)
        self.offset += size * count
        return self

    def uint32(self) -> CdrLayout:
        return self.field("I", 4)

    def uint64(self) -> CdrLayout:
        return self.field("Q", 8)

    def float64(self, count: int) -> CdrLayout:
        return self.field("d", 8, count)

    def zeros64(self, count: int) -> CdrLayout:
        """``count`` float64 zeros (a covariance nobody estimated): in the template, no value."""
        self._pad(8)
        self.template += bytes(8 * count)
        self.offset += 8 * count
        return self

    def string(self, text: str) -> CdrLayout:
        """A fixed string: its length and bytes are in the template, not among the values."""
        raw = text.encode() + b"\0"
        self._pad(4)
        self.template += len(raw).to_bytes(4, "little") + raw
        self.offset += 4 + len(raw)
        return self

    def header(self) -> CdrLayout:
        """``std_msgs/Header``'s stamp (int32 sec, uint32 nanosec); its frame_id follows (:meth:`string`)."""
        return self.field("i", 4).field("I", 4)

    def message(self) -> CdrMessage:
        return CdrMessage(bytes(self.template), self.values)


class CdrMessage:
    """A :class:`CdrLayout`'s messages: one (:meth:`one`) or many at once (:meth:`rows`), the same
    bytes either way (tests/test_record_tf.py). An integer its field cannot hold is refused (a
    ``struct.error`` or ValueError), never written wrapped around."""

    def __init__(self, template: bytes, values: Sequence[tuple[int, str, int]]) -> None:
        self.template = template
        self.size = len(template)
        # one struct for the whole message: each run of value fields with only zeros between
        # them (pad bytes), and the template's bytes before each run (its strings) as a constant
        # argument: (the constant, the run's numbers in one's arguments)
        parts = ["<"]
        self.pieces: list[tuple[bytes, int, int]] = []
        end, numbers = 0, 0
        for at, code, count in values:
            if not self.pieces or any(template[end:at]):
                parts.append(f"{at - end}s")
                self.pieces.append((template[end:at], numbers, numbers))
            elif at > end:
                parts.append(f"{at - end}x")
            parts.append(f"{count}{code}")
            end, numbers = at + struct.calcsize(f"<{count}{code}"), numbers + count
            constant, first, _ = self.pieces[-1]
            self.pieces[-1] = (constant, first, numbers)
        self.tail = () if not any(template[end:]) else (template[end:],)  # zeros: pad bytes
        parts.append(f"{len(template) - end}{'s' if self.tail else 'x'}")
        self.whole = struct.Struct("".join(parts))
        self.dtype = np.dtype(
            {
                "names": [f"v{i}" for i in range(len(values))],
                "formats": [_DTYPES[code] if count == 1 else (_DTYPES[code], (count,)) for _, code, count in values],
                "offsets": [at for at, _, _ in values],
                "itemsize": self.size,
            }
        )
        self.names = list(self.dtype.names or ())
        self.integers = [np.dtype(_DTYPES[code]) if code in "iIQ" else None for _, code, _ in values]

    def one(self, *numbers: Any) -> bytes:
        """One message: every number of its value fields, in the layout's order."""
        if len(self.pieces) == 2 and self.pieces[0][2] == 2 and not self.tail:  # a stamp, a frame, the rest
            (head, _, _), (frame, _, _) = self.pieces
            return self.whole.pack(head, numbers[0], numbers[1], frame, *numbers[2:])
        args: list[Any] = []
        for constant, first, end in self.pieces:
            args.append(constant)
            args += numbers[first:end]
        return self.whole.pack(*args, *self.tail)

    def rows(self, count: int, *values: np.ndarray | float) -> list[bytes]:
        """``count`` messages: ``values`` in the layout's order, each a column (count, or count x
        the field's numbers) or one number for every row."""
        packed = np.empty(count, self.dtype)
        packed.view(np.uint8).reshape(count, self.size)[:] = np.frombuffer(self.template, np.uint8)
        for name, kind, value in zip(self.names, self.integers, values, strict=True):
            if kind is not None:
                fits(value, kind)
            packed[name] = value
        return split(packed.tobytes(), self.size)


def fits(value: np.ndarray | float, kind: np.dtype[Any]) -> None:
    """ValueError unless every integer of ``value`` fits ``kind``."""
    numbers = np.asarray(value)
    if numbers.size:
        info = np.iinfo(kind)
        low, high = numbers.min(), numbers.max()
        if low < info.min or high > info.max:
            bad = low if low < info.min else high
            raise ValueError(f"{bad} does not fit a CDR {kind.name} field ({info.min} to {info.max})")


def split(data: bytes, size: int) -> list[bytes]:
    """``data`` in messages of ``size`` bytes."""
    return [data[at : at + size] for at in range(0, len(data), size)]


# -- planar poses: math's sine and cosine, one at a time or many ---------------------------
def planar(x: float, y: float, alpha: float) -> tuple[float, ...]:
    """A planar pose as ``geometry_msgs/Pose`` (or ``Transform``): position (x, y, 0), rotation about z."""
    return (x, y, 0.0, 0.0, 0.0, math.sin(alpha / 2), math.cos(alpha / 2))


def sin_cos(angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The sine and cosine of each angle by :mod:`math`'s, as one message at a time computes them
    (:func:`planar`, common.math.frames, rosbags' messages here): numpy's own may differ in the
    last bit."""
    values = np.asarray(angles, dtype=float).tolist()
    count = len(values)
    return np.fromiter(map(math.sin, values), float, count), np.fromiter(map(math.cos, values), float, count)


def planar_rows(x: np.ndarray, y: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """:func:`planar` of each row: rows of 7 numbers."""
    rows = np.zeros((len(x), 7))
    rows[:, 0], rows[:, 1] = x, y
    rows[:, 5], rows[:, 6] = sin_cos(np.asarray(alpha, dtype=float) / 2)
    return rows


# -- the messages ---------------------------------------------------------------------
@functools.cache  # frames: the pose frames (odom, goal) and the base frame
def _odometry(frame: str, child: str) -> CdrMessage:
    return CdrLayout().header().string(frame).string(child).float64(7).zeros64(36).float64(6).zeros64(36).message()


@functools.cache
def _twist_stamped(frame: str) -> CdrMessage:
    return CdrLayout().header().string(frame).float64(6).message()


@functools.cache
def _transition(frame: str) -> CdrMessage:
    return CdrLayout().header().string(frame).uint64().uint32().float64(7).message()


@functools.cache
def _weights(frame: str) -> CdrMessage:
    layout = CdrLayout().header().string(frame).uint64().uint64().field("i", 4)
    return layout.float64(Q_FEATURES).float64(V_FEATURES).float64(2).uint32().message()


def _twists(actions: np.ndarray) -> np.ndarray:
    """``geometry_msgs/Twist`` of each (v, omega): linear (v, 0, 0), angular (0, 0, omega)."""
    twist = np.zeros((len(actions), 6))
    twist[:, 0], twist[:, 5] = actions[:, 0], actions[:, 1]
    return twist


def odometry_cdr(t_ns: int, frame: str, child: str, state: Vector, action: tuple[float, float]) -> bytes:
    """``nav_msgs/Odometry`` of a planar ``state`` holding ``action``, covariances zero."""
    pose = planar(float(state[0]), float(state[1]), float(state[2]))
    v, omega = action
    return _odometry(frame, child).one(*divmod(int(t_ns), NS), *pose, v, 0.0, 0.0, 0.0, 0.0, omega)


def odometry_rows(t_ns: np.ndarray, frame: str, child: str, poses: np.ndarray, actions: np.ndarray) -> list[bytes]:
    """:func:`odometry_cdr` of each row: ``poses`` rows of :func:`planar_rows`, ``actions`` (v, omega)."""
    sec, nanosec = np.divmod(t_ns, NS)
    return _odometry(frame, child).rows(len(t_ns), sec, nanosec, poses, _twists(actions))


def twist_stamped_cdr(t_ns: int, frame: str, v: float, omega: float) -> bytes:
    """``geometry_msgs/TwistStamped``: linear (v, 0, 0), angular (0, 0, omega)."""
    return _twist_stamped(frame).one(*divmod(int(t_ns), NS), v, 0.0, 0.0, 0.0, 0.0, omega)


def twist_stamped_rows(t_ns: np.ndarray, frame: str, actions: np.ndarray) -> list[bytes]:
    """:func:`twist_stamped_cdr` of each row of ``actions`` (v, omega)."""
    sec, nanosec = np.divmod(t_ns, NS)
    return _twist_stamped(frame).rows(len(t_ns), sec, nanosec, _twists(actions))


def transition_cdr(t_ns: int, frame: str, episode: int, step: int, values: Sequence[float]) -> bytes:
    """``srl_msgs/Transition`` (:data:`SRL_MSGS`): ``values`` = x, y, alpha, v, omega, stage_cost,
    accumulated_cost."""
    return _transition(frame).one(*divmod(int(t_ns), NS), episode, step, *values)


def transition_rows(
    t_ns: np.ndarray, frame: str, episodes: np.ndarray, steps: np.ndarray, values: np.ndarray
) -> list[bytes]:
    """:func:`transition_cdr` of each row (``values``: rows of 7)."""
    sec, nanosec = np.divmod(t_ns, NS)
    return _transition(frame).rows(len(t_ns), sec, nanosec, episodes, steps, values)


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
    return _weights(frame).one(
        *divmod(int(t_ns), NS),
        episode,
        version,
        trained_step,
        *(float(w) for w in q_weights),
        *(float(v) for v in v_weights),
        float(residuals[0]),
        float(residuals[1]),
        pairs,
    )


# -- /tf: transforms of many frames in one message ----------------------------------------
@functools.lru_cache(maxsize=4096)  # the frame pairs of a fleet's robots, bounded whatever ids come
def transform_template(parent: str, child: str) -> tuple[bytes, bytes]:
    """One ``geometry_msgs/TransformStamped`` of a TFMessage with every value 0, as the first of
    the message (4 bytes into the body, after the count) and as any other (at a multiple of 8:
    the one before ends with a float64); each starts with its stamp and ends with its 7 doubles."""
    first, other = (CdrLayout(offset=at).header().string(parent).string(child).float64(7) for at in (4, 0))
    return bytes(first.template), bytes(other.template)


TF_BY_NUMPY = 16  # a TFMessage of more transforms is packed with numpy (tf_message)


def tf_message(t_ns: Sequence[int], templates: Sequence[tuple[bytes, bytes]], poses: Sequence[Vector]) -> bytes:
    """``tf2_msgs/TFMessage`` of ``len(templates)`` transforms: each one's frames as
    :func:`transform_template` gives them, its stamp ``t_ns`` and its pose (:func:`planar`). A
    few one by one; more at once with numpy: the transforms differ in size (their frames'
    names), so their bytes are joined first and the stamps and poses written at their offsets."""
    count = len(templates)
    if count > TF_BY_NUMPY:
        return _tf_rows(np.asarray(t_ns, dtype=np.int64), templates, np.asarray(poses, dtype=float))
    parts = [CDR_LE, count.to_bytes(4, "little")]
    for index, (stamp, (first, other), pose) in enumerate(zip(t_ns, templates, poses, strict=True)):
        packer, frames = _transform_struct(other if index else first)
        parts.append(packer.pack(*divmod(int(stamp), NS), frames, *pose))
    return b"".join(parts)


@functools.lru_cache(maxsize=8192)  # two per frame pair of transform_template
def _transform_struct(template: bytes) -> tuple[struct.Struct, bytes]:
    """A transform of :func:`transform_template` as one struct: its stamp, its frames (the
    template's bytes between, an argument) and its pose."""
    frames = template[8:-56]
    return struct.Struct(f"<iI{len(frames)}s7d"), frames


def _tf_rows(t_ns: np.ndarray, templates: Sequence[tuple[bytes, bytes]], poses: np.ndarray) -> bytes:
    count = len(templates)
    parts = [CDR_LE, count.to_bytes(4, "little"), templates[0][0], *[other for _, other in templates[1:]]]
    sizes = np.fromiter(map(len, parts[2:]), np.int64, count)
    ends = 8 + np.cumsum(sizes)
    message = np.frombuffer(bytearray(b"".join(parts)), np.uint8)
    message[(ends - sizes)[:, None] + np.arange(8)] = _heads(t_ns)
    doubles = np.ascontiguousarray(poses, dtype="<f8").view(np.uint8).reshape(count, 56)
    message[(ends - 56)[:, None] + np.arange(56)] = doubles
    return message.tobytes()


def tf_cdr(transforms: Sequence[tuple[int, str, str, Pose2D]]) -> bytes:
    """``tf2_msgs/TFMessage`` of planar ``(stamp [ns], parent, child, pose)`` transforms (:func:`tf_message`)."""
    return tf_message(
        [t_ns for t_ns, _, _, _ in transforms],
        [transform_template(parent, child) for _, parent, child, _ in transforms],
        [planar(float(pose.x), float(pose.y), float(pose.theta)) for _, _, _, pose in transforms],
    )


# -- the path: many poses, the paths of many robots at once ------------------------------
def _align(offset: int, size: int) -> int:
    return -(-offset // size) * size


@functools.lru_cache(maxsize=1024)  # a path's frames (odom, goal) and its length (up to PATH_POSES)
def _path_template(frame: str, own: str, count: int) -> tuple[np.ndarray, int, int, int]:
    """``nav_msgs/Path`` of ``count`` poses with every value 0, and where its poses start, where
    the first pose's doubles start in it and the size of every pose after the first.

    After the header (stamp, ``frame``) and the sequence's length, each ``PoseStamped`` is its
    stamp, ``own`` (its frame) and 7 doubles aligned to 8; a pose ends 8-aligned, so every pose
    after the first starts 8-aligned: the first may be padded differently (by where the header
    left it), the others alike."""
    head, mine = frame.encode() + b"\0", own.encode() + b"\0"
    start = _align(12 + len(head), 4) + 4  # after the header and the sequence's length
    first_doubles = _align(start + 12 + len(mine), 8) - start
    other = _align(12 + len(mine), 8) + 56
    size = start + (first_doubles + 56 + other * (count - 1) if count else 0)
    template = np.zeros(4 + size, np.uint8)
    template[:4] = np.frombuffer(CDR_LE, np.uint8)
    payload = template[4:]
    payload[8:12] = np.frombuffer(len(head).to_bytes(4, "little"), np.uint8)
    payload[12 : 12 + len(head)] = np.frombuffer(head, np.uint8)
    payload[start - 4 : start] = np.frombuffer(count.to_bytes(4, "little"), np.uint8)
    poses = [payload[start : start + 12 + len(mine)].reshape(1, -1)]
    if count > 1:
        poses.append(payload[start + first_doubles + 56 :].reshape(count - 1, other))
    for pose in poses if count else []:
        pose[:, 8:12] = np.frombuffer(len(mine).to_bytes(4, "little"), np.uint8)
        pose[:, 12 : 12 + len(mine)] = np.frombuffer(mine, np.uint8)
    template.flags.writeable = False
    return template, start, first_doubles, other


def path_rows(t_ns: np.ndarray, frame: str, own: str, stamps: np.ndarray, poses: np.ndarray) -> list[bytes]:
    """``nav_msgs/Path`` per row: stamped ``t_ns[i]`` in ``frame``, its poses ``poses[i]`` (rows
    of :func:`planar_rows`) stamped ``stamps[i]`` [ns] in ``own``; every row the same count of
    poses."""
    rows, count = stamps.shape
    template, start, first_doubles, other = _path_template(frame, own, count)
    out = np.empty((rows, len(template)), np.uint8)
    out[:] = template
    payload = out[:, 4:]
    payload[:, :8] = _heads(t_ns)
    if count:
        heads = _heads(stamps.reshape(-1)).reshape(rows, count, 8)
        doubles = np.ascontiguousarray(poses, dtype="<f8").view(np.uint8).reshape(rows, count, 56)
        payload[:, start : start + 8] = heads[:, 0]
        payload[:, start + first_doubles : start + first_doubles + 56] = doubles[:, 0]
        if count > 1:
            rest = payload[:, start + first_doubles + 56 :].reshape(rows, count - 1, other)
            rest[:, :, :8] = heads[:, 1:]
            rest[:, :, other - 56 :] = doubles[:, 1:]
    return split(out.tobytes(), len(template))


def _heads(t_ns: np.ndarray) -> np.ndarray:
    """Each stamp as a ``builtin_interfaces/Time`` (int32 sec, uint32 nanosec): rows of 8 bytes."""
    sec, nanosec = np.divmod(np.asarray(t_ns, dtype=np.int64).reshape(-1), NS)
    fits(sec, _TIME["sec"])
    head = np.empty(len(sec), _TIME)
    head["sec"], head["nanosec"] = sec, nanosec
    return head.view(np.uint8).reshape(-1, 8)
