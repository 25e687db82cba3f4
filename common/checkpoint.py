"""Durable JSON files: written atomically (write, fsync, rename), read back with a clear error.

A reader never sees a half-written file: the new content goes to a temporary file in the same
directory, is flushed to disk, and replaces the old file with one ``os.replace`` (atomic on
POSIX). A process killed at any moment leaves either the old or the new checkpoint.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterable
from pathlib import Path
from typing import Any


class CheckpointError(ValueError):
    """A checkpoint file exists but cannot be used (unreadable, not JSON, wrong schema)."""


def atomic_write_json(path: Path, payload: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    data = json.dumps(payload, separators=(",", ":"), allow_nan=False).encode()
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
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


def to_runs(steps: Iterable[int]) -> list[list[int]]:
    """Sorted integers as inclusive runs ``[[first, last], ...]`` (compact for contiguous steps)."""
    runs: list[list[int]] = []
    for step in sorted(steps):
        if runs and step == runs[-1][1] + 1:
            runs[-1][1] = step
        elif not runs or step > runs[-1][1]:
            runs.append([step, step])
    return runs


def from_runs(runs: Iterable[Iterable[int]]) -> set[int]:
    steps: set[int] = set()
    for first, last in runs:
        if last < first:
            raise CheckpointError(f"bad run [{first}, {last}]")
        steps.update(range(first, last + 1))
    return steps

