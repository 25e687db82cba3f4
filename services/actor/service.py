"""actor: the delta-periodic loop of stacked RL-QV (or its baselines).

* realtime: ticks at absolute times ``t0 + k delta`` on the monotonic clock; at each tick it
  takes the newest state, solves, publishes the action and one transition. It never waits for
  the critic: it uses the newest weights it holds and reports their staleness. If the state
  stopped arriving (zero goes out within ``action_timeout_steps * delta`` of the last state),
  never came, or the plant's liveliness token vanished (zero at the next tick), it commands
  zero velocity at every tick and records no transition (so the critic sees a gap, never a
  false pair); fresh states resume the loop.
* lockstep: runs Algorithm 1 (:func:`common.config.assembly.run_episode`) with the plant behind its Zenoh
  queryable and the off-board critic; with ``sync_critic`` it waits (bounded) for the weights
  trained on the previous step, which makes the distributed run the paper's algorithm exactly.

The real-time loop is :class:`services.actor.realtime.RealtimeActor`; the ports (weights inbox,
lockstep plant, critic port) are in :mod:`services.actor.ports`.
"""

from __future__ import annotations

import gc
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from common.config.assembly import build_actor, episode_summary, run_episode
from common.config.settings import Settings
from common.contracts.keys import ACTION, STATE, TRANSITION, WEIGHTS
from common.contracts.messages import (
    Action,
    MessageError,
    Transition,
)
from common.contracts.summaries import LockstepActorSummary, format_status_line
from common.math.actor import StackedActor
from common.math.agents import learns
from common.math.stats import summarize
from common.net.provenance import SourceGate
from common.net.transport import Bus, bus_status, start_status_thread
from common.process.runtime import realtime_priority
from common.system.clock import Ticker
from services.actor.ports import WeightsInbox, ZenohCriticPort, ZenohPlant, new_episode_id
from services.actor.realtime import Counts, RealtimeActor, Steps

log = logging.getLogger(__name__)


def run(
    settings: Settings, bus: Bus, mode: str, stop: threading.Event, duration: float | None, sync_critic: bool
) -> dict[str, Any]:
    actor = build_actor(settings)  # built once, before the loop starts
    inbox = wire_weights(settings, bus)
    # the liveliness token means "ready": declared by each mode once all its inputs are subscribed
    if mode == "lockstep":
        return _run_lockstep(settings, bus, actor, inbox, sync_critic)
    return _run_realtime(settings, bus, actor, inbox, stop, duration)


def _run_lockstep(
    settings: Settings, bus: Bus, actor: StackedActor, inbox: WeightsInbox, sync_critic: bool
) -> dict[str, Any]:
    bus.declare_alive(settings.transport.robot)
    bus.wait_alive(settings.transport.robot, "plant", timeout=30.0)
    if sync_critic and learns(settings.actor.agent):
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
            "episode_id": episode_id,
            "weights_version": inbox.current().version,
            "staleness_steps": summarize(port.staleness) | {"max": float(max(port.staleness, default=0))},
            "critic_timeouts": port.timeouts,
            "trajectory": [[float(c) for c in s] for s in episode.states],
            "counters": dict(bus.counters),
        }
    )
    return LockstepActorSummary.model_validate(summary).to_json_dict()


def wire_weights(settings: Settings, bus: Bus) -> WeightsInbox:
    """One robot's weights inbox on the bus (``settings.transport.robot``'s keys): weights only
    from the live critic session of that robot (its identity watched, common.net.provenance)."""
    robot = settings.transport.robot
    critic_gate = SourceGate("critic")
    bus.watch_identities(robot, "critic", critic_gate)
    inbox = WeightsInbox(settings, bus, critic_gate)
    bus.subscribe(WEIGHTS, WEIGHTS.key(robot), inbox.offer, with_source=True)
    return inbox


def wire_realtime(
    settings: Settings,
    bus: Bus,
    actor: StackedActor | Steps,
    inbox: WeightsInbox,
    counters: Counts,
    episode_id: int,
    publish_action: Callable[[Action], None] | None = None,
    publish_transition: Callable[[Transition], None] | None = None,
) -> RealtimeActor:
    """One robot's real-time loop on the bus (``settings.transport.robot``'s keys): its action and
    transition publishers, the plant's session identities and liveliness watched. Provenance
    first: the caller subscribes the states after this, so the live plant sessions are known
    before the first state is judged (one actor: a callback per state; the actor host: the
    newest, judged at the robot's tick). ``publish_action``, ``publish_transition``: where its
    actions and transitions go instead of their own keys (an actor host's outboxes,
    services/actor/host.py Outbox)."""
    robot = settings.transport.robot
    loop = RealtimeActor(
        settings,
        actor,
        inbox,
        publish_action or bus.publisher(ACTION, robot),
        publish_transition or bus.publisher(TRANSITION, robot, cache=settings.transport.transition_cache),
        counters,
        episode_id,
    )
    bus.watch_identities(robot, "plant", loop.plant_gate, loop.on_plant_identity)
    bus.watch_alive(robot, "plant", loop.on_plant_token)
    return loop


def _run_realtime(
    settings: Settings,
    bus: Bus,
    actor: StackedActor,
    inbox: WeightsInbox,
    stop: threading.Event,
    duration: float | None,
) -> dict[str, Any]:
    """The real-time loop (services/actor/realtime.py) wired to the Zenoh bus."""
    robot = settings.transport.robot
    episode_id = new_episode_id()
    loop = wire_realtime(settings, bus, actor, inbox, bus, episode_id)
    bus.subscribe(STATE, STATE.key(robot), loop.on_state, with_source=True)
    bus.declare_alive(robot)
    inbox.reset(episode_id)
    actor.reset()
    start_time = time.monotonic()
    end = None if duration is None else start_time + duration
    # What exists now is frozen out of the garbage collector (the loop collects in its slack
    # time, RealtimeActor.run); the clock starts after that collection, which can take longer
    # than a tick on a busy machine.
    gc.collect()
    gc.freeze()
    try:
        ticker = Ticker(settings.plant.sampling_time, stop)
        loop.ticker = ticker
        first_version: list[float] = []

        def log_status(counters: dict[str, float]) -> None:
            # the live status at INFO: `docker compose up` shows it (compose runs the actor at
            # INFO); srl up prints the same line from the published status instead
            log.info("status %s", format_status_line(counters, time.monotonic() - start_time, first_version))

        start_status_thread(
            bus, [(robot, bus_status(bus, loop.status))], settings.transport.status_period, stop, log_status
        )
        with realtime_priority(settings.actor.realtime_priority, "actor") as priority:
            loop.run(ticker, end)
    finally:
        gc.unfreeze()
    summary = loop.summary()
    summary["counters"]["realtime_priority"] = float(priority)
    return summary


__all__ = ["MessageError", "run"]
