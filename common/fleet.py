"""A fleet (issue 16): which robots one host serves, and where a simulated fleet starts.

Pure: strings and numbers in, ids and states out (no settings, no transport).

* :func:`parse_robots` -- ``--robots r1,r2,...`` (explicit ids) or ``--robots K`` (``robot1`` ..
  ``robotK``); a repeated or malformed id is refused with one line (:class:`FleetError`).
* :func:`circle_starts` -- distinct starts on a circle around the target, each turned away from
  it (the paper's ``alpha_0 = atan2(y_0, x_0)``), so every robot has the same parking task.
"""

from __future__ import annotations

import math
import re

MAX_ROBOTS = 1000  # one host; far beyond what 2 cores serve at delta = 0.1 s (README "Fleet")
_ID = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")  # one key chunk, as common/keys.py requires


class FleetError(ValueError):
    """A robot list that cannot be served: said in one line."""


def parse_robots(text: str, prefix: str = "robot") -> list[str]:
    """``"K"`` -> ``[prefix1 .. prefixK]``; ``"a,b,c"`` -> ``["a", "b", "c"]`` (order kept)."""
    text = text.strip()
    if text.isdigit():
        count = int(text)
        if not 1 <= count <= MAX_ROBOTS:
            raise FleetError(f"--robots {text}: a fleet has 1 to {MAX_ROBOTS} robots")
        return [f"{prefix}{i}" for i in range(1, count + 1)]
    robots = [part.strip() for part in text.split(",")]
    seen: set[str] = set()
    for robot in robots:
        if not _ID.match(robot):
            raise FleetError(f"--robots: robot id {robot!r} must be 1-64 characters of A-Z a-z 0-9 _ -")
        if robot in seen:
            raise FleetError(f"--robots: robot id {robot!r} is given twice")
        seen.add(robot)
    if len(robots) > MAX_ROBOTS:
        raise FleetError(f"--robots: {len(robots)} robots; a fleet has 1 to {MAX_ROBOTS} robots")
    return robots


def circle_starts(count: int, radius: float) -> list[tuple[float, float, float]]:
    """``count`` starts evenly on a circle of ``radius`` metres around the target (the first on
    the +x axis), each heading away from the target: ``(r cos t, r sin t, t)``."""
    if count < 1:
        raise FleetError("a fleet has at least one robot")
    if not (math.isfinite(radius) and radius > 0):
        raise FleetError(f"the start circle's radius must be a positive number of metres, got {radius}")
    starts = []
    for i in range(count):
        theta = 2.0 * math.pi * i / count
        starts.append(
            (radius * math.cos(theta), radius * math.sin(theta), math.atan2(math.sin(theta), math.cos(theta)))
        )
    return starts
