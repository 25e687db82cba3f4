"""plant_sim: the simulated robot, ``plant.model``: the exact sample-and-hold unicycle (ideal)
or a TurtleBot3's actuators and odometry (actuator, common/math/turtlebot.py; physics, the MuJoCo
Burger of common/math/physics.py). Its states carry the
reported pose (the odometry) and, since a simulator knows it, the true pose beside it.

* lockstep (:func:`run`): queryables ``plant/reset`` and ``plant/step`` (declared in this mode
  only: apply this action for ``duration``, return the next state). A repeated request for the
  step just applied (a retry after a lost reply) returns the same reply again instead of applying
  the action twice.
* realtime: a plant host (services/plant_sim/host.py) of this one robot or of many integrates
  continuously at ``state_rate`` Hz with the newest action held, publishes the states, and stops
  a robot (zero velocity) when no action arrived for ``action_timeout_steps * delta``
  (:class:`ActionIntake`). It serves no query: a step or reset from anyone would move the robot
  behind the actor's back, so neither queryable is declared.
Every applied action is clamped to the robot's limits; messages are validated by schema.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from common.config.settings import Settings
from common.contracts.messages import Action, PlantState, ResetRequest, StepRequest
from common.contracts.summaries import PlantSummary
from common.math.plant_models import simulated_robot
from common.math.turtlebot import SimulatedRobot
from common.net.provenance import ActionGate, SourceGate
from common.net.transport import Bus, bus_status, start_status_thread
from common.process.runtime import realtime_priority
from common.system.clock import Ticker

log = logging.getLogger(__name__)


def action_timeout(settings: Settings) -> float:
    """[s] how old the newest action may be before the watchdog stops the robot."""
    return settings.transport.action_timeout_steps * settings.plant.sampling_time


def state_ticks(
    settings: Settings, bus: Bus, stop: threading.Event, duration: float | None
) -> Iterator[tuple[float, float]]:
    """The real-time plant's clock: ``(now, seconds since the previous tick)`` at
    ``transport.state_rate`` until ``stop`` or ``duration``; the missed ticks counted on ``bus``
    at the end (one robot's plant_sim and the plant host alike).

    The caller's loop runs under ``SCHED_FIFO`` at ``plant.realtime_priority`` where the user may
    (:func:`~common.process.runtime.realtime_priority`, counted as ``realtime_priority``, 0 where
    refused), as the actor's tick thread does: the actors act on the states it publishes, and a
    state published late is a robot stopped on a stale state (docs/fleets.md)."""
    ticker = Ticker(1.0 / settings.transport.state_rate, stop)
    end = None if duration is None else time.monotonic() + duration
    with realtime_priority(settings.plant.realtime_priority, "plant") as priority:
        bus.count("realtime_priority", priority)
        last = time.monotonic()
        try:
            while (now := ticker.wait()) is not None and (end is None or now < end):
                yield now, now - last
                last = now
        finally:
            bus.count("missed_ticks", ticker.missed)


class ActionIntake:
    """One robot's actions into a plant: only the live actor session's, in its order
    (:class:`~common.net.provenance.ActionGate`: a stray or forged publisher on the key is refused,
    counted), each held until the next; zero velocity at once when the followed actor session is
    gone, and from the watchdog when no action came for ``action_timeout_steps * delta``.
    One plant_sim and each robot of the plant host alike (transport-free).

    ``hold`` takes the action to hold (it clamps it to the robot's limits), ``reject`` a refusal
    (what, why), ``count`` (optional) each of ``actions_applied``, ``actor_lost_stops`` and
    ``watchdog_stops`` as it happens; the same counts are kept as attributes. ``arrivals``,
    ``index``: where it keeps when the held action arrived (NaN: holding zero), element ``index``
    of an array of many robots' (a plant host's: :func:`due_watchdogs` reads them all at once).
    ``action_dim``: the system's actions (a stop holds ``action_dim`` zeros; the robot's
    ``(v, omega)``: 2)."""

    def __init__(
        self,
        hold: Callable[[Any], None],
        reject: Callable[[str, str], None],
        count: Callable[[str], None] | None = None,
        arrivals: np.ndarray | None = None,
        index: int = 0,
        lock: threading.Lock | None = None,
        action_dim: int = 2,
    ) -> None:
        self.hold, self.reject, self.count = hold, reject, count
        self.zero = np.zeros(action_dim)  # what a stop holds: the system's zero action
        self.gate = ActionGate(SourceGate("actor"))
        self.lock = lock or threading.Lock()  # a plant host's robots share one (its batch intake)
        self.arrivals = np.full(1, math.nan) if arrivals is None else arrivals
        self.index = index
        self.applied = 0
        self.refused = 0
        self.watchdog_stops = 0
        self.actor_lost_stops = 0

    @property
    def at(self) -> float | None:
        """When the held action arrived (None: holding zero)."""
        at = float(self.arrivals[self.index])
        return None if math.isnan(at) else at

    @at.setter
    def at(self, value: float | None) -> None:
        self.arrivals[self.index] = math.nan if value is None else value

    def _counted(self, name: str) -> None:
        if self.count is not None:
            self.count(name)

    def on_action(self, message: Action, source: str | None) -> None:
        self.take(message, source)

    def take(self, message: Action, source: str | None) -> float | None:
        """An action from session ``source``: held if admitted; when it arrived (None: refused)."""
        now = time.monotonic()
        with self.lock:
            if not self.admitted(message.episode, message.step, source, now):
                return None
            self.hold(message.action)
            self.at = now
        self._counted("actions_applied")
        return now

    def admitted(self, episode: int, step: int, source: str | None, now: float) -> bool:
        """Under :attr:`lock`: does the gate admit the action (counted as applied: the caller holds
        it and sets :attr:`at` before the lock is released)? A refusal is counted and reported."""
        refusal = self.gate.admit(episode, step, source, now)
        if refusal is not None:
            self.refused += 1
            self.reject(*refusal)
            return False
        self.applied += 1
        return True

    def on_actor_identity(self, zid: str, alive: bool) -> None:
        with self.lock:
            if not alive and self.gate.lost(zid, time.monotonic()):  # the followed actor is gone: stop at once
                self.at = None
                self.hold(self.zero)
                self.actor_lost_stops += 1
                self._counted("actor_lost_stops")

    def watchdog(self, now: float, timeout: float) -> None:
        """Zero velocity once the held action is older than ``timeout`` [s], until a fresh one."""
        with self.lock:
            if self.at is not None and now - self.at > timeout:
                self.watchdog_stops += 1
                self._counted("watchdog_stops")
                self.at = None  # stopped: zero until the next fresh action
                self.hold(self.zero)


def due_watchdogs(arrivals: np.ndarray, now: float, timeout: float) -> np.ndarray:
    """The robots whose held action is older than ``timeout`` at ``now`` (:meth:`ActionIntake.watchdog`'s
    test, the same arithmetic, for all robots at once; NaN, holding zero, is never due): each
    one's own watchdog then decides under its lock (an action may have come since)."""
    with np.errstate(invalid="ignore"):
        due: np.ndarray = np.flatnonzero((now - arrivals) > timeout)
    return due


class SimulatedPlant:
    """The state machine behind both modes (transport-free, so it is testable directly)."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.robot_id = settings.transport.robot
        self.system, self.wire = settings.system, settings.wire  # the robot's, or another system's
        self.bounds = np.array(settings.action_max)
        self.lock = threading.Lock()
        self.episode = 0
        self.state = settings.start_state()  # the true state (ideal: also the reported one)
        # the TurtleBot3 (actuator or physics model) whose odometry is reported (None: ideal)
        self.robot = self._new_robot()
        self.held = np.zeros(self.system.action_dim)
        self.seq = 0
        self.next_step = 0
        self._last_reply: tuple[tuple[int, int], PlantState] | None = None

    def _new_robot(self) -> SimulatedRobot | None:
        s = self.settings
        return simulated_robot(s.plant.model, s.turtlebot_params(), s.physics_params(), self.state)

    @property
    def reported(self) -> np.ndarray:
        """What the robot reports: its odometry (ideal: the true state)."""
        return self.state if self.robot is None else self.robot.odometry

    def _message(self) -> PlantState:
        self.seq += 1
        reported, true = self.reported, self.state
        return self.wire.state(
            **self.wire.named,
            robot=self.robot_id,
            episode=self.episode,
            seq=self.seq,
            stamp_ns=time.monotonic_ns(),
            state=tuple(float(c) for c in reported),
            source="sim",
            true_state=tuple(float(c) for c in true),
            saturated_commands=0 if self.robot is None else self.robot.saturated_commands,
        )

    def _hold(self, action: np.ndarray) -> None:
        """A new command (the TurtleBot converts it as its firmware does, once per command)."""
        self.held = np.asarray(action, dtype=float)
        if self.robot is not None:
            self.robot.command(float(self.held[0]), float(self.held[1]))

    def _integrate(self, duration: float) -> None:
        if self.robot is None:  # the exact sample-and-hold (another system: its row's step)
            self.state = self.system.step(self.state, self.held, duration)
        else:
            self.robot.advance(duration)
            self.state = self.robot.true_pose.copy()

    def clamp(self, action: tuple[float, ...]) -> np.ndarray:
        return np.clip(np.asarray(action, dtype=float), -self.bounds, self.bounds)

    def reset(self, request: ResetRequest) -> PlantState:
        with self.lock:
            self.episode = request.episode
            self.state = np.asarray(request.state, dtype=float)
            if self.robot is not None:  # at rest at the start, odometry from there, slip re-seeded
                self.robot = self._new_robot()
            self.held = np.zeros(self.system.action_dim)
            self.next_step = 0
            self._last_reply = None
            return self._message()

    def step(self, request: StepRequest) -> PlantState:
        with self.lock:
            if request.episode != self.episode:
                raise ValueError(f"step for episode {request.episode}, plant is in episode {self.episode}")
            key = (request.episode, request.step)
            if self._last_reply is not None and self._last_reply[0] == key:
                return self._last_reply[1]  # a retried request: never apply an action twice
            if request.step != self.next_step:
                raise ValueError(f"step {request.step} out of order, expected {self.next_step}")
            self._hold(self.clamp(request.action))
            self._integrate(request.duration)
            self.next_step += 1
            reply = self._message()
            self._last_reply = (key, reply)
            return reply

    def hold(self, action: np.ndarray) -> None:
        """Real time: the newest action (or zero after the watchdog), held until the next."""
        with self.lock:
            self._hold(action)

    def advance(self, duration: float) -> PlantState:
        with self.lock:
            self._integrate(duration)
            return self._message()


def run(settings: Settings, bus: Bus, stop: threading.Event, duration: float | None) -> dict:
    """The lockstep plant of one robot: it moves only when the actor steps it (real time is a
    plant host's, services/plant_sim/host.py, of one robot or many)."""
    plant = SimulatedPlant(settings)
    robot = settings.transport.robot
    # one plant per robot: a second simulator (or a bridge) for the same robot would
    # make the actor follow one robot's states while commanding another
    bus.refuse_other_plant(robot)
    publish_state = bus.publisher(settings.wire.STATE, robot)
    bus.serve(settings.wire.PLANT_RESET, robot, lambda r: _publish(publish_state, plant.reset(r)))
    bus.serve(settings.wire.PLANT_STEP, robot, lambda r: _publish(publish_state, plant.step(r)))
    bus.declare_sole_plant(robot)  # and a plant started at the same moment: one of the two yields
    start_status_thread(
        bus, [(robot, bus_status(bus, lambda: {"seq": plant.seq}))], settings.transport.status_period, stop
    )
    log.info("plant_sim ready (lockstep mode, robot %s)", robot)
    stop.wait(duration)
    return PlantSummary.model_validate(
        {
            "mode": "lockstep",
            "plant_model": settings.plant.model,
            "final_state": [float(c) for c in plant.reported],
            "true_final_state": [float(c) for c in plant.state],
            "saturated_commands": 0 if plant.robot is None else plant.robot.saturated_commands,
            "counters": dict(bus.counters),
        }
    ).to_json_dict()


def _publish(publish_state: Callable[[PlantState], None], message: PlantState) -> PlantState:
    publish_state(message)
    return message
