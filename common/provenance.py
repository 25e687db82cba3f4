"""Which publisher a receiver believes: the live session of a singleton service.

A plant's states, an actor's actions and a critic's weights are accepted only from a session
whose identity token (``srl/<robot>/alive/<service>/<zid>``, :func:`common.keys.identity_key`)
is live. Zenoh stamps every sample of a session that has timestamping on (every srl session,
:func:`common.transport.zenoh_config`) with that session's id, so the receiver compares the
sample's timestamp id with the live identities:

* a sample from any other session (a second plant, a stray test client, a forger that does not
  spoof ids) is refused and counted;
* two live identities of a singleton service (two plants for one robot) are a *conflict*: the
  receiver must not follow either (the actor commands zero and reports it);
* a new identity after the old one vanished is a restart: the receiver resynchronizes its
  sequence numbers and versions per source instead of refusing the new stream forever.

Limits (README "Security"): a Zenoh client can forge a timestamp id, so this does not stop a
determined attacker who already reaches the router; the access rules (``--secure``: login, role
rules, TLS) do. This class is pure (no zenoh): the transport feeds it tokens and sample sources.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Literal

Verdict = Literal["accept", "foreign", "conflict", "unknown"]


class PlantConflictError(RuntimeError):
    """A plant (simulator or robot bridge) would start beside a live plant of the same robot."""


@dataclass
class SourceGate:
    """Live identities of one singleton service, and the verdict on a sample's source."""

    service: str
    live: set[str] = field(default_factory=set)
    generation: int = 0  # bumped whenever the set of live identities changes
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def update(self, zid: str, alive: bool) -> None:
        with self.lock:
            before = set(self.live)
            if alive:
                self.live.add(zid)
            else:
                self.live.discard(zid)
            if self.live != before:
                self.generation += 1

    def verdict(self, source: str | None) -> Verdict:
        """``accept`` only a sample of the one live identity; ``conflict`` while two or more are
        live (follow neither); ``unknown`` while none is; ``foreign`` for any other source."""
        with self.lock:
            if len(self.live) > 1:
                return "conflict"
            if not self.live:
                return "unknown"
            return "accept" if source in self.live else "foreign"

    @property
    def conflict(self) -> bool:
        with self.lock:
            return len(self.live) > 1

    def sources(self) -> list[str]:
        with self.lock:
            return sorted(self.live)


@dataclass
class SequenceGuard:
    """Per-source order of a stream (states' ``seq``, actions' ``(episode, step)``).

    A value must be newer than the last accepted one of its source, and at most ``max_jump``
    ahead of it: one message from the far future must not lock out every real one after it.
    ``restart_after`` consecutive refusals of an *old* value from the live source are taken as
    that source having restarted its count (the reference is reset to the new stream)."""

    max_jump: int
    restart_after: int = 20
    last: dict[str, int] = field(default_factory=dict)
    old_run: dict[str, int] = field(default_factory=dict)

    def check(self, source: str, value: int) -> str | None:
        """None if accepted (the reference moves); else the reason of the refusal."""
        last = self.last.get(source)
        if last is None:
            self.last[source], self.old_run[source] = value, 0
            return None
        if value > last + self.max_jump:
            return f"{value} jumps more than {self.max_jump} ahead of {last}"
        if value <= last:
            run = self.old_run.get(source, 0) + 1
            self.old_run[source] = run
            if run < self.restart_after:
                return f"{value} not newer than {last}"
            # the source counts from scratch again (its process restarted under the same identity)
        self.last[source], self.old_run[source] = value, 0
        return None

    def forget(self, keep: set[str]) -> None:
        """Drop the references of sources no longer live (bounded memory, fresh on return)."""
        for source in [s for s in self.last if s not in keep]:
            self.last.pop(source, None)
            self.old_run.pop(source, None)
