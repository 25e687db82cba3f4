"""actor: the delta-periodic loop of stacked RL-QV (or its baselines).

* realtime: ticks at absolute times ``t0 + k delta`` on the monotonic clock; at each tick it
  takes the newest state, solves, publishes the action and one transition. It never waits for
  the critic: it uses the newest weights it holds and reports their staleness. If the state
  stopped arriving (zero goes out within ``action_timeout_steps * delta`` of the last state),
  never came, or the plant's liveliness token vanished (zero at the next tick), it commands
  zero velocity at every tick and records no transition (so the critic sees a gap, never a
  false pair); fresh states resume the loop.
* lockstep: runs Algorithm 1 (:func:`common.assembly.run_episode`) with the plant behind its Zenoh
  queryable and the off-board critic; with ``sync_critic`` it waits (bounded) for the weights
  trained on the previous step, which makes the distributed run the paper's algorithm exactly.

Weights are accepted only for the current episode and a strictly newer version; the schema
already guarantees finite values of the right length.
"""

from __future__ import annotations

import gc
import logging
import math
import os
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.actor import StackedActor
from common.assembly import build_actor, episode_summary, run_episode
from common.clock import Ticker
from common.critic import Sample
from common.features import stage_cost
from common.keys import ACTION, PLANT_RESET, PLANT_STEP, STATE, TRANSITION, WEIGHTS, Service
from common.messages import (
    Action,
    CriticWeights,
    Message,
    MessageError,
    PlantState,
    ResetRequest,
    StepRequest,
    Transition,
)
from common.provenance import SequenceGuard, SourceGate
from common.settings import Settings
from common.stats import summarize
from common.transport import Bus, start_status_thread

log = logging.getLogger(__name__)
MAX_VERSION_AHEAD_US = 60_000_000  # clock skew allowed between the critic's host and ours
# A state's seq may run at most this far ahead of the last accepted one of its plant session
# (plant_sim publishes at transport.state_rate <= 1000 Hz, the bridge at the odometry rate):
# one forged PlantState(seq=2**62) must not make every real state "old" for the rest of the run.
MAX_SEQ_JUMP = 10_000
# Weights beyond the critic's box are refused; without a box (critic.weight_bounds = []) this
# is the bound: far above any fit of ours (README), far below where the objective overflows.
MAX_ABS_WEIGHT_UNBOXED = 1e6
PUBLISH_TIMES_KEPT = 1000  # steps whose publication time is kept (weight age in ms)


@dataclass
class HeldWeights:
    q: np.ndarray
    v: np.ndarray
    version: int
    trained_step: int
    received_at: float


class WeightsInbox:
    """Newest accepted critic weights of the current episode (thread-safe).

    Weights are accepted only (issue 13): from the live critic session when a ``gate`` is given
    (its identity token, common.provenance), for the current episode, newer than the held
    version of the same critic session (a new session -- a restarted critic -- resynchronizes),
    within the configured weight box (else the last good weights are kept), and trained on a
    step the actor has already published (``published_step``): a forged far-future version or
    trained step can neither lock out the real critic nor falsify the staleness figures.
    """

    def __init__(self, settings: Settings, bus: Bus, gate: SourceGate | None = None) -> None:
        self.settings = settings
        self.bus = bus
        self.gate = gate
        self.cond = threading.Condition()
        self.episode = -1
        self.published_step = -1  # the newest transition step this actor published (this episode)
        self.source: str | None = None  # the critic session whose versions are held
        bounds = settings.critic.bounds
        self.box = bounds if bounds is not None else (-MAX_ABS_WEIGHT_UNBOXED, MAX_ABS_WEIGHT_UNBOXED)
        self.held = HeldWeights(settings.initial_q_weights(), settings.initial_v_weights(), 0, -1, time.monotonic())

    def reset(self, episode: int) -> HeldWeights:
        with self.cond:
            self.episode = episode
            self.published_step = -1
            self.source = None
            self.held = HeldWeights(
                self.settings.initial_q_weights(), self.settings.initial_v_weights(), 0, -1, time.monotonic()
            )
            return self.held

    def published(self, step: int) -> None:
        with self.cond:
            self.published_step = max(self.published_step, step)

    def offer(self, message: CriticWeights, source: str | None = None) -> None:
        if self.gate is not None:
            verdict = self.gate.verdict(source)
            if verdict != "accept":
                self.bus.reject(
                    "critic/weights", f"from session {source} ({verdict}: live critic {self.gate.sources() or 'none'})"
                )
                return
        low, high = self.box
        weights = (*message.q_weights, *message.v_weights)
        if min(weights) < low or max(weights) > high:
            self.bus.reject(
                "critic/weights",
                f"weights outside the box [{low:g}, {high:g}] "
                f"(min {min(weights):g}, max {max(weights):g}); keeping version {self.held.version}",
            )
            return
        with self.cond:
            if message.episode != self.episode:
                self.bus.reject("critic/weights", f"episode {message.episode} is not {self.episode}")
                return
            if message.trained_step > self.published_step:
                self.bus.reject(
                    "critic/weights",
                    f"trained on step {message.trained_step}, but the actor published only up to {self.published_step}",
                )
                return
            if message.version > time.time_ns() // 1000 + MAX_VERSION_AHEAD_US:
                # critic versions count from the wall clock in microseconds: one far ahead is
                # forged or corrupt (a sanity bound; provenance is what keeps forgers out)
                self.bus.reject("critic/weights", f"version {message.version} is from the future")
                return
            same_source = source == self.source
            if same_source and message.version <= self.held.version:
                self.bus.reject("critic/weights", f"version {message.version} <= held {self.held.version}")
                return
            if not same_source and self.source is not None:
                log.info("critic session %s replaces %s: versions resynchronized", source, self.source)
                self.bus.count("critic_resyncs")
            self.source = source
            self.held = HeldWeights(
                np.array(message.q_weights),
                np.array(message.v_weights),
                message.version,
                message.trained_step,
                time.monotonic(),
            )
            self.bus.count("weights_accepted")
            self.cond.notify_all()

    def current(self) -> HeldWeights:
        with self.cond:
            return self.held

    def wait_trained(self, step: int, timeout: float) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: self.held.trained_step >= step, timeout)


def new_episode_id() -> int:
    """Episode ids increase across restarts (milliseconds since the epoch)."""
    return time.time_ns() // 1_000_000


class ZenohPlant:
    """The plant behind its lockstep queryables; retries are safe (the plant is idempotent)."""

    def __init__(self, settings: Settings, bus: Bus, episode: int) -> None:
        self.settings, self.bus, self.episode = settings, bus, episode
        self.robot = settings.transport.robot
        self.step_index = 0

    def _query(self, service: Service[Any, Any], request: Message) -> Any:
        timeout = self.settings.transport.query_timeout
        for attempt in range(3):
            try:
                return self.bus.query(service, self.robot, request, timeout)
            except TimeoutError:
                self.bus.count("plant_query_retries")
                log.warning("plant query timed out (attempt %d)", attempt + 1)
        raise TimeoutError(f"plant did not answer {service.pattern} three times")

    def reset(self, state: np.ndarray) -> np.ndarray:
        self.step_index = 0
        reply = self._query(
            PLANT_RESET,
            ResetRequest(
                robot=self.robot, episode=self.episode, state=(float(state[0]), float(state[1]), float(state[2]))
            ),
        )
        return np.array(reply.state)

    def apply(self, action: np.ndarray, duration: float) -> np.ndarray:
        request = StepRequest(
            robot=self.robot,
            episode=self.episode,
            step=self.step_index,
            action=(float(action[0]), float(action[1])),
            duration=duration,
        )
        reply = self._query(PLANT_STEP, request)
        self.step_index += 1
        return np.array(reply.state)


class ZenohCriticPort:
    """Transitions out to the off-board critic; weights back (optionally waited for)."""

    def __init__(self, settings: Settings, bus: Bus, inbox: WeightsInbox, episode: int, sync: bool) -> None:
        self.settings, self.bus, self.inbox, self.episode, self.sync = settings, bus, inbox, episode, sync
        self.robot = settings.transport.robot
        self.publish = bus.publisher(TRANSITION, self.robot, cache=settings.transport.transition_cache)
        self.staleness: list[int] = []
        self.timeouts = 0

    def reset(self) -> tuple[np.ndarray, np.ndarray]:
        held = self.inbox.reset(self.episode)
        return held.q, held.v

    def record(self, sample: Sample) -> tuple[np.ndarray, np.ndarray]:
        self.inbox.published(sample.step)
        self.publish(
            Transition(
                robot=self.robot,
                episode=self.episode,
                step=sample.step,
                state=(float(sample.state[0]), float(sample.state[1]), float(sample.state[2])),
                action=(float(sample.action[0]), float(sample.action[1])),
                cost=float(sample.cost),
            )
        )
        needs_fit = self.settings.actor.agent != "mpc" and sample.step % self.settings.critic.update_every == 0
        if self.sync and needs_fit and not self.inbox.wait_trained(sample.step, self.settings.transport.critic_timeout):
            self.timeouts += 1
            self.bus.count("critic_timeouts")
            log.warning(
                "no weights trained on step %d within %.1f s; going on with version %d",
                sample.step,
                self.settings.transport.critic_timeout,
                self.inbox.current().version,
            )
        held = self.inbox.current()
        # staleness of the weights the NEXT step will use: ideally trained on this step
        self.staleness.append(sample.step - held.trained_step)
        return held.q, held.v


def run(
    settings: Settings, bus: Bus, mode: str, stop: threading.Event, duration: float | None, sync_critic: bool
) -> dict:
    robot = settings.transport.robot
    actor = build_actor(settings)  # built once, before the loop starts
    critic_gate = SourceGate("critic")
    bus.watch_identities(robot, "critic", critic_gate)
    inbox = WeightsInbox(settings, bus, critic_gate)
    bus.subscribe(WEIGHTS, WEIGHTS.key(robot), inbox.offer, with_source=True)
    # the liveliness token means "ready": declared by each mode once all its inputs are subscribed
    if mode == "lockstep":
        return _run_lockstep(settings, bus, actor, inbox, sync_critic)
    return _run_realtime(settings, bus, actor, inbox, stop, duration)


def _run_lockstep(
    settings: Settings, bus: Bus, actor: StackedActor, inbox: WeightsInbox, sync_critic: bool
) -> dict[str, Any]:
    bus.declare_alive(settings.transport.robot)
    bus.wait_alive(settings.transport.robot, "plant", timeout=30.0)
    if sync_critic and settings.actor.agent != "mpc":
        bus.wait_alive(settings.transport.robot, "critic", timeout=30.0)
    episode_id = new_episode_id()
    inbox.reset(episode_id)
    plant = ZenohPlant(settings, bus, episode_id)
    port = ZenohCriticPort(settings, bus, inbox, episode_id, sync_critic)
    log.info(
        "actor lockstep episode %d: %s, N = %d, %d steps",
        episode_id,
        settings.actor.agent,
        settings.actor.horizon,
        settings.steps,
    )
    episode = run_episode(settings, actor=actor, plant=plant, critic=port)
    summary = episode_summary(episode, settings)
    summary.update(
        {
            "service": "actor",
            "mode": "lockstep",
            "episode_id": episode_id,
            "weights_version": inbox.current().version,
            "staleness_steps": summarize(port.staleness) | {"max": float(max(port.staleness, default=0))},
            "critic_timeouts": port.timeouts,
            "trajectory": [[float(c) for c in s] for s in episode.states],
            "counters": dict(bus.counters),
        }
    )
    return summary


def _run_realtime(
    settings: Settings,
    bus: Bus,
    actor: StackedActor,
    inbox: WeightsInbox,
    stop: threading.Event,
    duration: float | None,
) -> dict[str, Any]:
    robot = settings.transport.robot
    delta = settings.plant.sampling_time
    # A state older than this at a tick means the plant is silent: command zero. The last state
    # seen at t0 is then stale at the first tick after t0 + (n - 1) delta, i.e. the zero goes
    # out within n delta of the state stopping (n = action_timeout_steps >= 2).
    stale_after = (settings.transport.action_timeout_steps - 1) * delta
    latest: dict[str, tuple[PlantState, float] | None] = {"state": None}
    last_accepted: dict[str, PlantState | None] = {"state": None}  # for the summary: never a refused one
    state_lock = threading.Lock()
    # Provenance (issue 13): states only from the live plant session (its identity token), in
    # order per session, never more than MAX_SEQ_JUMP ahead; a new session resynchronizes.
    plant_gate = SourceGate("plant")
    order = SequenceGuard(MAX_SEQ_JUMP)
    episodes: dict[str, int] = {}
    refused_at = [0.0]  # when the live plant's last state was refused (a lockout shows in status)

    def on_plant_identity(zid: str, alive: bool) -> None:
        with state_lock:
            order.forget(set(plant_gate.sources()))
            if not alive:
                episodes.pop(zid, None)
            if plant_gate.conflict:
                latest["state"] = None  # follow neither of two plants
        if plant_gate.conflict:
            bus.count("plant_conflicts")
            log.error(
                "two plants are alive for robot %s (sessions %s): commanding zero velocity until one is gone",
                robot,
                ", ".join(plant_gate.sources()),
            )

    def on_state(message: PlantState, source: str | None) -> None:
        verdict = plant_gate.verdict(source)
        if verdict != "accept":
            bus.reject(f"state.{verdict}", f"from session {source} (live plant: {plant_gate.sources() or 'none'})")
            return
        assert source is not None
        with state_lock:
            if episodes.get(source) != message.episode:  # a new stream of the live plant (or its reset)
                episodes[source] = message.episode
                order.last.pop(source, None)
            refusal = order.check(source, message.seq)
            now = time.monotonic()
            if refusal is not None:
                refused_at[0] = now
                bus.reject("state", f"seq {refusal}")
                return
            latest["state"] = (message, now)
            last_accepted["state"] = message

    bus.watch_identities(robot, "plant", plant_gate, on_plant_identity)
    bus.subscribe(STATE, STATE.key(robot), on_state, with_source=True)

    def on_plant_token(alive: bool) -> None:
        # The plant (simulator or robot bridge) vanished: its last state is no longer the
        # robot's. Forget it, so the next tick commands zero velocity instead of waiting for
        # the state to go stale; fresh states resume the loop.
        if not alive:
            with state_lock:
                latest["state"] = None
            bus.count("plant_lost")
            log.warning("plant liveliness lost: commanding zero velocity until its state returns")

    bus.watch_alive(robot, "plant", on_plant_token)
    bus.declare_alive(robot)
    publish_action = bus.publisher(ACTION, robot)
    publish_transition = bus.publisher(TRANSITION, robot, cache=settings.transport.transition_cache)
    episode_id = new_episode_id()
    inbox.reset(episode_id)
    actor.reset()

    periods: list[float] = []
    latencies: list[float] = []
    staleness_steps: list[int] = []
    staleness_ms: list[float] = []
    costs: list[float] = []
    # the last M transitions as published: what a critic's replay must hold (checked by tests)
    tail: deque[list[float]] = deque(maxlen=settings.critic.replay_size)
    publish_times: dict[int, float] = {}
    published_steps: list[list[int]] = []  # the steps of the transitions published, as [first, last] runs
    counters = {"steps": 0, "stale_state_stops": 0, "plant_conflict_stops": 0}
    start_state = None
    start_time = time.monotonic()

    def extra() -> dict[str, float]:
        held = inbox.current()
        shown = latest["state"]  # for the live status line of `srl up`: pose and J so far
        pose = shown[0].state if shown is not None else (float("nan"),) * 3  # nan: left out
        return {
            "x": pose[0],
            "y": pose[1],
            "alpha": pose[2],
            "accumulated_cost": math.fsum(costs),
            "steps": counters["steps"],
            "missed_deadlines": ticker.missed,
            "solver_failures": actor.counters.failures,
            "weights_version": held.version,
            "staleness_steps": float(staleness_steps[-1]) if staleness_steps else 0.0,
            "solve_ms_last": actor.counters.solve_seconds[-1] * 1e3 if actor.counters.solve_seconds else 0.0,
            "plant_sources": float(len(plant_gate.sources())),
            "plant_conflict": float(plant_gate.conflict),
            "lockout_suspect": float(lockout_suspect()),
        }

    def lockout_suspect() -> bool:
        """The live plant's states are being refused and none was accepted for over a second:
        the pattern a forged far-ahead sequence number or episode leaves (status, issue 13)."""
        with state_lock:
            held = latest["state"]
        now = time.monotonic()
        return now - refused_at[0] < 1.0 and (held is None or now - held[1] > 1.0)

    def stop_robot(k: int) -> None:
        publish_action(
            Action(
                robot=robot, episode=episode_id, step=k, stamp_ns=time.monotonic_ns(), action=(0.0, 0.0), state_seq=-1
            )
        )
        actor.reset()  # the plan no longer matches the robot

    def step_once(k: int, tick: float, held_state: tuple[PlantState, float]) -> None:
        nonlocal start_state
        message, received = held_state
        state = np.array(message.state)
        if start_state is None:
            start_state = state
        weights = inbox.current()
        step = actor.step(state, weights.q, weights.v)
        action = (float(step.action[0]), float(step.action[1]))
        publish_action(
            Action(
                robot=robot,
                episode=episode_id,
                step=k,
                stamp_ns=time.monotonic_ns(),
                action=action,
                state_seq=message.seq,
            )
        )
        done = time.monotonic()
        # transport/loop latency: state arrival -> action out, minus the solve itself
        latencies.append(max(0.0, done - max(received, tick) - step.solve_seconds))
        cost = delta * float(stage_cost(state, step.action, settings.cost.r_diag))
        costs.append(cost)
        inbox.published(k)  # before the transition goes out: weights trained on it may come back at once
        publish_transition(
            Transition(
                robot=robot,
                episode=episode_id,
                step=k,
                state=(float(state[0]), float(state[1]), float(state[2])),
                action=action,
                cost=cost,
            )
        )
        publish_times[k] = time.monotonic()
        publish_times.pop(k - PUBLISH_TIMES_KEPT, None)
        tail.append([k, float(state[0]), float(state[1]), float(state[2]), *action, cost])
        if published_steps and published_steps[-1][1] == k - 1:
            published_steps[-1][1] = k
        else:
            published_steps.append([k, k])
        if settings.actor.agent != "mpc":
            staleness_steps.append((k - 1) - weights.trained_step)
            seen = publish_times.get(weights.trained_step)
            staleness_ms.append((done - seen) * 1e3 if seen is not None else float("nan"))
        counters["steps"] += 1

    end = None if duration is None else start_time + duration
    previous_tick = None
    # Garbage collection off the critical path: what exists now is frozen out of the collector,
    # automatic collection is off, and the loop collects in its slack time after each tick's
    # work is out (the young generation every tick, the middle one every 10, all every 600).
    # SRL_ACTOR_AUTOMATIC_GC=1 keeps Python's automatic collection (for comparison).
    gc.collect()
    gc.freeze()
    manual_gc = gc.isenabled() and os.environ.get("SRL_ACTOR_AUTOMATIC_GC") != "1"
    if manual_gc:
        gc.disable()
    # the clock starts after that collection (it can take longer than a tick on a busy machine)
    ticker = Ticker(delta, stop)
    start_status_thread(bus, robot, settings.transport.status_period, stop, extra)
    try:
        while (tick := ticker.wait()) is not None and (end is None or tick < end):
            if previous_tick is not None:
                periods.append(tick - previous_tick)
            previous_tick = tick
            k = ticker.index - 1
            with state_lock:
                held_state = latest["state"]
            if plant_gate.conflict:
                counters["plant_conflict_stops"] += 1
                stop_robot(k)
            elif held_state is None or tick - held_state[1] > stale_after:
                counters["stale_state_stops"] += 1
                stop_robot(k)
            else:
                try:
                    step_once(k, tick, held_state)
                except Exception:  # never let one bad tick end the loop that keeps the robot safe
                    bus.count("tick_errors")
                    log.exception("actor tick %d failed; commanding zero velocity", k)
                    stop_robot(k)
            if manual_gc:
                gc.collect(2 if k % 600 == 599 else 1 if k % 10 == 9 else 0)
    finally:
        if manual_gc:
            gc.enable()
        gc.unfreeze()

    with state_lock:
        last = last_accepted["state"]
    # on the way out: stop the robot
    publish_action(
        Action(
            robot=robot,
            episode=episode_id,
            step=ticker.index,
            stamp_ns=time.monotonic_ns(),
            action=(0.0, 0.0),
            state_seq=-1,
        )
    )
    jitter = [abs(p - delta) for p in periods]
    return {
        "service": "actor",
        "mode": "realtime",
        "agent": settings.actor.agent,
        "horizon": settings.actor.horizon,
        "episode_id": episode_id,
        "steps": counters["steps"],
        "accumulated_cost": float(np.sum(costs)),
        "start_state": None if start_state is None else [float(c) for c in start_state],
        "final_state": None if last is None else [float(c) for c in last.state],
        "weights_version": inbox.current().version,
        "loop": {
            "period_ms": summarize(periods, 1e3),
            "jitter_ms": summarize(jitter, 1e3),
            "missed_deadlines": ticker.missed,
            "late_ticks": ticker.late,
        },
        "solve_ms": summarize(actor.counters.solve_seconds, 1e3),
        "solver_failures": actor.counters.failures,
        "latency_ms": summarize(latencies, 1e3),
        "staleness_steps": summarize(staleness_steps),
        "staleness_ms": summarize([s for s in staleness_ms if s == s]),
        "stale_state_stops": counters["stale_state_stops"],
        "plant_conflict_stops": counters["plant_conflict_stops"],
        "plant_sources": plant_gate.sources(),
        "transitions_tail": list(tail),
        "transition_steps": published_steps,
        "counters": dict(bus.counters),
    }


__all__ = ["MessageError", "run"]
