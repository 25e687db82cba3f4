"""The plant host: one ``srl plant-sim --robots ...`` process simulates many robots.

Real time only. One timer at ``transport.state_rate``; each period every robot is advanced with
its newest action held and its state published: the states of one period as one batch on
``srl/@batch/state`` (common.contracts.keys.Batch; a host of one robot on ``srl/<robot>/state``). The ideal unicycle of
the whole fleet is one numpy step (:func:`common.math.dynamics.exact_steps`), another sampled
system (``plant.system``) its row's step (:meth:`common.math.systems.System.steps`), its messages
the system's (common/contracts/wire.py); the TurtleBot3 models
(``plant.model = actuator | physics``) step one :class:`SimulatedPlant` per robot. Each robot
keeps what one plant_sim keeps: only its live actor session's actions, in order
(:class:`~common.net.provenance.ActionGate`), the watchdog (zero velocity after
``action_timeout_steps * delta`` without a fresh action, tested for every robot at once at each
state tick, :func:`~services.plant_sim.service.due_watchdogs`; and at once when its actor vanishes),
one plant per robot (a second plant of any robot of the list refuses to start), and the truth
beside the reported state. Robots start on a circle around the target (common/math/fleet.py).

A robot whose actor drives it has its state published only at the state ticks just before its
actor's next tick (``transport.state_sync``, :class:`StateSync`): its actor reads one state per
``delta``, so at a state rate of ``n / delta`` all but one of every ``n`` states would go unread
(at 50 Hz and ``delta = 0.1`` s, four of every five, through the router for every robot).
A state tick at which no robot's state is due and no robot moves (the ideal unicycle, every robot
holding zero: a fleet at rest) is quiet: its watchdogs run, nothing else (:func:`plant_tick`).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.config.settings import Settings
from common.contracts.columns import Columns, choice_code, columns_of
from common.contracts.messages import Action, PlantState
from common.contracts.summaries import FleetPlantSummary, PlantSummary
from common.math.plant_models import plant_model_row
from common.net.transport import Bus, bus_status, start_status_thread
from common.system.clock import STATE_SYNC_MARGIN_S
from services.plant_sim.service import ActionIntake, SimulatedPlant, action_timeout, due_watchdogs, state_ticks

log = logging.getLogger(__name__)

SYNC_WINDOW = 50  # a robot's phase is learned from its last this many actions (5 s at delta = 0.1 s)
SYNC_MIN_ACTIONS = 5  # before that many, every state tick publishes the robot's state


class StateSync:
    """Which robots' states a plant host publishes at a state tick (``transport.state_sync``).

    An actor uses the newest state at its tick, once per ``delta``. Its tick ``k`` is due at
    ``T0 + k delta``, and its action of step ``k`` arrives at that plus the tick's lateness, the
    solve and the transport, never before; so the least ``arrival - k delta`` of a robot's last
    :data:`SYNC_WINDOW` actions is ``T0`` plus the shortest such delay (~1 ms), on this process's
    clock alone (no clock of another host is read), and the next tick is due at about that plus
    ``(k + 1) delta``. From one state period and :data:`STATE_SYNC_MARGIN_S` before that, until the
    robot's next action arrives, every state tick publishes the robot's state. So the newest
    state at an on-time tick is the same one it would be with every state tick published (the
    last one before the tick), and a late actor gets every state tick until it acts. A robot
    without :data:`SYNC_MIN_ACTIONS` actions, or without one for two ``delta`` (starting, stopped,
    its actor gone), gets every state tick, as without sync. Transport-free (unit-tested)."""

    def __init__(self, robots: int, delta: float, period: float) -> None:
        self.delta, self.period = delta, period
        self.offsets = np.full((robots, SYNC_WINDOW), np.inf)  # arrival - step * delta
        self.count = np.zeros(robots, dtype=np.int64)  # actions since the phase was (re)learned
        self.step = np.full(robots, -1, dtype=np.int64)  # the newest action's step
        self.at = np.full(robots, -np.inf)  # its arrival
        self.lock = threading.Lock()

    def action(self, index: int, step: int, now: float) -> None:
        """Robot ``index``'s action of ``step`` arrived (admitted) at ``now``."""
        with self.lock:
            if step <= self.step[index]:  # a new episode or actor: its phase is learned again
                self.offsets[index] = np.inf
                self.count[index] = 0
            self.offsets[index, self.count[index] % SYNC_WINDOW] = now - step * self.delta
            self.count[index] += 1
            self.step[index] = step
            self.at[index] = now

    def actions(self, indices: list[int], steps: list[int], now: float) -> None:
        """:meth:`action` of robots ``indices`` with ``steps``, all arrived at ``now``, as arrays
        (a robot twice: one by one, in order)."""
        if len(set(indices)) < len(indices):
            for index, step in zip(indices, steps, strict=True):
                self.action(index, step, now)
            return
        rows, numbers = np.array(indices, dtype=np.intp), np.array(steps, dtype=np.int64)
        with self.lock:
            again = rows[numbers <= self.step[rows]]  # a new episode or actor: its phase is learned again
            if len(again):
                self.offsets[again] = np.inf
                self.count[again] = 0
            self.offsets[rows, self.count[rows] % SYNC_WINDOW] = now - numbers * self.delta
            self.count[rows] += 1
            self.step[rows] = numbers
            self.at[rows] = now

    def due(self, now: float) -> np.ndarray:
        """For every robot: publish its state at the state tick ``now``?"""
        with self.lock:
            synced = (self.count >= SYNC_MIN_ACTIONS) & (now - self.at < 2.0 * self.delta)
            next_tick = self.offsets.min(axis=1) + (self.step + 1) * self.delta
            due: np.ndarray = ~synced | (now > next_tick - self.period - STATE_SYNC_MARGIN_S)
            return due


class FleetPlant:
    """K robots' states (transport-free). ``plant.model = ideal``: one (K, n) array of the
    system's states stepped at once; otherwise one :class:`SimulatedPlant` (a TurtleBot3 model)
    per robot."""

    def __init__(self, settings: Settings, robots: list[str], starts: np.ndarray) -> None:
        self.robots = robots
        self.system, self.wire = settings.system, settings.wire
        self.bounds = np.array(settings.action_max)
        self.lock = threading.Lock()
        self.ideal = plant_model_row(settings.plant.model).exact
        self.states = np.array(starts, dtype=float).reshape(len(robots), self.system.state_dim)
        self.held = np.zeros((len(robots), self.system.action_dim))
        # A system that a zero action does not hold (a pendulum falls) waits at its start for its
        # first action: its run begins with its actor's, not while the actor is being built.
        self.waiting = None if self.system.still_at_zero else np.ones(len(robots), dtype=bool)
        # a round's columns beside the states: the system's name, a simulator's source
        self.named = self.wire.named_columns(self.wire.state) | {
            "source": choice_code(self.wire.state, "source", "sim")
        }
        self.seq = np.zeros(len(robots), dtype=np.int64)
        # when each robot's held action arrived (NaN: holding zero): its RobotIntake's, for the
        # watchdogs of every robot at once (service.due_watchdogs)
        self.arrivals = np.full(len(robots), np.nan)
        self.plants: list[SimulatedPlant] = []
        if not self.ideal:
            for robot, start in zip(robots, self.states, strict=True):
                own = settings.model_copy(
                    update={
                        "transport": settings.transport.model_copy(update={"robot": robot}),
                        "episode": settings.episode.model_copy(update={"start": [float(c) for c in start]}),
                    }
                )
                self.plants.append(SimulatedPlant(own))

    def hold(self, index: int, action: tuple[float, ...] | np.ndarray) -> None:
        """The newest action of robot ``index`` (clamped to the robot's limits), held until the next."""
        clamped = np.clip(np.asarray(action, dtype=float), -self.bounds, self.bounds)
        with self.lock:
            self.held[index] = clamped
            if self.waiting is not None:
                self.waiting[index] = False
            if not self.ideal:
                self.plants[index].hold(clamped)

    def hold_many(self, indices: list[int], actions: np.ndarray) -> None:
        """:meth:`hold` of robots ``indices``, ``actions`` ``(len(indices), m)``, in order."""
        clamped = np.clip(np.asarray(actions, dtype=float), -self.bounds, self.bounds)
        with self.lock:
            self.held[indices] = clamped
            if self.waiting is not None:
                self.waiting[indices] = False
            if not self.ideal:
                for index, action in zip(indices, clamped, strict=True):
                    self.plants[index].hold(action)

    def advance(self, duration: float, due: np.ndarray | None = None) -> Columns[PlantState]:
        """Every robot ``duration`` seconds on; the states of the robots ``due`` a publication (all:
        None), in robot order, as one round's columns (a robot not due moved on all the same).
        The ideal unicycle's round is the fleet's arrays: no message is built per robot."""
        stamp = time.monotonic_ns()
        with self.lock:
            if not self.ideal:
                messages = [plant.advance(duration) for plant in self.plants]
                chosen = messages if due is None else [m for m, d in zip(messages, due, strict=True) if d]
                return columns_of(self.wire.state, chosen)
            if self.waiting is None or not self.waiting.any():
                self.states = self.system.steps(self.states, self.held, duration)
            else:  # the robots waiting for their first action stay at their starts
                moving = ~self.waiting
                self.states[moving] = self.system.steps(self.states[moving], self.held[moving], duration)
            self.seq += 1
            rows = np.arange(len(self.robots)) if due is None else np.flatnonzero(due)
            states, seqs = self.states[rows], self.seq[rows]  # copies: the next step moves on
        count = len(rows)
        robots = self.robots if count == len(self.robots) else [self.robots[i] for i in rows.tolist()]
        return Columns.of(
            self.wire.state,
            robots,
            {
                **self.named,
                "episode": 0,
                "seq": seqs,
                "stamp_ns": stamp,
                "state": states,
                "true_state": states,
                "saturated_commands": 0,
            },
        )

    def still(self) -> bool:
        """No robot moves over a state tick: the ideal unicycle, every robot holding zero (its exact
        step is then the identity); another system only while every robot waits for its first
        action (``System.still_at_zero``). A TurtleBot3 model is never still here: its wheels' lag and
        its odometry run on after a zero command."""
        with self.lock:
            if self.waiting is not None:
                return self.ideal and bool(self.waiting.all())
            return self.ideal and not self.held.any()

    def saturated_commands(self, index: int) -> int:
        """Commands of robot ``index`` a wheel could not follow (the ideal unicycle has no wheels: 0)."""
        robot = None if self.ideal else self.plants[index].robot
        return 0 if robot is None else robot.saturated_commands

    def reported(self, index: int) -> list[float]:
        if self.ideal:
            return [float(c) for c in self.states[index]]
        return [float(c) for c in self.plants[index].reported]

    def truth(self, index: int) -> list[float]:
        if self.ideal:
            return [float(c) for c in self.states[index]]
        return [float(c) for c in self.plants[index].state]


class RobotIntake(ActionIntake):
    """One robot's actions into the fleet plant, as one plant_sim takes them (its gate, its
    watchdog clock, its counters), each admitted one also timing its actor's phase (``sync``).
    ``lock``: the host's, shared by every robot's intake (:class:`ActionRounds` takes a batch's
    actions under it)."""

    def __init__(
        self,
        plant: FleetPlant,
        index: int,
        bus: Bus,
        sync: StateSync | None = None,
        lock: threading.Lock | None = None,
    ) -> None:
        self.index, self.sync = index, sync
        self.robot = robot = plant.robots[index]

        def hold(action: Any) -> None:
            plant.hold(index, action)

        def reject(what: str, why: str) -> None:
            bus.reject(what, f"robot {robot}: {why}")

        # the host's counts: the robot's in a host of one; its action's arrival in the plant's array
        super().__init__(hold, reject, bus.count, plant.arrivals, index, lock, plant.system.action_dim)

    def on_action(self, message: Action, source: str | None) -> None:
        now = self.take(message, source)
        if now is not None and self.sync is not None:
            self.sync.action(self.index, message.step, now)


class ActionRounds:
    """A plant host's actions, a sample (an actor host's tick group, or one robot's action) at a
    time as columns (Bus.subscribe_columns): each row through its robot's gate, in order, under
    the host's intake lock (that of every :class:`RobotIntake`, so no watchdog or lost actor
    interleaves), then the admitted ones held, their arrivals noted and their actors' phases
    timed as arrays. What each robot's intake does with its action alone, bit for bit
    (``tests/test_plant_host.py``), with no message built and no call per robot but the gate's."""

    def __init__(
        self, plant: FleetPlant, intakes: list[RobotIntake], count: Callable[[str, int], None], sync: StateSync | None
    ) -> None:
        self.plant, self.intakes, self.count, self.sync = plant, intakes, count, sync
        self.index = {robot: i for i, robot in enumerate(plant.robots)}
        self.lock = intakes[0].lock if intakes else threading.Lock()

    def __call__(self, columns: Columns[Action], source: str | None) -> None:
        now = time.monotonic()
        episodes, steps = columns.field("episode").tolist(), columns.field("step").tolist()
        indices: list[int] = []
        rows: list[int] = []
        with self.lock:
            for row, robot in enumerate(columns.robots):
                i = self.index.get(robot)
                if i is not None and self.intakes[i].admitted(episodes[row], steps[row], source, now):
                    indices.append(i)
                    rows.append(row)
            if not indices:
                return
            self.plant.hold_many(indices, columns.field("action")[rows])
            self.plant.arrivals[indices] = now
        self.count("actions_applied", len(indices))
        if self.sync is not None:
            self.sync.actions(indices, [steps[row] for row in rows], now)


@dataclass
class PlantHostRun:
    """What a plant host's run leaves for its summary."""

    robots: list[str]
    starts: np.ndarray
    plant: FleetPlant
    intakes: list[RobotIntake]


def run_plant_host(
    settings: Settings,
    bus: Bus,
    robots: list[str],
    starts: np.ndarray,
    stop: threading.Event,
    duration: float | None,
    synced: bool,
) -> PlantHostRun:
    """Simulate ``robots`` from ``starts`` in real time until ``stop`` or ``duration``: one robot
    (``srl plant-sim``) or a fleet (``--robots``) alike. ``synced``: each robot's states only at the
    state ticks just before its actor's (:class:`StateSync`, ``transport.state_sync``, one robot's
    as a fleet's); else every state tick, at ``state_rate`` (``srl up --view``: the view draws them)."""
    plant = FleetPlant(settings, robots, starts)
    for robot in robots:  # one plant per robot, before declaring
        bus.refuse_other_plant(robot)
    # the states of one state tick in one round, as one batch (common.contracts.keys.Batch)
    publish_states = bus.round_publisher(settings.wire.STATE, batches=len(robots) > 1)
    period = 1.0 / settings.transport.state_rate
    sync = StateSync(len(robots), settings.plant.sampling_time, period) if synced else None
    lock = threading.Lock()  # every robot's intake's: a batch of actions is taken under it
    intakes = [RobotIntake(plant, i, bus, sync, lock) for i in range(len(robots))]
    for robot, intake in zip(robots, intakes, strict=True):
        bus.watch_identities(robot, "actor", intake.gate.gate, intake.on_actor_identity)
    actions = settings.wire.ACTION
    bus.subscribe_columns(
        actions, [actions.key(robot) for robot in robots], ActionRounds(plant, intakes, bus.count, sync)
    )
    bus.declare_sole_plants(robots)
    rows = [(robot, plant_status(plant, intake)) for robot, intake in zip(robots, intakes, strict=True)]
    if len(robots) == 1:  # the host's counters are its one robot's (refused actions: srl up's live line)
        rows = [(robots[0], bus_status(bus, rows[0][1]))]
    start_status_thread(bus, rows, settings.transport.status_period, stop)
    log.info("plant host ready: %d robots (%s)", len(robots), settings.plant.model)
    timeout = action_timeout(settings)
    for now, elapsed in state_ticks(settings, bus, stop, duration):
        round_ = plant_tick(plant, intakes, sync, now, elapsed, timeout)
        if round_ is None:  # quiet: nothing moved, nothing due
            bus.count("states_held_back", len(robots))
            bus.count("quiet_ticks")
            continue
        publish_states(round_)
        bus.count("states_published", len(round_))
        bus.count("states_held_back", len(robots) - len(round_))
    return PlantHostRun(robots, np.array(starts, dtype=float).reshape(len(robots), -1), plant, intakes)


def plant_tick(
    plant: FleetPlant,
    intakes: list[RobotIntake],
    sync: StateSync | None,
    now: float,
    elapsed: float,
    timeout: float,
) -> Columns[PlantState] | None:
    """One state tick at ``now``, ``elapsed`` s after the previous: the watchdogs due, then every
    robot advanced and the round of states due (``sync`` None: every robot's). None: a quiet tick,
    no robot's state due (``sync``) and none moving (:meth:`FleetPlant.still`): nothing is
    advanced (a still robot's step is the identity) and nothing published. A fleet at rest whose
    actor hosts tick in one or two phases a period wakes to publish at one or two of the
    period's state ticks; the others cost the watchdogs' test alone."""
    for i in due_watchdogs(plant.arrivals, now, timeout):
        intakes[i].watchdog(now, timeout)
    due = None if sync is None else sync.due(now)
    if due is not None and not due.any() and plant.still():
        return None
    return plant.advance(elapsed, due)


def plant_host_summary(run: PlantHostRun, settings: Settings, bus: Bus, radius: float) -> FleetPlantSummary:
    """What a plant host prints, whatever the number of robots: each robot's own
    :class:`PlantSummary` and the process's counters; a host of one robot prints its robot's
    (common.contracts.summaries.robot_summary)."""
    return FleetPlantSummary(
        robots=run.robots,
        plant_model=settings.plant.model,
        circle_radius_m=radius,
        per_robot={
            robot: PlantSummary(
                mode="realtime",
                plant_model=settings.plant.model,
                start_state=[float(c) for c in run.starts[i]],
                final_state=run.plant.reported(i),
                true_final_state=run.plant.truth(i),
                saturated_commands=run.plant.saturated_commands(i),
                counters={
                    "actions_applied": run.intakes[i].applied,
                    "actions_refused": run.intakes[i].refused,
                    "watchdog_stops": run.intakes[i].watchdog_stops,
                    "actor_lost_stops": run.intakes[i].actor_lost_stops,
                },
            )
            for i, robot in enumerate(run.robots)
        },
        missed_ticks=int(bus.counters.get("missed_ticks", 0)),
        counters={k: float(v) for k, v in bus.counters.items()},
    )


def plant_status(plant: FleetPlant, intake: RobotIntake) -> Callable[[], dict[str, float]]:
    """One robot's status counters (``srl/<robot>/status/plant``)."""
    i = intake.index

    def counters() -> dict[str, float]:
        return {
            "seq": float(plant.seq[i]) if plant.ideal else float(plant.plants[i].seq),
            "actions_applied": float(intake.applied),
            "watchdog_stops": float(intake.watchdog_stops),
        }

    return counters
