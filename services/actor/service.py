"""actor: the delta-periodic loop of stacked RL-QV (or its baselines).

* realtime: one robot is an actor host of one (:func:`services.actor.host.run_host`, the same
  code that serves a fleet): it ticks at absolute times ``t0 + k delta`` on the monotonic clock;
  at each tick it takes the newest state, solves, publishes the action and one transition. It
  never waits for the critic: it uses the newest weights it holds and reports their staleness.
  If the state stopped arriving (zero goes out within ``action_timeout_steps * delta`` of the
  last state), never came, or the plant's liveliness token vanished (zero at the next tick), it
  commands zero velocity at every tick and records no transition (so the critic sees a gap,
  never a false pair); fresh states resume the loop.
* lockstep: runs Algorithm 1 (:func:`common.config.assembly.run_episode`) with the plant behind
  its Zenoh queryable and the off-board critic; with ``sync_critic`` it waits (bounded) for the
  weights trained on the previous step, which makes the distributed run the paper's algorithm
  exactly.

The real-time loop of one robot is :class:`services.actor.realtime.RealtimeActor`, scheduled by
:class:`services.actor.host.HostScheduler`; the ports (weights inbox, lockstep plant, critic port)
are in :mod:`services.actor.ports`.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

from common.config.assembly import build_actor, episode_summary, run_episode
from common.config.settings import Settings
from common.contracts.messages import MessageError
from common.contracts.summaries import LockstepActorSummary, printed_summary
from common.math.actor import StackedActor
from common.math.agents import learns
from common.math.stats import summarize
from common.net.transport import Bus
from services.actor.host import run_host
from services.actor.ports import WeightsInbox, ZenohCriticPort, ZenohPlant, new_episode_id, wire_weights

log = logging.getLogger(__name__)


def run(
    settings: Settings, bus: Bus, mode: str, stop: threading.Event, duration: float | None, sync_critic: bool
) -> dict[str, Any]:
    # the liveliness token means "ready": declared by each mode once all its inputs are subscribed
    if mode == "lockstep":
        actor = build_actor(settings)  # built once, before the loop starts
        return _run_lockstep(settings, bus, actor, wire_weights(settings, bus), sync_critic)
    return printed_summary(run_host(settings, bus, [settings.transport.robot], stop, duration), False)


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


__all__ = ["MessageError", "run"]
