"""Durable JSON files: written atomically (write, fsync, rename), read back with a clear error;
and private files (:func:`write_private`: secrets, keys).

A reader never sees a half-written file: the new content goes to a temporary file in the same
directory, is flushed to disk, and replaces the old file with one ``os.replace`` (atomic on
POSIX). A process killed at any moment leaves either the old or the new checkpoint -- and, if it
was killed mid-write, its temporary file (``.<name>.<pid>.<random>.tmp``), which
:func:`remove_stale_temporaries` deletes at the next start.
"""

from __future__ import annotations

import bisect
import contextlib
import json
import logging
import operator
import os
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)


class CheckpointError(ValueError):
    """A checkpoint file exists but cannot be used (unreadable, not JSON, wrong schema)."""


def atomic_write_json(path: Path, payload: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    data = json.dumps(payload, separators=(",", ":"), allow_nan=False).encode()
    # the writer's pid in the name: a later start can tell a dead writer's leftover from a live one's
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{os.getpid()}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def write_private(path: Path, data: bytes) -> None:
    """Create ``path`` readable by its owner only (0600), failing if it exists: the mode is set
    when the file is created, so its content is never readable by others, not even for a moment."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as file:
        file.write(data)


class CheckpointWriter:
    """Writes a checkpoint's newest payload to ``path`` (:func:`atomic_write_json`) in a thread
    of its own, so the caller's loop does not wait for the encoding, the write and the fsync
    (a fleet's critic writes every learner at once: at 100 robots ~0.3 MB, whose fsync alone
    may take tens of ms on a busy disk). A payload given while one is being written waits; a
    newer one replaces it (each holds everything: the newest is the checkpoint).

    A write that fails is raised again by the next :meth:`submit` or by :meth:`close` (the
    caller fails as if it had written itself); :meth:`close` writes what is still pending and
    ends the thread. ``seconds`` is called with each write's duration."""

    def __init__(self, path: Path, seconds: Callable[[float], None] | None = None) -> None:
        self.path = path
        self.seconds = seconds
        self._pending: dict[str, Any] | None = None
        self._error: BaseException | None = None
        self._closing = False
        self._changed = threading.Condition()
        self._thread = threading.Thread(target=self._run, name="checkpoint-writer", daemon=True)
        self._thread.start()

    def submit(self, payload: dict[str, Any]) -> None:
        """Write ``payload`` (a fresh object the caller no longer changes) as soon as the writer is free."""
        with self._changed:
            self._raise_error()
            self._pending = payload
            self._changed.notify_all()

    def close(self) -> None:
        """Write what is pending, end the thread; raise a failed write's error."""
        with self._changed:
            self._closing = True
            self._changed.notify_all()
        self._thread.join()
        with self._changed:
            self._raise_error()

    def _raise_error(self) -> None:
        if self._error is not None:
            error, self._error = self._error, None
            raise error

    def _run(self) -> None:
        while True:
            with self._changed:
                while self._pending is None and not self._closing:
                    self._changed.wait()
                payload, self._pending = self._pending, None
                if payload is None:  # closing, nothing left
                    return
            started = time.perf_counter()
            try:
                atomic_write_json(self.path, payload)
            except BaseException as error:  # handed to the caller's next submit or close
                log.error("checkpoint %s not written: %s", self.path, error)
                with self._changed:
                    self._error = error
                continue
            if self.seconds is not None:
                self.seconds(time.perf_counter() - started)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    return True


def remove_stale_temporaries(path: Path) -> list[Path]:
    """Delete the temporary files that writers of ``path`` killed mid-write left beside it.

    Only files named as :func:`atomic_write_json` names them (``.<name>.<pid>.<random>.tmp``, or
    the older ``.<name>.<random>.tmp``) are considered, and one whose writer is still running
    (another process; never this one, which is only starting) is kept. The removed paths."""
    prefix = f".{path.name}."
    removed: list[Path] = []
    try:
        candidates = list(path.parent.glob(f"{glob_escape(prefix)}*.tmp"))
    except OSError:
        return removed
    for candidate in candidates:
        middle = candidate.name[len(prefix) : -len(".tmp")]
        pid_text = middle.split(".", 1)[0] if "." in middle else ""
        if pid_text.isdigit() and int(pid_text) != os.getpid() and _pid_alive(int(pid_text)):
            continue  # a live writer's file, about to be renamed
        with contextlib.suppress(FileNotFoundError):
            candidate.unlink()
            removed.append(candidate)
            log.warning("removed %s, left by a write that was killed", candidate)
    return removed


def glob_escape(text: str) -> str:
    """``text`` with glob's special characters taken literally."""
    return "".join(f"[{c}]" if c in "*?[" else c for c in text)


def read_json(path: Path) -> dict[str, Any] | None:
    """The file's object, None if there is no file; :class:`CheckpointError` if unusable."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        return None
    except OSError as error:
        raise CheckpointError(f"cannot read {path}: {error}") from error
    try:
        payload = json.loads(text)
    except json.JSONDecodeError as error:
        raise CheckpointError(f"{path} is not valid JSON: {error}") from error
    if not isinstance(payload, dict):
        raise CheckpointError(f"{path} does not hold a JSON object")
    return payload


def set_aside(path: Path, reason: str) -> Path:
    """Rename an unusable checkpoint (kept for inspection, never silently deleted)."""
    target = path.with_name(f"{path.name}.unusable")
    os.replace(path, target)
    target.with_name(f"{target.name}.why").write_text(reason + "\n")
    return target


class StepRuns:
    """A set of integers (the steps a critic has seen) held as sorted, disjoint inclusive runs
    ``[first, last]``, the form a checkpoint stores (:meth:`runs`). Steps arrive almost in
    order, so there are a few runs however many steps: membership is a bisection, adding the next
    step extends the last run, and the checkpoint form costs one list per run -- not a sort of
    every step held (6,000 per robot after 10 min; a fleet's critic writes it every second)."""

    def __init__(self, runs: Iterable[Iterable[int]] = ()) -> None:
        """From :meth:`runs`'s form (runs in any order, overlapping or not); a run whose last step
        is before its first is a CheckpointError."""
        self._firsts: list[int] = []
        self._lasts: list[int] = []
        self._count = 0
        for first, last in sorted((int(a), int(b)) for a, b in runs):
            if last < first:
                raise CheckpointError(f"bad run [{first}, {last}]")
            if self._lasts and first <= self._lasts[-1] + 1:  # overlaps or touches the last run
                if last > self._lasts[-1]:
                    self._count += last - self._lasts[-1]
                    self._lasts[-1] = last
                continue
            self._firsts.append(first)
            self._lasts.append(last)
            self._count += last - first + 1

    def __contains__(self, step: object) -> bool:
        # Any integer (numpy's too), as a set of ints takes them; operator.index refuses the rest
        # (an isinstance check against the runtime protocol SupportsIndex costs microseconds).
        try:
            value = operator.index(step)  # type: ignore[arg-type]
        except TypeError:
            return False
        index = bisect.bisect_right(self._firsts, value) - 1
        return index >= 0 and value <= self._lasts[index]

    def __len__(self) -> int:
        return self._count

    @property
    def last(self) -> int | None:
        """The highest step held (None: none)."""
        return self._lasts[-1] if self._lasts else None

    def __iter__(self) -> Iterator[int]:
        for first, last in zip(self._firsts, self._lasts, strict=True):
            yield from range(first, last + 1)

    def add(self, step: int) -> None:
        index = bisect.bisect_right(self._firsts, step) - 1  # the run starting at or before it
        if index >= 0 and step <= self._lasts[index]:
            return  # held already
        joins_before = index >= 0 and self._lasts[index] == step - 1
        joins_after = index + 1 < len(self._firsts) and self._firsts[index + 1] == step + 1
        if joins_before and joins_after:  # it closes the gap between two runs
            self._lasts[index] = self._lasts[index + 1]
            del self._firsts[index + 1], self._lasts[index + 1]
        elif joins_before:
            self._lasts[index] = step
        elif joins_after:
            self._firsts[index + 1] = step
        else:
            self._firsts.insert(index + 1, step)
            self._lasts.insert(index + 1, step)
        self._count += 1

    def keep_after(self, floor: int) -> None:
        """Forget every step at or before ``floor``."""
        cut = bisect.bisect_right(self._lasts, floor)  # the runs ending at or before it go whole
        self._count -= sum(last - first + 1 for first, last in zip(self._firsts[:cut], self._lasts[:cut], strict=True))
        del self._firsts[:cut], self._lasts[:cut]
        if self._firsts and self._firsts[0] <= floor:  # the run across it is cut
            self._count -= floor + 1 - self._firsts[0]
            self._firsts[0] = floor + 1

    def runs(self) -> list[list[int]]:
        """The set as sorted inclusive runs ``[[first, last], ...]`` (compact for contiguous steps)."""
        return [[first, last] for first, last in zip(self._firsts, self._lasts, strict=True)]
