"""Columnar batches (common/contracts/columns.py): the binary form of a round of many robots'
messages. A decoder written from the reference page alone reads them; decoding accepts exactly
what the per-message schema accepts, and builds the messages that schema would."""

from __future__ import annotations

import json
import math
import random
import re
import struct
from pathlib import Path
from typing import Any

import pytest

from common.contracts.columns import (
    INT_ABSENT,
    SCHEMA_CODES,
    Columns,
    batch_payloads,
    batch_rows,
    batch_system,
    columns_of,
    decode_batch,
    decode_columns,
    encode_columns,
    layout,
)
from common.contracts.messages import (
    Action,
    CriticWeights,
    Message,
    MessageError,
    PlantState,
    RobotId,
    Transition,
    decode,
)

PAGE = Path(__file__).resolve().parents[1] / "docs" / "reference" / "messages.md"


def samples(count: int, seed: int = 3) -> dict[type[Message], list[Message]]:
    """Valid messages of every batch schema, optional fields present in some and absent in others."""
    rng = random.Random(seed)

    def vec(n: int, scale: float = 5.0) -> tuple[float, ...]:
        return tuple(rng.uniform(-scale, scale) for _ in range(n))

    # srl's own schemas (another system's, made by common.contracts.wire in this process, share their codes)
    out: dict[type[Message], list[Message]] = {schema: [] for schema in SCHEMA_CODES if batch_system(schema) is None}
    for i in range(count):
        robot = rng.choice(["r", "robot", "tb3_-"]) + str(i)
        out[PlantState].append(
            PlantState(
                robot=robot,
                episode=i,
                seq=rng.randrange(2**40),
                stamp_ns=rng.randrange(2**62),
                state=vec(3),
                source=rng.choice(["sim", "robot"]),
                true_state=vec(3) if i % 2 else None,
                saturated_commands=i if i % 3 else None,
                map_to_odom=vec(3) if i % 4 == 1 else None,
            )
        )
        out[Action].append(Action(robot=robot, episode=i, step=i, stamp_ns=i, action=vec(2), state_seq=i - 1))
        out[Transition].append(
            Transition(robot=robot, episode=0, step=i, state=vec(3), action=vec(2), cost=rng.uniform(0, 9))
        )
        out[CriticWeights].append(
            CriticWeights(
                robot=robot,
                episode=0,
                version=i + 1,
                trained_step=i - 1,
                q_weights=vec(15, 1e6),
                v_weights=vec(6, 1e6),
                q_residual=rng.uniform(0, 1),
                v_residual=0.0,
                pairs=i,
            )
        )
    return out


# -- the decoder a reader of the reference page writes --------------------------------------------
def page_layout() -> dict[str, tuple[int, list[tuple[str, str, int]]]]:
    """Per schema, from docs/reference/messages.md's "Columnar batches": its code and its columns
    (name, type, width) in order."""
    text = PAGE.read_text()
    section = text[text.index("## Columnar batches") :]
    assert "the magic `SRLC`" in section and "joined by a newline" in section
    found = {}
    for block in section.split("### ")[1:]:
        name = block.split(" batch", 1)[0]
        code = int(re.search(r"Schema code \*\*(\d+)\*\*", block).group(1))  # type: ignore[union-attr]
        columns = [
            (match[0], match[1], int(match[2]))
            for match in re.findall(r"^\| `(\w+)` \| (int64|float64) \| (\d+) \|", block, flags=re.MULTILINE)
        ]
        found[name] = (code, columns)
    return found


def read_from_page(payload: bytes, name: str) -> list[dict[str, Any]]:
    """A batch as the page describes it: the header, the manifest, the padding, the int64 block,
    the float64 block (each row the columns of its type, in the table's order)."""
    code, columns = page_layout()[name]
    header = struct.unpack_from("<4sBBBBIIQQ", payload, 0)
    magic, fmt, schema_version, got_code, reserved, rows, size, seq, stamp = header
    assert (magic, fmt, got_code, reserved) == (b"SRLC", 1, code, 0) and seq >= 1 and stamp > 0
    robots = payload[32 : 32 + size].decode("ascii").split("\n")
    offset = 32 + size + (-size % 8)
    rows_out: list[dict[str, Any]] = [{"schema_version": schema_version, "robot": r} for r in robots]
    for kind, letter in (("int64", "q"), ("float64", "d")):
        of_kind = [(column, width) for column, k, width in columns if k == kind]
        row_width = sum(width for _, width in of_kind)
        numbers = struct.unpack_from(f"<{rows * row_width}{letter}", payload, offset)
        offset += 8 * rows * row_width
        for i in range(rows):
            at = i * row_width
            for column, width in of_kind:
                rows_out[i][column] = numbers[at : at + width]
                at += width
    assert offset == len(payload)
    return rows_out


def test_a_decoder_written_from_the_reference_page_reads_every_batch() -> None:
    """The page's tables say the column order, types and widths; its text says the header, the
    manifest, the padding, the absent markers and the choices' indices. What this decoder reads
    is every message sent, field by field."""
    for schema, messages in samples(40).items():
        (payload,) = batch_payloads(messages)
        read = read_from_page(payload, schema.__name__)
        for got, message in zip(read, messages, strict=True):
            expected = message.model_dump()
            for column in layout(schema):
                if column.kind == "choice":
                    got[column.name] = column.choices[got[column.name][0]]  # "the name's index in its list"
                elif column.kind == "int":
                    (value,) = got[column.name]
                    got[column.name] = None if value == -(2**63) else value
                elif all(math.isnan(v) for v in got[column.name]):
                    got[column.name] = None
                elif column.scalar:
                    (got[column.name],) = got[column.name]
            assert got == expected


# -- the same acceptance as the per-message schema -------------------------------------------------
BAD_FLOATS = [math.nan, math.inf, -math.inf, 1e300, -1e300, 1e4 + 1e-9, -1e4, 1e6 + 1, -1e-300, 1e12 + 1, 1e12]
BAD_INTS = [-1, -2, 0, 2**62]


def perturbed(message: Message, rng: random.Random) -> tuple[dict[str, Any], Columns[Any]]:
    """One field of ``message`` set to a value near or past the schema's bounds: as a JSON object
    and as the columns of a batch of one."""
    schema = type(message)
    values = message.model_dump()
    columns = columns_of(schema, [message])
    column = rng.choice(layout(schema))
    array = columns.field(column.name)  # a view: writing it writes the batch
    if column.kind == "choice":
        code = rng.choice([-1, 0, 1, 2])
        array[0] = code
        values[column.name] = column.choices[code] if 0 <= code < len(column.choices) else "other"
    elif column.kind == "int":
        value = rng.choice(BAD_INTS + ([INT_ABSENT] if column.optional else []))
        array[0] = value
        values[column.name] = None if value == INT_ABSENT else value
    else:
        row = array.reshape(1, -1)[0]
        if column.optional and rng.random() < 0.3:
            row[:] = math.nan  # absent
            values[column.name] = None
        else:
            if values[column.name] is None:
                row[:] = 0.5
            index = rng.randrange(column.width)
            row[index] = rng.choice(BAD_FLOATS)
            vector = [float(v) for v in row]
            values[column.name] = vector[0] if column.scalar else vector
    return values, columns


def test_columnar_decoding_accepts_exactly_what_the_message_schema_accepts() -> None:
    """2,000 messages with one field set near or past its bounds (NaN, infinities, huge, just
    past a bound, exactly at one, absent): a batch of it is refused exactly when the message's
    JSON is, and what it accepts is the message the JSON gives. Both outcomes occur."""
    rng = random.Random(11)
    outcomes = {True: 0, False: 0}
    pool = [m for messages in samples(50).values() for m in messages]
    for _ in range(2000):
        values, columns = perturbed(rng.choice(pool), rng)
        schema = columns.schema
        try:
            expected: Message | None = decode(schema, json.dumps(values).encode())
        except MessageError:
            expected = None
        (payload,) = encode_columns(columns)
        try:
            (got,) = decode_batch(schema, payload)
        except MessageError as error:
            assert expected is None, f"refused what the schema accepts: {values}: {error}"
            assert "\n" not in str(error) and "item 0." in str(error)
            outcomes[False] += 1
            continue
        assert expected is not None, f"accepted what the schema refuses: {values}"
        assert got == expected and got.encode() == expected.encode()
        outcomes[True] += 1
    assert min(outcomes.values()) > 300, outcomes


def test_decoded_messages_are_their_validated_selves() -> None:
    """A message built from a batch equals the message validated from its own JSON, encodes to
    the same bytes, has the same fields set, and is as frozen."""
    for schema, messages in samples(12).items():
        decoded = [item for payload in batch_payloads(messages) for item in decode_batch(schema, payload)]
        for got, message in zip(decoded, messages, strict=True):
            again = decode(schema, message.encode())
            assert got == again and got.encode() == again.encode()
            assert got.model_fields_set == again.model_fields_set
            with pytest.raises(Exception, match="frozen"):
                got.robot = "x"  # type: ignore[misc]


def test_a_batch_holds_one_schema_and_64_bit_integers_only() -> None:
    action = samples(1)[Action][0]
    with pytest.raises(MessageError, match="holds Action messages only"):
        list(batch_payloads([action, samples(1)[Transition][0]]))
    with pytest.raises(MessageError, match="beyond 64 bits"):
        list(batch_payloads([action.model_copy(update={"step": 2**63})]))
    (payload,) = batch_payloads([action])
    assert batch_rows(payload) == 1 and batch_rows(next(batch_payloads([action] * 7))) == 7  # a counter's view
    assert batch_rows(action.encode()) is None and batch_rows(b"SRLC") is None
    with pytest.raises(MessageError, match="a batch of another schema"):
        decode_columns(Transition, payload)


def test_a_field_with_no_column_form_is_named_when_a_schema_is_laid_out(monkeypatch: pytest.MonkeyPatch) -> None:
    """A message of a batch schema that gains a field the columns cannot carry fails at once,
    naming it (not on the wire). The control: every schema a batch carries is laid out."""
    import common.contracts.columns as columns_module

    class Tagged(Message):
        robot: RobotId
        note: str

    class Loose(Message):
        robot: str  # no pattern: the manifest's check would not be the schema's

    for schema in (Tagged, Loose):
        monkeypatch.setitem(columns_module.SCHEMA_CODES, schema, 9)
    with pytest.raises(TypeError, match="note"):
        layout(Tagged)
    with pytest.raises(TypeError, match="robot"):
        layout(Loose)
    assert all(layout(schema) for schema in SCHEMA_CODES if schema not in (Tagged, Loose))
