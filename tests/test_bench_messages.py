"""``srl bench messages``: the codec rows measure srl's own messages, and over a router every robot
message sent is validated on arrival, one per robot and batched alike."""

from __future__ import annotations

import json

import pytest

from common.contracts.messages import decode
from tools.bench.messages import KINDS, codec_row, format_table, sample_message
from tools.cli import main as srl


@pytest.mark.parametrize("kind", KINDS)
def test_the_sample_messages_are_valid_and_round_trip(kind: str) -> None:
    message = sample_message(kind, 3, 17)
    assert decode(type(message), message.encode()) == message
    assert message.robot == "robot4"


def test_a_codec_row_times_the_message_of_its_kind() -> None:
    row = codec_row("weights", repeats=50)
    assert row["bytes"] == len(sample_message("weights", 0, 17).encode())
    assert row["decode_us"] > 0 and row["encode_us"] > 0 and row["parse_us"] > 0
    assert row["validate_us"] == pytest.approx(max(0.0, row["decode_us"] - row["parse_us"]))


def test_the_table_fails_a_run_that_lost_messages() -> None:
    row = {"publisher_us": 1.0, "router_us": 1.0, "subscriber_us": 1.0, "total_us": 3.0}
    result = {
        "codec": [codec_row("state", repeats=10)],
        "robots": 2,
        "kind": "state",
        "rate_hz": 10.0,
        "seconds": 1.0,
        "rounds": 1,
        "rows": [
            {"way": "each", **row, "sent": 20, "validated": 20},
            {"way": "batched", **row, "sent": 20, "validated": 19},
        ],
        "load_before": [0.0, 0.0, 0.0],
        "load_after": [0.0, 0.0, 0.0],
    }
    assert "target FAIL nothing lost" in format_table(result)
    result["rows"][1]["validated"] = 20  # type: ignore[index]
    assert "target PASS nothing lost" in format_table(result)


@pytest.mark.parametrize("flags", [["--robots", "0"], ["--rounds", "0"], ["--seconds", "0.5"]])
def test_bad_options_are_refused_in_one_line(flags: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    assert srl(["bench", "messages", *flags]) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and error.startswith("srl: error:"), error


@pytest.mark.integration
@pytest.mark.slow
def test_over_a_router_every_robot_message_sent_is_validated(capsys: pytest.CaptureFixture[str]) -> None:
    assert (
        srl(["bench", "messages", "--robots", "5", "--seconds", "2", "--rounds", "1", "--kind", "transition", "--json"])
        == 0
    )
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert [r["way"] for r in result["runs"]] == ["each", "threaded", "batched"]  # in turn
    for row in result["rows"]:
        assert row["sent"] >= 5 * 15 and row["validated"] == row["sent"], row  # ~10 Hz for 2 s, nothing lost
        assert row["publisher_us"] >= 0 and row["subscriber_us"] >= 0
    assert [c["kind"] for c in result["codec"]] == list(KINDS)
