"""An actor host serves the robots its arrival rule holds at rest as arrays (services/actor/host.py
RestCheck, RealtimeActor.tick with an AtRest): the same actions, transitions and summaries as each robot's
own step, bit for bit; only the work differs."""

from __future__ import annotations

import math
import threading
from typing import Any

import numpy as np
import pytest

from common.config.assembly import arrival_rule, arrival_tolerances, build_actor
from common.config.settings import Settings
from common.contracts.columns import Columns, check_columns, decode_columns, encode_columns
from common.contracts.messages import Action, PlantState, Transition
from common.math.actor_problem import ActorMemory
from common.math.arrival import arrival_masks, arrival_update
from common.math.dynamics import exact_step
from common.math.features import stage_cost, stage_cost_rows
from common.net.provenance import SourceGate
from services.actor.host import HostScheduler, Outbox, RestCheck, RobotActor
from services.actor.ledger import Ledger
from services.actor.ports import WeightsInbox
from services.actor.realtime import AtRest, RealtimeActor, Rests
from tests.harness import FakeCounts

DELTA = 0.1
TICKS = 70


def test_the_group_arrival_test_is_each_robots_own_including_its_edges() -> None:
    tolerances = arrival_tolerances(Settings.load())
    assert tolerances is not None
    rng = np.random.default_rng(3)
    edge = tolerances.position / math.sqrt(2.0)  # on the position tolerance's circle
    turns = 2.0 * math.pi * rng.integers(-40, 40, 400)
    states = np.vstack(
        [
            rng.uniform(-0.06, 0.06, (2000, 3)) * [1.0, 1.0, 4.0],
            np.column_stack([np.full(400, edge), np.full(400, edge), turns + rng.uniform(-0.2, 0.2, 400)]),
            np.column_stack([np.zeros(400), np.zeros(400), turns + np.pi * rng.choice([-1.0, 1.0], 400)]),
            [[math.nan, 0.0, 0.0], [0.0, math.inf, 0.0], [0.0, 0.0, -math.inf]],
        ]
    )
    inner, outer = arrival_masks(states, tolerances)
    for arrived, ours in ((False, inner), (True, outer)):
        assert ours.tolist() == [arrival_update(arrived, state, tolerances) for state in states]
    assert 0 < inner.sum() < outer.sum() < len(states)  # every answer occurs


def test_the_stage_cost_of_many_rows_is_each_rows_bit_for_bit() -> None:
    rng = np.random.default_rng(4)
    r_diag = Settings.load().r_diag
    states, actions = rng.normal(size=(500, 3)) * 3.0, rng.normal(size=(500, 2))
    rows = stage_cost_rows(states, actions, r_diag)
    assert [float(c) for c in rows] == [float(stage_cost(s, a, r_diag)) for s, a in zip(states, actions, strict=True)]


class FakeClock:
    def __init__(self) -> None:
        self.now = 10.0
        self.on_sleep: Any = None

    def clock(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> bool:
        self.now += seconds
        if self.on_sleep is not None:
            self.on_sleep()
        return False


# Robot a and d are parked (d like a real robot: no truth), b is parked, pushed between the inner
# and the outer tolerances, then pushed out of them (its actor resumes), c drives in from 0.25 m.
STARTS = {
    "a": (0.01, -0.005, 0.02),
    "b": (0.02, 0.01, 0.05),
    "c": (0.25, 0.15, 0.0),
    "d": (-0.012, 0.004, -0.03),
}
PUSHES = {("b", 15): (0.04, 0.0, 0.05), ("b", 30): (0.2, 0.1, 0.3), ("d", 20): (0.1, 0.05, 0.1)}


def run_host(
    rest: bool,
    arrays_from: int = 1,
    outboxes: bool = False,
    rows: bool = False,
    pull: bool = False,
    starts: dict[str, tuple[float, float, float]] = STARTS,
    group: int = 2,
) -> tuple[list[Action], list[Any], list[dict[str, Any]], int, HostScheduler, list[float]]:
    """The four robots on one built actor, a fake plant and a fake clock, for :data:`TICKS`
    periods; ``rest``: with the host's RestCheck (deciding groups of ``arrays_from`` robots or more
    as arrays). What the host sent (each transition with what
    the robot's loop then knew of its critic's fits, and its actor's memory), each robot's
    summary, and the robot ticks served at rest. ``outboxes``: what the robots send goes in
    rounds, as an actor host sends them (services/actor/host.py Outbox: a round of messages, or
    with ``rows`` (ticks at rest put rows) a batch of columns, each sent encoded and decoded as on
    the wire); the fourth value is then the rounds sent as columns. ``pull``: robots at rest tick
    with the first group (HostScheduler's ``pull``). Then the scheduler, and the times the host's
    thread woke. ``starts`` and ``group``: other robots, another tick group."""
    settings = Settings.load(actor={"jit": False, "host_tick_group": group})
    shared = build_actor(settings)
    fake = FakeClock()
    actions: list[Action] = []
    transitions: list[Any] = []
    loops: list[RealtimeActor] = []
    truths = {}
    column_rounds = [0]

    def wire(deliver: Any) -> Any:
        def send(round_: Any) -> None:
            if isinstance(round_, Columns):
                column_rounds[0] += 1
                check_columns(round_)
                for payload in encode_columns(round_):
                    for message in decode_columns(round_.schema, payload).items():
                        deliver(message)
            else:
                for message in round_:
                    deliver(message)

        return send

    def sent(transition: Transition) -> None:
        loop = next(loop for loop in loops if loop.robot == transition.robot)
        actor = loop.actor
        assert isinstance(actor, RobotActor) and actor.memory.arrival is not None
        arrival = actor.memory.arrival
        memory = (
            actor.counters.arrived_steps,
            actor.counters.solves,
            arrival.arrived,
            arrival.arrivals,
            arrival.docked,
        )
        fits = (bool(loop.ledger.resting[loop.row]), int(loop.ledger.newest[loop.row]))
        transitions.append((transition, *fits, memory))

    boxes = (
        (
            Outbox(wire(actions.append), clock=fake.clock, schema=Action),
            Outbox(wire(sent), wait=None, schema=Transition),
        )
        if outboxes
        else None
    )
    system = settings.system
    ledger = Ledger(
        len(starts), system.state_dim, system.action_dim, settings.critic.replay_size, arrival_tolerances(settings)
    )
    for row, (robot, start) in enumerate(starts.items()):
        own = settings.model_copy(update={"transport": settings.transport.model_copy(update={"robot": robot})})
        counts = FakeCounts()
        critic = SourceGate("critic")
        critic.update("c1", True)
        inbox = WeightsInbox(own, counts, critic)  # type: ignore[arg-type]
        actor = RobotActor(shared, ActorMemory(arrival=arrival_rule(own)))
        if boxes is None:
            loop = RealtimeActor(
                own, actor, inbox, actions.append, sent, counts, 7, clock=fake.clock, ledger=ledger, row=row
            )
        else:
            publish = (boxes[0].put, boxes[1].put)
            loop = RealtimeActor(own, actor, inbox, *publish, counts, 7, clock=fake.clock, ledger=ledger, row=row)
            loop.rest_columns = boxes if rows else None
        inbox.reset(7)
        loop.plant_gate.update("p1", True)
        loops.append(loop)
        truths[robot] = np.array(start)
    seq = [0]
    last = [fake.now]

    def plant() -> None:  # every robot moved by its last action since the last wake-up, then published
        elapsed = fake.now - last[0]
        last[0] = fake.now
        seq[0] += 1
        held = {a.robot: np.array(a.action) for a in actions}
        for loop in loops:
            robot = loop.robot
            truths[robot] = exact_step(truths[robot], held.get(robot, np.zeros(2)), elapsed)
            push = PUSHES.get((robot, int((fake.now - 10.0) / DELTA)))
            if push is not None:
                truths[robot] = np.array(push)
            state = tuple(float(c) for c in truths[robot])
            message = PlantState(
                robot=robot,
                episode=0,
                seq=seq[0],
                stamp_ns=0,
                state=state,  # type: ignore[arg-type]
                source="sim",
                true_state=None if robot == "d" else state,  # type: ignore[arg-type]
            )
            loop.on_state(message, "p1", fake.now)

    plant()
    woke: list[float] = []

    def wake() -> None:
        woke.append(fake.now)
        plant()

    fake.on_sleep = wake
    served = [0]
    check = RestCheck(settings, loops, arrays_from)

    def counted(members: Any, now: float) -> Rests | None:
        rests = check(members, now)
        served[0] += 0 if rests is None else len(rests)
        return rests

    scheduler = HostScheduler(
        loops,
        DELTA,
        threading.Event(),
        clock=fake.clock,
        sleep=fake.sleep,
        group=group,
        rests=counted if rest else None,
        outboxes=() if boxes is None else boxes,
        pull=pull,
    )
    scheduler.run(end=fake.now + TICKS * DELTA, manual_gc=False)
    summaries = [loop.summary() for loop in loops]
    return actions, transitions, summaries, column_rounds[0] if outboxes else served[0], scheduler, woke


TIMING = ("loop", "solve_ms", "latency_ms", "staleness_ms")


def assert_sent_alike(ours: tuple[Any, ...], theirs: tuple[Any, ...]) -> None:
    """Two of :func:`run_host`'s runs sent the same: every action (but its stamp), every
    transition (every field: state, action, cost; with the fits and memory its loop then knew),
    in the same order, and each robot's summary but its timings."""
    assert len(ours[0]) == len(theirs[0])
    for mine, other in zip(ours[0], theirs[0], strict=True):
        assert (mine.robot, mine.step, mine.action, mine.state_seq) == (
            other.robot,
            other.step,
            other.action,
            other.state_seq,
        )
    assert ours[1] == theirs[1]
    for mine, other in zip(ours[2], theirs[2], strict=True):
        assert {k: v for k, v in mine.items() if k not in TIMING} == {k: v for k, v in other.items() if k not in TIMING}


@pytest.mark.parametrize("arrays_from", [1, 3])  # groups of two: as arrays; their steps (too few)
def test_robots_at_rest_served_as_arrays_send_and_report_what_their_own_steps_do(arrays_from: int) -> None:
    rested, step = run_host(rest=True, arrays_from=arrays_from), run_host(rest=False)
    # the rest path served exactly the ticks whose step found the robot arrived after an arrived step
    held: dict[str, bool] = {}
    expected = 0
    for transition, _, _, memory in step[1]:
        arrived = memory[2]
        expected += arrived and held.get(transition.robot, False)
        held[transition.robot] = arrived
    assert step[3] == 0 and rested[3] == (expected if arrays_from <= 2 else 0) and expected > TICKS
    assert_sent_alike(rested, step)
    by_robot = dict(zip(STARTS, rested[2], strict=True))
    # what the scenario says happened: c drove in and rests, b left its rest and came back, d has no truth
    sent = [t for t, *_ in rested[1]]
    assert [t.action for t in sent if t.robot == "c"][-5:] == [(0.0, 0.0)] * 5
    assert math.hypot(*by_robot["c"]["final_state"][:2]) < 0.03
    assert by_robot["d"]["truth"] is None and by_robot["a"]["truth"] is not None
    moving = [t.step for t in sent if t.robot == "b" and t.action != (0.0, 0.0)]
    assert moving and min(moving) > 25  # b rested through its push between the tolerances
    between = [resting for t, resting, *_ in rested[1] if t.robot == "b" and 17 <= t.step < 28]
    assert between and not any(between)  # at rest there, but outside the inner tolerances: fitted


def test_an_actor_host_sends_the_ticks_at_rest_as_rows_of_its_rounds_bit_for_bit() -> None:
    """The host's rounds (services/actor/host.py Outbox): ticks at rest put rows, no message built;
    what the plant and the critic decode is what every robot's own steps send, in the same order
    (each transition with what its loop then knew), and the summaries are theirs."""
    rows, steps = run_host(rest=True, outboxes=True, rows=True), run_host(rest=False, outboxes=True)
    assert rows[3] > TICKS and steps[3] == 0  # rounds went as columns; the steps' never did
    assert_sent_alike(rows, steps)


def test_robots_at_rest_tick_with_the_first_group_once_a_period_and_send_what_their_own_steps_do() -> None:
    """HostScheduler's ``pull``: the robots of the second group (c drives in and comes to rest, d
    is parked) tick with the first group once at rest, early and never late. Each robot sends
    the same steps, actions and transitions (state, action, cost, the fits and memory its loop
    then knew) as its own steps at its own phase (only which state sample answered may differ:
    the plant publishes when the host wakes), and once every robot rests the host wakes once a
    period instead of once per group."""
    pulled, own = run_host(rest=True, pull=True), run_host(rest=False)
    scheduler, woke = pulled[4], pulled[5]
    assert scheduler.pulled > TICKS // 2 and own[4].pulled == 0

    def values(message: Any) -> list[float]:
        return [*getattr(message, "state", ()), *message.action, getattr(message, "cost", 0.0)]

    # the fake plant integrates between the thread's wake-ups, fewer with pull: a moving robot's
    # states differ in the last bits (exact_step over one interval or two), nothing more
    for robot in STARTS:
        actions = [[a for a in run[0] if a.robot == robot] for run in (pulled, own)]
        transitions = [[t for t in run[1] if t[0].robot == robot] for run in (pulled, own)]
        assert len(actions[0]) == len(actions[1]) > TICKS - 2 and len(transitions[0]) == len(transitions[1])
        for m, o in [*zip(*actions, strict=True), *((a[0], b[0]) for a, b in zip(*transitions, strict=True))]:
            assert m.step == o.step and np.allclose(values(m), values(o), rtol=0, atol=1e-12), (robot, m, o)
        assert [t[1:] for t in transitions[0]] == [t[1:] for t in transitions[1]]  # the fits and memory then known
    for mine, other in zip(pulled[2], own[2], strict=True):
        assert mine["loop"]["missed_deadlines"] == 0 and mine["loop"]["late_ticks"] == 0
        assert mine["steps"] == other["steps"] and mine["transition_steps"] == other["transition_steps"]
        assert mine["loop"]["jitter_ms"]["max"] < 1e-6  # early ticks and the ticks after them not counted
    # the last 20 periods, every robot at rest (b's second push is at tick 30): one wake-up each
    last = [t for t in woke if t > woke[-1] - 20 * DELTA + 1e-9]
    assert len(last) == 20, len(last)
    assert len([t for t in own[5] if t > own[5][-1] - 20 * DELTA + 1e-9]) == 40  # two groups


def test_a_robot_at_rest_by_its_steps_is_pulled_too() -> None:
    """c drives in while e and f, of its group, are parked and pulled: at its own phase c is then
    alone, too few for RestCheck (fewer than 2), and rests by its steps. It is pulled all the
    same, so the fleet at rest wakes its host once a period."""
    parked = {"e": (0.01, 0.01, 0.0), "f": (-0.01, 0.0, 0.01)}
    order = ("a", "b", "d", "c", "e", "f")  # groups of 3: (a, b, d) and (c, e, f)
    starts = {robot: {**STARTS, **parked}[robot] for robot in order}
    pulled = run_host(rest=True, pull=True, arrays_from=2, starts=starts, group=3)
    scheduler, woke = pulled[4], pulled[5]
    last = [t for t in woke if t > woke[-1] - 20 * DELTA + 1e-9]
    assert len(last) == 20, len(last)
    assert scheduler.pulled > TICKS // 2


@pytest.mark.parametrize("change", ["newer state", "second plant", "none"])
def test_a_robot_decided_at_rest_takes_its_step_when_its_state_changed_and_stops_for_a_second_plant(
    change: str,
) -> None:
    """Between the group's decision and the robot's tick a newer state came: the tick is a step
    (a solve, the newer state answered); a second plant came: zero, no transition, as any tick;
    nothing changed (the control): the tick is served at rest."""
    settings = Settings.load(actor={"jit": False})
    fake = FakeClock()
    sent: list[Any] = []
    counts = FakeCounts()
    critic = SourceGate("critic")
    inbox = WeightsInbox(settings, counts, critic)  # type: ignore[arg-type]
    actor = RobotActor(build_actor(settings), ActorMemory())
    loop = RealtimeActor(settings, actor, inbox, sent.append, sent.append, counts, 7, clock=fake.clock)
    loop.plant_gate.update("p1", True)
    state = PlantState(robot="robot1", episode=0, seq=1, stamp_ns=0, state=(0.5, 0.2, 0.0), source="sim")
    loop.on_state(state, "p1", fake.now)
    decided = loop.latest
    assert decided is not None
    if change == "second plant":
        loop.plant_gate.update("p2", True)
    elif change == "newer state":
        loop.on_state(state.model_copy(update={"seq": 2}), "p1", fake.now)
    held: list[bool] = []
    count = int(loop.ledger.accepted[loop.row])  # the state's identity: the states accepted so far
    if change == "newer state":
        count -= 1  # decided on the state before
    message, received = decided
    state_values = np.array(message.state)
    rest = AtRest(count, message.seq, received, state_values, None, 0.25, None, False, lambda: held.append(True))
    loop.tick(0, fake.now, rest=rest)
    actions = [m for m in sent if isinstance(m, Action)]
    transitions = [m for m in sent if isinstance(m, Transition)]
    assert len(actions) == 1
    if change == "newer state":
        assert not held and actor.counters.solves == 1 and actions[0].state_seq == 2 and len(transitions) == 1
    elif change == "second plant":
        assert not held and actor.counters.solves == 0 and actions[0].state_seq == -1 and transitions == []
    else:
        assert held and actor.counters.solves == 0 and actions[0].action == (0.0, 0.0)
        assert transitions[0].cost == 0.25 and actions[0].state_seq == 1
