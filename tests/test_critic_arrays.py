"""The critic takes a batch as arrays (services/critic/service.py ``CriticLearner.take_batch``).

The contract: a batch's common rows (one per robot, the step after its newest, no fit to make)
are taken as arrays, the others one by one, and everything comes out as the row path made it,
transition by transition -- the published weights (values, versions, order), the steps the
history recovery is asked for, the counters, the replays and the checkpoint -- for robots
driving, at rest, between the arrival rule's tolerances, with duplicates, late and too old
steps, new and stale episodes, a robot joining late, a robot with several rows in a batch, a
checkpoint's continuation, per-robot and pooled, coalescing or not."""

from __future__ import annotations

import copy
from typing import Any

import numpy as np
import pytest

from common.config.settings import Settings
from common.contracts.columns import Columns, batch_payloads, decode_columns
from common.contracts.messages import CriticWeights, Transition
from services.critic.service import CriticLearner, Row, coalesced_fits

REST = (0.01, -0.005, 0.02)  # inside the arrival rule's inner tolerances (0.03 m, 0.1 rad)
OTHER_REST = (-0.004, 0.012, -0.05)
BETWEEN = (0.04, 0.0, 0.0)  # beyond the inner position tolerance, within the outer (0.045 m)
ROBOTS = ("drive", "stop", "rest", "between", "dup", "again", "late", "episode", "joiner", "old", "twice", "mover")


def scenario(ticks: int = 60, seed: int = 11) -> list[list[Transition]]:
    """One batch of transitions per tick (the last ones several ticks in one batch: a critic
    behind); each robot's story in its comment."""
    rng = np.random.default_rng(seed)
    batches: list[list[Transition]] = []
    rows: list[Transition] = []  # the tick's

    def add(robot: str, step: int, state: tuple[float, ...] | None = None, episode: int = 1) -> None:
        """A transition of the tick: at ``state`` with a zero command, or driving (None)."""
        moving = state is None
        rows.append(
            Transition(
                robot=robot,
                episode=episode,
                step=step,
                state=tuple(float(x) for x in rng.uniform(-1.0, 1.0, 3)) if state is None else state,
                action=tuple(float(x) for x in rng.uniform(-0.2, 0.2, 2)) if moving else (0.0, 0.0),
                cost=float(rng.uniform(0.0, 1.0)) if moving else 1e-6,
            )
        )

    for k in range(ticks):
        add("drive", k)  # drives: a fit due at every step
        add("stop", k, None if k < 10 else REST)  # drives, then stops: fitted once more, then at rest
        add("rest", k, OTHER_REST)  # at rest from its first step
        add("between", k, BETWEEN)  # a zero command between the tolerances: every due fit made
        add("dup", k, REST)
        if k == 12:
            add("dup", 11, REST)  # its previous step again, in the same batch
        if k == 20:
            add("again", 15, REST)  # re-delivered, alone in its batch: a duplicate
        elif k == 21:
            add("again", 20, REST)
            add("again", 21, REST)
        else:
            add("again", k, REST)
        if k != 20:  # step 20 held back three ticks: a late step
            add("late", k, REST)
        if k == 23:
            add("late", 20, REST)
        if k < 30:
            add("episode", k, REST)
        elif k == 35:
            add("episode", 35, REST, episode=1)  # of the episode before, alone: stale
        else:
            add("episode", k - 30, REST, episode=2)  # a new episode
        if k >= 15:
            add("joiner", k, REST)  # heard first at step 15: the steps before it are missing
        if k == 40:
            add("old", 5, REST)  # far behind its newest, alone in its batch: too old
        elif k == 41:
            add("old", 40, REST)
            add("old", 41, REST)
        else:
            add("old", k, REST)
        if k < 25:
            add("twice", k)
        elif k == 25:
            add("twice", 25)
            add("twice", 26)  # two steps in one batch
        else:
            add("twice", k + 1)
        add("mover", k, REST if k < 35 else OTHER_REST)  # at rest, moved once (fitted), at rest again
        batches.append(rows.copy())
        rows.clear()
    # a critic behind: the last ticks come three at a time
    return [*batches[:-6], batches[-6] + batches[-5] + batches[-4], batches[-3] + batches[-2] + batches[-1]]


def columns(batch: list[Transition]) -> Columns[Transition]:
    """The batch as the critic's intake hands it over: decoded from its payload."""
    (payload,) = batch_payloads(batch)
    return decode_columns(Transition, payload)


def rows_of(batch: Columns[Transition]) -> list[Row]:
    """Every row of a batch as a :class:`Row`, as the critic took them one by one."""
    states, actions = np.array(batch.field("state")), np.array(batch.field("action"))
    episodes, steps, costs = (batch.field(name).tolist() for name in ("episode", "step", "cost"))
    return [Row(robot, episodes[i], steps[i], states[i], actions[i], costs[i]) for i, robot in enumerate(batch.robots)]


class Outputs:
    """What a critic hands the service while it takes a batch."""

    def __init__(self) -> None:
        self.published: list[CriticWeights] = []
        self.missing: list[tuple[str, int, range]] = []

    def continued(self, weights: CriticWeights) -> None:
        self.published.append(weights)

    def need(self, robot: str, episode: int, steps: range) -> None:
        self.missing.append((robot, episode, steps))


def take_row_by_row(
    learner: CriticLearner, batch: Columns[Transition], coalesce: bool, heard: set[str], out: Outputs
) -> None:
    """The batch through the row path: every row on its own, in order (confirm, the first row of
    a robot, take), then the batch's end (flush)."""
    rows = rows_of(batch)
    repeats = coalesce and len({row.robot for row in rows}) < len(rows)
    update_every = learner.settings.critic.update_every
    superseded = coalesced_fits(rows, update_every, learner.resting(rows)) if repeats else set()
    defer = coalesce and learner.pool is not None
    outgoing = []
    for index, row in enumerate(rows):
        continued = learner.confirm(row)
        if continued is not None:
            out.continued(continued)
        if row.robot not in heard:
            heard.add(row.robot)
            missing = learner.missing_before(row)
            if missing:
                out.need(row.robot, row.episode, missing)
        outgoing += learner.take(row, fit=not defer and index not in superseded, defer=True)
    out.published += outgoing + learner.flush()


COUNTERS = (
    "received",
    "accepted",
    "duplicates",
    "too_old",
    "stale_episode",
    "fits_at_rest",
    "fits_coalesced",
    "version",
)


def everything(learner: CriticLearner) -> dict[str, Any]:
    """Counters, the checkpoint, and each replay's samples and rings as they are read back."""
    return {
        **{name: getattr(learner, name) for name in COUNTERS},
        "state": learner.state(),
        "replays": {
            robot: (
                [(s.step, s.state.tolist(), s.action.tolist(), s.cost) for s in x.replay.samples],
                x.replay.table().tolist(),
                (x.replay.start, x.replay.steps.tolist(), x.replay.rows.tolist()),  # the rings, slot for slot
            )
            for robot, x in learner.learners.items()
        },
        "fitted": {robot: (x.fitted, x.newest, x.seen.runs()) for robot, x in learner.learners.items()},
    }


def restarted(learner: CriticLearner, settings: Settings) -> CriticLearner:
    """A critic restarted from ``learner``'s checkpoint (its versions go on from the same count)."""
    again = CriticLearner(settings, fleet_size=learner.fleet_size)
    again.restore(copy.deepcopy(learner.state()))
    again.version = learner.version
    return again


@pytest.mark.parametrize("pooled", [False, True])
@pytest.mark.parametrize("coalesce", [False, True])
@pytest.mark.parametrize("update_every", [1, 2])
def test_a_batch_taken_as_arrays_is_the_row_path_bit_for_bit(
    pooled: bool, coalesce: bool, update_every: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    settings = Settings.load(
        critic={"checkpoint": "", "replay_size": 5, "update_every": update_every, "pooled": pooled},
        transport={"transition_cache": 5},  # a retention of 10 steps: "old"'s step 5 is too old at 40
    )
    size = len(ROBOTS) if pooled else None
    old, new = CriticLearner(settings, fleet_size=size), CriticLearner(settings, fleet_size=size)
    new.version = old.version  # versions start from the clock
    heard: set[str] = set()
    rows_taken: list[int] = []
    take = CriticLearner.take
    monkeypatch.setattr(CriticLearner, "take", lambda self, *a, **kw: rows_taken.append(1) or take(self, *a, **kw))
    total, asked = 0, []
    for tick, transitions in enumerate(scenario()):
        if tick == 45:  # both restart from their checkpoints: each robot's learner continues its run
            assert old.duplicates == 2 and old.too_old == 1 and old.stale_episode == 1
            at_rest = old.fits_at_rest
            old, new, heard = restarted(old, settings), restarted(new, settings), set()
        if tick == 46:  # ... but this one's first transition after it is of a new run
            transitions = [t.model_copy(update={"episode": 3}) if t.robot == "episode" else t for t in transitions]
        batch = columns(transitions)
        by_rows, by_arrays = Outputs(), Outputs()
        before = len(rows_taken)
        take_row_by_row(old, batch, coalesce, heard, by_rows)
        total += len(rows_taken) - before
        before = len(rows_taken)
        by_arrays.published += new.take_batch(batch, coalesce, by_arrays.continued, by_arrays.need)
        total -= len(rows_taken) - before  # the rows taken one by one by the new path
        assert by_arrays.published == by_rows.published, tick
        assert by_arrays.missing == by_rows.missing, tick
        asked += by_rows.missing
        assert everything(new) == everything(old), tick
        assert new.heard == heard
    assert asked == [("joiner", 1, range(6, 15))]  # its steps before the first heard, within the retention
    if pooled:
        assert total == 0  # the pooled learner fits the fleet as it steps: every row on its own
    else:
        assert at_rest + old.fits_at_rest > 300 // update_every and total > 400  # most rows taken as arrays
        assert old.fits_coalesced > 0 if coalesce else old.fits_coalesced == 0


def test_a_fit_left_to_the_batchs_end_is_made_first_as_take_makes_it() -> None:
    """A robot whose due fit :meth:`CriticLearner.take` left to the batch's end (``defer``) is
    fitted on its replay as it was before its next row enters, also when that row, at rest,
    would be a common one."""
    settings = Settings.load(critic={"checkpoint": ""})
    states = [(0.5, 0.5, 0.0), REST, REST]  # it arrives at step 1 (a fit due), rests at step 2
    stream = [
        Transition(robot="a", episode=1, step=k, state=s, action=(0.0, 0.0), cost=0.1) for k, s in enumerate(states)
    ]
    old, new = CriticLearner(settings), CriticLearner(settings)
    new.version = old.version
    heard: set[str] = set()
    take_row_by_row(old, columns(stream[:1]), False, heard, Outputs())
    new.take_batch(columns(stream[:1]))
    for learner in (old, new):
        assert learner.take(stream[1], defer=True) == [] and set(learner.due) == {"a"}
    by_rows = Outputs()
    take_row_by_row(old, columns(stream[2:]), False, heard, by_rows)
    assert [w.trained_step for w in by_rows.published] == [1] and old.fits_at_rest == 1
    assert new.take_batch(columns(stream[2:])) == by_rows.published
    assert everything(new) == everything(old)
