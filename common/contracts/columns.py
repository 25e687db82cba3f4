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
| 16 to 16 + `m` | the manifest: the rows' robot ids, ASCII, joined by a newline |
| then | zero bytes up to a multiple of 8 |
| then | the schema's columns, in its table's order: each `n` rows of `width` numbers, row after row |

A column is int64 or float64. An optional field is absent in a row where all its numbers are
NaN (a float column) or -2**63 (an int64 column); a choice (a field of a few names) is the
name's index in its list. The payload is exactly that long: no byte before, between or after.

Every guarantee of the per-message schema holds, and is derived from it (:func:`layout`): the
same fields, bounds and sizes, finite numbers, the robot id's pattern, the schema version. A
batch with one bad row is refused whole, with one line naming the row and the field. Integers
are 64-bit: a message whose integer does not fit cannot be put in a batch (MessageError when it
is encoded). tests/test_columns.py decodes batches with what the reference page says alone."""

from __future__ import annotations

import re
import struct
import types
import typing
from collections.abc import Iterator, Sequence
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
# magic, format version, schema version, schema code, reserved (0), rows, manifest bytes
HEADER = struct.Struct("<4sBBBBII")
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


def _row_bytes(schema: type[Message]) -> int:
    return sum(8 * c.width for c in layout(schema))


def _pad(size: int) -> int:
    return -size % 8


class Columns(Generic[M]):
    """A batch of ``schema`` as arrays: ``robots`` (the manifest, one id a row) and one array per
    column (``(rows,)`` for a number, ``(rows, width)`` for a tuple; float64 or int64), already
    validated (:func:`decode_columns`) or to be encoded (:func:`encode_columns`)."""

    def __init__(self, schema: type[M], robots: Sequence[str], arrays: dict[str, np.ndarray]) -> None:
        self.schema = schema
        self.robots = list(robots)
        self.arrays = arrays

    def __len__(self) -> int:
        return len(self.robots)

    def item(self, row: int) -> M:
        """Row ``row`` as a message (no second validation: the arrays were validated)."""
        values: dict[str, Any] = {"schema_version": SCHEMA_VERSION, "robot": self.robots[row]}
        for column in layout(self.schema):
            value = self.arrays[column.name][row]
            if column.kind == "choice":
                values[column.name] = column.choices[int(value)]
            elif column.kind == "int":
                values[column.name] = None if column.optional and value == INT_ABSENT else int(value)
            elif column.scalar:
                values[column.name] = float(value)
            elif column.optional and np.isnan(value[0]):
                values[column.name] = None
            else:
                values[column.name] = tuple(value.tolist())
        return _built(self.schema, values)

    def items(self) -> Iterator[M]:
        return (self.item(row) for row in range(len(self)))


def _built(schema: type[M], values: dict[str, Any]) -> M:
    """A message of ``values`` that were validated as columns, built as pydantic's
    ``model_construct`` builds one (its own path costs ~8 us a message, this ~3 us): the fields
    set are those present, as decoding the message's JSON would set them. tests/test_columns.py
    checks every schema's messages equal their validated selves, field by field."""
    message = schema.__new__(schema)
    object.__setattr__(message, "__dict__", values)
    object.__setattr__(message, "__pydantic_fields_set__", {k for k, v in values.items() if v is not None})
    object.__setattr__(message, "__pydantic_extra__", None)
    object.__setattr__(message, "__pydantic_private__", None)
    return message


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
    arrays: dict[str, np.ndarray] = {}
    count = len(messages)
    for column in layout(schema):
        values = [getattr(m, column.name) for m in messages]
        if column.kind == "choice":
            arrays[column.name] = np.array([column.choices.index(v) for v in values], dtype=np.int64)
        elif column.kind == "int":
            try:
                arrays[column.name] = np.array([INT_ABSENT if v is None else v for v in values], dtype=np.int64)
            except OverflowError:
                raise MessageError(f"{schema.__name__}.{column.name}: an integer beyond 64 bits") from None
        else:
            shape = (count,) if column.scalar else (count, column.width)
            rows = [(np.nan,) * column.width if v is None else v for v in values]
            arrays[column.name] = np.array(rows, dtype=np.float64).reshape(shape)
    return Columns(schema, [m.robot for m in messages], arrays)  # type: ignore[attr-defined]  # every batch schema names its robot


def encode_columns(columns: Columns[Any]) -> Iterator[bytes]:
    """``columns`` as payloads, each within :data:`MAX_PAYLOAD_BYTES` (as many as it takes), rows
    in order. The arrays are written as they are: :func:`decode_columns` is what checks them."""
    schema = columns.schema
    code = SCHEMA_CODES[schema]
    row_bytes = _row_bytes(schema)
    start, count = 0, len(columns)
    while start < count:
        size, end = HEADER.size + 8, start  # the header and the manifest's padding, at most
        while end < count and size + len(columns.robots[end]) + 1 + row_bytes <= MAX_PAYLOAD_BYTES:
            size += len(columns.robots[end]) + 1 + row_bytes
            end += 1
        if end == start:
            raise MessageError(f"{schema.__name__}: a row does not fit a batch")
        manifest = "\n".join(columns.robots[start:end]).encode()
        parts = [HEADER.pack(MAGIC, FORMAT_VERSION, SCHEMA_VERSION, code, 0, end - start, len(manifest))]
        parts += [manifest, b"\0" * _pad(len(manifest))]
        for column in layout(schema):
            parts.append(np.ascontiguousarray(columns.arrays[column.name][start:end], dtype=column.dtype).tobytes())
        yield b"".join(parts)
        start = end


def _refuse(what: str, row: int, name: str, why: str) -> MessageError:
    return MessageError(f"{what}: item {row}.{name}: {why}")


def _check(what: str, column: Column, values: np.ndarray) -> None:
    """One column's rows against the schema: the first bad number refuses the batch."""
    grid = values.reshape(-1, column.width)
    present = np.ones(len(grid), dtype=bool)
    if column.kind == "choice":
        bad = (grid < 0) | (grid >= len(column.choices))
        why = f"not one of {', '.join(column.choices)}"
    elif column.kind == "int":
        if column.optional:
            present = grid[:, 0] != INT_ABSENT
        lower = np.asarray(column.lower)
        bad = present[:, None] & ((grid <= lower) if column.strict_lower else (grid < lower))
        why = f"below {column.lower[0]:g}"
    else:
        finite = np.isfinite(grid)
        if column.optional:
            absent = np.isnan(grid).all(axis=1)
            present = ~absent
            finite |= absent[:, None]
        lower, upper = np.asarray(column.lower), np.asarray(column.upper)
        with np.errstate(invalid="ignore"):
            low = (grid <= lower) if column.strict_lower else (grid < lower)
            out = present[:, None] & (low | (grid > upper))
        if not finite.all():
            row, index = np.argwhere(~finite)[0]
            name = column.name if column.scalar else f"{column.name}.{index}"
            raise _refuse(what, int(row), name, "Input should be a finite number")
        bad, why = out, "out of the schema's bounds"
    if bad.any():
        row, index = np.argwhere(bad)[0]
        name = column.name if column.scalar else f"{column.name}.{index}"
        raise _refuse(what, int(row), name, f"{why} ({grid[row, index]!r})")


def check_columns(columns: Columns[Any], what: str | None = None) -> None:
    """``columns`` against their schema (every row's robot id and every number), as
    :func:`decode_columns` checks a payload: a host checks the round it built from its arrays
    before it is sent, as building each message would. Any problem -> one MessageError line."""
    what = what or f"{columns.schema.__name__} batch"
    for row, robot in enumerate(columns.robots):
        if ROBOT_ID.fullmatch(robot) is None:
            raise _refuse(what, row, "robot", f"String should match pattern '^{ROBOT_ID.pattern}$'")
    for column in layout(columns.schema):
        values = np.asarray(columns.arrays[column.name])
        if (
            values.dtype != np.dtype(column.dtype)
            or values.shape[:1] != (len(columns),)
            or values.size != len(columns) * column.width
        ):
            raise MessageError(
                f"{what}: {column.name}: {values.dtype} {values.shape}, "
                f"not {len(columns)} rows of {column.width} {column.dtype}"
            )
        _check(what, column, values.reshape(-1))


def batch_rows(payload: bytes) -> int | None:
    """The rows a batch's header announces, unchecked (a counter's view of a sample); None: no
    columnar batch's header."""
    if len(payload) < HEADER.size:
        return None
    magic, version, _, _, _, rows, _ = HEADER.unpack_from(payload)
    return int(rows) if magic == MAGIC and version == FORMAT_VERSION else None


def choice_code(schema: type[Message], field: str, name: str) -> int:
    """The number a batch carries for ``name`` in ``schema``'s choice ``field`` (its index)."""
    column = next(c for c in layout(schema) if c.name == field)
    return column.choices.index(name)


def decode_columns(schema: type[M], payload: bytes) -> Columns[M]:
    """A batch of ``schema`` from its payload, validated as arrays: the header (magic, format and
    schema versions, the schema's code), sizes that add up exactly, every robot id, every column
    within the schema's bounds. Any problem -> one MessageError line; nothing is half-read."""
    what = f"{schema.__name__} batch"
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise MessageError(f"{what}: payload of {len(payload)} bytes exceeds {MAX_PAYLOAD_BYTES}")
    if len(payload) < HEADER.size:
        raise MessageError(f"{what}: payload: {len(payload)} bytes, shorter than a header")
    magic, version, schema_version, code, reserved, rows, manifest_size = HEADER.unpack_from(payload)
    if magic != MAGIC:
        raise MessageError(f"{what}: payload: not a columnar batch")
    if version != FORMAT_VERSION or reserved != 0:
        raise MessageError(f"{what}: payload: format version {version}, this reads {FORMAT_VERSION}")
    if schema_version != SCHEMA_VERSION:
        raise MessageError(f"{what}: schema_version: {schema_version}, this reads {SCHEMA_VERSION}")
    if code != SCHEMA_CODES[schema]:
        raise MessageError(f"{what}: payload: a batch of another schema (code {code})")
    columns = layout(schema)
    body = HEADER.size + manifest_size + _pad(manifest_size)
    expected = body + rows * _row_bytes(schema)
    if rows == 0 or len(payload) != expected:
        raise MessageError(f"{what}: payload: {len(payload)} bytes, {rows} rows need {expected}")
    try:
        robots = payload[HEADER.size : HEADER.size + manifest_size].decode("ascii").split("\n")
    except UnicodeDecodeError:
        raise MessageError(f"{what}: manifest: robot ids are ASCII") from None
    if len(robots) != rows:
        raise MessageError(f"{what}: manifest: {len(robots)} robot ids for {rows} rows")
    arrays: dict[str, np.ndarray] = {}
    offset = body
    for column in columns:
        values = np.frombuffer(payload, dtype=column.dtype, count=rows * column.width, offset=offset)
        offset += values.nbytes
        arrays[column.name] = values if column.scalar else values.reshape(rows, column.width)
    decoded = Columns(schema, robots, arrays)
    check_columns(decoded, what)
    return decoded
