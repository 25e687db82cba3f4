"""One robot's counters in a process that serves many (an actor host, a bridge host)."""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable

from common.net.provenance import QUIET_REFUSALS

log = logging.getLogger(__name__)


class RobotCounts:
    """The counters of ONE robot (its status and summary), with the ``count``/``reject`` interface
    every port of a service takes. A refusal is counted here and then either handed to ``forward``
    (e.g. the process's ``Bus.reject``: counted and logged there too) or logged here, at most once a
    second per kind, with the robot's id."""

    def __init__(self, robot: str, service: str, forward: Callable[[str, str], None] | None = None) -> None:
        self.robot, self.service, self.forward = robot, service, forward
        self.counters: Counter[str] = Counter()
        self.lock = threading.Lock()
        self.warned: dict[str, float] = {}

    def count(self, name: str, amount: int = 1) -> None:
        with self.lock:
            self.counters[name] += amount

    def reject(self, what: str, reason: str) -> None:
        self.count(f"rejected.{what}")
        if self.forward is not None:
            self.forward(what, f"robot {self.robot}: {reason}")
            return
        now = time.monotonic()
        if now - self.warned.get(what, 0.0) >= 1.0:
            self.warned[what] = now
            level = logging.INFO if what in QUIET_REFUSALS else logging.WARNING
            log.log(level, "%s %s: rejected %s: %s", self.service, self.robot, what, reason)

    def snapshot(self) -> dict[str, int]:
        with self.lock:
            return dict(self.counters)
