"""Columnar batches: many robots' messages of one schema in one binary sample, validated as arrays.

A batch (common.contracts.keys.Batch) carries the messages a host sends in one round: a plant
host's states of a state tick, an actor host's actions or transitions of a tick group, a fleet
critic's weights of a fit round. Its payload is columns of fixed dtype, not one JSON text per
robot: a host writes a round from its arrays, and a receiver checks it with a few array
operations and builds messages only for the robots it serves.

A payload, every number little-endian:

| Bytes | Holds |
|---|---|
| 0-3 | the magic `SRLC` |
| 4 | the format version, 1 (this layout) |
| 5 | the messages' schema version (`schema_version`) |
| 6 | the schema's code (the table below each schema) |
| 7 | 0 (reserved) |
| 8-11 | `n`, the rows (unsigned 32-bit, at least 1) |
| 12-15 | `m`, the manifest's bytes (unsigned 32-bit) |
| 16-23 | the batch's sequence number: its publisher's batches count 1, 2, 3, ... (unsigned 64-bit) |
| 24-31 | the stamp: when it was sent, the sender's monotonic clock [ns] (unsigned 64-bit) |
| 32 to 32 + `m` | the manifest: the rows' robot ids, ASCII, joined by a newline |
| then | zero bytes up to a multiple of 8 |
| then | the int64 block: `n` rows, each the schema's int64 columns in its table's order |
| then | the float64 block: `n` rows, each the schema's float64 columns in its table's order |

A batch of a system other than the robot (common.contracts.wire) names it first: its manifest's
first line is `@` and the system's name, before the robot ids (`n + 1` lines).

A column of width `w` is `w` numbers of each row. An optional field is absent in a row where all
its numbers are NaN (a float64 column) or -2**63 (an int64 column); a choice (a field of a few
names) is the name's index in its list. The payload is exactly that long: no byte before,
between or after. Two blocks, not one array per column: a receiver checks each block with one
comparison against its bounds, whatever the fields.

Every guarantee of the per-message schema holds, and is derived from it (:func:`layout`): the
same fields, bounds and sizes, finite numbers, the robot id's pattern, the schema version. A
batch with one bad row is refused whole, with one line naming the row and the field. Integers
are 64-bit: a message whose integer does not fit cannot be put in a batch (MessageError when it
is encoded). tests/test_columns.py decodes batches with what the reference page says alone."""

from __future__ import annotations

import itertools
import math
import re
import struct
import time
import types
import typing
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Generic, Literal, get_args, get_origin

import annotated_types
import numpy as np

from common.contracts.messages import (
    MAX_PAYLOAD_BYTES,
    SCHEMA_VERSION,
    Action,
    CriticWeights,
    M,
    Message,
    MessageError,
    PlantState,
    Transition,
)

MAGIC = b"SRLC"
FORMAT_VERSION = 1  # this layout; the messages' own version is SCHEMA_VERSION
# magic, format version, schema version, schema code, reserved (0), rows, manifest bytes, the
# sender's batch sequence number, its stamp [ns]
HEADER = struct.Struct("<4sBBBBIIQQ")
INT_ABSENT = -(2**63)  # an optional integer that is absent (no field takes it: all are >= -1)
# one row per schema a batch may carry: its code in the header (a batch of another schema is refused)
SCHEMA_CODES: dict[type[Message], int] = {PlantState: 1, Action: 2, Transition: 3, CriticWeights: 4}
ROBOT_ID = re.compile(r"[A-Za-z0-9_\-]{1,64}")  # messages.RobotId's pattern (checked: layout)


@dataclass(frozen=True)
class Column:
    """One field of a schema as a column of ``width`` numbers a row (``kind``: "int" int64,
    "float" float64, "choice" int64 index into ``choices``), with the schema's bounds per number
    (inclusive, or ``strict``) and whether it may be absent."""

    name: str
    kind: Literal["int", "float", "choice"]
    width: int
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    strict_lower: bool
    optional: bool
    choices: tuple[str, ...] = ()
    scalar: bool = True  # a number (False: a tuple of ``width`` numbers, even of one)

    @property
    def dtype(self) -> str:
        return "<f8" if self.kind == "float" else "<i8"


def _bounds(metadata: Sequence[Any]) -> tuple[float, float, bool]:
    lower, upper, strict = -np.inf, np.inf, False
    for item in metadata:
        if isinstance(item, annotated_types.Ge):
            lower = float(item.ge)  # type: ignore[arg-type]  # a number in every schema
        elif isinstance(item, annotated_types.Gt):
            lower, strict = float(item.gt), True  # type: ignore[arg-type]
        elif isinstance(item, annotated_types.Le):
            upper = float(item.le)  # type: ignore[arg-type]
        elif isinstance(item, annotated_types.Lt):
            raise TypeError("a strict upper bound has no column form")
    return lower, upper, strict


def _element(annotation: Any) -> tuple[type, list[Any]]:
    """A tuple element's type and its constraints (``Annotated[float, Field(ge=...)]``)."""
    if get_origin(annotation) is typing.Annotated:
        base, *extra = get_args(annotation)
        return base, [m for info in extra for m in getattr(info, "metadata", [info])]
    return annotation, []


def _column(name: str, annotation: Any, metadata: list[Any]) -> Column:
    optional = False
    if get_origin(annotation) in (typing.Union, types.UnionType):
        members = [a for a in get_args(annotation) if a is not type(None)]
        if len(members) != 1:
            raise TypeError(f"{name}: only X | None has a column form")
        annotation, optional = members[0], True
    if get_origin(annotation) is Literal:
        return Column(name, "choice", 1, (0.0,), (0.0,), False, optional, tuple(get_args(annotation)))
    if annotation is int or annotation is float:
        lower, upper, strict = _bounds(metadata)
        return Column(name, "int" if annotation is int else "float", 1, (lower,), (upper,), strict, optional)
    if get_origin(annotation) is tuple:
        elements = get_args(annotation)
        if len(elements) == 2 and elements[1] is Ellipsis:  # tuple[X, ...] of a fixed length
            lengths = {getattr(m, "min_length", None) for m in metadata} | {
                getattr(m, "max_length", None) for m in metadata
            }
            lengths.discard(None)
            if len(lengths) != 1:
                raise TypeError(f"{name}: a variable-length tuple has no column form")
            elements = (elements[0],) * int(lengths.pop())  # type: ignore[arg-type]
        parts = [_element(e) for e in elements]
        if any(base is not float for base, _ in parts):
            raise TypeError(f"{name}: only tuples of floats have a column form")
        bounds = [_bounds(m) for _, m in parts]
        if any(strict for _, _, strict in bounds):
            raise TypeError(f"{name}: a strict bound in a tuple has no column form")
        lowers = tuple(b[0] for b in bounds)
        uppers = tuple(b[1] for b in bounds)
        return Column(name, "float", len(parts), lowers, uppers, False, optional, scalar=False)
    raise TypeError(f"{name}: {annotation} has no column form")


def layout(schema: type[Message]) -> tuple[Column, ...]:
    """``schema``'s columns, in its fields' order (``schema_version`` is the header's, ``robot``
    the manifest's), derived from its fields and their constraints: a field added to a message
    is in its batches, or this refuses the schema with a TypeError naming the field."""
    if schema not in SCHEMA_CODES:
        raise TypeError(f"{schema.__name__} has no batch form")
    laid = _LAYOUTS.get(schema)
    if laid is None:
        laid = _LAYOUTS[schema] = _laid_out(schema)
    return laid


_LAYOUTS: dict[type[Message], tuple[Column, ...]] = {}


def _laid_out(schema: type[Message]) -> tuple[Column, ...]:
    columns = []
    for name, info in schema.model_fields.items():
        if name == "schema_version":
            continue
        if name == "robot":
            pattern = next((m.pattern for m in info.metadata if getattr(m, "pattern", None)), None)
            if pattern != "^" + ROBOT_ID.pattern + "$":
                raise TypeError(f"{schema.__name__}.robot: the manifest checks {ROBOT_ID.pattern}, not {pattern}")
            continue
        columns.append(_column(name, info.annotation, list(info.metadata)))
    return tuple(columns)


FLOAT_LIMIT = float(np.finfo(np.float64).max)  # an unbounded float's bound: any finite number
INT_LIMIT = 2**63 - 1


@dataclass(frozen=True)
class Spans:
    """Where a schema's columns sit in a batch's two blocks (a row of ``ints`` numbers, then one of
    ``floats``), and every number's bounds as arrays (one comparison checks a block)."""

    int_columns: tuple[tuple[Column, int], ...]  # (column, first number in a row of the int block)
    float_columns: tuple[tuple[Column, int], ...]
    ints: int
    floats: int
    int_lower: np.ndarray
    int_upper: np.ndarray
    float_lower: np.ndarray
    float_upper: np.ndarray

    def column(self, index: int, floats: bool) -> tuple[Column, int]:
        """The column of a block's ``index``-th number, and its place in the column."""
        for column, start in self.float_columns if floats else self.int_columns:
            if start <= index < start + column.width:
                return column, index - start
        raise IndexError(index)


_SPANS: dict[type[Message], Spans] = {}


def spans(schema: type[Message]) -> Spans:
    found = _SPANS.get(schema)
    if found is not None:
        return found
    int_columns, float_columns = [], []
    int_lower: list[float] = []
    int_upper: list[float] = []
    float_lower: list[float] = []
    float_upper: list[float] = []
    for column in layout(schema):
        if column.strict_lower:
            raise TypeError(f"{schema.__name__}.{column.name}: a strict bound has no column form")
        if column.kind == "float":
            float_columns.append((column, len(float_lower)))
            float_lower += [max(v, -FLOAT_LIMIT) for v in column.lower]
            float_upper += [min(v, FLOAT_LIMIT) for v in column.upper]
        else:
            int_columns.append((column, len(int_lower)))
            int_lower += [max(v, -INT_LIMIT) for v in column.lower]
            int_upper.append(len(column.choices) - 1 if column.kind == "choice" else INT_LIMIT)
    found = _SPANS[schema] = Spans(
        tuple(int_columns),
        tuple(float_columns),
        len(int_lower),
        len(float_lower),
        np.array(int_lower, dtype=np.int64),
        np.array(int_upper, dtype=np.int64),
        np.array(float_lower),
        np.array(float_upper),
    )
    return found


def _row_bytes(schema: type[Message]) -> int:
    return sum(8 * c.width for c in layout(schema))


def _pad(size: int) -> int:
    return -size % 8


class Columns(Generic[M]):
    """A batch of ``schema`` as arrays: ``robots`` (the manifest, one id a row), ``ints`` (rows x
    the schema's int64 numbers: its integers and choices, in its table's order) and ``floats``
    (rows x its float64 numbers); :meth:`field` is one column of them. Validated
    (:func:`decode_columns`, :func:`check_columns`) or to be."""

    def __init__(self, schema: type[M], robots: Sequence[str], ints: np.ndarray, floats: np.ndarray) -> None:
        self.schema = schema
        self.robots = list(robots)
        self.ints, self.floats = ints, floats
        self.seq, self.stamp_ns = 0, 0  # a decoded batch's header (0: not sent)
        self._rows: tuple[list[list[int]], list[list[float]]] | None = None  # as Python values (item)

    @classmethod
    def of(cls, schema: type[M], robots: Sequence[str], fields: dict[str, Any]) -> Columns[M]:
        """From one array (or scalar, for every row) per field: ``(rows,)`` for a number,
        ``(rows, width)`` for a tuple (NaN rows: absent), a choice's code, :data:`INT_ABSENT`."""
        laid = spans(schema)
        count = len(robots)
        ints = np.empty((count, laid.ints), dtype=np.int64)
        floats = np.empty((count, laid.floats))
        for block, columns in ((ints, laid.int_columns), (floats, laid.float_columns)):
            for column, start in columns:
                value = np.asarray(fields[column.name])
                block[:, start : start + column.width] = value.reshape(-1, column.width) if value.ndim else value
        return cls(schema, robots, ints, floats)

    def __len__(self) -> int:
        return len(self.robots)

    def field(self, name: str) -> np.ndarray:
        """One column: ``(rows,)`` for a number, ``(rows, width)`` for a tuple (a view)."""
        laid = spans(self.schema)
        for block, columns in ((self.ints, laid.int_columns), (self.floats, laid.float_columns)):
            for column, start in columns:
                if column.name == name:
                    view = block[:, start : start + column.width]
                    return view[:, 0] if column.scalar else view
        raise KeyError(name)

    def item(self, row: int) -> M:
        """Row ``row`` as a message (no second validation: the blocks were validated). The blocks
        are read as Python values once per batch, on the first call."""
        if self._rows is None:
            self._rows = (self.ints.tolist(), self.floats.tolist())
        return _builder(self.schema)(self.robots[row], self._rows[0][row], self._rows[1][row])  # type: ignore[no-any-return]

    def items(self) -> Iterator[M]:
        return (self.item(row) for row in range(len(self)))

    @classmethod
    def joined(cls, schema: type[M], parts: Sequence[Columns[M]]) -> Columns[M]:
        """``parts`` (batches of ``schema``) as one batch, their rows in order (a round a host
        put together from several runs of rows)."""
        if len(parts) == 1:
            return parts[0]
        laid = spans(schema)
        return cls(
            schema,
            [robot for part in parts for robot in part.robots],
            np.vstack([part.ints for part in parts]).reshape(-1, laid.ints),
            np.vstack([part.floats for part in parts]).reshape(-1, laid.floats),
        )

    def take(self, rows: Sequence[int]) -> Columns[M]:
        """The rows ``rows`` (in that order) as a batch of their own, with this one's header."""
        chosen = list(rows)
        taken = Columns(self.schema, [self.robots[row] for row in chosen], self.ints[chosen], self.floats[chosen])
        taken.seq, taken.stamp_ns = self.seq, self.stamp_ns
        return taken


_BUILDERS: dict[type[Message], Callable[[str, list[int], list[float]], Any]] = {}


def _builder(schema: type[Message]) -> Callable[[str, list[int], list[float]], Any]:
    """``build(robot, ints, floats)``: a message of ``schema`` from one row's Python values (its
    blocks' ``tolist()`` rows), built as pydantic's ``model_construct`` builds one (its own
    generic path costs ~8 us a message, a loop over per-field readers ~4 us; this function,
    written once per schema from its layout, ~2 us): the fields set are those present, as
    decoding the message's JSON sets them. tests/test_columns.py checks every schema's messages
    equal their validated selves, fields set included."""
    found = _BUILDERS.get(schema)
    if found is not None:
        return found
    laid = spans(schema)
    starts = {c.name: ("i", start) for c, start in laid.int_columns}
    starts.update({c.name: ("f", start) for c, start in laid.float_columns})
    fields = [f"'schema_version': {SCHEMA_VERSION}", "'robot': robot"]
    absent = []
    namespace: dict[str, Any] = {"ABSENT": INT_ABSENT, "new": object.__new__, "put": object.__setattr__}
    for index, column in enumerate(layout(schema)):
        block, start = starts[column.name]
        numbers = [f"{block}[{start + k}]" for k in range(column.width)]
        if column.kind == "choice":
            namespace[f"choices{index}"] = column.choices
            value = f"choices{index}[{numbers[0]}]"
        elif column.kind == "int":
            value = f"(None if {numbers[0]} == ABSENT else {numbers[0]})" if column.optional else numbers[0]
        elif column.scalar:
            value = numbers[0]
        else:
            value = f"({', '.join(numbers)},)"
            if column.optional:  # absent: every number NaN (checked), so the first is
                value = f"(None if {numbers[0]} != {numbers[0]} else {value})"
        fields.append(f"{column.name!r}: {value}")
        if column.optional:
            absent.append(f"    if values[{column.name!r}] is None:\n        fields.discard({column.name!r})")
    namespace["SCHEMA"], namespace["EVERY"] = schema, frozenset(schema.model_fields)
    source = "\n".join(
        [
            "def build(robot, i, f):",
            f"    values = {{{', '.join(fields)}}}",
            "    message = new(SCHEMA)",
            "    put(message, '__dict__', values)",
            "    fields = set(EVERY)",
            *absent,
            "    put(message, '__pydantic_fields_set__', fields)",
            "    put(message, '__pydantic_extra__', None)",
            "    put(message, '__pydantic_private__', None)",
            "    return message",
        ]
    )
    exec(source, namespace)  # our own source, from the schema's layout
    built: Callable[[str, list[int], list[float]], Any] = namespace["build"]
    _BUILDERS[schema] = built
    return built


def batch_payloads(messages: Sequence[Message]) -> Iterator[bytes]:
    """``messages`` (of one schema) as columnar batches within :data:`MAX_PAYLOAD_BYTES`."""
    if not messages:
        return iter(())
    schema = type(messages[0])
    if any(type(m) is not schema for m in messages):
        raise MessageError(f"a batch of {schema.__name__} holds {schema.__name__} messages only")
    return encode_columns(columns_of(schema, messages))


def decode_batch(schema: type[M], payload: bytes) -> list[M]:
    """A batch's messages, each validated as :func:`~common.contracts.messages.decode` validates
    one (:func:`decode_columns`). One bad row refuses the batch (MessageError naming it): a
    sender that writes one bad row is not trusted with the others."""
    return list(decode_columns(schema, payload).items())


def columns_of(schema: type[M], messages: Sequence[M]) -> Columns[M]:
    """``messages`` (each of ``schema``) as columns; an integer beyond 64 bits -> MessageError."""
    laid = spans(schema)
    ints: list[list[int]] = [[] for _ in messages]
    floats: list[list[float]] = [[] for _ in messages]
    for column, _ in laid.int_columns:
        name = column.name
        for row, message in zip(ints, messages, strict=True):
            value = getattr(message, name)
            row.append(
                column.choices.index(value) if column.kind == "choice" else INT_ABSENT if value is None else value
            )
    for column, _ in laid.float_columns:
        absent = [math.nan] * column.width
        for numbers, message in zip(floats, messages, strict=True):
            vector = getattr(message, column.name)
            if column.scalar:
                numbers.append(vector)
            else:
                numbers.extend(absent if vector is None else vector)
    try:
        int_block = np.array(ints, dtype=np.int64).reshape(len(messages), laid.ints)
    except OverflowError:
        raise MessageError(f"{schema.__name__}: an integer beyond 64 bits") from None
    float_block = np.array(floats, dtype=np.float64).reshape(len(messages), laid.floats)
    return Columns(schema, [m.robot for m in messages], int_block, float_block)  # type: ignore[attr-defined]  # every batch schema names its robot


def encode_columns(columns: Columns[Any], sequence: Iterator[int] | None = None) -> Iterator[bytes]:
    """``columns`` as payloads, each within :data:`MAX_PAYLOAD_BYTES` (as many as it takes), rows
    in order, each numbered by ``sequence`` (a publisher's count; None: 1, 2, ...) and stamped
    when encoded. The blocks are written as they are: :func:`check_columns` is what checks them."""
    numbers = itertools.count(1) if sequence is None else sequence
    schema = columns.schema
    code = SCHEMA_CODES[schema]
    row_bytes = _row_bytes(schema)
    system = batch_system(schema)
    named = [] if system is None else [SYSTEM_MARK + system]  # the manifest's first line
    start, count = 0, len(columns)
    while start < count:
        size, end = HEADER.size + 8 + sum(len(line) + 1 for line in named), start  # with the padding, at most
        while end < count and size + len(columns.robots[end]) + 1 + row_bytes <= MAX_PAYLOAD_BYTES:
            size += len(columns.robots[end]) + 1 + row_bytes
            end += 1
        if end == start:
            raise MessageError(f"{schema.__name__}: a row does not fit a batch")
        manifest = "\n".join([*named, *columns.robots[start:end]]).encode()
        yield b"".join(
            (
                HEADER.pack(
                    MAGIC,
                    FORMAT_VERSION,
                    SCHEMA_VERSION,
                    code,
                    0,
                    end - start,
                    len(manifest),
                    next(numbers),
                    time.monotonic_ns(),
                ),
                manifest,
                b"\0" * _pad(len(manifest)),
                np.ascontiguousarray(columns.ints[start:end], dtype="<i8").tobytes(),
                np.ascontiguousarray(columns.floats[start:end], dtype="<f8").tobytes(),
            )
        )
        start = end


SYSTEM_MARK = "@"  # a manifest's first line "@<system>": no robot id begins so


def batch_system(schema: type[Message]) -> str | None:
    """The system a schema's batches name first in their manifest: one made for a system other
    than the robot (common.contracts.wire; its ``system`` field a choice of that one name)."""
    field = schema.model_fields.get("system")
    if field is None:
        return None
    (name,) = get_args(field.annotation)
    return str(name)


def _refuse(what: str, row: int, name: str, why: str) -> MessageError:
    return MessageError(f"{what}: item {row}.{name}: {why}")


_IDS_KEPT = 4096  # robot ids known valid (bounded whatever ids senders invent)
_valid_ids: set[str] = set()


def _check_robots(what: str, robots: Sequence[str]) -> None:
    for row, robot in enumerate(robots):
        if robot in _valid_ids:
            continue
        if ROBOT_ID.fullmatch(robot) is None:
            raise _refuse(what, row, "robot", f"String should match pattern '^{ROBOT_ID.pattern}$'")
        if len(_valid_ids) >= _IDS_KEPT:
            _valid_ids.clear()
        _valid_ids.add(robot)


def _first_bad(what: str, laid: Spans, block: np.ndarray, good: np.ndarray, floats: bool) -> MessageError:
    """The refusal of a block's first bad number (row by row, in the block's order)."""
    row, index = (int(i) for i in np.argwhere(~good)[0])
    column, place = laid.column(index, floats)
    name = column.name if column.scalar else f"{column.name}.{place}"
    value = block[row, index]
    if floats and not math.isfinite(value):
        return _refuse(what, row, name, "Input should be a finite number")
    if column.kind == "choice":
        return _refuse(what, row, name, f"not one of {', '.join(column.choices)} ({value!r})")
    return _refuse(what, row, name, f"out of the schema's bounds ({value!r})")


def check_columns(columns: Columns[Any], what: str | None = None) -> None:
    """``columns`` against their schema (every row's robot id and every number), as
    :func:`decode_columns` checks a payload: a host checks the round it built from its arrays
    before it is sent, as building each message would. Any problem -> one MessageError line.
    A block is checked by two comparisons with its bounds (a NaN or an infinity fails them);
    only an optional field's absent rows are let through after."""
    what = what or f"{columns.schema.__name__} batch"
    laid = spans(columns.schema)
    count = len(columns)
    ints, floats = columns.ints, columns.floats
    if ints.shape != (count, laid.ints) or floats.shape != (count, laid.floats):
        raise MessageError(f"{what}: blocks {ints.shape} and {floats.shape} for {count} rows")
    _check_robots(what, columns.robots)
    good = (ints >= laid.int_lower) & (ints <= laid.int_upper)
    if not good.all():
        for column, start in laid.int_columns:
            if column.optional:
                good[:, start] |= ints[:, start] == INT_ABSENT
        if not good.all():
            raise _first_bad(what, laid, ints, good, floats=False)
    good = (floats >= laid.float_lower) & (floats <= laid.float_upper)
    if not good.all():
        for column, start in laid.float_columns:
            if column.optional:
                absent = np.isnan(floats[:, start : start + column.width]).all(axis=1)
                good[absent, start : start + column.width] = True
        if not good.all():
            raise _first_bad(what, laid, floats, good, floats=True)


def batch_rows(payload: bytes) -> int | None:
    """The rows a batch's header announces, unchecked (a counter's view of a sample); None: no
    columnar batch's header."""
    if len(payload) < HEADER.size:
        return None
    magic, version, _, _, _, rows, *_ = HEADER.unpack_from(payload)
    return int(rows) if magic == MAGIC and version == FORMAT_VERSION else None


def choice_code(schema: type[Message], field: str, name: str) -> int:
    """The number a batch carries for ``name`` in ``schema``'s choice ``field`` (its index)."""
    column = next(c for c in layout(schema) if c.name == field)
    return column.choices.index(name)


def decode_columns(schema: type[M], payload: bytes) -> Columns[M]:
    """A batch of ``schema`` from its payload, validated as arrays: the header (magic, format and
    schema versions, the schema's code), sizes that add up exactly, every robot id, every number
    within the schema's bounds. Any problem -> one MessageError line; nothing is half-read."""
    what = f"{schema.__name__} batch"
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise MessageError(f"{what}: payload of {len(payload)} bytes exceeds {MAX_PAYLOAD_BYTES}")
    if len(payload) < HEADER.size:
        raise MessageError(f"{what}: payload: {len(payload)} bytes, shorter than a header")
    magic, version, schema_version, code, reserved, rows, manifest_size, seq, stamp = HEADER.unpack_from(payload)
    if magic != MAGIC:
        raise MessageError(f"{what}: payload: not a columnar batch")
    if version != FORMAT_VERSION or reserved != 0:
        raise MessageError(f"{what}: payload: format version {version}, this reads {FORMAT_VERSION}")
    if schema_version != SCHEMA_VERSION:
        raise MessageError(f"{what}: schema_version: {schema_version}, this reads {SCHEMA_VERSION}")
    if code != SCHEMA_CODES[schema]:
        raise MessageError(f"{what}: payload: a batch of another schema (code {code})")
    laid = spans(schema)
    try:
        robots = payload[HEADER.size : HEADER.size + manifest_size].decode("ascii").split("\n")
    except UnicodeDecodeError:
        raise MessageError(f"{what}: manifest: robot ids are ASCII") from None
    system = batch_system(schema)  # named before the sizes: another system's batch is said to be one
    named = robots[0][len(SYSTEM_MARK) :] if robots[0].startswith(SYSTEM_MARK) else None
    if named != system:
        raise MessageError(f"{what}: manifest: a batch of system {named or 'unicycle'}, not {system or 'unicycle'}")
    if system is not None:
        robots = robots[1:]
    body = HEADER.size + manifest_size + _pad(manifest_size)
    expected = body + rows * _row_bytes(schema)
    if rows == 0 or len(payload) != expected:
        raise MessageError(f"{what}: payload: {len(payload)} bytes, {rows} rows need {expected}")
    if len(robots) != rows:
        raise MessageError(f"{what}: manifest: {len(robots)} robot ids for {rows} rows")
    ints = np.frombuffer(payload, dtype="<i8", count=rows * laid.ints, offset=body).reshape(rows, laid.ints)
    at = body + ints.nbytes
    floats = np.frombuffer(payload, dtype="<f8", count=rows * laid.floats, offset=at).reshape(rows, laid.floats)
    decoded = Columns(schema, robots, ints, floats)
    check_columns(decoded, what)
    decoded.seq, decoded.stamp_ns = seq, stamp
    return decoded
