"""The plant host's watchdogs as arrays (services/plant_sim/host.py): one test per state tick over
every robot's action arrival picks exactly the robots whose own watchdog stops them."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from common.config.settings import Settings
from common.contracts.columns import columns_of
from common.contracts.messages import Action
from services.plant_sim.host import ActionRounds, FleetPlant, RobotIntake, StateSync, plant_tick
from services.plant_sim.service import due_watchdogs
from tests.harness import FakeCounts

TIMEOUT = 0.25  # and now = 1024: now - TIMEOUT and back are exact


def test_the_watchdogs_due_are_each_robots_own_test_and_holding_zero_is_never_due() -> None:
    rng = np.random.default_rng(5)
    now = 1024.0
    arrivals = now - rng.uniform(0.0, 0.6, 300)
    arrivals[::7] = math.nan  # holding zero: nothing to stop
    arrivals[1] = now - TIMEOUT  # exactly at the timeout: not yet
    due = due_watchdogs(arrivals, now, TIMEOUT)
    own = [i for i, at in enumerate(arrivals) if not math.isnan(at) and now - at > TIMEOUT]
    assert due.tolist() == own and 0 < len(own) < 300 and 1 not in own


def test_a_plant_hosts_watchdog_stops_the_robots_due_and_leaves_the_others_driving() -> None:
    settings = Settings.load()
    robots = [f"r{i}" for i in range(4)]
    plant = FleetPlant(settings, robots, np.zeros((4, 3)))
    counts = FakeCounts()
    intakes = [RobotIntake(plant, i, counts) for i in range(4)]  # type: ignore[arg-type]
    for i, intake in enumerate(intakes):
        intake.gate.gate.update("actor1", True)
        message = Action(robot=robots[i], episode=1, step=i, stamp_ns=0, action=(0.1, 0.2), state_seq=-1)
        assert intake.take(message, "actor1") is not None
    assert np.isfinite(plant.arrivals).all() and (plant.held != 0.0).all()
    plant.arrivals[[1, 3]] -= 1.0  # two robots' actions are a second old
    now = float(np.nanmax(plant.arrivals)) + 0.01
    for i in due_watchdogs(plant.arrivals, now, TIMEOUT):
        intakes[i].watchdog(now, TIMEOUT)
    assert [intake.watchdog_stops for intake in intakes] == [0, 1, 0, 1]
    assert plant.held.tolist() == [[0.1, 0.2], [0.0, 0.0], [0.1, 0.2], [0.0, 0.0]]
    assert [intake.at is None for intake in intakes] == [False, True, False, True]
    assert counts.counters["watchdog_stops"] == 2
    assert due_watchdogs(plant.arrivals, now + 0.1, TIMEOUT).tolist() == []  # stopped: zero held, none due


def test_a_sync_of_many_actions_at_once_is_each_ones_own() -> None:
    """StateSync.actions (a batch's admitted actions as arrays) leaves what StateSync.action of
    each in turn leaves: phases, counts, newest steps and arrivals, a restart (a step at or before
    the newest) and a robot twice included."""
    rng = np.random.default_rng(11)
    together, alone = StateSync(6, 0.1, 0.02), StateSync(6, 0.1, 0.02)
    now = 100.0
    for k in range(80):
        indices = sorted(rng.choice(6, size=int(rng.integers(1, 7)), replace=False).tolist())
        if k % 13 == 5:
            indices.append(indices[0])  # a robot twice in one batch
        steps = [k if rng.random() > 0.1 else int(rng.integers(0, k + 1)) for _ in indices]
        now += float(rng.uniform(0.0, 0.1))
        together.actions(indices, steps, now)
        for index, step in zip(indices, steps, strict=True):
            alone.action(index, step, now)
    for name in ("offsets", "count", "step", "at"):
        assert np.array_equal(getattr(together, name), getattr(alone, name)), name
    assert (together.count < 80).any()  # restarts happened


def test_a_batch_of_actions_is_taken_as_each_robots_intake_takes_its_own(monkeypatch: pytest.MonkeyPatch) -> None:
    """ActionRounds: the rows of an actor host's batch through each robot's gate, held, timed and
    counted as arrays; what each robot's intake makes of its action alone, refusals included (a
    second actor session, a step out of order, a robot this host does not serve), and the
    watchdog afterwards."""
    settings = Settings.load()
    robots = [f"r{i}" for i in range(5)]

    def host() -> tuple[FleetPlant, list[RobotIntake], StateSync, FakeCounts]:
        plant = FleetPlant(settings, robots, np.zeros((5, 3)))
        counts, sync, lock = FakeCounts(), StateSync(5, 0.1, 0.02), threading.Lock()
        intakes = [RobotIntake(plant, i, counts, sync, lock) for i in range(5)]  # type: ignore[arg-type]
        for intake in intakes:
            intake.gate.gate.update("actor1", True)
        return plant, intakes, sync, counts

    clock = iter(np.arange(50.0, 60.0, 0.01).tolist())
    monkeypatch.setattr("time.monotonic", lambda: next(clock))
    batches = []
    for k in range(1, 6):
        rows = [
            Action(robot=r, episode=1, step=k, stamp_ns=0, action=(0.05 * k, -0.3 * k), state_seq=k) for r in robots
        ]
        rows[1] = rows[1].model_copy(update={"step": 1})  # r1's step out of order after the first
        rows.append(Action(robot="elsewhere", episode=1, step=k, stamp_ns=0, action=(0.1, 0.1), state_seq=k))
        batches.append((rows, "actor2" if k == 3 else "actor1"))  # k = 3: another actor session's
    plant, intakes, sync, counts = host()
    rounds = ActionRounds(plant, intakes, counts.count, sync)
    for rows, source in batches:
        rounds(columns_of(Action, rows), source)
    clock = iter(np.arange(50.0, 60.0, 0.01).tolist())
    theirs, their_intakes, their_sync, their_counts = host()
    for rows, source in batches:
        now = next(clock)
        for message in rows:
            if message.robot in robots:
                monkeypatch.setattr("time.monotonic", lambda now=now: now)
                their_intakes[robots.index(message.robot)].on_action(message, source)
    assert np.array_equal(plant.held, theirs.held) and np.array_equal(plant.arrivals, theirs.arrivals)
    assert [(i.applied, i.refused) for i in intakes] == [(i.applied, i.refused) for i in their_intakes]
    assert [(i.applied, i.refused) for i in intakes] == [(4, 1), (1, 4), (4, 1), (4, 1), (4, 1)]
    assert counts.counters == their_counts.counters and counts.counters["actions_applied"] == 17
    for name in ("offsets", "count", "step", "at"):
        assert np.array_equal(getattr(sync, name), getattr(their_sync, name)), name
    assert plant.held[0].tolist() == [min(0.25, settings.plant.v_max), max(-1.5, -settings.plant.omega_max)]  # clamped
    now = float(np.nanmax(plant.arrivals)) + 1.0
    for i in due_watchdogs(plant.arrivals, now, TIMEOUT):
        intakes[i].watchdog(now, TIMEOUT)
    assert (plant.held == 0.0).all() and [i.watchdog_stops for i in intakes] == [1] * 5


def test_a_quiet_state_tick_advances_and_publishes_nothing_and_still_runs_the_watchdogs() -> None:
    """plant_tick: a tick at which no robot's state is due (StateSync) and every ideal robot holds
    zero is quiet (None: nothing advanced, nothing published); one robot moving, one robot due, no
    sync (every state published) or a TurtleBot3 model each make it a full tick. Skipping the
    quiet ticks leaves every robot where advancing at every tick leaves it, bit for bit, and a
    watchdog due on a quiet tick stops its robot all the same."""
    settings = Settings.load()
    robots = [f"r{i}" for i in range(3)]
    starts = np.array([[1.0, 0.5, 0.3], [-0.7, 0.2, -1.0], [0.1, -0.4, 2.0]])
    delta, period = settings.plant.sampling_time, 1.0 / settings.transport.state_rate

    def host(model: str = "ideal") -> tuple[FleetPlant, list[RobotIntake], StateSync]:
        own = settings.model_copy(update={"plant": settings.plant.model_copy(update={"model": model})})
        plant = FleetPlant(own, robots, starts.copy())
        sync = StateSync(3, delta, period)
        counts, lock = FakeCounts(), threading.Lock()
        intakes = [RobotIntake(plant, i, counts, sync, lock) for i in range(3)]  # type: ignore[arg-type]
        for k in range(10):  # every robot's actor acted at the steps' phase: the states are synced
            sync.actions([0, 1, 2], [k, k, k], 100.0 + k * delta)
        return plant, intakes, sync

    plant, intakes, sync = host()
    after = 100.0 + 9 * delta  # the last action came at 100.9; the next tick is due at 101.0
    quiet = after + 0.02  # 101.0 - period - margin = 100.975: not yet due
    assert not sync.due(quiet).any() and sync.due(after + 0.08).all()
    assert plant_tick(plant, intakes, sync, quiet, period, 10.0) is None
    assert np.array_equal(plant.states, starts) and plant.seq.tolist() == [0, 0, 0]
    # a full tick: the robots due, or one moving, or every state wanted, or a TurtleBot3 model
    due = plant_tick(plant, intakes, sync, after + 0.08, period, 10.0)
    assert due is not None and len(due) == 3
    plant.hold(1, (0.1, 0.2))
    moving = plant_tick(plant, intakes, sync, quiet, period, 10.0)
    assert moving is not None and len(moving) == 0  # advanced, no state due
    assert not np.array_equal(plant.states[1], starts[1]) and plant.seq.tolist() == [2, 2, 2]
    plant.hold(1, (0.0, 0.0))
    assert plant_tick(plant, intakes, None, quiet, period, 10.0) is not None
    turtlebots, their_intakes, their_sync = host("actuator")
    assert plant_tick(turtlebots, their_intakes, their_sync, quiet, period, 10.0) is not None

    # skipping the quiet ticks moves no robot another way than advancing at each of them
    skipping, every = host()[0], host()[0]
    rng = np.random.default_rng(3)
    for tick in range(200):
        action = rng.uniform(-0.2, 0.2, 2) if tick % 40 < 10 else np.zeros(2)  # drive, then rest
        for plant_ in (skipping, every):
            plant_.hold(tick % 3, action)
        if not skipping.still():  # as plant_tick decides with no robot due
            skipping.advance(period)
        every.advance(period)
    assert np.array_equal(skipping.states, every.states) and not np.array_equal(every.states, starts)

    # a watchdog due on a quiet tick: the robot's zero is held, its stop counted
    plant, intakes, sync = host()
    for intake in intakes:
        intake.gate.gate.update("actor1", True)
    message = Action(robot="r2", episode=1, step=20, stamp_ns=0, action=(0.0, 0.0), state_seq=-1)
    assert intakes[2].take(message, "actor1") is not None
    plant.arrivals[2] = quiet - 1.0
    assert plant_tick(plant, intakes, sync, quiet, period, 0.5) is None
    assert [intake.watchdog_stops for intake in intakes] == [0, 0, 1]


def test_another_systems_plant_waits_for_its_first_action_then_steps_by_its_row_and_stops_at_its_zero() -> None:
    """A plant host of another system (the pendulum, which a zero torque does not hold up): each
    robot stays at its start until its first action (its run begins with its actor's), then moves
    by its row's step, bit for bit; a round is the system's states (a batch of the system's own,
    as the actor reads it); an action beyond the row's box is clamped to it; the watchdog holds
    the system's zero (one torque)."""
    from common.contracts.columns import decode_columns, encode_columns

    settings = Settings.load(plant={"system": "pendulum"})
    row, wire = settings.system, settings.wire
    starts = np.array([[0.4, 0.0], [-0.2, 0.1]])
    plant = FleetPlant(settings, ["p0", "p1"], starts.copy())
    counts, lock = FakeCounts(), threading.Lock()
    intakes = [RobotIntake(plant, i, counts, None, lock) for i in range(2)]  # type: ignore[arg-type]
    period = 1.0 / settings.transport.state_rate
    assert plant.still()  # nothing moves before the first action
    waiting = plant_tick(plant, intakes, None, 100.0, period, 10.0)
    assert waiting is not None and np.array_equal(waiting.field("state"), starts)
    (payload,) = encode_columns(waiting)
    decoded = decode_columns(wire.state, payload)
    assert [item.system for item in decoded.items()] == ["pendulum", "pendulum"]
    assert [list(item.state) for item in decoded.items()] == starts.tolist()

    plant.hold(0, (5.0,))  # beyond the row's box: clamped to 0.1 N m
    assert plant.held[0].tolist() == [row.action_max[0]] and not plant.still()
    moved = plant_tick(plant, intakes, None, 100.0 + period, period, 10.0)
    assert moved is not None
    assert np.array_equal(plant.states[0], row.step(starts[0], np.array(row.action_max), period))
    assert np.array_equal(plant.states[1], starts[1])  # still waiting for its first action

    intakes[1].gate.gate.update("actor1", True)
    action = wire.action(system="pendulum", robot="p1", episode=1, step=0, stamp_ns=0, action=(0.05,), state_seq=-1)
    assert intakes[1].take(action, "actor1") is not None
    plant.arrivals[1] = 99.0  # its action is older than the timeout at the next tick
    plant_tick(plant, intakes, None, 100.0 + 2 * period, period, 0.5)
    assert [intake.watchdog_stops for intake in intakes] == [0, 1] and plant.held[1].tolist() == [0.0]


def test_a_plant_host_of_one_prints_its_robots_row_of_the_hosts_summary_with_the_process_counters() -> None:
    """One summary type: a plant host's rows are PlantSummary, and a host of one robot prints its
    row (counters: the process's with the robot's own), the type ``srl plant-sim`` always printed."""
    from common.contracts.summaries import PlantSummary, robot_summary
    from services.plant_sim.host import PlantHostRun, plant_host_summary

    settings = Settings.load()

    class FakeBus:
        def __init__(self, counters: dict[str, int]) -> None:
            self.counters = counters

    def host_run(robots: list[str]) -> PlantHostRun:
        starts = np.array([[1.0 + i, 1.0, 0.5] for i in range(len(robots))])
        plant = FleetPlant(settings, robots, starts)
        counts = FakeCounts()
        intakes = [RobotIntake(plant, i, counts) for i in range(len(robots))]  # type: ignore[arg-type]
        for i, intake in enumerate(intakes):
            intake.gate.gate.update("actor1", True)
            for step in range(i + 1):  # robot i: i + 1 actions applied
                message = Action(robot=robots[i], episode=1, step=step, stamp_ns=0, action=(0.1, 0.0), state_seq=-1)
                assert intake.take(message, "actor1") is not None
        return PlantHostRun(robots, starts, plant, intakes)

    host = plant_host_summary(host_run(["a", "b"]), settings, FakeBus({"states_published": 9}), 1.5)  # type: ignore[arg-type]
    assert [row.counters["actions_applied"] for row in host.per_robot.values()] == [1, 2]
    assert host.per_robot["b"].start_state == [2.0, 1.0, 0.5] and host.per_robot["b"].mode == "realtime"

    alone = plant_host_summary(host_run(["a"]), settings, FakeBus({"states_published": 9}), 1.5)  # type: ignore[arg-type]
    own = PlantSummary.model_validate(robot_summary(alone))
    assert own.start_state == own.final_state == [1.0, 1.0, 0.5]  # not advanced: its actions only held
    assert own.counters == {
        "states_published": 9,
        "actions_applied": 1,
        "actions_refused": 0,
        "watchdog_stops": 0,
        "actor_lost_stops": 0,
    }
    assert own.plant_model == settings.plant.model and own.service == "plant"
