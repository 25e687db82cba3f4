"""A fleet on one machine (docs/fleets.md): robot lists, starts on a circle, the vectorized plant against
the single-robot plant, one built actor shared by robots against one actor per robot (bit for
bit), the host's earliest-deadline-first scheduler on a fake clock, the one-line refusals, and
(slow) a 3-robot fleet of real processes: actor host, plant host, critic."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from common.config.assembly import arrival_rule, build_actor, local_critic
from common.config.settings import Settings
from common.contracts.summaries import PARKED_WITHIN_M
from common.math.actor_problem import ActorCounters, ActorMemory
from common.math.dynamics import exact_step, exact_steps
from common.math.fleet import FleetError, circle_starts, parse_robots
from common.math.loop import ExactPlant, run_algorithm1
from common.math.stats import Window
from services.actor.host import HostScheduler, RobotActor, RobotTicker
from services.plant_sim.host import FleetPlant
from tests.harness import ROOT, free_port, srl

# -- robot lists and starts -----------------------------------------------------------------


def test_a_count_names_robot1_to_robot_k_and_a_list_keeps_its_order() -> None:
    assert parse_robots("3") == ["robot1", "robot2", "robot3"]
    assert parse_robots("b, a,c_2") == ["b", "a", "c_2"]


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("r1,r2,r1", "'r1' is given twice"),
        ("r1,r/2", "'r/2' must be 1-64 characters"),
        ("r1,,r2", "'' must be 1-64 characters"),
        ("0", "1 to 1000 robots"),
        ("1001", "1 to 1000 robots"),
    ],
)
def test_a_bad_robot_list_is_refused_in_one_line(text: str, says: str) -> None:
    with pytest.raises(FleetError) as error:
        parse_robots(text)
    assert says in str(error.value) and "\n" not in str(error.value)


@pytest.mark.integration
@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["actor", "--robots", "a,b,a"], "robot id 'a' is given twice"),
        (["plant-sim", "--robots", "a,b*"], "robot id 'b*' must be"),
        (["critic", "--robots", "x,x"], "robot id 'x' is given twice"),
        (["actor", "--robots", "2", "--mode", "lockstep"], "real time only"),
        (["up", "--robots", "a,a"], "robot id 'a' is given twice"),
    ],
)
def test_the_commands_refuse_a_bad_fleet_in_one_line(argv: list[str], says: str) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "tools.cli", *argv], capture_output=True, text=True, timeout=60, check=False
    )
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and says in lines[0], done.stderr


def test_starts_are_distinct_on_the_circle_and_head_away_from_the_target() -> None:
    starts = np.array(circle_starts(7, 1.5))
    assert np.allclose(np.hypot(starts[:, 0], starts[:, 1]), 1.5)
    assert len({(round(x, 9), round(y, 9)) for x, y, _ in starts}) == 7
    for x, y, alpha in starts:  # heading along the outward radius
        assert math.cos(alpha) == pytest.approx(x / 1.5) and math.sin(alpha) == pytest.approx(y / 1.5)
    with pytest.raises(FleetError):
        circle_starts(3, 0.0)


# -- the plant host ---------------------------------------------------------------------------


def test_the_vectorized_unicycle_is_the_single_robot_exact_step() -> None:
    rng = np.random.default_rng(16)
    states = rng.uniform(-3, 3, (200, 3))
    actions = np.column_stack([rng.uniform(-0.22, 0.22, 200), rng.uniform(-2.84, 2.84, 200)])
    actions[:20, 1] = 0.0  # straight lines
    actions[20:40, 1] = 1e-12  # and nearly straight ones
    many = exact_steps(states, actions, 0.1)
    one = np.array([exact_step(s, u, 0.1) for s, u in zip(states, actions, strict=True)])
    assert np.allclose(many, one, rtol=0, atol=1e-14)


def test_the_fleet_plant_holds_each_robots_action_clamped_and_reports_every_robot() -> None:
    settings = Settings.load()
    robots = ["a", "b", "c"]
    starts = np.array(circle_starts(3, 1.5))
    plant = FleetPlant(settings, robots, starts)
    plant.hold(1, (5.0, -9.0))  # beyond the limits: clamped
    messages = list(plant.advance(0.1).items())
    assert [m.robot for m in messages] == robots and [m.seq for m in messages] == [1, 1, 1]
    assert messages[0].state == tuple(starts[0]) and messages[2].state == tuple(starts[2])  # held at zero
    expected = exact_step(starts[1], np.array([0.22, -2.84]), 0.1)
    assert np.allclose(messages[1].state, expected, atol=1e-14)
    assert messages[1].true_state == messages[1].state


# -- one built actor, many robots -------------------------------------------------------------


def test_robots_sharing_one_built_actor_act_as_one_actor_each_bit_for_bit() -> None:
    settings = Settings.load(actor={"jit": False})
    shared = build_actor(settings)
    robots = [RobotActor(shared, ActorMemory(arrival=arrival_rule(settings))) for _ in range(2)]
    alone = [build_actor(settings) for _ in range(2)]
    q, v = settings.initial_q_weights(), settings.initial_v_weights()
    states = [np.array(s) for s in circle_starts(2, 1.5)]
    truth = [s.copy() for s in states]
    for _ in range(25):  # interleaved: robot 0, robot 1, robot 0, ... on the shared problem
        for i in range(2):
            mine, theirs = robots[i].step(states[i], q, v), alone[i].step(truth[i], q, v)
            assert np.array_equal(mine.action, theirs.action) and np.array_equal(mine.plan, theirs.plan)
            states[i] = exact_step(states[i], mine.action, 0.1)
            truth[i] = exact_step(truth[i], theirs.action, 0.1)
    for i in range(2):
        assert robots[i].counters.solves == alone[i].counters.solves == 25
    robots[0].reset()
    assert robots[0].memory.previous_x is None and robots[1].memory.previous_x is not None


# -- the host's scheduler on a fake clock -------------------------------------------------------


class FakeClock:
    def __init__(self) -> None:
        self.now = 50.0
        self.sleeps = 0

    def clock(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> bool:
        self.now += seconds
        self.sleeps += 1
        return False


@dataclass
class FakeLoop:
    """What HostScheduler uses of a RealtimeActor; each tick takes ``work`` seconds of the clock."""

    robot: str
    fake: FakeClock
    served: list[tuple[str, int, float]]
    work: float = 0.001
    periods: Window = field(default_factory=Window)
    jitter: Window = field(default_factory=Window)
    ticker: Any = None
    zero: tuple[float, ...] = (0.0, 0.0)  # the system's zero action, sent on the way out
    sent: list[tuple[int, tuple[float, float]]] = field(default_factory=list)
    counters: ActorCounters = field(default_factory=ActorCounters)
    hurried: list[bool] = field(default_factory=list)  # the scheduler's hurry at each tick
    hurried_work: float | None = None  # a hurried tick's time (None: as any other)

    def tick(self, k: int, tick: float, hurry: bool = False, rest: Any = None) -> None:
        self.served.append((self.robot, k, tick))
        self.hurried.append(hurry)
        self.fake.now += self.hurried_work if hurry and self.hurried_work is not None else self.work

    def send(self, k: int, action: tuple[float, float], state_seq: int) -> None:
        self.sent.append((k, action))


def host(
    count: int, work: float = 0.001, budget: float = 1.0, group: int = 1
) -> tuple[HostScheduler, list[FakeLoop], list[tuple[str, int, float]], FakeClock]:
    fake = FakeClock()
    served: list[tuple[str, int, float]] = []
    loops = [FakeLoop(f"r{i}", fake, served, work) for i in range(count)]
    scheduler = HostScheduler(
        loops,  # type: ignore[arg-type]
        0.1,
        threading.Event(),
        clock=fake.clock,
        sleep=fake.sleep,
        budget=budget,
        group=group,
    )
    return scheduler, loops, served, fake


def test_the_host_serves_every_robot_each_period_in_deadline_order_with_spread_phases() -> None:
    scheduler, loops, served, fake = host(4)
    start = fake.now
    scheduler.run(end=start + 10 * 0.1 + 0.01, manual_gc=False)
    assert [(r, k) for r, k, _ in served[:8]] == [
        ("r0", 0),
        ("r1", 0),
        ("r2", 0),
        ("r3", 0),
        ("r0", 1),
        ("r1", 1),
        ("r2", 1),
        ("r3", 1),
    ]
    for i, loop in enumerate(loops):
        ticks = [t for r, _, t in served if r == loop.robot]
        assert len(ticks) >= 9
        assert ticks[0] == pytest.approx(start + 0.1 + i * 0.025)  # phase i delta / K
        assert np.allclose(np.diff(ticks), 0.1)
        assert loop.ticker.missed == 0 and loop.jitter.maximum == pytest.approx(0.0, abs=1e-9)
        assert loop.sent[-1][1] == (0.0, 0.0)  # every robot stopped on the way out


def test_a_host_serves_a_tick_group_back_to_back_with_one_wake_up() -> None:
    # actor.host_tick_group: 6 robots in groups of 3 are 2 phases of the period (0 and delta / 2);
    # each group's ticks run one after another, so the host wakes twice a period, not 6 times.
    scheduler, loops, served, fake = host(6, work=0.002, group=3)
    start = fake.now
    scheduler.run(end=start + 10 * 0.1 + 0.01, manual_gc=False)
    for i, loop in enumerate(loops):
        ticks = [t for r, _, t in served if r == loop.robot]
        # robot i: its group's phase, then the 2 ms ticks of the robots before it in the group
        assert ticks[0] == pytest.approx(start + 0.1 + (i // 3) * 0.05 + (i % 3) * 0.002)
        assert np.allclose(np.diff(ticks), 0.1) and loop.ticker.missed == 0
    assert not any(h for loop in loops for h in loop.hurried)  # waiting for its group is not late
    grouped_sleeps = fake.sleeps
    scheduler, loops, served, fake = host(6, work=0.002)  # the negative control: one phase per robot
    scheduler.run(end=fake.now + 10 * 0.1 + 0.01, manual_gc=False)
    assert fake.sleeps >= 2.5 * grouped_sleeps, (fake.sleeps, grouped_sleeps)


@pytest.mark.parametrize(("work", "rounds"), [(0.0005, [3, 3]), (0.0025, [2, 1, 2, 1])])
def test_a_hosts_actions_leave_as_one_round_per_tick_group_or_once_the_first_has_waited(
    work: float, rounds: list[int]
) -> None:
    """Outbox: each robot's action is put at the end of its tick; a group's actions leave
    together when the group is served, or as soon as the first has waited ACTION_WAIT_S (2 ms),
    so no action waits much longer than that; every action leaves once, in order, and the stop
    actions on the way out leave too. Transitions (an outbox without a wait) leave once per
    group, whatever the work: one round per group and period, what their cache is sized for."""
    from common.contracts.messages import Action
    from services.actor.host import ACTION_WAIT_S, Outbox

    sent: list[list[Action]] = []
    scheduler, loops, _, fake = host(6, work=work, group=3)
    outbox = Outbox(sent.append, clock=fake.clock)
    transitions: list[list[str]] = []
    following = Outbox(transitions.append, "transitions", clock=fake.clock, wait=None)
    scheduler.outboxes = (outbox, following)
    put_at: dict[tuple[str, int], float] = {}
    left_at: dict[tuple[str, int], float] = {}

    def send(robot: str) -> Any:
        def put(k: int, action: tuple[float, float], state_seq: int) -> None:
            put_at[(robot, k)] = fake.now
            outbox.put(Action(robot=robot, episode=0, step=k, stamp_ns=0, action=action, state_seq=state_seq))

        return put

    original = outbox.send

    def record(round_: list[Action]) -> None:
        for a in round_:
            left_at[(a.robot, a.step)] = fake.now
        original(round_)

    outbox.send = record

    def acting(loop: FakeLoop) -> Any:
        ticking, put = loop.tick, send(loop.robot)

        def tick(k: int, t: float, hurry: bool = False, rest: Any = None) -> None:
            ticking(k, t, hurry)
            put(k, (0.1, 0.0), k)
            following.put(f"{loop.robot}/{k}")

        return tick

    for loop in loops:
        loop.tick = acting(loop)  # type: ignore[method-assign]
        loop.send = send(loop.robot)  # type: ignore[method-assign]
    scheduler.run(end=fake.now + 0.1 + 0.06, manual_gc=False)  # one period: both groups once
    stops = sent.pop()  # on the way out: every robot's zero action, in one round
    assert [(a.robot, a.action) for a in stops] == [(f"r{i}", (0.0, 0.0)) for i in range(6)]
    assert [len(r) for r in sent] == rounds
    assert [a.robot for r in sent for a in r] == [f"r{i}" for i in range(6)]  # each once, in order
    assert transitions == [[f"r{i}/0" for i in range(3)], [f"r{i}/0" for i in range(3, 6)]]
    waited = [left_at[key] - put_at[key] for key in put_at if key in left_at and key[1] == 0]
    assert max(waited) <= ACTION_WAIT_S + work + 1e-12


def test_a_round_of_actions_that_cannot_be_sent_is_counted_and_the_next_one_goes(
    caplog: pytest.LogCaptureFixture,
) -> None:
    from common.contracts.messages import Action
    from services.actor.host import Outbox

    sent: list[list[str]] = []

    def send(round_: list[Action]) -> None:
        if not sent:
            sent.append([])
            raise RuntimeError("the session is closed")
        sent.append([a.robot for a in round_])

    outbox = Outbox(send, clock=lambda: 0.0)
    for robot in ("r0", "r1"):
        outbox.put(Action(robot=robot, episode=0, step=0, stamp_ns=0, action=(0.1, 0.0), state_seq=0))
    outbox.flush()  # raises inside: logged and counted, not raised
    assert outbox.failed_rounds == 1 and "could not be sent" in caplog.text and not outbox.pending
    outbox.put(Action(robot="r2", episode=0, step=1, stamp_ns=0, action=(0.1, 0.0), state_seq=0))
    outbox.flush()
    assert sent[1:] == [["r2"]] and outbox.failed_rounds == 1


def test_a_tick_group_that_begins_late_is_hurried_whole() -> None:
    scheduler, loops, _, fake = host(4, work=0.001, group=2)
    loops[1].work = 0.06  # the second group (r2, r3), due 0.05 after the first, begins 0.01 late
    scheduler.run(end=fake.now + 0.35, manual_gc=False)
    assert all(loops[2].hurried) and all(loops[3].hurried) and loops[2].hurried
    assert not any(loops[0].hurried) and not any(loops[1].hurried)


def test_a_tick_served_late_is_solved_in_a_hurry_and_one_on_time_is_not() -> None:
    # HURRY_FRACTION: more than 5 ms behind its due time, a robot's tick gets the lighter solve
    # (StackedActor.step hurry: no runner-up polish, no vertex search) so the host catches up.
    scheduler, loops, _, fake = host(2)
    loops[0].work = 0.02  # r1, due 0.05 after r0, is served on time
    scheduler.run(end=fake.now + 0.35, manual_gc=False)
    assert not any(loops[0].hurried) and not any(loops[1].hurried)
    scheduler, loops, _, fake = host(2)
    loops[0].work = 0.06  # r1 is served 0.01 late every period: hurried, not yet a missed deadline
    scheduler.run(end=fake.now + 0.35, manual_gc=False)
    assert loops[1].hurried and all(loops[1].hurried) and loops[1].ticker.missed == 0
    assert not any(loops[0].hurried)


def test_a_host_over_its_cpu_budget_hurries_until_its_last_round_is_back_under() -> None:
    # actor.host_cpu_budget: 4 robots of 10 ms each (on time: one every 25 ms) spend 40 ms of each
    # 100 ms period. Under a budget of 0.5 no tick is hurried; under 0.3 the first round is full
    # (nothing spent yet), then a tick is hurried whenever the last round's ticks took over 30 ms,
    # and a hurried tick (4 ms) brings the round back under: full and hurried ticks alternate.
    scheduler, loops, _, fake = host(4, work=0.01, budget=0.5)
    scheduler.run(end=fake.now + 2.0, manual_gc=False)
    assert scheduler.over_budget == 0 and not any(h for loop in loops for h in loop.hurried)
    scheduler, loops, _, fake = host(4, work=0.01, budget=0.3)
    for loop in loops:
        loop.hurried_work = 0.004
    scheduler.run(end=fake.now + 2.0, manual_gc=False)
    hurried = [h for loop in loops for h in loop.hurried]
    assert not any(loop.hurried[0] for loop in loops)  # the first round: nothing spent before it
    assert scheduler.over_budget == sum(hurried)  # on time throughout: every hurry is the budget's
    assert 0.2 * len(hurried) < sum(hurried) < 0.8 * len(hurried), sum(hurried)
    assert all(loop.ticker.missed == 0 for loop in loops)
    # the spent ring holds one round: its sum is the last 4 ticks' time, under budget + one tick
    assert scheduler.spent_sum == pytest.approx(sum(scheduler.spent)) and scheduler.spent_sum <= 0.3 * 0.1 + 0.01


_PRIORITY_PROBE = """
import logging, os, resource, sys, threading
from common.process.runtime import realtime_priority
logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stdout)
if len(sys.argv) > 1:  # an unprivileged user: no rtprio limit (lowering it is always allowed), no root
    resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))
    if os.geteuid() == 0:
        os.setgid(65534)
        os.setuid(65534)
seen = {}
release = threading.Event()
helper = threading.Thread(target=release.wait)  # a thread that may hold the GIL the block waits for
helper.start()
policy = lambda tid: (os.sched_getscheduler(tid) & ~os.SCHED_RESET_ON_FORK, os.sched_getparam(tid).sched_priority)
with realtime_priority(10, "probe") as granted:
    seen["inside"] = policy(0)
    seen["helper"] = policy(helper.native_id)
    started = threading.Thread(target=lambda: seen.update(thread=os.sched_getscheduler(0)))
    started.start()
    started.join()
seen["helper after"] = policy(helper.native_id)
release.set()
helper.join()
print("helper", *seen["helper"], "then", *seen["helper after"])
print("granted", granted, "inside", *seen["inside"], "thread", seen["thread"])
print("after", os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
"""


@pytest.mark.integration
@pytest.mark.parametrize("user", [pytest.param("allowed", marks=pytest.mark.needs_rtprio), "refused"])
def test_the_tick_thread_is_real_time_where_allowed_and_normal_with_one_line_where_not(user: str) -> None:
    """common.process.runtime.realtime_priority (actor.realtime_priority): where the user may (root,
    CAP_SYS_NICE or an rtprio limit), the block runs under SCHED_FIFO at the priority, a thread it
    starts is normal (SCHED_RESET_ON_FORK), and the thread gets its policy back after; where it
    may not (the rtprio limit lowered to 0 and, as root, the user switched to nobody), one INFO
    line says so and nothing changes."""
    argv = [sys.executable, "-c", _PRIORITY_PROBE] + (["refused"] if user == "refused" else [])
    result = subprocess.run(argv, capture_output=True, text=True, timeout=60, cwd=Path(__file__).parents[1])
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    assert lines[-1] == f"after {os.SCHED_OTHER} 0", lines
    if user == "allowed":
        assert lines[-2] == f"granted 10 inside {os.SCHED_FIFO} 10 thread {os.SCHED_OTHER}", lines
        assert lines[0] == "probe: ticks under SCHED_FIFO 10"
        # the thread already running is real-time one step below for the block, normal after it
        assert lines[1] == "probe: the threads it may wait for under SCHED_FIFO 9: 1", lines
        assert lines[-3] == f"helper {os.SCHED_FIFO} 9 then {os.SCHED_OTHER} 0", lines
    else:
        assert lines[-2] == f"granted 0 inside {os.SCHED_OTHER} 0 thread {os.SCHED_OTHER}", lines
        assert lines[-3] == f"helper {os.SCHED_OTHER} 0 then {os.SCHED_OTHER} 0", lines
        assert len(lines) == 4 and lines[0].startswith("probe: ticks at normal priority (SCHED_FIFO 10 refused: "), (
            lines
        )
        assert "CAP_SYS_NICE or an rtprio limit" in lines[0]


_PLANT_PROBE = """
import collections, os, sys, threading
from common.config.settings import Settings
from services.plant_sim.service import state_ticks
class Counts:  # the part of a Bus that state_ticks uses
    counters = collections.Counter()
    def count(self, name, amount=1):
        self.counters[name] += amount
settings = Settings.load(plant={"realtime_priority": int(sys.argv[1])}, transport={"state_rate": 100.0})
bus = Counts()
seen = set()
for now, elapsed in state_ticks(settings, bus, threading.Event(), 0.1):
    seen.add((os.sched_getscheduler(0) & ~os.SCHED_RESET_ON_FORK, os.sched_getparam(0).sched_priority))
print("inside", *sorted(seen), "counted", bus.counters["realtime_priority"])
print("after", os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
"""


@pytest.mark.integration
@pytest.mark.parametrize("priority", [pytest.param(10, marks=pytest.mark.needs_rtprio), 0])
def test_the_plants_state_loop_is_real_time_at_its_priority_and_normal_after(priority: int) -> None:
    """plant.realtime_priority: the real-time plant's loop (plant_sim and the plant host,
    services.plant_sim.service.state_ticks) runs every tick under SCHED_FIFO at the priority, counts
    it (``realtime_priority``), and gives the thread its policy back when the loop ends; 0 leaves
    the loop in the normal class (the negative control)."""
    argv = [sys.executable, "-c", _PLANT_PROBE, str(priority)]
    result = subprocess.run(argv, capture_output=True, text=True, timeout=60, cwd=Path(__file__).parents[1])
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    policy = os.SCHED_FIFO if priority else os.SCHED_OTHER
    assert lines == [f"inside ({policy}, {priority}) counted {priority}", f"after {os.SCHED_OTHER} 0"], lines


def test_a_tick_served_over_a_quarter_period_late_is_a_missed_deadline_and_whole_periods_are_skipped() -> None:
    scheduler, loops, _, fake = host(2)
    loops[0].work = 0.02  # r1 is due 0.05 after r0: served on time
    scheduler.run(end=fake.now + 0.35, manual_gc=False)
    assert loops[1].ticker.missed == 0
    scheduler, loops, _, fake = host(2)
    loops[0].work = 0.09  # r1 is served 0.04 late: more than a quarter period, missed
    scheduler.run(end=fake.now + 0.35, manual_gc=False)
    assert loops[1].ticker.missed >= 1 and loops[1].ticker.late >= 1 and loops[0].ticker.missed == 0
    ticker = RobotTicker(0.1, 0.0)
    # 0.35 s after tick 0's due time: ticks 0, 1, 2 skipped (missed), tick 3 served 0.05 s late (missed too)
    assert ticker.serve(0.1 + 0.35) == 3
    assert ticker.missed == 4 and ticker.late == 1 and ticker.next_due == pytest.approx(0.5)


# -- a fleet of real processes ------------------------------------------------------------------


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.timing  # staleness <= 5 steps: a latency bound
@pytest.mark.parametrize("layout", ["host", "process"])
def test_a_fleet_of_three_gets_actions_approaches_and_reports_per_robot(layout: str) -> None:
    from tools.launch.up import UpOptions, run_up

    settings = Settings.load()
    summary = run_up(settings, UpOptions([], duration=8.0, robots=["fa", "fb", "fc"], layout=layout, quiet=True))
    fleet = summary["fleet"]
    assert fleet["robots"] == 3 and [row["robot"] for row in fleet["rows"]] == ["fa", "fb", "fc"]
    for row in fleet["rows"]:
        assert row["steps"] >= 40, row  # actions at delta for most of the 8 s
        assert row["final_distance_m"] < 1.5 - 0.5, row  # from 1.5 m: approached (parks within ~15 s)
        assert row["staleness_max_steps"] <= 5
    assert fleet["parked"] == sum(row["final_distance_m"] <= PARKED_WITHIN_M for row in fleet["rows"])
    assert summary["critic"]["transitions_received"] >= fleet["steps"] - 3
    # the critic kept up: never more than a second of the fleet's transitions waiting for it
    waiting = summary["critic"]["waiting_transitions"]
    assert 1 <= waiting["median"] <= waiting["max"] <= 3 * 10, waiting
    assert summary["processes"] == (4 if layout == "host" else 2 + 2 * 3)
    assert summary["rss_mb"] > 0 and summary["cpu_percent"] > 0


@pytest.mark.integration
@pytest.mark.slow
def test_a_fleet_of_one_prints_the_one_robot_summary_and_a_fleets_figures() -> None:
    """``srl up --robots 1`` is the same launcher as ``srl up`` (tools/launch/up.py): it prints the
    one robot's summary (steps, J, final state, critic), and its JSON has the fleet's figures too."""
    router = f"tcp/127.0.0.1:{free_port()}"
    done = srl("up", "--robots", "1", "--duration", "4", "--no-jit", "--router", router, "--json", timeout=180)
    assert done.returncode == 0, done.stderr[-3000:]
    lines = done.stdout.splitlines()
    summary = json.loads(lines[-1])
    assert lines[0].startswith("srl up: realtime run, plant sim, agent rlqv"), done.stdout
    assert any(line.startswith("  accumulated J") or "accumulated J" in line for line in lines), done.stdout
    assert any(line.startswith("  critic ") for line in lines) and not any("robots reporting" in x for x in lines)
    assert summary["robots"] == ["robot1"] and summary["layout"] == "host" and summary["steps"] >= 20
    assert [row["robot"] for row in summary["fleet"]["rows"]] == ["robot1"]
    assert summary["fleet"]["steps"] == summary["steps"] and summary["critic"]["transitions_received"] > 0
    assert summary["processes"] == 4 and summary["cpu_percent"] > 0
    # its critic's checkpoint was the run's own, removed with it: not offered to resume from
    assert summary["critic"]["checkpoint"] is None and not any(x.startswith("  checkpoint") for x in lines)


def test_a_fleets_cpu_is_split_where_every_robot_has_first_arrived() -> None:
    """The rest mark: made at the first read with every robot arrived, never moved; a robot that
    leaves the tolerance later shows in ``fewest_arrived``. The phases add up to the run."""
    from tools.launch.measure import RssSeries, RunMeasures, rest_mark

    mark = rest_mark(None, 1.0, {"actor": 0.4, "plant": 0.1}, 2, 3)
    assert mark is None  # 2 of 3 arrived: the robots still drive
    mark = rest_mark(mark, 2.0, {"actor": 1.0, "plant": 0.5}, 3, 3)
    assert mark is not None and (mark.at, mark.cpu_seconds, mark.fewest_arrived) == (
        2.0,
        {"actor": 1.0, "plant": 0.5},
        3,
    )
    assert rest_mark(mark, 3.0, {"actor": 1.1, "plant": 0.6}, 2, 3) is mark  # one robot left the tolerance
    assert (mark.at, mark.fewest_arrived) == (2.0, 2)
    measures = RunMeasures({"actor": 3.0, "plant": 0.5}, {}, (0.0, 0.0), RssSeries(), {}, 6.0, 6.0, mark)
    phases = measures.phases()
    assert phases is not None
    assert phases["driving"]["seconds"] == 2.0 and phases["at_rest"]["seconds"] == 4.0
    assert phases["driving"]["cpu_percent_by_service"] == pytest.approx({"actor": 50.0, "plant": 25.0})
    assert phases["at_rest"]["cpu_percent_by_service"] == pytest.approx({"actor": 50.0, "plant": 0.0})
    assert phases["at_rest"]["fewest_arrived"] == 2
    assert "wakes_per_second" not in phases["at_rest"]  # not read: not said
    counted = RunMeasures(
        {"actor": 3.0}, {}, (0.0, 0.0), RssSeries(), {}, 6.0, 6.0, mark, None, {"actor": 40.0, "plant": 2.0}
    )
    rest = counted.phases()["at_rest"]  # type: ignore[index]
    assert rest["wakes_per_second"] == 42.0 and rest["wakes_per_second_by_service"] == {"actor": 40.0, "plant": 2.0}
    whole = measures.fields(2)["cpu_percent"] * 6.0  # the run's CPU is the phases' together
    assert whole == pytest.approx(phases["driving"]["cpu_percent"] * 2.0 + phases["at_rest"]["cpu_percent"] * 4.0)
    # negative control: without a mark (not every robot arrived) there are no phases
    unsplit = RunMeasures({"actor": 3.0}, {}, (0.0, 0.0), RssSeries(), {}, 6.0, 6.0)
    assert unsplit.phases() is None and unsplit.fields(1)["cpu_phases"] is None


@pytest.mark.integration
@pytest.mark.slow
def test_a_fleet_that_parks_reports_its_cpu_while_driving_and_at_rest() -> None:
    """Two robots from 0.3 m park within a few seconds of a 10 s run: the summary splits the run's
    CPU where every robot has first reported itself arrived, and ``srl up`` prints both."""
    from tools.launch.up import UpOptions, format_fleet_summary, run_up

    summary = run_up(Settings.load(), UpOptions([], duration=10.0, robots=["ra", "rb"], quiet=True, circle=0.3))
    assert summary["fleet"]["parked"] == 2
    phases = summary["cpu_phases"]
    assert phases is not None, summary
    driving, at_rest = phases["driving"], phases["at_rest"]
    assert driving["seconds"] > 0 and at_rest["seconds"] >= 3.0, phases
    assert driving["seconds"] + at_rest["seconds"] == pytest.approx(summary["run_seconds"])
    assert at_rest["fewest_arrived"] == 2
    services = set(summary["cpu_percent_by_service"])
    assert set(driving["cpu_percent_by_service"]) == set(at_rest["cpu_percent_by_service"]) == services
    spent = driving["cpu_percent"] * driving["seconds"] + at_rest["cpu_percent"] * at_rest["seconds"]
    assert spent == pytest.approx(summary["cpu_percent"] * summary["run_seconds"])
    assert "once every robot had arrived" in format_fleet_summary(summary)
    assert "at times only" not in format_fleet_summary(summary)  # no robot left the tolerance
    at_rest["fewest_arrived"] = 1  # one of the two left it for a while: said
    assert "no solve, no fit; at times only 1 of 2 arrived)" in format_fleet_summary(summary)


@pytest.mark.integration
@pytest.mark.slow
def test_a_fleet_of_physics_robots_drives_mujoco_turtlebots_with_odometry_beside_the_truth(tmp_path: Path) -> None:
    """``srl up --robots K --plant physics``: the plant host steps one MuJoCo TurtleBot3 per robot
    (lag, deadband, slip, odometry); the actors see odometry, the summary keeps the truth beside
    it. Negative control: the ideal unicycle's odometry IS the truth."""
    from tools.launch.up import UpOptions, format_fleet_summary, run_up

    settings = Settings.load()
    finals: dict[str, dict[str, Any]] = {}
    for plant in ("physics", "sim"):
        summary = run_up(
            settings,
            UpOptions([], duration=8.0, robots=["pa", "pb"], quiet=True, plant=plant, summary_dir=tmp_path / plant),
        )
        assert summary["plant"] == plant
        rows = summary["fleet"]["rows"]
        assert [row["robot"] for row in rows] == ["pa", "pb"]
        for row in rows:
            assert row["steps"] >= 40 and row["final_distance_m"] < 1.5 - 0.5, row  # approached
        plant_summary = json.loads((tmp_path / plant / "plant.json").read_text())
        assert plant_summary["plant_model"] == ("physics" if plant == "physics" else "ideal")
        finals[plant] = plant_summary["per_robot"]
        assert ("MuJoCo" in format_fleet_summary(summary)) == (plant == "physics")
    for robot in ("pa", "pb"):
        sim, physics = finals["sim"][robot], finals["physics"][robot]
        assert sim["final_state"] == sim["true_final_state"]
        drift = np.hypot(*np.subtract(physics["final_state"][:2], physics["true_final_state"][:2]))
        assert drift > 1e-4, physics  # odometry is not the truth on the physics robot


@pytest.mark.integration
@pytest.mark.slow
def test_a_secure_fleet_logs_every_service_in_and_every_robot_learns(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``srl up --robots 2 --secure``: fresh logins per role, mutual TLS, and a router whose rules
    grant each role the keys of BOTH robots (transport.acl_robots). Were the rules one robot's
    (the single-robot ACL), the second robot's actions, states and weights would be refused by
    the router: here both drive on learned weights, nothing is refused, and no secret is left."""
    import tempfile

    from tools.launch.up import UpOptions, format_fleet_summary, run_up

    # a temporary directory of its own: tests running beside it write their own srl-secure-*
    private = tmp_path / "tmp"
    private.mkdir()
    monkeypatch.setenv("TMPDIR", str(private))
    monkeypatch.setattr(tempfile, "tempdir", str(private))
    before = {p.name for p in Path(tempfile.gettempdir()).glob("srl-secure-*")}
    summary = run_up(
        Settings.load(), UpOptions([], duration=8.0, robots=["sa", "sb"], quiet=True, secure=True, summary_dir=tmp_path)
    )
    assert summary["secure"] is True and summary["router"].startswith("tls/")
    assert "mutual TLS" in format_fleet_summary(summary)
    actors = json.loads((tmp_path / "actor.json").read_text())["per_robot"]
    plant = json.loads((tmp_path / "plant.json").read_text())
    for row in summary["fleet"]["rows"]:
        robot = row["robot"]
        assert row["steps"] >= 40 and row["final_distance_m"] < 1.5 - 0.5, row  # it drove, on its own actions
        assert actors[robot]["weights_version"] > 0, actors[robot]  # the critic's weights reached its actor
    assert summary["critic"]["transitions_received"] == summary["fleet"]["steps"]
    refused = {k: v for k, v in plant["counters"].items() if k.startswith("rejected.") and k != "rejected.action.late"}
    assert refused == {}, refused
    assert {p.name for p in Path(tempfile.gettempdir()).glob("srl-secure-*")} == before  # secrets removed


# -- the critic behind a fleet --------------------------------------------------------------------


def _transition(robot: str, step: int, episode: int = 1) -> Any:
    from common.contracts.messages import Transition

    return Transition(robot=robot, episode=episode, step=step, state=(1.0, 0.0, 0.0), action=(0.0, 0.0), cost=0.1)


def test_a_critic_behind_fits_each_robot_once_per_batch_on_its_newest_transition() -> None:
    from services.critic.service import CriticLearner, coalesced_fits

    batch = [_transition("a", 0), _transition("b", 0), _transition("a", 1), _transition("b", 1), _transition("a", 2)]
    assert coalesced_fits(batch, 1) == {0, 1, 2}
    assert coalesced_fits([_transition("a", 0), _transition("a", 1, episode=2)], 1) == set()  # another episode
    learner = CriticLearner(Settings.load())
    superseded = coalesced_fits(batch, 1)
    fitted = [learner.on_transition(m, fit=i not in superseded) for i, m in enumerate(batch)]
    assert [f is not None for f in fitted] == [False, False, False, True, True]
    assert [f.trained_step for f in fitted if f is not None] == [1, 2]
    assert learner.fits_coalesced == 3 and learner.accepted == 5


@pytest.mark.integration
@pytest.mark.slow
def test_the_fleet_bench_prints_host_and_baseline_rows_with_the_load_and_cleans_up(tmp_path: Path) -> None:
    """``srl bench fleet --record --outside`` in miniature: one host row and one baseline row, each
    with srl record and an outside subscriber of every robot's transition key attached, bounded,
    and nothing of it left behind: no srl process (its children are in its own session: none may
    outlive it), no recording, no scratch directory."""
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "tools.cli",
            "bench",
            "fleet",
            "--robots",
            "2",
            "--baseline",
            "2",
            "--seconds",
            "5",
            "--record",
            "--outside",
            "--json",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
        env={**os.environ, "TMPDIR": str(tmp_path)},
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert list(tmp_path.iterdir()) == []  # the recordings and the fleets' scratch directories are gone
    lines = done.stdout.strip().splitlines()
    assert any(line.split()[:3] == ["2", "host", "x1"] for line in lines), done.stdout
    assert any(line.split()[:2] == ["2", "process"] for line in lines), done.stdout
    result = json.loads(lines[-1])
    assert [(r["robots"], r["layout"]) for r in result["rows"]] == [(2, "host"), (2, "process")]
    for row in result["rows"]:
        assert row["fleet"]["robots"] == 2 and len(row["load_before"]) == 3 and row["rss_mb"] > 0
        assert row["processes"] == (5 if row["layout"] == "host" else 3 + 2 * 2)  # with the recorder
        assert row["recorder"].startswith("srl record: recorded ") and row["recording_mb"] > 0, row["recorder"]
        assert "(2 robots: robot1, robot2)" in row["recorder"]  # both robots in the recording
        assert row["recorder_dropped"] == 0, row["recorder"]  # the writer kept up: nothing lost
        # the outsider got the robots' transitions on their own keys (srl sends them while it subscribes),
        # each once: 5 s of 10 steps a second per robot at most, from when both robots were served
        assert 2 * 20 <= row["outside_received"] <= 2 * 55, row["outside_received"]
        # CPU per robot per tick: all processes' CPU over the run, per robot per delta
        assert row["cpu_ms_per_robot_tick"] == pytest.approx(row["cpu_percent"] / 100 * 0.1 * 1e3 / 2)
        # of it, Zenoh's runtime threads: most of a router's CPU (Zenoh's own work), a part of every other's
        zenoh, cpu = row["zenoh_cpu_percent_by_service"], row["cpu_percent_by_service"]
        assert set(zenoh) == set(cpu) and all(zenoh[name] >= 0 for name in zenoh), zenoh  # CPU in 10 ms ticks
        assert 0 < row["zenoh_cpu_percent"] < row["cpu_percent"] and zenoh["router"] > 0.5 * cpu["router"], (zenoh, cpu)
        # parking by the robots' own states: 5 s from 1.5 m away is too short to arrive
        fleet = row["fleet"]
        own = [r["own_final_distance_m"] for r in fleet["rows"]]
        assert fleet["worst_own_final_distance_m"] == max(own) and fleet["at_target"] == 0
        assert row["cpu_phases"] is None  # so no robot arrived: the run is not split into driving and rest


@pytest.mark.integration
def test_the_cpu_of_zenohs_threads_is_read_by_their_names() -> None:
    from tools.launch.measure import ZENOH_THREAD, ZenohCpu, cpu_of

    assert all(ZENOH_THREAD.match(name) for name in ("rx-0", "tx-12", "app-0", "acc-0", "net-3"))
    assert not any(ZENOH_THREAD.match(name) for name in ("python", "rx", "rx-", "srl-rx-0", "rx-0x", "tx-1-a"))
    busy = subprocess.Popen(
        [sys.executable, "-c", "import time\nend = time.time() + 20\nwhile time.time() < end: pass"]
    )
    try:
        time.sleep(1.0)  # a process without Zenoh, busy on its main thread
        zenoh = ZenohCpu({"p": busy.pid})
        # until it has run 0.3 s on a CPU: on a loaded machine (the suite's other workers) that
        # takes longer than 0.3 s of wall time; bounded by its 20 s of life
        deadline = time.monotonic() + 15.0
        while cpu_of({"p": busy.pid})["p"] <= 0.3 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert cpu_of({"p": busy.pid})["p"] > 0.3 and zenoh.seconds() == {"p": 0.0}
    finally:
        busy.kill()
        busy.wait()
    assert ZenohCpu({"gone": busy.pid}).seconds() == {"gone": 0.0}  # a process that is gone: nothing


@pytest.mark.integration
def test_wakes_count_every_threads_waits_that_ended_and_not_its_work() -> None:
    """A process sleeping 10 ms at a time in two threads wakes ~200 times a second, one that spins
    on a CPU (its negative control) hardly ever; a thread that ended keeps the wakes read before it
    ended."""
    from tools.launch.measure import Wakes, wake_rates

    sleeper = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import threading, time\n"
            "def nap():\n    for _ in range(150): time.sleep(0.01)\n"
            "threading.Thread(target=nap).start()\nnap()\ntime.sleep(20)",
        ]
    )
    spinner = subprocess.Popen(
        [sys.executable, "-c", "import time\nend = time.time() + 20\nwhile time.time() < end: pass"]
    )
    try:
        time.sleep(0.3)  # both started
        wakes = Wakes({"sleeper": sleeper.pid, "spinner": spinner.pid})
        first = (time.monotonic(), wakes.totals())
        for _ in range(15):  # read as the bench reads, while the naps go on (a thread keeps what was read)
            time.sleep(0.2)
            last = (time.monotonic(), wakes.totals())
        # the sleeper's naps are over (150 x >= 10 ms) and its second thread has ended
        rates = wake_rates([first, last])
        assert rates is not None
        assert rates["sleeper"] * 3.0 >= 200, rates  # 2 x 150 naps, less the ~0.3 s before the first reading
        assert rates["spinner"] * 3.0 < 30, rates
    finally:
        for process in (sleeper, spinner):
            process.kill()
            process.wait()
    assert wake_rates([first]) is None and wake_rates([(1.0, {"p": 5.0}), (1.0, {"p": 9.0})]) is None
    assert wake_rates([(1.0, {"p": 5.0}), (3.0, {"p": 9.0})]) == {"p": 2.0}


# eight threads named as Zenoh names its workers, started 0.5 s in, each on a CPU for less than a
# clock tick (10 ms), then ending 1 s later
_SHORT_THREADS = """
import threading, time
def work(i):
    with open(f"/proc/self/task/{threading.get_native_id()}/comm", "w") as comm:
        comm.write(f"rx-{i}")
    end = time.thread_time() + 0.006
    while time.thread_time() < end:
        pass
    time.sleep(1.0)
time.sleep(0.5)
for i in range(8):
    threading.Thread(target=work, args=(i,), daemon=True).start()
time.sleep(10)
"""


@pytest.mark.integration
def test_the_cpu_of_zenohs_threads_keeps_threads_that_started_and_ended_and_time_below_a_clock_tick() -> None:
    from tools.launch.measure import ZenohCpu

    def threads(pid: int, count: int) -> None:
        deadline = time.monotonic() + 5.0
        while len(os.listdir(f"/proc/{pid}/task")) != count and time.monotonic() < deadline:
            time.sleep(0.02)

    short = subprocess.Popen([sys.executable, "-c", _SHORT_THREADS])
    try:
        zenoh = ZenohCpu({"p": short.pid})  # before the threads exist: each counts from zero
        threads(short.pid, 9)
        time.sleep(0.3)  # every thread has run its 6 ms and sleeps
        running = zenoh.seconds()["p"]
        if os.path.exists(f"/proc/{short.pid}/task/{short.pid}/schedstat"):  # a kernel with scheduler info
            # 8 x 6 ms: counted in whole ticks thread by thread, most of it would be lost (8 x 0 ticks)
            assert 0.040 <= running < 0.2, running
        else:  # ticks only: what is counted is not lost
            assert 0.0 <= running < 0.2, running
        threads(short.pid, 1)
        assert zenoh.seconds()["p"] == running  # the threads have ended: what they ran is kept
    finally:
        short.kill()
        short.wait()


def test_the_fleet_bench_judges_100_and_300_robots_as_one_robot_alone() -> None:
    from tools.bench.fleet import checks, cpu_ms_per_robot_tick

    assert cpu_ms_per_robot_tick(162.0, 100, 0.1) == pytest.approx(1.62)  # 1.62 cores for 1000 robot ticks a second
    fleet = {"missed_deadlines": 0, "latency_p99_ms": 1.0, "staleness_p99_steps": 1.0, "parked": 100, "at_target": 100}
    row = {"robots": 100, "fleet": fleet, "rss_mb": 900.0, "cpu_percent": 40.0, "cpus": 2, "seconds": 40}
    row["cpu_ms_per_robot_tick"] = cpu_ms_per_robot_tick(row["cpu_percent"], 100, 0.1)  # 0.4 ms
    assert all(checks(row).values()) and len(checks(row)) == 7
    one_off = {**row, "fleet": {**fleet, "at_target": 99}}
    assert [name for name, ok in checks(one_off).items() if not ok] == ["every robot at its target"]
    busy = {**row, "cpu_percent": 150.0, "cpu_ms_per_robot_tick": 1.5}  # 75 % of the 2 cores
    assert sorted(name for name, ok in checks(busy).items() if not ok) == [
        "CPU <= 70 % of the machine",
        "CPU per robot tick <= 0.5 ms",
    ]
    big = {**row, "robots": 300, "fleet": {**fleet, "at_target": 300}, "rss_mb": 2100.0, "cpu_ms_per_robot_tick": 0.6}
    assert sorted(name for name, ok in checks(big).items() if not ok) == [
        "CPU per robot tick <= 0.5 ms",
        "RSS <= 2.0 GB",
    ]
    # with srl record attached (--record): the recording is complete only if its writer dropped nothing
    recorded = {**row, "recording_mb": 30.0, "recorder_dropped": 0}
    assert checks(recorded)["recording complete"] and len(checks(recorded)) == 8
    assert [name for name, ok in checks({**recorded, "recorder_dropped": 24264}).items() if not ok] == [
        "recording complete"
    ]


@pytest.mark.integration
@pytest.mark.slow
def test_critics_shard_a_fleet_by_robot_each_learning_only_its_own() -> None:
    """``srl critic --robots``: a shard subscribes to its robots' transitions only, so two critics
    split a fleet across processes or hosts (docs/fleets.md); each robot's
    weights come from its own shard, and a robot of neither shard is learned by none."""
    from common.contracts.columns import batch_payloads, decode_batch
    from common.contracts.keys import STATUS, TRANSITION_BATCH, WEIGHTS, WEIGHTS_BATCH
    from common.contracts.messages import CriticWeights, ServiceStatus
    from tests.harness import Proc, free_port, open_session, random_transitions, wait_until

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = Proc("router", ["router", "--router", endpoint])
    shards = {
        "a": Proc("critic-a", ["critic", "--router", endpoint, "--robot", "a", "--robots", "s1,s2"]),
        "b": Proc("critic-b", ["critic", "--router", endpoint, "--robot", "b", "--robots", "s3"]),
    }
    import zenoh
    import zenoh.ext

    session = None
    try:
        session = open_session(endpoint, 30, "the router")

        def alive() -> set[str]:
            replies = session.liveliness().get("srl/*/alive/critic/**", timeout=0.5)
            return {str(r.ok.key_expr).split("/")[1] for r in replies if r.ok is not None}

        wait_until(lambda: alive() >= {"s1", "s2", "s3"}, 60, "both shards alive")
        fits: dict[str, list[int]] = {}
        lock = threading.Lock()

        def on_weights(sample: Any) -> None:
            w = CriticWeights.model_validate_json(sample.payload.to_bytes())
            with lock:
                fits.setdefault(w.robot, []).append(w.version)

        def on_batch(sample: Any) -> None:  # shard a's rounds of s1 and s2 (common.contracts.keys.Batch)
            for w in decode_batch(CriticWeights, sample.payload.to_bytes()):
                with lock:
                    fits.setdefault(w.robot, []).append(w.version)

        received: dict[str, float] = {}

        def on_status(sample: Any) -> None:
            status = ServiceStatus.model_validate_json(sample.payload.to_bytes())
            with lock:
                counters = status.counters
                received[status.robot] = counters.get("transitions_received", 0) - counters.get("duplicates", 0)

        subscriber = session.declare_subscriber(WEIGHTS.pattern.format(robot="*"), on_weights)
        batches = session.declare_subscriber(WEIGHTS_BATCH.pattern, on_batch)
        statuses = session.declare_subscriber(STATUS.pattern.format(robot="*", service="critic"), on_status)
        sent = random_transitions(20, robots=("s1", "s2", "s3", "s4"))
        # as the actor hosts publish them: on the batch key (Batch.on_demand), through a cached
        # advanced publisher, so a shard recovers what a loaded machine's router dropped (a plain
        # put of 80 samples in a burst lost 27 of shard a's 40 in one CI run, 2026-11-25)
        publisher = zenoh.ext.declare_advanced_publisher(
            session,
            TRANSITION_BATCH.pattern,
            cache=zenoh.ext.CacheConfig(64),
            sample_miss_detection=zenoh.ext.MissDetectionConfig(heartbeat=0.5, sporadic_heartbeat=None),
            publisher_detection=True,
        )
        for step in range(0, len(sent), 4):  # a round: every robot's step
            (payload,) = batch_payloads(sent[step : step + 4])
            publisher.put(payload)
        wait_until(lambda: {"s1", "s2", "s3"} <= set(fits), 30, "weights of every served robot")
        wait_until(lambda: received.get("a", 0) >= 40 and received.get("b", 0) >= 20, 30, "all at their shards")
        subscriber.undeclare()
        batches.undeclare()
        statuses.undeclare()
        assert "s4" not in fits  # in no shard: learned by none
        assert shards["a"].stop() == 0 and shards["b"].stop() == 0
        summaries = {name: proc.summary() for name, proc in shards.items()}
        unique = {name: s["transitions_received"] - s["duplicates"] for name, s in summaries.items()}
        assert unique == {"a": 40, "b": 20}, summaries  # each its own robots' 20 steps, nothing of the others
    finally:
        if session is not None:
            session.close()
        for proc in (*shards.values(), router):
            proc.stop()


def test_actor_hosts_auto_is_one_up_to_fifty_robots_else_one_per_core_and_bad_values_are_refused() -> None:
    """``--actor-hosts`` of ``srl up --robots`` and ``srl bench fleet`` (one rule, common.process.runtime.fleet_hosts,
    which ``srl actor --hosts`` shares)."""
    from common.config.arguments import UsageError
    from common.process.runtime import usable_cores
    from tools.launch.up import actor_hosts

    cores = usable_cores()
    assert actor_hosts("auto", 8) == 1 and actor_hosts("auto", 50) == 1
    assert actor_hosts("auto", 51) == min(cores, 51) and actor_hosts("auto", 100) == min(cores, 100)
    assert actor_hosts("3", 8) == 3
    for bad, size in (("0", 8), ("9", 8), ("two", 8), ("", 8)):
        with pytest.raises(UsageError, match="--actor-hosts"):
            actor_hosts(bad, size)


def test_a_robots_counts_count_its_refusals_and_forward_or_log_them_with_its_id(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """common.process.counts.RobotCounts: the one per-robot counter of the actor host and the bridge host."""
    from common.process.counts import RobotCounts

    forwarded: list[tuple[str, str]] = []
    actor = RobotCounts("r7", "actor", forward=lambda what, reason: forwarded.append((what, reason)))
    actor.count("steps", 3)
    actor.reject("state", "NaN")
    assert actor.snapshot() == {"steps": 3, "rejected.state": 1}
    assert forwarded == [("state", "robot r7: NaN")]
    bridge = RobotCounts("tb3_1", "robot_bridge")
    with caplog.at_level("WARNING", logger="common.process.counts"):
        for _ in range(5):
            bridge.reject("odom", "stale")
    assert bridge.snapshot() == {"rejected.odom": 5}
    assert [r.getMessage() for r in caplog.records] == ["robot_bridge tb3_1: rejected odom: stale"]  # once a second


def _children_of(pid: int) -> list[int]:
    """The live child processes of ``pid`` (from /proc: their parent pid field)."""
    children = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid and fields[0] != "Z":
                children.append(int(entry.name))
    return children


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.integration
@pytest.mark.slow
def test_one_actor_command_splits_its_robots_over_host_processes_that_live_and_die_together() -> None:
    """``srl actor --robots K --hosts 2`` (compose's fleet profile, a hand-started fleet): two host
    processes, each serving its half under its own session; a SIGTERM stops both cleanly (two
    summaries); a child killed stops the command with a non-zero code; the parent killed by
    SIGKILL takes its child with it."""
    from tests.harness import Proc, free_port, open_session, wait_until

    robots = ["h1", "h2", "h3", "h4"]
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = Proc("router", ["router", "--router", endpoint])
    plant = Proc("plant", ["plant-sim", "--router", endpoint, "--robots", ",".join(robots)])
    actors: list[Proc] = []
    session = None
    try:
        session = open_session(endpoint, 30, "the router")

        def serving() -> dict[str, set[str]]:
            """zid of each live actor -> the robots it serves (liveliness srl/<robot>/alive/actor/<zid>)."""
            hosts: dict[str, set[str]] = {}
            for reply in session.liveliness().get("srl/*/alive/actor/**", timeout=0.5):
                parts = str(reply.ok.key_expr).split("/") if reply.ok is not None else []
                if len(parts) == 5:  # the identity token (the other one, .../alive/actor, names no session)
                    hosts.setdefault(parts[4], set()).add(parts[1])
            return hosts

        def start() -> Proc:
            actor = Proc("actor", ["actor", "--router", endpoint, "--robots", ",".join(robots), "--hosts", "2"])
            actors.append(actor)
            # a host declares its robots' tokens one by one: wait for every robot, not for the first of each host
            wait_until(
                lambda: sorted(len(served) for served in serving().values()) == [2, 2],
                90,
                "two actor hosts alive, serving every robot",
            )
            return actor

        # 1. two processes, the robots in contiguous halves; SIGTERM to the command stops both
        actor = start()
        assert sorted(map(sorted, serving().values())) == [["h1", "h2"], ["h3", "h4"]]
        children = _children_of(actor.process.pid)
        assert len(children) == 1, children
        time.sleep(2.0)  # every robot acts for a while
        os.kill(actor.process.pid, signal.SIGTERM)
        assert actor.process.wait(timeout=30) == 0, actor.stderr[-10:]
        wait_until(lambda: not _alive(children[0]), 15, "the child host stopped with the command")
        time.sleep(0.1)
        summaries = [json.loads(line) for line in actor.stdout if line.startswith("{")]
        assert sorted(sorted(s["per_robot"]) for s in summaries) == [["h1", "h2"], ["h3", "h4"]], actor.stdout[-4:]
        for s in summaries:
            assert all(row["steps"] >= 10 for row in s["per_robot"].values()), s["per_robot"]
        wait_until(lambda: serving() == {}, 15, "no actor left alive")

        # 2. a child host killed: the command stops the other and ends non-zero (its supervisor restarts it)
        actor = start()
        (child,) = _children_of(actor.process.pid)
        os.kill(child, signal.SIGKILL)
        assert actor.process.wait(timeout=30) == 128 + signal.SIGKILL
        assert any("was killed by SIGKILL: stopping the others" in line for line in actor.stderr), actor.stderr[-10:]
        wait_until(lambda: serving() == {}, 15, "no actor left alive")

        # 3. the command killed outright: its child host dies with it
        actor = start()
        (child,) = _children_of(actor.process.pid)
        os.kill(actor.process.pid, signal.SIGKILL)
        actor.process.wait(timeout=10)
        wait_until(lambda: not _alive(child), 15, "the orphaned child host ended")
        wait_until(lambda: serving() == {}, 15, "no actor left alive")
    finally:
        if session is not None:
            session.close()
        for proc in (*actors, plant, router):
            proc.stop()


@pytest.mark.integration
def test_hosts_without_robots_or_beyond_one_per_robot_is_refused_in_one_line() -> None:
    from tests.harness import srl

    for argv, says in (
        (["actor", "--hosts", "2"], "--hosts splits the robots of --robots over processes: give --robots too"),
        (["actor", "--robots", "2", "--hosts", "3"], "--hosts 3: 1 to one per robot (2)"),
        (["actor", "--robots", "2", "--hosts", "many"], "--hosts 'many': a number of actor processes, or auto"),
    ):
        result = srl(*argv, "--connect-timeout", "1")
        assert result.returncode == 2 and result.stderr.strip().splitlines() == [f"srl: error: {says}"], result.stderr


class AlwaysHurried:
    """An actor whose every step is hurried (what an overloaded host does at worst): the actor
    port of common.math.loop.run_algorithm1."""

    def __init__(self, actor: Any) -> None:
        self.actor, self.problem, self.counters = actor, actor.problem, actor.counters

    def reset(self) -> None:
        self.actor.reset()

    def step(self, state: np.ndarray, q_weights: np.ndarray, v_weights: np.ndarray) -> Any:
        return self.actor.step(state, q_weights, v_weights, hurry=True)


@pytest.mark.parametrize("start", [(2.0, 2.0), (-2.0, 1.0), (1.0, -2.0)])
def test_a_robot_hurried_at_every_step_parks_as_the_unhurried_one(start: tuple[float, float]) -> None:
    # A hurried step in the closed loop (Algorithm 1 as shipped, the robot's own critic): every
    # step hurried once the robot has a plan -- an overloaded host's worst -- against no hurry at
    # all. The warm polish alone (no search, no vertex search) still parks the robot and the
    # accumulated cost moves little. The search's count shows the hurried run did skip it (an
    # actor that searched anyway fails it).
    base = Settings.load()
    settings = base.model_copy(update={"actor": base.actor.model_copy(update={"jit": False})})
    runs = {}
    for hurry in ("hurried", None):
        actor = build_actor(settings)
        port = AlwaysHurried(actor) if hurry else actor
        plant = ExactPlant()
        critic = local_critic(settings)
        state = np.array([*start, settings.start_state()[2]])
        runs[hurry] = (
            run_algorithm1(port, [plant], [critic], [state], 300, 0.1, tuple(settings.r_diag))[0],  # type: ignore[arg-type]
            actor.counters,
        )
    (hurried, counters), (plain, _) = runs["hurried"], runs[None]
    assert counters.hurried_solves > 0.9 * counters.solves  # every solve hurried (a few start cold: no plan)
    assert counters.phase_counts["search"] < 0.1 * counters.solves
    for episode in (hurried, plain):
        assert math.hypot(*episode.final_state[:2]) < PARKED_WITHIN_M
    assert hurried.accumulated_cost <= 1.01 * plain.accumulated_cost


def test_the_fleet_page_shows_each_processs_wakes_at_rest_where_the_run_measured_them() -> None:
    """The benchmark page's at-rest cell says how often each process woke once the data has it
    (``srl bench fleet`` from its wakes/s column on); data without it is shown as before."""
    from tools.docs.benchmarks import fleet_body

    data = json.loads((ROOT / "docs" / "benchmarks" / "data" / "fleet.json").read_text())
    row = next(r for r in data["rows"] if r.get("cpu_phases"))
    before = "\n".join(fleet_body({**data, "rows": [row]}))
    assert "/s)" not in before.split("how long each phase lasted:")[1]  # no wakes in the data: none shown
    rest = dict(row["cpu_phases"]["at_rest"])
    rest["wakes_per_second_by_service"] = {name: 40.0 + i for i, name in enumerate(rest["cpu_percent_by_service"])}
    counted = {**row, "cpu_phases": {**row["cpu_phases"], "at_rest": rest}}
    page = "\n".join(fleet_body({**data, "rows": [counted]})).split("how long each phase lasted:")[1]
    first = next(iter(rest["cpu_percent_by_service"]))
    assert f"{first} {rest['cpu_percent_by_service'][first]:.1f} (40/s)" in page
    assert page.count("/s)") == len(rest["cpu_percent_by_service"])  # at rest only: driving has none
