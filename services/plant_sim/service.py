"""plant_sim: the simulated robot (exact sample-and-hold unicycle).

* lockstep: queryables ``plant/reset`` and ``plant/step`` (declared in this mode only: apply
  this action for ``duration``, return the next state). A repeated request for the step just
  applied (a retry after a lost reply) returns the same reply again instead of applying the
  action twice.
* realtime: integrates continuously at ``state_rate`` Hz with the newest action held, publishes
  the state each period, and stops the robot (zero velocity) when no action arrived for
  ``action_timeout_steps * delta``. It serves no query: a step or reset from anyone would move
  the robot behind the actor's back (issue 13, finding 3), so neither queryable is declared.
Every applied action is clamped to the robot's limits; messages are validated by schema.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import numpy as np

from common.clock import Ticker
from common.dynamics import exact_step
from common.keys import ACTION, PLANT_RESET, PLANT_STEP, STATE
from common.messages import Action, PlantState, ResetRequest, StepRequest
from common.provenance import ActionGate, SourceGate
from common.settings import Settings
from common.summaries import PlantSummary
from common.transport import Bus, start_status_thread

log = logging.getLogger(__name__)


class SimulatedPlant:
    """The state machine behind both modes (transport-free, so it is testable directly)."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.robot = settings.transport.robot
        self.bounds = np.array([settings.plant.v_max, settings.plant.omega_max])
        self.lock = threading.Lock()
        self.episode = 0
        self.state = settings.start_state()
        self.seq = 0
        self.next_step = 0
        self._last_reply: tuple[tuple[int, int], PlantState] | None = None

    def _message(self) -> PlantState:
        self.seq += 1
        return PlantState(
            robot=self.robot,
            episode=self.episode,
            seq=self.seq,
            stamp_ns=time.monotonic_ns(),
            state=(float(self.state[0]), float(self.state[1]), float(self.state[2])),
            source="sim",
        )

    def clamp(self, action: tuple[float, float]) -> np.ndarray:
        return np.clip(np.asarray(action, dtype=float), -self.bounds, self.bounds)

    def reset(self, request: ResetRequest) -> PlantState:
        with self.lock:
            self.episode = request.episode
            self.state = np.asarray(request.state, dtype=float)
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
            self.state = exact_step(self.state, self.clamp(request.action), request.duration)
            self.next_step += 1
            reply = self._message()
            self._last_reply = (key, reply)
            return reply

    def advance(self, action: np.ndarray, duration: float) -> PlantState:
        with self.lock:
            self.state = exact_step(self.state, action, duration)
            return self._message()


def run(settings: Settings, bus: Bus, mode: str, stop: threading.Event, duration: float | None) -> dict:
    plant = SimulatedPlant(settings)
    robot = settings.transport.robot
    # one plant per robot (issue 13): a second simulator (or a bridge) for the same robot would
    # make the actor follow one robot's states while commanding another
    bus.refuse_other_plant(robot)
    publish_state = bus.publisher(STATE, robot)
    if mode == "lockstep":  # real time: nobody may teleport or step the robot (the queryables do not exist)
        bus.serve(PLANT_RESET, robot, lambda r: _publish(publish_state, plant.reset(r)))
        bus.serve(PLANT_STEP, robot, lambda r: _publish(publish_state, plant.step(r)))

    latest: dict[str, object] = {"action": np.zeros(2), "at": None}
    # whose actions drive the robot: only the live actor session's, in its order (issue 13: the
    # same gate as the robot bridge's; a stray or forged publisher on the key is refused, counted)
    actions = ActionGate(SourceGate("actor"))
    action_lock = threading.Lock()

    def on_action(message: Action, source: str | None) -> None:
        now = time.monotonic()
        with action_lock:
            refusal = actions.admit(message.episode, message.step, source, now)
            if refusal is not None:
                bus.reject(*refusal)
                return
            latest["action"] = plant.clamp(message.action)
            latest["at"] = now
        bus.count("actions_applied")

    def on_actor_identity(zid: str, alive: bool) -> None:
        with action_lock:
            if not alive and actions.lost(zid):  # the followed actor is gone: stop at once
                latest["action"], latest["at"] = np.zeros(2), None
                bus.count("actor_lost_stops")

    if mode == "realtime":
        bus.watch_identities(robot, "actor", actions.gate, on_actor_identity)
        bus.subscribe(ACTION, ACTION.key(robot), on_action, with_source=True)
    bus.declare_sole_plant(robot)  # and a plant started at the same moment: one of the two yields
    start_status_thread(bus, robot, settings.transport.status_period, stop, lambda: {"seq": plant.seq})
    log.info("plant_sim ready (%s mode, robot %s)", mode, robot)

    if mode == "realtime":
        period = 1.0 / settings.transport.state_rate
        timeout = settings.transport.action_timeout_steps * settings.plant.sampling_time
        ticker = Ticker(period, stop)
        end = None if duration is None else time.monotonic() + duration
        last = time.monotonic()
        while (now := ticker.wait()) is not None and (end is None or now < end):
            at = latest["at"]
            fresh = at is not None and now - float(at) <= timeout  # type: ignore[arg-type]
            if not fresh and at is not None:
                bus.count("watchdog_stops")
                latest["at"] = None  # stopped: zero until the next fresh action
                latest["action"] = np.zeros(2)
            action = latest["action"] if fresh else np.zeros(2)
            publish_state(plant.advance(action, now - last))  # type: ignore[arg-type]
            last = now
        bus.count("missed_ticks", ticker.missed)
    else:
        stop.wait(duration)
    return PlantSummary.model_validate(
        {"mode": mode, "final_state": [float(c) for c in plant.state], "counters": dict(bus.counters)}
    ).to_json_dict()


def _publish(publish_state: Callable[[PlantState], None], message: PlantState) -> PlantState:
    publish_state(message)
    return message
