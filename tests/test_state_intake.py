"""An actor host takes a batch of states at once (services/actor/realtime.py StateIntake): the
states that continue their robots' streams as arrays, the others one by one through
RealtimeActor.on_state. Whatever comes (forged sources, other episodes, old, repeated and
far-ahead seqs, a robot twice in a batch, states alone on a robot's key among the batches, plants
that appear and vanish), each robot holds and
counts what its own on_state, fed the same states one by one, holds and counts."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from common.config.assembly import arrival_tolerances
from common.config.settings import Settings
from common.contracts.columns import columns_of
from common.contracts.messages import PlantState
from common.math.actor_problem import ActorMemory
from common.net.provenance import SourceGate
from services.actor.host import RestCheck, RobotActor
from services.actor.ledger import HeldState, Ledger
from services.actor.ports import WeightsInbox
from services.actor.realtime import MAX_SEQ_JUMP, RealtimeActor, StateIntake
from tests.harness import FakeCounts

ROBOTS = ("a", "b", "c")
SETTINGS = Settings.load(actor={"jit": False})


class Clock:
    def __init__(self) -> None:
        self.now = 5.0

    def __call__(self) -> float:
        return self.now


def host(clock: Clock) -> list[RealtimeActor]:
    """Three loops of one ledger (a host's), their actor never stepped, plant p1 live."""
    system = SETTINGS.system
    ledger = Ledger(
        len(ROBOTS), system.state_dim, system.action_dim, SETTINGS.critic.replay_size, arrival_tolerances(SETTINGS)
    )
    loops = []
    for row, robot in enumerate(ROBOTS):
        own = SETTINGS.model_copy(update={"transport": SETTINGS.transport.model_copy(update={"robot": robot})})
        counts = FakeCounts()
        inbox = WeightsInbox(own, counts, SourceGate("critic"))  # type: ignore[arg-type]
        actor = RobotActor(None, ActorMemory())  # type: ignore[arg-type]
        loop = RealtimeActor(own, actor, inbox, print, print, counts, 7, clock=clock, ledger=ledger, row=row)
        loop.plant_gate.update("p1", True)
        loop.on_plant_identity("p1", True)
        loops.append(loop)
    return loops


def step_reads(held: HeldState) -> tuple[Any, ...]:
    """What a step reads of a held state: its values (a message's tuple or the arrays' list alike)."""
    state, truth, seq, received = held
    return list(state), None if truth is None else list(truth), seq, received


def seen(loop: RealtimeActor) -> tuple[Any, ...]:
    """What a loop shows of its states: the held one and when it came, the newest accepted, its
    counters, the refusals' marks."""
    latest = loop.latest
    last = loop.last_accepted
    return (
        None if latest is None else (latest[0].model_dump(), latest[1]),
        None if latest is None else step_reads(loop.ledger.held_state(loop.row)),
        None if last is None else last.model_dump(),
        dict(loop.counts.counters),  # type: ignore[attr-defined]
        loop.refused_at,
        loop.order.resyncs,
    )


SEQS = st.one_of(
    *[st.integers(-3, 3)] * 4,  # a step back, a repeat, the next ones
    st.sampled_from([MAX_SEQ_JUMP, MAX_SEQ_JUMP + 1, 2 * MAX_SEQ_JUMP + 5, -(2**40)]),  # far back: seq 0
)
ROW = st.tuples(st.sampled_from(ROBOTS), st.sampled_from([0] * 6 + [1]), SEQS, st.floats(-2.0, 2.0))
# mostly the live plant's batches (the path taken as arrays), among forgeries and plants' changes
EVENT = st.one_of(
    *[st.tuples(st.just("batch"), st.just("p1"), st.lists(ROW, min_size=1, max_size=5))] * 6,
    st.tuples(st.just("batch"), st.sampled_from(["p2", None]), st.lists(ROW, min_size=1, max_size=5)),
    st.tuples(st.just("alone"), st.sampled_from(["p1", "p1", "p2"]), st.lists(ROW, min_size=1, max_size=1)),
    st.tuples(st.just("identity"), st.sampled_from(["p1", "p2"]), st.booleans()),
    st.tuples(st.just("token"), st.just(""), st.just(False)),
)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(EVENT, min_size=1, max_size=40), st.booleans())
def test_a_batch_of_states_is_taken_as_each_state_alone(events: list[Any], truth: bool) -> None:
    clock = Clock()
    batched, alone = host(clock), host(clock)
    intake = StateIntake(batched)
    streams = dict.fromkeys(ROBOTS, 0)  # each robot's real seq, counting on
    for kind, source, detail in events:
        clock.now += 0.02
        if kind == "identity":
            for loops in (batched, alone):
                for loop in loops:
                    loop.plant_gate.update(source, detail)
                    loop.on_plant_identity(source, detail)
        elif kind == "token":
            for loops in (batched, alone):
                loops[0].on_plant_token(False)
        else:
            messages = []
            for robot, episode, step, x in detail:
                streams[robot] += 1
                seq = max(0, streams[robot] + step)
                state = (x, 0.5, 0.1)
                messages.append(
                    PlantState(
                        robot=robot,
                        episode=episode,
                        seq=seq,
                        stamp_ns=0,
                        state=state,
                        true_state=state if truth else None,
                        source="sim",
                    )
                )
            if kind == "alone":  # on its robot's key (a robot bridge's)
                intake.alone(messages[0], source, clock.now)
            else:
                intake(columns_of(PlantState, messages), source, clock.now)
            for message in messages:
                alone[ROBOTS.index(message.robot)].on_state(message, source, clock.now)
        for ours, theirs in zip(batched, alone, strict=True):
            assert seen(ours) == seen(theirs)


def test_the_common_states_are_held_without_a_message_and_read_as_the_arrays_say() -> None:
    """The control: a plant streaming in order is taken as arrays (the ledger follows it; no
    message is built until one is read), and a forged far-ahead seq is refused as alone."""
    clock = Clock()
    loops = host(clock)
    ledger = loops[0].ledger
    intake = StateIntake(loops)

    def states(seq: int, x: float) -> Any:
        return columns_of(
            PlantState,
            [PlantState(robot=r, episode=0, seq=seq, stamp_ns=0, state=(x, 0.0, 0.0), source="sim") for r in ROBOTS],
        )

    intake(columns_of(PlantState, []), "p1", 0.5)  # an empty batch: nothing
    assert not ledger.held.any() and not ledger.follow.any()
    intake(states(1, 0.1), "p1", 1.0)  # the first state of each: one by one
    assert ledger.follow.all() and all(pair is not None for pair in ledger.pairs)
    intake(states(2, 0.2), "p1", 2.0)
    assert ledger.follow.all() and ledger.pairs == [None] * 3  # taken as arrays: nothing built
    assert ledger.state[:, 0].tolist() == [0.2] * 3 and ledger.accepted.tolist() == [2] * 3
    assert np.isinf(ledger.truth).all() and ledger.received.tolist() == [2.0] * 3
    latest = loops[1].latest
    assert latest is not None and latest[0].seq == 2 and latest[0].state == (0.2, 0.0, 0.0) and latest[1] == 2.0
    intake(states(2 + MAX_SEQ_JUMP + 1, 0.9), "p1", 3.0)  # too far ahead: refused
    assert not ledger.follow.any() and ledger.accepted.tolist() == [2] * 3
    assert all(loop.counts.counters["rejected.state"] == 1 for loop in loops)  # type: ignore[attr-defined]
    intake(states(3, 0.3), "p1", 4.0)  # the stream goes on: one by one, then followed again
    assert ledger.follow.all() and ledger.state[:, 0].tolist() == [0.3] * 3


def test_a_rest_check_refuses_loops_of_two_ledgers() -> None:
    """It reads one ledger's rows: loops of two hosts are refused when it is made, not misread."""
    clock = Clock()
    one, other = host(clock), host(clock)
    with pytest.raises(ValueError, match="one ledger"):
        RestCheck(SETTINGS, [one[0], other[1]])
    assert RestCheck(SETTINGS, one).loops == one  # the control: one host's loops


def test_a_state_intake_is_made_of_one_hosts_loops_each_once() -> None:
    """It holds states in one ledger's rows, a robot's in its own: loops of two hosts, a robot
    twice, or none are refused when it is made (a ValueError), not misread at every batch."""
    clock = Clock()
    one, other = host(clock), host(clock)
    for loops, why in (([one[0], other[1]], "one ledger"), ([one[0], one[0]], "once"), ([], "no loop")):
        with pytest.raises(ValueError, match=why):
            StateIntake(loops)
    assert StateIntake(one).robots == {loop.robot: (loop, loop.row) for loop in one}  # the control
