"""What the real-time loops of an actor host keep of their robots' runs, one row per robot.

A :class:`~services.actor.realtime.RealtimeActor` records each tick it serves (its cost, its
latency, its weights' staleness, what its critic fits of it, the steps and the transitions it
published) into its row of the host's :class:`Ledger`; a loop of its own (one robot) has a ledger
of one row. A step records one row (:meth:`Ledger.record`); the robots a host serves at rest in
one tick group record theirs as array operations, one per statistic for the whole group
(:meth:`Ledger.record_rows`). Both keep the same values, bit for bit
(``tests/test_host_rest.py``), and the same bounds: the statistics are windows
(:class:`common.math.stats.WindowRows`), the published steps the newest :data:`RUNS_KEPT` runs,
the publication times the newest :data:`PUBLISH_TIMES_KEPT` steps, the transitions' tail the
newest ``replay_size``. Every array is allocated whole when the ledger is made: a loop's memory
never grows while it runs.

A row also holds its robot's newest accepted state (:meth:`Ledger.hold`, :meth:`Ledger.hold_rows`):
its values as arrays, which a host's tick group reads at rest and a step reads as values
(:meth:`Ledger.held_state`), and where it came from (a message, or a batch of states and its row),
built into a message only when a report reads it (:meth:`Ledger.newest_state`). Its loop's lock
is the ledger's (:attr:`Ledger.lock`): a batch of states is taken for all its robots under it.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from collections.abc import Sequence
from typing import Any

import numpy as np

from common.math.arrival import ArrivalTolerances
from common.math.critic import Sample, at_rest, at_rest_rows
from common.math.stats import WindowRow, WindowRows

PUBLISH_TIMES_KEPT = 1000  # steps whose publication time is kept (weight age in ms)
RUNS_KEPT = 1000  # [first, last] runs of published steps kept for the summary (a gap opens a run)
NO_STEP = -(2**62)  # a row's previous sample before its first (no step is the one after it)
ACCEPTED, SEQ = 0, 1  # a row's marks: the states it accepted so far, the newest one's seq


HeldState = tuple[Sequence[float], "Sequence[float] | None", int, float]
"""A robot's newest accepted state as a step reads it from its ledger row (no message built):
``(state, truth, seq, received)``: its values, its true values (None: none sent), its seq and when
it came. A plain tuple, not a NamedTuple: a step reads it on the latency's path, just after its
thread woke, where a NamedTuple's Python-level constructor cost ~8 us (a cold core)."""


class Ledger:
    """``count`` robots' records, row ``i`` robot ``i``'s. ``tolerances``: the arrival rule's, for
    what the critic fits (common.math.critic.at_rest; None: it fits every transition)."""

    def __init__(
        self, count: int, state_dim: int, action_dim: int, replay_size: int, tolerances: ArrivalTolerances | None
    ) -> None:
        self.state_dim, self.action_dim = state_dim, action_dim
        self.tolerances = tolerances
        self.steps = np.zeros(count, dtype=np.int64)
        self.arrived_steps = np.zeros(count, dtype=np.int64)
        self.episode = np.zeros(count, dtype=np.int64)  # each robot's episode id (its loop's)
        # each robot's WeightsInbox.marks: the newest step published, the held weights' trained step
        self.weights = np.full((count, 2), -1, dtype=np.int64)
        self.cost = np.zeros(count)  # the accumulated cost, on the reported states
        self.true_cost = np.zeros(count)  # on the true states, where the plant sends them
        self.latencies, self.staleness_steps, self.staleness_ms = (WindowRows(count) for _ in range(3))
        # when each of the newest steps was published (slot k % KEPT holds step k)
        self.published_step = np.full((count, PUBLISH_TIMES_KEPT), -1, dtype=np.int64)
        self.published_at = np.full((count, PUBLISH_TIMES_KEPT), math.nan)
        # the transitions' tail: rows (k, state, action, cost) in a ring of replay_size
        self.tail = np.zeros((count, replay_size, 2 + state_dim + action_dim))
        self.tail_next = np.zeros(count, dtype=np.intp)
        self.tail_count = np.zeros(count, dtype=np.int64)
        # the runs of published steps: the open one as arrays, the closed ones per robot
        self.run_first = np.full(count, -1, dtype=np.int64)
        self.run_last = np.full(count, NO_STEP, dtype=np.int64)
        self.closed_runs: list[deque[list[int]]] = [deque(maxlen=RUNS_KEPT - 1) for _ in range(count)]
        # what the critic fits (common.math.critic.FitsDue, one per row): the previous sample sent,
        # whether it was at rest, the newest step fitted (-1: none)
        self.previous_step = np.full(count, NO_STEP, dtype=np.int64)
        self.previous = np.zeros((count, state_dim + action_dim))
        self.resting = np.zeros(count, dtype=bool)
        self.newest = np.full(count, -1, dtype=np.int64)
        # each robot's newest accepted state: its values and its truth (a row of ``values``, which a
        # tick group reads at once), the count of states accepted (a tick decided at rest on a
        # state is served so only while it is still the newest) and its seq (a row of ``marks``),
        # when it came; ``held`` False: none yet, or forgotten (a plant gone)
        self.lock = threading.Lock()
        self.values = np.full((count, 2 * state_dim), math.inf)  # (state, truth): inf, none sent (a state is finite)
        self.state, self.truth = self.values[:, :state_dim], self.values[:, state_dim:]
        self.marks = np.zeros((count, 2), dtype=np.int64)  # (ACCEPTED, SEQ)
        self.accepted, self.seq = self.marks[:, ACCEPTED], self.marks[:, SEQ]
        self.received = np.zeros(count)
        self.held = np.zeros(count, dtype=bool)
        # where it came from: a message, or (a batch of states, its row); the (message, received)
        # pair once read (None: not built yet)
        self.came: list[Any] = [None] * count
        self.pairs: list[tuple[Any, float] | None] = [None] * count
        # whether a batch may take a row's next state as arrays (realtime.StateIntake): its last
        # accepted state's source and episode are what it follows, and its order guard and refusal
        # runs are as that acceptance left them (any refusal or change of plant clears it)
        self.follow = np.zeros(count, dtype=bool)
        self.follow_source = np.full(count, "", dtype=object)
        self.follow_episode = np.zeros(count, dtype=np.int64)

    # -- one row: a step -------------------------------------------------------------------
    def record(
        self,
        i: int,
        k: int,
        state: list[float],
        action: tuple[float, ...],
        cost: float,
        true_cost: float | None,
        arrived: bool,
        inner: bool | None,
    ) -> tuple[bool, int]:
        """Row ``i``'s step ``k``: its counts, costs and what its critic fits of it. Returns what the
        critic fitted before it (whether the previous sample was at rest, and the newest step
        fitted), from which the weights' staleness is measured. (At every robot's every step:
        Python values, one numpy read or write per array.)"""
        self.arrived_steps[i] += arrived
        self.cost[i] += cost
        if true_cost is not None:
            self.true_cost[i] += true_cost
        before = (self.resting.item(i), self.newest.item(i))
        n = self.state_dim
        previous_step = self.previous_step.item(i)
        previous = None
        if previous_step != NO_STEP:
            row = self.previous[i].tolist()
            previous = Sample(previous_step, row[:n], row[n:], math.nan)  # at_rest reads no cost
        # at_rest compares lengths and items only: Python lists here, not arrays (~10 times faster)
        resting = at_rest(previous, Sample(k, state, action, cost), self.tolerances, inner)  # type: ignore[arg-type]
        self.resting[i] = resting
        self.previous_step[i] = k
        self.previous[i] = (*state, *action)
        if not resting:
            self.newest[i] = k
        return before

    def published(self, i: int, k: int, now: float, values: list[float]) -> None:
        """Row ``i``'s transition of step ``k`` (``values``: state, action, cost) went out at ``now``."""
        slot = k % PUBLISH_TIMES_KEPT
        self.published_step[i, slot], self.published_at[i, slot] = k, now
        tail = self.tail_next.item(i)
        self.tail[i, tail] = (k, *values)
        self.tail_next[i] = (tail + 1) % self.tail.shape[1]
        self.tail_count[i] += 1
        last = self.run_last.item(i)
        if last != k - 1:  # a gap: the open run is closed, a new one opens
            if last != NO_STEP:
                self.closed_runs[i].append([self.run_first.item(i), last])
            self.run_first[i] = k
        self.run_last[i] = k
        self.steps[i] += 1

    # -- many rows: a tick group at rest -----------------------------------------------------
    def record_rows(
        self,
        rows: np.ndarray,
        ks: np.ndarray,
        states: np.ndarray,
        costs: np.ndarray,
        true_costs: np.ndarray,
        arrived: np.ndarray,
        inner: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`record` of the distinct ``rows`` at once, each of zero action; ``true_costs`` NaN
        where the state carries no truth. Returns ``before`` as arrays."""
        self.arrived_steps[rows] += arrived
        self.cost[rows] += costs
        known = ~np.isnan(true_costs)
        self.true_cost[rows[known]] += true_costs[known]
        before = (self.resting[rows], self.newest[rows])
        n = self.state_dim
        values = np.zeros((len(rows), n + self.action_dim))
        values[:, :n] = states
        if (n, self.action_dim) == (3, 2):  # at_rest's rule is a unicycle's
            resting = at_rest_rows(self.previous_step[rows], self.previous[rows], ks, values, self.tolerances, inner)
        else:
            resting = np.zeros(len(rows), dtype=bool)
        self.resting[rows] = resting
        self.previous_step[rows] = ks
        self.previous[rows] = values
        self.newest[rows] = np.where(resting, before[1], ks)
        return before

    def published_rows(self, rows: np.ndarray, ks: np.ndarray, now: float, values: np.ndarray) -> None:
        """:meth:`published` of the distinct ``rows`` at once (``values``: a row each)."""
        slots = ks % PUBLISH_TIMES_KEPT
        self.published_step[rows, slots], self.published_at[rows, slots] = ks, now
        self.tail[rows, self.tail_next[rows], 0] = ks
        self.tail[rows, self.tail_next[rows], 1:] = values
        self.tail_next[rows] = (self.tail_next[rows] + 1) % self.tail.shape[1]
        self.tail_count[rows] += 1
        extends = self.run_last[rows] == ks - 1
        for j in np.flatnonzero(~extends).tolist():  # a gap closes a run: rare, per robot
            i = int(rows[j])
            if self.run_last[i] != NO_STEP:
                self.closed_runs[i].append([int(self.run_first[i]), int(self.run_last[i])])
            self.run_first[i] = ks[j]
        self.run_last[rows] = ks
        self.steps[rows] += 1

    # -- the newest accepted state (under :attr:`lock`) ------------------------------------------
    def hold(self, i: int, message: Any, received: float, source: str) -> None:
        """Row ``i``'s newest accepted state is ``message`` (a PlantState of the system), from
        ``source``, which arrived at ``received``; the row's next state may come as arrays."""
        self.state[i] = message.state
        self.truth[i] = math.inf if message.true_state is None else message.true_state
        self.seq[i], self.received[i] = message.seq, received
        self.accepted[i] += 1
        self.held[i] = True
        self.came[i], self.pairs[i] = message, (message, received)
        self.follow[i], self.follow_source[i], self.follow_episode[i] = True, source, message.episode

    def hold_rows(self, rows: np.ndarray, batch: Any, taken: np.ndarray, received: float) -> None:
        """:meth:`hold` of the distinct ``rows`` at once: rows ``taken`` of ``batch`` (Columns of
        states), of the source and episode each row follows already."""
        self.state[rows] = batch.field("state")[taken]
        truth = batch.field("true_state")[taken]  # NaN rows: none sent
        self.truth[rows] = np.where(np.isnan(truth), math.inf, truth)
        self.seq[rows] = batch.field("seq")[taken]
        self.received[rows] = received
        self.accepted[rows] += 1
        self.held[rows] = True
        came, pairs = self.came, self.pairs
        for i, row in zip(rows.tolist(), taken.tolist(), strict=True):
            came[i], pairs[i] = (batch, row), None

    def held_state(self, i: int) -> HeldState:
        """Row ``i``'s newest accepted state as values (held or not): read from its message when it
        came as one (a robot's own key: one robot's path, where a tick reads it just after waking
        and five reads of the arrays cost ~15 us on a cold core), else from the row's arrays; the
        same values either way (the arrays were written from the message)."""
        pair = self.pairs[i]
        if pair is not None:
            message, received = pair
            return message.state, message.true_state, message.seq, received
        values = self.values[i].tolist()
        n = self.state_dim
        truth = values[n:]
        return values[:n], None if truth[0] == math.inf else truth, self.seq.item(i), self.received.item(i)

    def fresh_state(self, i: int, now: float, stale_after: float) -> HeldState | None:
        """:meth:`held_state` of row ``i`` if it holds a state that came at most ``stale_after``
        before ``now``; else None (a tick then stops its robot). A tick calls it just after waking:
        when the state came as a message, one read of the arrays (``held``)."""
        if not self.held.item(i):
            return None
        held = self.held_state(i)
        return None if now - held[3] > stale_after else held

    def newest_state(self, i: int) -> tuple[Any, float] | None:
        """Row ``i``'s newest accepted state and when it came, built once (None: none yet)."""
        pair = self.pairs[i]
        if pair is None:
            came = self.came[i]
            if came is None:
                return None
            batch, row = came
            pair = self.pairs[i] = (batch.item(row), self.received.item(i))
        return pair

    # -- reading a row ---------------------------------------------------------------------
    def windows(self, i: int) -> tuple[WindowRow, WindowRow, WindowRow]:
        """Row ``i``'s latency, staleness (steps) and staleness (ms) windows."""
        return self.latencies.row(i), self.staleness_steps.row(i), self.staleness_ms.row(i)

    def tail_of(self, i: int) -> list[list[float]]:
        """Row ``i``'s newest transitions, oldest first: ``[k, *state, *action, cost]`` each."""
        size = self.tail.shape[1]
        count = min(int(self.tail_count[i]), size)
        start = (int(self.tail_next[i]) - count) % size
        rows = self.tail[i, (start + np.arange(count)) % size]
        return [[int(row[0]), *row[1:].tolist()] for row in rows]

    def runs_of(self, i: int) -> list[list[int]]:
        """Row ``i``'s runs of published steps, ``[first, last]`` each, oldest first."""
        runs = [list(run) for run in self.closed_runs[i]]
        if self.run_last[i] != NO_STEP:
            runs.append([int(self.run_first[i]), int(self.run_last[i])])
        return runs
