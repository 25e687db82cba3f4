"""Which publisher a receiver believes: the live session of a singleton service.

A plant's states, an actor's actions and a critic's weights are accepted only from a session
whose identity token (``srl/<robot>/alive/<service>/<zid>``, :func:`common.contracts.keys.identity_key`)
is live. Zenoh stamps every sample of a session that has timestamping on (every srl session,
:func:`common.net.transport.zenoh_config`) with that session's id, so the receiver compares the
sample's timestamp id with the live identities:

* a sample from any other session (a second plant, a stray test client, a forger that does not
  spoof ids) is refused and counted;
* two live identities of a singleton service (two plants for one robot) are a *conflict*: the
  receiver must not follow either (the actor commands zero and reports it);
* a new identity after the old one vanished is a restart: the receiver resynchronizes its
  sequence numbers and versions per source instead of refusing the new stream forever.

Limits (docs/security.md): a Zenoh client can forge a timestamp id, so this does not stop a
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
        """Two or more identities live. Read without the lock: the set's size is read in one step
        (the GIL), and a verdict taken under the lock could change the moment after all the same
        (an actor host asks it of every robot at every tick at rest)."""
        return len(self.live) > 1

    def sources(self) -> list[str]:
        with self.lock:
            return sorted(self.live)


# A followed source whose values the receiver refuses this many times in a row, the refused values
# themselves forming an increasing stream, within RESYNC_WITHIN_S, is taken as having restarted
# (or as continuing after a forged value moved the reference): the receiver follows it again.
# At 10 Hz actions that is half a second of refused real actions at most per forged burst; a
# forger that can spoof the live session's id is then followed too (docs/security.md: only the
# access rules stop it), but it can no longer lock the real stream out.
RESYNC_AFTER = 5
RESYNC_WITHIN_S = 2.0


@dataclass
class RefusalRun:
    """Consecutive refusals of one followed source, and when they amount to a stream to resync to.

    A run grows only while each refused value is newer than the previous refused one (a live
    stream counting on from its own numbers; replays and duplicates are not) and the run is
    younger than ``within`` seconds (no clock given: no time limit)."""

    after: int = RESYNC_AFTER
    within: float = RESYNC_WITHIN_S
    count: int = 0
    newest: tuple[int, ...] | None = None
    since: float = 0.0

    def refused(self, value: tuple[int, ...], now: float | None = None) -> bool:
        """Count one refusal; True when it completes a run (then take ``value`` as the reference)."""
        coherent = (
            self.count > 0
            and self.newest is not None
            and value > self.newest
            and (now is None or now - self.since <= self.within)
        )
        if not coherent:
            self.count, self.since = 0, 0.0 if now is None else now
        self.count += 1
        self.newest = value
        if self.count >= self.after:
            self.accepted()
            return True
        return False

    def accepted(self) -> None:
        self.count, self.newest = 0, None


@dataclass
class SequenceGuard:
    """Per-source order of a stream (a plant's state ``seq``).

    A value must be newer than the last accepted one of its source, and at most ``max_jump``
    ahead of it: one message from the far future must not lock out every real one after it.
    ``restart_after`` consecutive refusals (old or too far ahead) of values that themselves
    increase (:class:`RefusalRun`) are taken as that source having restarted its count, or as a
    forged value having moved the reference: the reference is reset to the new stream."""

    max_jump: int
    restart_after: int = 20
    within: float = RESYNC_WITHIN_S
    last: dict[str, int] = field(default_factory=dict)
    old_run: dict[str, RefusalRun] = field(default_factory=dict)
    resyncs: int = 0

    def check(self, source: str, value: int, now: float | None = None) -> str | None:
        """None if accepted (the reference moves); else the reason of the refusal."""
        last = self.last.get(source)
        run = self.old_run.setdefault(source, RefusalRun(self.restart_after, self.within))
        if last is None:
            self.last[source] = value
            run.accepted()
            return None
        if value > last + self.max_jump:
            reason: str | None = f"{value} jumps more than {self.max_jump} ahead of {last}"
        elif value <= last:
            reason = f"{value} not newer than {last}"
        else:
            reason = None
        if reason is not None:
            if not run.refused((value,), now):
                return reason
            self.resyncs += 1  # the source counts from new numbers (restarted, or a forgery moved us)
        else:
            run.accepted()
        self.last[source] = value
        return None

    def forget(self, keep: set[str]) -> None:
        """Drop the references of sources no longer live (bounded memory, fresh on return)."""
        for source in [s for s in self.last if s not in keep]:
            self.last.pop(source, None)
            self.old_run.pop(source, None)


@dataclass
class ActionOrder:
    """The order of one actor session's actions, ``(episode, step)`` (the robot bridge's gate).

    Accepted: the first action; a newer step of the same episode at most ``max_step_jump`` ahead;
    a newer episode at most ``max_episode_jump`` ahead whose step is at most ``max_step_jump``.
    Anything else is refused, and a run of refused actions that increase among themselves
    (:class:`RefusalRun`) resynchronizes to them: one forged ``Action(episode=2**62)`` with the
    live actor's session id is refused alone, and a forged burst that was followed costs the real
    actor at most ``resync_after`` refused actions."""

    max_step_jump: int
    max_episode_jump: int
    resync_after: int = RESYNC_AFTER
    within: float = RESYNC_WITHIN_S
    last: tuple[int, int] | None = None
    resyncs: int = 0
    run: RefusalRun = field(default_factory=RefusalRun)

    def __post_init__(self) -> None:
        self.run = RefusalRun(self.resync_after, self.within)

    def reset(self) -> None:
        """A new actor session: its own episode and steps."""
        self.last = None
        self.run.accepted()

    def _refusal(self, order: tuple[int, int]) -> str | None:
        if self.last is None:
            return None
        (episode, step), (last_episode, last_step) = order, self.last
        if order <= self.last:
            return f"(episode, step) {order} not newer than {self.last}"
        if episode > last_episode + self.max_episode_jump:
            return f"episode {episode} jumps more than {self.max_episode_jump} ahead of {last_episode}"
        if episode > last_episode and step > self.max_step_jump:
            return f"step {step} of a new episode is beyond {self.max_step_jump}"
        if episode == last_episode and step > last_step + self.max_step_jump:
            return f"step {step} jumps more than {self.max_step_jump} ahead of {last_step}"
        return None

    def check(self, episode: int, step: int, now: float | None = None) -> str | None:
        """None if accepted (the reference moves; :attr:`resyncs` grows when by a resync)."""
        order = (episode, step)
        reason = self._refusal(order)
        if reason is not None:
            if not self.run.refused(order, now):
                return reason
            self.resyncs += 1
        else:
            self.run.accepted()
        self.last = order
        return None


# An action's step may run at most this far ahead of the last applied one of the same episode.
MAX_ACTION_STEP_JUMP = 10_000
# An actor's episode ids are its wall clock in milliseconds when the episode starts
# (services.actor.ports.new_episode_id): a session's next episode is at most a day ahead of its
# last. One forged Action(episode=2**62) with the live actor's session id is refused alone.
MAX_ACTION_EPISODE_JUMP = 86_400_000
# Actions of the followed actor session that arrive this soon after its identity token vanished
# are late, not foreign: a stopping actor's last puts can still be queued (Zenoh batches them)
# when its token's undeclaration overtakes them. They are refused and counted like any other
# refusal (``rejected.action.late``) but logged at INFO: a clean shutdown is no alarm.
LATE_WITHIN_S = 0.25
# Refusals that are part of normal operation: counted, logged at INFO instead of WARNING.
QUIET_REFUSALS = frozenset({"action.late"})


@dataclass
class ActionGate:
    """Whose actions a plant applies (the robot bridge and the real-time simulator alike): only
    the live actor session's (:class:`SourceGate`), in that session's own order
    (:class:`ActionOrder`, restarted when another live session takes over)."""

    gate: SourceGate
    order: ActionOrder = field(default_factory=lambda: ActionOrder(MAX_ACTION_STEP_JUMP, MAX_ACTION_EPISODE_JUMP))
    source: str | None = None  # the session whose actions are followed
    left: str | None = None  # the followed session that vanished last, and when (monotonic s)
    left_at: float | None = None

    def admit(self, episode: int, step: int, source: str | None, now: float | None = None) -> tuple[str, str] | None:
        """None if the action is to be applied; else (what, reason) of the refusal, ``what`` being
        ``action.<verdict>`` for another session, ``action.late`` for the followed session's
        actions within ``LATE_WITHIN_S`` after it vanished, and ``action`` for one out of order."""
        verdict = self.gate.verdict(source)
        if verdict != "accept":
            late = self.late_refusal(source, now) if verdict != "conflict" else None
            if late is not None:
                return late
            return f"action.{verdict}", f"from session {source} (live actor: {self.gate.sources() or 'none'})"
        if source != self.source:  # a new actor session: its own episode and steps
            self.source = source
            self.order.reset()
        refusal = self.order.check(episode, step, now)
        return None if refusal is None else ("action", refusal)

    def lost(self, zid: str, now: float | None = None) -> bool:
        """The session ``zid`` vanished: True (and nobody followed any more) if it was the one
        followed, whose last command must then be withdrawn at once."""
        if zid != self.source:
            return False
        self.source, self.left, self.left_at = None, zid, now
        return True

    def late_refusal(self, source: str | None, now: float | None) -> tuple[str, str] | None:
        """``("action.late", reason)`` if ``source`` is the followed session that vanished at most
        ``LATE_WITHIN_S`` ago (its actions still in flight when it left), else None."""
        if source is None or source != self.left:
            return None
        if now is None or self.left_at is None:
            return "action.late", f"from session {source}, which just left"
        if now - self.left_at > LATE_WITHIN_S:
            return None
        return "action.late", f"from session {source}, which left {1000 * (now - self.left_at):.0f} ms ago"


def yields_to(own: str, others: list[str]) -> list[str]:
    """The live sessions a singleton service's session ``own`` must yield to: those that sort
    before it. Two plants that both passed the start check (started at the same moment) compute
    the same answer each, so exactly one of them keeps running."""
    return sorted(other for other in others if other < own)
