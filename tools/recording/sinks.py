"""Where a recording's CDR samples go: an MCAP file in the rosbag2 layout (:class:`McapSink`),
consecutive files of it (:class:`SplitSink`), memory (:class:`MemorySink`); the live view's
server (tools/recording/view.py) is another :class:`Sink`. What the samples are, and which topic
each goes to, is the recorder's (:mod:`tools.recording.record`)."""

from __future__ import annotations

import contextlib
import glob
import json
import math
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from pathlib import Path
from typing import IO, Any, Protocol

import foxglove
from foxglove.mcap import MCAPCompression, MCAPWriteOptions

DISTRO = "humble"  # the message definitions of the recording (the same in Jazzy for these types)
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


class Sink(Protocol):
    """Where CDR samples go: an MCAP file (:class:`McapSink`) or a live server (tools/recording/view.py).

    ``write_rows`` writes many samples in order, as as many ``write`` calls would (a batch's rows:
    the recorder's writes are most of its CPU, and a call per sample most of theirs); a row that
    cannot be written raises :class:`RowWriteError` once the rows before it are written
    (:class:`RowsByOne` is the plain loop)."""

    def write(self, topic: str, ros_type: str, definition: str, data: bytes, t_ns: int) -> None: ...
    def write_rows(
        self,
        topics: Sequence[str],
        ros_types: Sequence[str],
        datas: Sequence[bytes],
        stamps: Sequence[int],
        definitions: Mapping[str, str],
    ) -> None: ...
    def close(self) -> None: ...


class RowWriteError(Exception):
    """Row ``row`` of a :meth:`Sink.write_rows` could not be written (``error``: why); the rows
    before it were, the rows after it were not tried."""

    def __init__(self, row: int, error: Exception) -> None:
        super().__init__(f"row {row}: {error}")
        self.row, self.error = row, error


class RowsByOne:
    """:meth:`Sink.write_rows` as a ``write`` per row (a sink with no faster way)."""

    def write(self, topic: str, ros_type: str, definition: str, data: bytes, t_ns: int) -> None:
        raise NotImplementedError

    def write_rows(
        self,
        topics: Sequence[str],
        ros_types: Sequence[str],
        datas: Sequence[bytes],
        stamps: Sequence[int],
        definitions: Mapping[str, str],
    ) -> None:
        rows_by_one(self.write, topics, ros_types, datas, stamps, definitions)


def rows_by_one(
    write: Callable[[str, str, str, bytes, int], None],
    topics: Sequence[str],
    ros_types: Sequence[str],
    datas: Sequence[bytes],
    stamps: Sequence[int],
    definitions: Mapping[str, str],
) -> None:
    """:meth:`Sink.write_rows` by a sink's ``write``, a row at a time."""
    for row, (topic, ros_type, data, t_ns) in enumerate(zip(topics, ros_types, datas, stamps, strict=True)):
        try:
            write(topic, ros_type, definitions[ros_type], data, t_ns)
        except Exception as error:
            raise RowWriteError(row, error) from error


class CdrChannels:
    """foxglove-sdk channels of one context, one per topic (a ``ros2msg`` schema, ``cdr`` messages),
    made at the topic's first sample: what an MCAP file and a live server log into. :meth:`log_of`
    is the channel's own ``log`` (its Rust side's): ``foxglove.Channel.log`` only adds the handling
    of JSON and ``str`` messages, which a CDR sample (bytes) never needs, at half the cost of a log."""

    def __init__(self, context: foxglove.Context, metadata: dict[str, str] | None = None) -> None:
        self.context, self.metadata = context, metadata
        self.schemas: dict[str, foxglove.Schema] = {}
        self.channels: dict[str, foxglove.Channel] = {}
        self.logs: dict[str, Callable[[bytes, int], None]] = {}

    def log_of(self, topic: str, ros_type: str, definition: str) -> Callable[[bytes, int], None]:
        """``log(data, t_ns)`` of ``topic``'s channel (made with ``ros_type``'s schema if new)."""
        logger = self.logs.get(topic)
        if logger is None:
            schema = self.schemas.get(ros_type)
            if schema is None:
                schema = self.schemas[ros_type] = foxglove.Schema(
                    name=ros_type, encoding="ros2msg", data=definition.encode()
                )
            channel = self.channels[topic] = foxglove.Channel(
                topic, schema=schema, message_encoding="cdr", context=self.context, metadata=self.metadata
            )
            logger = self.logs[topic] = channel.base.log
        return logger

    def clear(self) -> None:
        self.channels.clear()
        self.logs.clear()


class MemorySink(RowsByOne):
    """A :class:`Sink` that keeps every sample in memory, ``(t_ns, ros_type, data)`` per topic: for
    a short episode only (tests, the live view's figure in tools/docs/live_view.py)."""

    def __init__(self) -> None:
        self.samples: dict[str, list[tuple[int, str, bytes]]] = {}

    def write(self, topic: str, ros_type: str, definition: str, data: bytes, t_ns: int) -> None:
        self.samples.setdefault(topic, []).append((t_ns, ros_type, data))

    def close(self) -> None:
        pass


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
        self.channels = CdrChannels(self.context, {"offered_qos_profiles": QOS_YAML})
        self.counts: dict[str, int] = {}
        self.types: dict[str, str] = {}
        self.first_ns: int | None = None
        self.last_ns = 0
        self.extra_metadata = extra_metadata or {}
        self.closed = False
        self.failure: str | None = None
        self.chunk_started = time.monotonic()

    def write(self, topic: str, ros_type: str, definition: str, data: bytes, t_ns: int) -> None:
        self._check()
        self._log(topic, ros_type, definition)(data, t_ns)
        self.counts[topic] += 1
        self._span(t_ns, t_ns)
        self._age()

    def write_rows(
        self,
        topics: Sequence[str],
        ros_types: Sequence[str],
        datas: Sequence[bytes],
        stamps: Sequence[int],
        definitions: Mapping[str, str],
    ) -> None:
        """:meth:`write` of each row, in order, with one check of the writer before them and one
        test of the chunk's age after them (:class:`Sink`); a chunk that then fails to reach the
        disk fails the last row, as the write that completed it would."""
        if not topics:
            return
        try:
            self._check()
        except RecordingError as error:
            raise RowWriteError(0, error) from error
        logs, counts = self.channels.logs, self.counts
        for row, (topic, data, t_ns) in enumerate(zip(topics, datas, stamps, strict=True)):
            try:
                logger = logs.get(topic) or self._log(topic, ros_types[row], definitions[ros_types[row]])
                logger(data, t_ns)
            except Exception as error:
                if row:
                    self._span(min(stamps[:row]), max(stamps[:row]))
                raise RowWriteError(row, error) from error
            counts[topic] += 1
        self._span(min(stamps), max(stamps))
        try:
            self._age()
        except RecordingError as error:
            raise RowWriteError(len(topics) - 1, error) from error

    def _check(self) -> None:
        """Raise :class:`RecordingError` once a write has failed (a chunk the last write completed)."""
        if self.failure is None and self.disk.error is not None:
            self.failure = f"cannot write {self.path}: {self.disk.error}"
        if self.failure is not None:
            raise RecordingError(self.failure)

    def _log(self, topic: str, ros_type: str, definition: str) -> Callable[[bytes, int], None]:
        if topic not in self.counts:
            self.counts[topic], self.types[topic] = 0, ros_type
        return self.channels.log_of(topic, ros_type, definition)

    def _span(self, first: int, last: int) -> None:
        """Samples stamped from ``first`` to ``last`` were written."""
        self.first_ns = first if self.first_ns is None else min(self.first_ns, first)
        self.last_ns = max(self.last_ns, last)

    def _age(self) -> None:
        """A chunk older than :data:`CHUNK_SECONDS` to the disk, full or not."""
        now = time.monotonic()
        if now - self.chunk_started >= self.CHUNK_SECONDS:
            self.chunk_started = now
            self._written(self.writer.flush)

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
    ``latched`` topics: the recorder's target pose) are written again at the start of every file, with the
    new file's first stamp; ``/tf`` carries the goal frame every second anyway. ``split_seconds``
    0: one file, as :class:`McapSink` alone."""

    def __init__(
        self,
        path: Path,
        extra_metadata: dict[str, str] | None = None,
        split_seconds: float = 0.0,
        latched: Collection[str] = (),
    ) -> None:
        if not (math.isfinite(split_seconds) and split_seconds >= 0):
            raise RecordingError(f"a recording's part must span a positive time (0: one file), got {split_seconds}")
        self.split_ns = round(split_seconds * 1e9)
        self.latched_topics = frozenset(latched)
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
        if topic in self.latched_topics:
            self.latched[topic] = (ros_type, definition, data)
        self.counts[topic] = self.counts.get(topic, 0) + 1
        self.current.write(topic, ros_type, definition, data, t_ns)

    def write_rows(
        self,
        topics: Sequence[str],
        ros_types: Sequence[str],
        datas: Sequence[bytes],
        stamps: Sequence[int],
        definitions: Mapping[str, str],
    ) -> None:
        """:meth:`write` of each row, in order (:class:`Sink`): into the current file at once
        unless a row opens the next file or is latched (then row by row)."""
        if not topics:
            return
        first = self.file_first_ns
        if (
            first is None
            or (self.split_ns and max(stamps) - first >= self.split_ns)
            or not self.latched_topics.isdisjoint(topics)
        ):
            rows_by_one(self.write, topics, ros_types, datas, stamps, definitions)
            return
        try:
            self.current.write_rows(topics, ros_types, datas, stamps, definitions)
        except RowWriteError as failure:
            self._count(topics[: failure.row + 1])  # a row tried is counted, as by write
            raise
        self._count(topics)

    def _count(self, topics: Sequence[str]) -> None:
        counts = self.counts
        for topic in topics:
            counts[topic] = counts.get(topic, 0) + 1

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
