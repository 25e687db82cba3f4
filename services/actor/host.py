"""The actor host: one process serves many robots at ``delta``.

Each robot has what a single actor has -- its own :class:`~services.actor.realtime.RealtimeActor`
(state intake with provenance, weights inbox, statistics, transitions, staleness), its own plans
and warm starts, arrival rule and counters (:class:`~common.math.actor_problem.ActorMemory`), its own tick
accounting (:class:`RobotTicker`) and its own keys (``.../status/actor``, liveliness
``.../alive/actor``); its actions and its transitions leave with its tick group's, a batch each
(``srl/@batch/action``, ``srl/@batch/transition``, :class:`Outbox`; a host of one robot: on the
robot's keys). What they share is ONE built problem per
(agent, N): :class:`RobotActor` swaps a robot's memory into the shared
:class:`~common.math.actor.StackedActor` for its step. Every solve runs in one thread, the
scheduler's, so the CasADi function and its buffers are never used by two robots at once (its
buffers are the actor's own, rewritten before every solve: nothing leaks from one robot to the
next, ``tests/test_fleet.py`` checks the actions against one actor per robot, bit for bit).

Scheduling: robot ``i`` of ``K`` ticks at ``t0 + i delta / K + k delta`` (phases spread over the
period, so the work is too; ``t0`` placed in the plant's state period where a plant host that
syncs its states to the ticks sends each robot one state a period:
:func:`common.system.clock.tick_phase_offset`), and :class:`HostScheduler` serves the robot whose tick is due first
(earliest deadline first; ties by robot order): no robot waits for more than the others' work due
before its own. A tick served more than a quarter period late is a missed deadline, as for one
actor (common/system/clock.py); a tick more than a period late is skipped, counted as missed, and the
robot's schedule moves on (no burst of catch-up ticks).

Before the first tick, every robot whose state has come is solved once off the schedule
(:func:`prime_plans`), so its first tick polishes a plan: a cold solve costs several warm ones,
and every robot's cold first solve within the first period would put the host behind its
schedule from its first round.
"""

from __future__ import annotations

import gc
import heapq
import logging
import math
import os
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any, Generic, TypeVar

import numpy as np

from common.config.assembly import arrival_rule, arrival_tolerances, build_actor
from common.config.settings import Settings
from common.contracts.columns import Columns, columns_of
from common.contracts.messages import Action, Message, Transition
from common.contracts.summaries import FleetActorSummary, RealtimeActorSummary, fleet_view, format_status_line
from common.math.actor import StackedActor
from common.math.actor_problem import ActorCounters, ActorMemory, ActorProblem, ActorStep
from common.math.arrival import arrival_masks
from common.math.features import stage_cost_rows
from common.net.transport import Bus, bus_status, start_status_thread
from common.process.counts import RobotCounts
from common.process.runtime import realtime_priority
from common.system.clock import LATE_FRACTION, Ticker, aligned_start, tick_phase_offset
from services.actor.ledger import ACCEPTED, SEQ, Ledger
from services.actor.ports import WeightsInbox, new_episode_id, wire_weights
from services.actor.realtime import Counts, RealtimeActor, Rests, StateIntake, Steps, rest_ticks

log = logging.getLogger(__name__)

M = TypeVar("M", bound=Message)

# A tick served more than this fraction of a period after its due time is solved in a hurry
# (StackedActor.step: the warm polish only, no search and no vertex search): a host behind its
# schedule sheds the optional work
# until it is on time again, instead of missing deadlines.
HURRY_FRACTION = 0.05
# An actor host's actions leave in rounds (Outbox): those of one tick group together, or
# sooner once the oldest has waited this long. A plant host learns each robot's phase from when
# its actions arrive (services/plant_sim/host.py StateSync) and opens its window STATE_SYNC_MARGIN_S
# (5 ms, common/system/clock.py) early: a wait well inside that margin keeps every robot's newest state in the window.
ACTION_WAIT_S = 0.002
# A lower bound on the transitions one batch sample holds: a Transition's row of a columnar batch
# is at most 153 bytes, its JSON under 640 (tests/test_batch_wire.py checks a worst case); the
# sample's bound is 64 KiB.
TRANSITIONS_PER_SAMPLE = 100
# How long a host waits for its robots' first states to prime their plans (prime_plans) before
# its first tick: a plant started with it (srl up, compose) publishes within a second.
PRIME_WAIT_S = 3.0
# A tick group with at least this many robots at rest is served at rest as arrays (RestCheck); a
# smaller one takes its steps: numpy's ~10 calls cost ~50 us whatever the rows, a step at rest
# ~30 us (one robot's actor, a host of one, takes its steps at rest as before).
REST_ARRAYS_FROM = 4


def robot_settings(settings: Settings, robot: str) -> Settings:
    """The settings of one robot of the fleet: the same, but its own id (its keys)."""
    return settings.model_copy(update={"transport": settings.transport.model_copy(update={"robot": robot})})


def wire_realtime(
    settings: Settings,
    bus: Bus,
    actor: StackedActor | Steps,
    inbox: WeightsInbox,
    counters: Counts,
    episode_id: int,
    publish_action: Callable[[Action], None],
    publish_transition: Callable[[Transition], None],
    ledger: Ledger | None = None,
    row: int = 0,
) -> RealtimeActor:
    """One robot's real-time loop on the bus (``settings.transport.robot``'s keys): its action and
    transition publishers, the plant's session identities and liveliness watched. Provenance
    first: the caller subscribes the states after this, so the live plant sessions are known
    before the first state is judged (one actor: a callback per state; the actor host: the
    newest, judged at the robot's tick). ``publish_action``, ``publish_transition``: where its
    actions and transitions go (the host's outboxes, :class:`Outbox`); ``ledger``, ``row``: where
    it keeps its records (its host's ledger; None: one of its own)."""
    robot = settings.transport.robot
    loop = RealtimeActor(
        settings,
        actor,
        inbox,
        publish_action,
        publish_transition,
        counters,
        episode_id,
        ledger=ledger,
        row=row,
    )
    bus.watch_identities(robot, "plant", loop.plant_gate, loop.on_plant_identity)
    bus.watch_alive(robot, "plant", loop.on_plant_token)
    return loop


class RobotActor:
    """One robot's share of a built actor: its own memory, the shared problem (one step at a time)."""

    def __init__(self, shared: StackedActor, memory: ActorMemory) -> None:
        self.shared = shared
        self.memory = memory

    @property
    def problem(self) -> ActorProblem:
        return self.shared.problem

    @property
    def counters(self) -> ActorCounters:
        return self.memory.counters

    @property
    def arrived(self) -> bool:
        return self.memory.arrival is not None and self.memory.arrival.arrived

    def reset(self) -> None:
        self.memory.forget()

    def step(self, state: np.ndarray, q_weights: np.ndarray, v_weights: np.ndarray, hurry: bool = False) -> ActorStep:
        held = self.shared.swap_memory(self.memory)
        try:
            return self.shared.step(state, q_weights, v_weights, hurry)
        finally:
            self.memory = self.shared.swap_memory(held)


class RestCheck:
    """Which robots of a tick group their actor's arrival rule holds at rest at this tick,
    decided for the group at once as arrays: the outer tolerances (still arrived), the inner ones
    (what the critic fits, common.math.critic.at_rest) and the stage costs of a zero command, for
    every robot whose last step said "arrived" and whose newest state is fresh and from the one
    live plant. Each such robot's tick is then :meth:`RealtimeActor.tick
    <services.actor.realtime.RealtimeActor.tick>` with its row of :class:`~services.actor.realtime.Rests`:
    no step, its bookkeeping only (the arrival rule itself stays arrived). The
    decision and the values are those of the robot's own step, bit for bit
    (``tests/test_host_rest.py``); a group of fewer than ``arrays_from`` such robots takes its
    steps (:data:`REST_ARRAYS_FROM`). A host of actors without an arrival rule rests no robot."""

    def __init__(self, settings: Settings, loops: Sequence[RealtimeActor], arrays_from: int = REST_ARRAYS_FROM) -> None:
        if loops and any(loop.ledger is not loops[0].ledger for loop in loops):
            raise ValueError("a rest check reads one ledger: its loops must be one host's")
        self.loops = loops
        self.tolerances = arrival_tolerances(settings)
        self.r_diag = settings.r_diag
        self.delta = settings.plant.sampling_time
        self.system = settings.system
        self.arrays_from = max(1, arrays_from)
        # per robot, the last decision and the state and true state it was made on: a robot at
        # rest reports the same state tick after tick, and the decision is a function of it alone
        n, count = self.system.state_dim, len(loops)
        self.on = np.full((count, 2 * n), math.nan)  # (state, true state) as Ledger.values (NaN: none yet)
        self.inner = np.zeros(count, dtype=bool)
        self.stays = np.zeros(count, dtype=bool)
        self.costs = np.zeros((count, 2))  # (cost, true cost: NaN without the truth)
        self.rows = np.array([loop.row for loop in loops], dtype=np.intp)  # each robot's ledger row

    def __call__(self, members: Sequence[int], now: float) -> Rests | None:
        """Which of ``members`` (the host's robot numbers) are at rest now, a row each in their
        order (None: none)."""
        tolerances = self.tolerances
        if tolerances is None:
            return None
        # the robots whose last step said "arrived" (their newest state's freshness and plant are
        # checked at their tick, RealtimeActor.tick, as for any tick)
        loops = self.loops
        picked: list[int] = []
        chosen: list[RobotActor] = []
        for i in members:
            actor = loops[i].actor
            if isinstance(actor, RobotActor) and actor.arrived:
                picked.append(i)
                chosen.append(actor)
        if len(picked) < self.arrays_from:  # a few robots: their steps cost less than numpy's calls
            return None
        ledger = loops[0].ledger
        at = np.array(picked, dtype=np.intp)
        rows = self.rows[at]
        with ledger.lock:  # the newest states, as one moment saw them
            held, marks, received, values = (
                ledger.held[rows],
                ledger.marks[rows],
                ledger.received[rows],
                ledger.values[rows],
            )
        new = np.flatnonzero(held & ~(values == self.on[at]).all(axis=1))
        if len(new):
            self._decide(at[new], values[new])
        stays = held & self.stays[at]
        if not stays.any():
            return None
        kept = np.flatnonzero(stays)
        n, robots = self.system.state_dim, at[kept]
        values = values[kept]
        truths = values[:, n:]
        costs = self.costs[robots]
        return Rests(
            robots.tolist(),
            marks[kept, ACCEPTED],
            marks[kept, SEQ],
            received[kept],
            values[:, :n],
            np.where(np.isfinite(truths[:, :1]), truths, math.nan),  # the ledger's inf: no truth
            costs[:, 0],
            costs[:, 1],
            self.inner[robots],
            [chosen[j].memory.held_at_rest for j in kept.tolist()],
        )

    def _decide(self, robots: np.ndarray, values: np.ndarray) -> None:
        """The decisions for ``robots`` at their newest states and true states (``values`` as the
        ledger's, inf: no truth), as arrays: the outer tolerances (still arrived), the inner ones and the stage costs
        of a zero command."""
        assert self.tolerances is not None
        n, m = self.system.state_dim, self.system.action_dim
        states = values[:, :n]
        inner, stays = arrival_masks(states, self.tolerances)
        # the stage costs of a zero command, of the reported states and then of the true ones
        truths = values[:, n:]
        known = np.isfinite(truths[:, 0])
        costs = self.delta * stage_cost_rows(states, np.zeros((len(states), m)), self.r_diag)
        true_costs = np.full(len(states), math.nan)
        if known.any():
            true_costs[known] = self.delta * stage_cost_rows(
                truths[known], np.zeros((int(known.sum()), m)), self.r_diag
            )
        self.on[robots] = values
        self.inner[robots], self.stays[robots] = inner, stays
        self.costs[robots] = np.column_stack([costs, true_costs])


class Outbox(Generic[M]):
    """What a host's robots send at their ticks (actions, transitions), sent as rounds (``send``:
    Bus.round_publisher, one batch sample a round, common.contracts.keys.Batch):
    :class:`HostScheduler` flushes it when a tick group is served and before it sleeps, and, when
    ``wait`` is given, earlier once the oldest message has waited that long (the actions:
    :data:`ACTION_WAIT_S`). Used by the scheduler's thread only (every robot's messages are put
    at its ticks). ``what`` names the messages in the log.

    A robot's tick puts a message (:meth:`put`); the ticks a host serves at rest put theirs as
    columns of ``schema`` (:meth:`put_columns`, no message built); a round holds both in the
    order put, and goes as the messages when it holds only messages, else as one batch of columns
    (checked by the sender as a receiver checks it)."""

    def __init__(
        self,
        send: Callable[[Sequence[M] | Columns[M]], None],
        what: str = "actions",
        clock: Callable[[], float] = time.monotonic,
        wait: float | None = ACTION_WAIT_S,
        schema: type[M] | None = None,
    ) -> None:
        self.send, self.what, self.clock, self.wait = send, what, clock, wait
        self.schema = schema
        self.pending: list[M | Columns[M]] = []
        self.since = 0.0  # when the oldest pending message was put
        self.failed_rounds = 0

    def put(self, message: M) -> None:
        if not self.pending:
            self.since = self.clock()
        self.pending.append(message)

    def put_columns(self, robots: Sequence[str], fields: dict[str, Any]) -> None:
        """A message of ``schema`` for each of ``robots``, as ``Columns.of`` takes them: one array
        (or one value for every row) per field."""
        assert self.schema is not None, "an outbox of columns names their schema"
        if not self.pending:
            self.since = self.clock()
        self.pending.append(Columns.of(self.schema, robots, fields))

    def overdue(self, now: float) -> bool:
        return self.wait is not None and bool(self.pending) and now - self.since >= self.wait

    def flush(self) -> None:
        """Send what is pending. A send that fails is logged and counted (``failed_rounds``), and
        the scheduler goes on: the robots whose actions it held stop by their plant's watchdog,
        as they would if those actions had been lost on the way; a round of transitions lost is
        a gap in the critic's replay, as a transition lost on the way is."""
        if self.pending:
            pending, self.pending = self.pending, []
            try:
                self.send(self._round(pending))
            except Exception:  # a failed round must not end the loop that keeps every robot safe
                self.failed_rounds += 1
                log.exception("actor host: a round of %d %s could not be sent", len(pending), self.what)

    def _round(self, pending: list[M | Columns[M]]) -> Sequence[M] | Columns[M]:
        """The messages, or (rows among them) one batch of all of them in order."""
        if not any(isinstance(part, Columns) for part in pending):
            return pending  # type: ignore[return-value]  # only messages
        assert self.schema is not None
        parts: list[Columns[M]] = []
        messages: list[M] = []
        for part in pending:
            if isinstance(part, Columns):
                if messages:
                    parts.append(columns_of(self.schema, messages))
                    messages = []
                parts.append(part)
            else:
                messages.append(part)
        if messages:
            parts.append(columns_of(self.schema, messages))
        return Columns.joined(self.schema, parts)


def transition_rounds(robots: int, group: int) -> int:
    """The samples an actor host of ``robots`` sends per period on ``srl/@batch/transition``: one
    round per tick group (:class:`HostScheduler`), each of at most ``group`` transitions, as many
    samples as the 64 KiB bound takes (:data:`TRANSITIONS_PER_SAMPLE` at least per sample). Its
    publisher caches ``transport.transition_cache`` periods of them: as many of each robot's
    transitions as a publisher of one robot keeps."""
    groups = -(-robots // group)
    return groups * -(-min(group, robots) // TRANSITIONS_PER_SAMPLE)


def tick_groups(robots: int, group: int) -> int:
    """The phases of the period a host's ``robots`` tick in, ``group`` robots to a phase."""
    return -(-robots // group)


class RobotTicker(Ticker):
    """One robot's ticks in a host: tick ``k`` due at ``start + (k + 1) period`` (as
    :class:`~common.system.clock.Ticker`), served by :class:`HostScheduler` instead of slept to."""

    def __init__(self, period: float, start: float, late_fraction: float = LATE_FRACTION) -> None:
        super().__init__(period, clock=lambda: start, late_fraction=late_fraction)

    @property
    def next_due(self) -> float:
        return self.start + (self.index + 1) * self.period

    def serve(self, now: float) -> int:
        """The next tick is served at ``now``: its index ``k`` (missed and late ticks counted)."""
        self.index += 1
        due = self.start + self.index * self.period
        if now - due >= self.period:  # whole periods passed: skip them, no catch-up burst
            skipped = int((now - due) // self.period)
            self.missed += skipped
            self.index += skipped
            due += skipped * self.period
        if now - due > self.late_threshold:
            self.missed += 1
            self.late += 1
        self.last_tick = now
        return self.index - 1

    def wait(self) -> float | None:
        raise NotImplementedError("a host's robot ticks are served by HostScheduler")


class HostScheduler:
    """Serves many robots' ticks from one thread, earliest deadline first.

    ``budget``: the share of a period this thread may spend on ticks (the sum of its last round's
    tick times, one per robot); over it, the next tick is solved in a hurry (counted in
    ``over_budget``), as a tick served late is. With the thread real-time (``realtime_priority``)
    nothing else makes it shed work, and a real-time host that never sheds can take the cores the
    critic needs (docs/fleets.md).
    ``group`` (``actor.host_tick_group``): robots ``i // group`` share a phase of the period and are
    served back to back, one wake-up per group; a group is late (hurried) when its first tick is.
    ``pull``: robots at rest tick with the first group. The phases spread the solves over the
    period; a robot at rest solves nothing, yet each group tick costs every process a wake-up and
    a round of samples (docs/notes/at-rest-per-group.md). So when the first group is served, every
    robot of another group whose arrival rule holds it (its last tick served at rest, or a step
    that said "arrived") and whose next tick is due within a period is asked again (``rests``); those still at rest are
    served then, early (never late, their step index unchanged), in the same rounds. A robot that
    moves is served at its own phase again. A tick served early, and the tick after one, add no
    sample to the period and jitter windows: those measure the deadlines of the robot's own phase.
    ``clock`` and ``sleep`` (``sleep(seconds) -> True`` to stop) are injectable, as for Ticker."""

    def __init__(
        self,
        loops: list[RealtimeActor],
        period: float,
        stop: threading.Event,
        *,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], bool] | None = None,
        budget: float = 1.0,
        group: int = 1,
        outboxes: Sequence[Outbox[Any]] = (),
        rests: Callable[[Sequence[int], float], Rests | None] | None = None,
        start: float | None = None,
        pull: bool = False,
    ) -> None:
        self.loops, self.period, self.stop = loops, period, stop
        # which robots of a tick group are served at rest (RestCheck; None: every tick a step)
        self.rests = rests
        self.pull = pull and rests is not None
        self.early = [False] * len(loops)  # the robot's last tick was served early (pulled)
        self.pulled = 0  # ticks served early, with the first group
        self.group = group
        # the robots' actions and transitions, sent per group (none: each robot sends its own)
        self.outboxes = tuple(outboxes)
        self.clock = clock
        self.sleep = sleep or stop.wait
        start = clock() if start is None else start
        count = len(loops)
        groups = tick_groups(count, group)
        self.tickers = [RobotTicker(period, start + (i // group) * period / groups) for i in range(count)]
        for loop, ticker in zip(loops, self.tickers, strict=True):
            loop.ticker = ticker
        self.served = 0
        self.started = start
        self.warned = -1e9
        self.budget = budget * period
        self.spent = [0.0] * count  # the last round's tick times: a ring of one slot per robot
        self.spent_sum = 0.0
        self.over_budget = 0

    def run(self, end: float | None, manual_gc: bool = True) -> None:
        """Serve ticks until ``stop`` or until every robot's next tick is at or after ``end`` (then
        wait until the first of those is due); then each robot's last action is zero.

        ``manual_gc``: garbage collection off the critical path -- automatic collection is off
        while the loop runs (the caller froze what existed before), and the young generation is
        collected once per round of all robots (the middle one every 10, all every 600), only when
        the next tick is not due within 2 ms. SRL_ACTOR_AUTOMATIC_GC=1 keeps Python's automatic
        collection."""
        manual_gc = manual_gc and gc.isenabled() and os.environ.get("SRL_ACTOR_AUTOMATIC_GC") != "1"
        if manual_gc:
            gc.disable()
        heap = [(ticker.next_due, i) for i, ticker in enumerate(self.tickers)]
        heapq.heapify(heap)
        rounds, pending_gc = 0, -1
        count = len(self.loops)
        group_due, group_start = -1.0, 0.0  # the due time of the group being served, when it began
        rests: Rests | None = None  # its robots at rest (RestCheck) ...
        resting: dict[int, int] = {}  # ... each one's row there, until served
        # the first group's at rest, served with those pulled: (robot, due) and their rests
        deferred: list[tuple[int, float | None]] = []
        deferred_rests: list[Rests] = []
        try:
            while not self.stop.is_set():
                while heap[0][0] != self.tickers[heap[0][1]].next_due:  # a tick already served early
                    heapq.heappop(heap)
                due, i = heap[0]
                if end is not None and due >= end:  # the run ends when its first unserved tick is due:
                    self.flush()  # what answers the last ticks (the critic's weights) comes in meanwhile
                    self.sleep(max(0.0, due - self.clock()))
                    break
                wait = due - self.clock()
                if wait > 0:
                    self.flush()  # nothing is held back while the thread waits
                    if pending_gc >= 0 and wait > 0.002:
                        gc.collect(pending_gc)
                        pending_gc = -1
                        continue
                    if self.sleep(wait):
                        break
                heapq.heappop(heap)
                now = self.clock()
                if due != group_due:
                    group_due, group_start = due, now
                    rests = None if self.rests is None else self.rests(self.members(i, due), now)
                    resting = {} if rests is None else {robot: row for row, robot in enumerate(rests.at)}
                over = self.spent_sum > self.budget
                row = resting.pop(i, None)
                if row is not None:  # it and the robots after it due now and at rest: served at once
                    assert rests is not None
                    run: list[tuple[int, float | None]] = [(i, due)]
                    rows = [row]
                    while heap and heap[0][0] == due and heap[0][1] in resting:
                        j = heapq.heappop(heap)[1]
                        run.append((j, due))
                        rows.append(resting.pop(j))
                    self.over_budget += over * len(run)
                    if self.pull and i < self.group:  # with the robots pulled, once the group's others are served
                        deferred += run
                        deferred_rests.append(rests.take(rows))
                    else:
                        self._serve_rests(run, rests.take(rows), now, heap)
                else:
                    self.over_budget += over
                    k, previous = self._take(i, now, due)
                    # late: the group began late (its later ticks wait for the earlier ones by design)
                    late = group_start - due > HURRY_FRACTION * self.period
                    self.loops[i].tick(k, now, hurry=over or late)  # hurry: the lighter solve
                    self._measure(i, now, due, previous)  # once the action is out: not on its latency
                    self._spent(now)
                    self.served += 1
                    heapq.heappush(heap, (self.tickers[i].next_due, i))
                # the group is served (the next tick due is another phase's): its actions and
                # its transitions go out, a round each; or its first action has waited long enough
                if not heap or heap[0][0] != due:
                    if self.pull and i < self.group:
                        self._pull_rests(due, heap, deferred, deferred_rests)
                        deferred, deferred_rests = [], []
                    self.flush()
                elif self.outboxes:
                    flushed_at = self.clock()
                    for box in self.outboxes:
                        if box.overdue(flushed_at):
                            box.flush()
                while manual_gc and rounds < self.served // count:  # a round of every robot served
                    pending_gc = max(pending_gc, 2 if rounds % 600 == 599 else 1 if rounds % 10 == 9 else 0)
                    rounds += 1
        finally:
            if manual_gc:
                gc.enable()
        for loop, ticker in zip(self.loops, self.tickers, strict=True):  # on the way out: stop every robot
            loop.send(ticker.index, loop.zero, -1)
        self.flush()

    def _serve(self, i: int, now: float, due: float | None = None) -> int:
        """Robot ``i``'s next tick is served at ``now`` (``due``: at its own phase; None: early,
        pulled): its index ``k``, its ticker's accounting and its loop's period and jitter."""
        k, previous = self._take(i, now, due)
        self._measure(i, now, due, previous)
        return k

    def _take(self, i: int, now: float, due: float | None) -> tuple[int, float | None]:
        """:meth:`_serve`'s ticker accounting alone: the tick's index ``k`` and the robot's previous
        tick (None: its first), for :meth:`_measure` once the tick's action is out."""
        loop, ticker = self.loops[i], self.tickers[i]
        previous = ticker.last_tick if ticker.index else None
        missed = ticker.missed
        k = ticker.serve(now)
        if ticker.missed != missed and now - self.warned >= 1.0:
            self.warned = now
            log.warning(
                "robot %s: tick %d served %.1f ms late (%.1f s into the run; missed deadlines %d)",
                loop.robot,
                k,
                0.0 if due is None else 1e3 * (now - due),
                now - self.started,
                ticker.missed,
            )
        return k, previous

    def _measure(self, i: int, now: float, due: float | None, previous: float | None) -> None:
        """Robot ``i``'s period and jitter windows take its tick served at ``now`` (as :meth:`_serve`)."""
        if due is not None and previous is not None and not self.early[i]:
            loop = self.loops[i]
            loop.periods.append(now - previous)
            loop.jitter.append(abs(now - previous - self.period))
        self.early[i] = due is None

    def _serve_rests(
        self, run: list[tuple[int, float | None]], rests: Rests, now: float, heap: list[tuple[float, int]]
    ) -> None:
        """The robots of ``run``, ``(robot, due)`` (``due`` as :meth:`_serve`'s), served at ``now``
        at their ``rests`` (a row each), in order: those still ready (:meth:`Rests.ready`)
        together, as arrays (services.actor.realtime.rest_ticks), any other by its own tick (a
        step, or a stop); then each robot's next tick on the ``heap``."""
        loops = [self.loops[i] for i, _ in run]
        ks = [self._serve(i, now, due) for i, due in run]
        ready = rests.ready(loops, now)
        if ready.all():
            self._rest_ticks(loops, ks, now, rests)
        else:
            rows: list[int] = []
            for j in range(len(run)):
                if ready[j]:
                    rows.append(j)
                    continue
                self._rest_ticks([loops[r] for r in rows], [ks[r] for r in rows], now, rests.take(rows))
                rows = []
                loops[j].tick(ks[j], now)  # a step (or a stop: its state changed, or a second plant)
            self._rest_ticks([loops[r] for r in rows], [ks[r] for r in rows], now, rests.take(rows))
        self._spent(now, len(run))
        self.served += len(run)
        tickers = self.tickers
        for i, _ in run:  # an entry at its own phase, if it was pulled, is now stale
            heapq.heappush(heap, (tickers[i].next_due, i))

    def _rest_ticks(self, loops: list[RealtimeActor], ks: list[int], now: float, rests: Rests) -> None:
        if not loops:
            return
        try:
            rest_ticks(loops, ks, now, rests)
        except Exception:  # never let one bad tick end the loop that keeps every robot safe
            log.exception("actor host: %d ticks at rest failed; commanding zero velocity", len(loops))
            for loop, k in zip(loops, ks, strict=True):
                loop.counts.count("tick_errors")
                loop.stop_robot(k)
                loop.last_step = k

    def _spent(self, now: float, ticks: int = 1) -> None:
        """``ticks`` ticks begun at ``now`` are done: their time, shared, enters the last round's
        (the budget's)."""
        spent = (self.clock() - now) / ticks
        count = len(self.loops)
        for served in range(self.served, self.served + ticks):
            slot = served % count
            self.spent_sum = max(0.0, self.spent_sum + spent - self.spent[slot])
            self.spent[slot] = spent

    def _pull_rests(
        self,
        due: float,
        heap: list[tuple[float, int]],
        deferred: list[tuple[int, float | None]],
        deferred_rests: list[Rests],
    ) -> None:
        """The first group, due at ``due``, is served but its robots at rest (``deferred``): serve
        them now, and with them, at once, the robots of the other groups still at rest whose next
        tick is due within a period (``pull``). A robot is asked when its arrival rule holds it
        (``arrived``), whether its last tick was served at rest or was a step: a group left with
        too few robots at rest for RestCheck takes its steps, and its robots must be pulled all
        the same, or they wake the host every period."""
        candidates = [
            j
            for j in range(self.group, len(self.loops))
            if self.loops[j].arrived and due < self.tickers[j].next_due < due + self.period
        ]
        now = self.clock()
        run, parts = list(deferred), list(deferred_rests)
        if candidates:
            assert self.rests is not None
            pulled = self.rests(candidates, now)
            if pulled is not None:
                run += [(j, None) for j in pulled.at]
                parts.append(pulled)
                self.pulled += len(pulled)
        if run:
            self._serve_rests(run, Rests.joined(parts), now, heap)

    def members(self, i: int, due: float) -> list[int]:
        """The robots of robot ``i``'s tick group whose next tick is due at ``due`` (a robot that
        skipped ticks is due at another time: served as a group of its own)."""
        first = i - i % self.group
        return [j for j in range(first, min(first + self.group, len(self.loops))) if self.tickers[j].next_due == due]

    def flush(self) -> None:
        for box in self.outboxes:
            box.flush()


def robot_status(loop: RealtimeActor, count: RobotCounts) -> Callable[[], dict[str, float]]:
    """One robot's status counters (``srl/<robot>/status/actor``): its own counts and its loop's."""

    def counters() -> dict[str, float]:
        with count.lock:
            values = {k: float(v) for k, v in count.counters.items()}
        values.update(loop.status())
        return values

    return counters


def run_host(
    settings: Settings, bus: Bus, robots: list[str], stop: threading.Event, duration: float | None
) -> FleetActorSummary:
    """The real-time loops of ``robots`` in this process, over one Zenoh session."""
    started = time.monotonic()
    # built once for every robot (one compiled problem per agent, N)
    shared = build_actor(settings)
    log.info(
        "actor host: %d robots, %s N = %d, built in %.1f s",
        len(robots),
        settings.actor.agent,
        settings.actor.horizon,
        time.monotonic() - started,
    )
    loops: list[RealtimeActor] = []
    counts: list[RobotCounts] = []
    inboxes: list[WeightsInbox] = []
    batches = len(robots) > 1
    wire = settings.wire  # the system's messages (the robot's: srl's own)
    outbox = Outbox(bus.round_publisher(wire.ACTION, batches=batches), schema=wire.action)
    # transitions go in batches, a host of one robot's too (common.contracts.keys.Batch.on_demand),
    # through an advanced publisher whose cache keeps transition_cache periods of rounds
    cache = settings.transport.transition_cache * transition_rounds(len(robots), settings.actor.host_tick_group)
    transitions = Outbox(
        bus.round_publisher(wire.TRANSITION, batches=batches, cache=cache, robots=robots),
        "transitions",
        wait=None,
        schema=wire.transition,
    )
    system = settings.system
    replay, tolerances = settings.critic.replay_size, arrival_tolerances(settings)
    ledger = Ledger(len(robots), system.state_dim, system.action_dim, replay, tolerances)
    for row, robot in enumerate(robots):
        own = robot_settings(settings, robot)
        count = RobotCounts(robot, "actor", forward=bus.reject)
        inbox = wire_weights(own, bus)
        actor = RobotActor(shared, ActorMemory(arrival=arrival_rule(own)))
        episode = new_episode_id()
        loop = wire_realtime(own, bus, actor, inbox, count, episode, outbox.put, transitions.put, ledger, row)
        loop.rest_columns = (outbox, transitions)  # ticks at rest put columns, build no message
        loops.append(loop)
        counts.append(count)
        inboxes.append(inbox)
    # every state judged as it arrives (provenance, order, episode: RealtimeActor.on_state), so a
    # forged state just before a tick cannot displace the live plant's newest; a batch's states
    # at once, as arrays where they continue their robots' streams (StateIntake)
    intake = StateIntake(loops)

    def on_states(batch: Columns[Any], source: str | None) -> None:
        intake(batch, source, time.monotonic())

    def on_state(message: Any, source: str | None) -> None:
        intake.alone(message, source, time.monotonic())

    bus.subscribe_columns(wire.STATE, [wire.STATE.key(robot) for robot in robots], on_states, alone=on_state)
    for robot, loop, inbox in zip(robots, loops, inboxes, strict=True):
        bus.declare_alive(robot)
        inbox.reset(loop.episode_id)
    log.info("actor host ready: %d robots in %.1f s", len(robots), time.monotonic() - started)
    rows = [(robot, robot_status(loop, count)) for robot, loop, count in zip(robots, loops, counts, strict=True)]
    log_status: Callable[[dict[str, float]], None] | None = None
    if len(robots) == 1:
        # a host of one robot: the process's counters are the robot's (refusals on the bus: srl up's
        # live line), and its status line is logged at INFO (`docker compose up` shows it; srl up
        # prints the same line from the published status); a host of many logs none (K lines a
        # second are not read by anyone)
        rows = [(robots[0], bus_status(bus, rows[0][1]))]
        first_version: list[float] = []

        def log_status(values: dict[str, float]) -> None:
            log.info("status %s", format_status_line(values, time.monotonic() - started, first_version))

    start_status_thread(bus, rows, settings.transport.status_period, stop, log_status)
    primed = prime_plans(loops, stop, PRIME_WAIT_S)
    log.info("actor host: %d of %d robots primed in %.1f s", primed, len(robots), time.monotonic() - started)
    gc.collect()
    gc.freeze()
    period, groups = settings.plant.sampling_time, tick_groups(len(robots), settings.actor.host_tick_group)
    state_period = 1.0 / settings.transport.state_rate
    # two state periods idle first: a state that came during the solves above waited for the GIL
    # to be taken in, and its arrival time is late by as much, off the states' grid
    stop.wait(2.0 * state_period)
    arrivals = [loop.latest[1] for loop in loops if loop.latest is not None]
    start = aligned_start(
        time.monotonic(),
        max(arrivals, default=None),
        tick_phase_offset(period, groups, state_period),
        state_period,
    )
    scheduler = HostScheduler(
        loops,
        period,
        stop,
        budget=settings.actor.host_cpu_budget,
        group=settings.actor.host_tick_group,
        outboxes=(outbox, transitions),
        # a host whose groups never reach REST_ARRAYS_FROM robots (one robot's) asks for no rests
        rests=RestCheck(settings, loops)
        if min(len(robots), settings.actor.host_tick_group) >= REST_ARRAYS_FROM
        else None,
        start=start,
        pull=True,  # robots at rest tick with the first group: one group tick a period at rest
    )
    try:
        with realtime_priority(settings.actor.realtime_priority, "actor host") as priority:
            end = None if duration is None else time.monotonic() + duration
            scheduler.run(end)
    finally:
        gc.unfreeze()
    log.info(
        "actor host: %d of %d ticks over the CPU budget (%.0f %% of a period) solved in a hurry",
        scheduler.over_budget,
        scheduler.served,
        100 * settings.actor.host_cpu_budget,
    )
    return host_summary(
        robots,
        loops,
        bus,
        {
            "ticks_over_budget": float(scheduler.over_budget),
            "ticks_pulled_at_rest": float(scheduler.pulled),
            "realtime_priority": float(priority),
            "failed_action_rounds": float(outbox.failed_rounds),
            "failed_transition_rounds": float(transitions.failed_rounds),
        },
    )


def prime_plans(loops: list[RealtimeActor], stop: threading.Event, wait: float) -> int:
    """Before the first tick, each robot's first solve (:meth:`RealtimeActor.prime`) from its first
    state, off the schedule; robots whose state has not come within ``wait`` seconds start
    without (they solve cold at their first state). The number primed."""
    deadline = time.monotonic() + wait
    pending = list(range(len(loops)))
    while pending and not stop.is_set():
        waiting = []
        for i in pending:
            if not loops[i].prime():
                waiting.append(i)
        pending = waiting
        if pending and (time.monotonic() >= deadline or stop.wait(0.01)):
            break
    return len(loops) - len(pending)


def host_summary(robots: list[str], loops: list[RealtimeActor], bus: Bus, host: dict[str, float]) -> FleetActorSummary:
    """What ``srl actor --robots`` prints: every robot's own summary, the fleet's view, and the
    process's counters with ``host``'s (:class:`FleetActorSummary`, whatever the number of robots)."""
    per_robot = {
        robot: RealtimeActorSummary.model_validate(loop.summary()) for robot, loop in zip(robots, loops, strict=True)
    }
    return FleetActorSummary(
        robots=robots,
        per_robot=per_robot,
        fleet=fleet_view(per_robot),
        counters={k: float(v) for k, v in bus.counters.items()} | host,
    )
