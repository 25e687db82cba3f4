"""Adding a row to one of srl's tables of variants (the agents, the simulated plant models): the
one place a registered name is checked. A name is what the settings, the command lines and the
docs show, so it is short, lower case and unused."""

from __future__ import annotations

import re
from typing import TypeVar

R = TypeVar("R")


def add_row(table: dict[str, R], kind: str, name: str, row: R, extra: str = "") -> None:
    """``table[name] = row``; ValueError (one line) for a name that is taken or not 1-32 of
    a-z 0-9 _ (and the characters of ``extra``), starting with a letter."""
    allowed = "a-z0-9_" + re.escape(extra)
    if not re.fullmatch(f"[a-z][{allowed}]{{0,31}}", name):
        shown = " ".join(["a-z", "0-9", "_", *extra])
        raise ValueError(f"{kind} name {name!r}: 1-32 of {shown}, starting with a letter")
    if name in table:
        raise ValueError(f"{kind} {name!r} exists already")
    table[name] = row
