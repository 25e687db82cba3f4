"""Adding a row to a table of variants (common/math/rows.py): the one check of a registered name."""

from __future__ import annotations

import re

import pytest

from common.math.rows import add_row


def test_a_row_is_added_once_under_a_name_a_setting_can_hold() -> None:
    table: dict[str, int] = {"mpc": 0}
    add_row(table, "agent", "rlqv+", 1, extra="+")
    add_row(table, "plant model", "x" * 32, 2)
    assert table == {"mpc": 0, "rlqv+": 1, "x" * 32: 2}
    refused = {
        "mpc": "'mpc' exists already",
        "Mpc2": "1-32 of a-z 0-9 _ +, starting with a letter",
        "2mpc": "starting with a letter",
        "x" * 33: "1-32 of",
        "a b": "1-32 of",
        "": "1-32 of",
    }
    for name, why in refused.items():
        with pytest.raises(ValueError, match=f"^agent.*{re.escape(why)}"):
            add_row(table, "agent", name, 9, extra="+")
    with pytest.raises(ValueError, match=r"plant model name 'a\+b': 1-32 of a-z 0-9 _, starting"):
        add_row(table, "plant model", "a+b", 9)  # + only where the table allows it
    assert table == {"mpc": 0, "rlqv+": 1, "x" * 32: 2}  # nothing refused was added
