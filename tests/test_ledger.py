"""An actor host's ledger (services/actor/ledger.py): a tick group's records as array operations
keep exactly what each robot's own records keep, and a weights inbox's published and trained
steps live in its loop's row."""

from __future__ import annotations

import math

import numpy as np
import pytest

from common.config.assembly import arrival_tolerances
from common.config.settings import Settings
from common.contracts.messages import CriticWeights
from common.math.stats import Window, WindowRows
from common.net.provenance import SourceGate
from services.actor.ledger import RUNS_KEPT, Ledger
from services.actor.ports import PUBLISHED, TRAINED, WeightsInbox
from tests.harness import FakeCounts


def test_window_rows_keep_what_a_window_of_each_row_keeps() -> None:
    rng = np.random.default_rng(5)
    rows, windows = WindowRows(4, size=7), [Window(7) for _ in range(4)]
    for _ in range(40):  # past the ring's end: the oldest values overwritten
        chosen = rng.choice(4, size=int(rng.integers(1, 5)), replace=False)
        values = rng.normal(size=len(chosen))
        values[rng.random(len(chosen)) < 0.1] = rng.choice([math.nan, math.inf, -math.inf])
        if rng.random() < 0.5:
            rows.append_rows(chosen, values)
        else:
            for i, value in zip(chosen.tolist(), values.tolist(), strict=True):
                rows.append(i, value)
        for i, value in zip(chosen.tolist(), values.tolist(), strict=True):
            windows[i].append(value)
    for i, window in enumerate(windows):
        row = rows.row(i)
        assert row.count == window.count and len(row) == len(window) and row.count > 7
        assert row.values().tolist() == window.values().tolist()
        assert row.summary(1e3) == window.summary(1e3) and row.last == window.last
    empty = WindowRows(1).row(0)
    assert empty.count == 0 and all(math.isnan(v) for v in empty.summary().values())
    with pytest.raises(ValueError, match="at least one"):
        WindowRows(0)


def ledgers(count: int = 3, replay: int = 4) -> tuple[Ledger, Ledger]:
    tolerances = arrival_tolerances(Settings.load())
    return Ledger(count, 3, 2, replay, tolerances), Ledger(count, 3, 2, replay, tolerances)


def assert_same(one: Ledger, other: Ledger) -> None:
    for name in ("steps", "arrived_steps", "cost", "true_cost", "published_step", "previous_step", "previous"):
        assert np.array_equal(getattr(one, name), getattr(other, name)), name
    for name in ("resting", "newest", "run_first", "run_last", "tail_count"):
        assert np.array_equal(getattr(one, name), getattr(other, name)), name
    for i in range(len(one.steps)):
        assert one.tail_of(i) == other.tail_of(i) and one.runs_of(i) == other.runs_of(i)


def test_a_groups_records_as_arrays_are_each_robots_own_records() -> None:
    """Robots at rest (zero action, the same state), with a gap in one's steps (a new run), a state
    inside and one outside the inner tolerances, one without truth: record_rows and
    published_rows keep what each robot's record and published keep, bit for bit, across the
    tail's ring and the runs."""
    rows_ledger, own_ledger = ledgers()
    states = np.array([[0.01, -0.005, 0.02], [0.04, 0.0, 0.05], [-0.012, 0.004, -0.03]])
    inner = np.array([True, False, True])
    true_costs = np.array([0.25, 0.5, math.nan])
    for i in range(3):  # each robot's first step, a solve that said "arrived"
        for ledger in (rows_ledger, own_ledger):
            ledger.record(i, 0, states[i], (0.0, 0.0), 0.1, 0.2, True, None)
            ledger.published(i, 0, 1.0, [*states[i].tolist(), 0.0, 0.0, 0.1])
    befores = []
    for k in range(1, 9):
        ks = np.array([k, k, k + 5 * (k >= 4)])  # robot 2 skips steps from k = 4 on
        rows = np.arange(3)
        costs = np.array([0.1, 0.2, 0.3]) * k
        got = rows_ledger.record_rows(rows, ks, states, costs, true_costs, np.ones(3, dtype=bool), inner)
        values = np.column_stack([states, np.zeros((3, 2)), costs])
        rows_ledger.published_rows(rows, ks, 2.0 + k, values)
        own = []
        for i in range(3):
            true_cost = None if math.isnan(true_costs[i]) else float(true_costs[i])
            cost = float(costs[i])
            own.append(own_ledger.record(i, int(ks[i]), states[i], (0.0, 0.0), cost, true_cost, True, bool(inner[i])))
            own_ledger.published(i, int(ks[i]), 2.0 + k, values[i].tolist())
        assert [(bool(r), int(n)) for r, n in zip(*got, strict=True)] == own
        befores.append(own)
    assert_same(rows_ledger, own_ledger)
    # what happened: robots 0 rests from its second sample, 1 (outside the inner tolerances) never
    # rests, 2 rests but after its gap; a run per gap
    assert rows_ledger.resting.tolist() == [True, False, True] and rows_ledger.newest.tolist() == [0, 8, 9]
    assert rows_ledger.runs_of(2) == [[0, 3], [9, 13]] and rows_ledger.runs_of(0) == [[0, 8]]
    assert len(rows_ledger.tail_of(0)) == 4 and rows_ledger.tail_of(0)[-1][0] == 8
    assert rows_ledger.true_cost.tolist() == pytest.approx([0.2 + 8 * 0.25, 0.2 + 8 * 0.5, 0.2])


def test_the_runs_kept_are_the_newest_however_many_gaps() -> None:
    ledger = Ledger(1, 3, 2, 4, None)
    for k in range(0, 2 * (RUNS_KEPT + 5), 2):  # every step a gap: a run each
        ledger.published(0, k, 0.0, [0.0] * 6)
    runs = ledger.runs_of(0)
    assert len(runs) == RUNS_KEPT and runs[-1] == [2 * (RUNS_KEPT + 4)] * 2 and runs[0] == [10, 10]


def test_an_inbox_keeps_its_published_and_trained_steps_in_the_row_it_is_bound_to() -> None:
    """A host writes the published step of many robots at once (rest_ticks): the inbox judges
    weights against it, and its accepted weights' trained step is there for the host to read."""
    settings = Settings.load()
    counts = FakeCounts()
    gate = SourceGate("critic")
    gate.update("c1", True)
    inbox = WeightsInbox(settings, counts, gate)  # type: ignore[arg-type]
    inbox.reset(7)
    inbox.published(3)
    marks = np.full((4, 2), -1, dtype=np.int64)
    inbox.bind(marks, 2)
    assert marks[2].tolist() == [3, -1] and inbox.published_step == 3  # carried over

    def weights(trained: int, version: int) -> CriticWeights:
        q = tuple(settings.initial_q_weights().tolist())
        v = tuple(settings.initial_v_weights().tolist())
        return CriticWeights(
            robot="robot1",
            episode=7,
            version=version,
            trained_step=trained,
            q_weights=q,
            v_weights=v,
            q_residual=0.0,
            v_residual=0.0,
            pairs=1,
        )

    inbox.offer(weights(5, 1), "c1")
    assert inbox.current().version == 0 and counts.counters["rejected.critic/weights"] == 1
    marks[2, PUBLISHED] = 5  # as the host's ticks at rest write it
    inbox.offer(weights(5, 2), "c1")
    assert inbox.current().version == 2 and marks[2, TRAINED] == 5 and marks[[0, 1, 3]].max() == -1
    inbox.reset(8)
    assert marks[2].tolist() == [-1, -1]
