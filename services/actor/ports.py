"""The actor's ports: what the loop talks to, over Zenoh.

* :class:`WeightsInbox` -- the newest accepted critic weights (provenance, box, versions, trained
  step: common.net.provenance);
* :class:`ZenohPlant` -- the plant behind its lockstep queryables (``plant/reset``, ``plant/step``);
* :class:`ZenohCriticPort` -- transitions out to the off-board critic, weights back.

The lockstep actor (services/actor/service.py) and the experiment's workers
(tools/experiment/runner.py) run :func:`common.config.assembly.run_episode` over these ports.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.config.assembly import arrival_tolerances
from common.config.settings import Settings
from common.contracts.keys import Service
from common.contracts.messages import CriticWeights, Message, PlantState, Transition
from common.math.agents import fit_due, learns
from common.math.critic import FitsDue, Sample
from common.net.provenance import RESYNC_AFTER, RESYNC_WITHIN_S, RefusalRun, SourceGate
from common.net.transport import MISSED, Bus

log = logging.getLogger(__name__)
# A critic's versions start at its host's wall clock in microseconds when it starts and then
# count one per publication (services/critic/service.py), so an honest version is never ahead of
# our clock by more than the skew between the two hosts: NTP keeps hosts within milliseconds,
# 5 s tolerates a badly synchronized one. This refuses a single forged far-future version; it
# cannot bound a forged version *within* the window (the real versions, which lag the clock, never
# catch up with it): the resync below does (common.net.provenance.RefusalRun).
MAX_VERSION_AHEAD_US = 5_000_000
# Weights beyond the critic's box are refused; without a box (critic.weight_bounds = []) this
# is the bound: far above any fit of ours (docs/concepts.md), far below where the objective overflows.
MAX_ABS_WEIGHT_UNBOXED = 1e6
PUBLISHED, TRAINED = 0, 1  # the columns of a WeightsInbox's marks


@dataclass
class HeldWeights:
    q: np.ndarray
    v: np.ndarray
    version: int
    trained_step: int
    received_at: float
    residuals: tuple[float, float] = (math.nan, math.nan)  # the fit's TD residuals (Q, V); nan: initial


class WeightsInbox:
    """Newest accepted critic weights of the current episode (thread-safe).

    Weights are accepted only: from the live critic session when a ``gate`` is given
    (its identity token, common.net.provenance), for the current episode, newer than the held
    version of the same critic session (a new session -- a restarted critic -- resynchronizes),
    within the configured weight box (else the last good weights are kept), and trained on a
    step the actor has already published (``published_step``): a forged far-future version or
    trained step can neither lock out the real critic nor falsify the staleness figures.

    The published step and the held weights' trained step are a row of ``marks`` (columns
    :data:`PUBLISHED`, :data:`TRAINED`): its own, or its loop's row of its host's
    (:meth:`bind`), which a host's ticks at rest read and write for many robots at once
    (services/actor/realtime.py rest_ticks; only the loop's thread writes the published step).
    """

    def __init__(self, settings: Settings, bus: Bus, gate: SourceGate | None = None) -> None:
        self.settings = settings
        self.bus = bus
        self.gate = gate
        self.cond = threading.Condition()
        self.episode = -1
        # the newest transition step this actor published (this episode), the held weights' trained step
        self.marks, self.mark = np.full((1, 2), -1, dtype=np.int64), 0
        self.source: str | None = None  # the critic session whose versions are held
        # refused versions of the followed critic in a row; weights come every update_every steps
        period = settings.critic.update_every * settings.plant.sampling_time
        self.refusals = RefusalRun(RESYNC_AFTER, RESYNC_WITHIN_S + 2 * RESYNC_AFTER * period)
        bounds = settings.critic.bounds
        self.box = bounds if bounds is not None else (-MAX_ABS_WEIGHT_UNBOXED, MAX_ABS_WEIGHT_UNBOXED)
        self.held = HeldWeights(settings.initial_q_weights(), settings.initial_v_weights(), 0, -1, time.monotonic())

    @property
    def published_step(self) -> int:
        return int(self.marks[self.mark, PUBLISHED])

    def bind(self, marks: np.ndarray, row: int) -> None:
        """Keep the published and trained steps in row ``row`` of ``marks`` from now on."""
        with self.cond:
            marks[row] = self.marks[self.mark]
            self.marks, self.mark = marks, row

    def reset(self, episode: int) -> HeldWeights:
        with self.cond:
            self.episode = episode
            self.marks[self.mark] = -1
            self.source = None
            self.refusals.accepted()
            self.held = HeldWeights(
                self.settings.initial_q_weights(), self.settings.initial_v_weights(), 0, -1, time.monotonic()
            )
            return self.held

    def published(self, step: int) -> None:
        with self.cond:
            self.marks[self.mark, PUBLISHED] = max(self.published_step, step)

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
            same_source = source == self.source
            if message.version > time.time_ns() // 1000 + MAX_VERSION_AHEAD_US:
                reason: str | None = f"version {message.version} is from the future"
            elif same_source and message.version <= self.held.version:
                reason = f"version {message.version} <= held {self.held.version}"
            else:
                reason = None
            if reason is not None:
                # a run of refused versions of the followed critic that count on among themselves
                # is the real critic after a forged version (with its session id) moved ours, or a
                # critic host whose clock is ahead: follow it (common.net.provenance.RefusalRun)
                if not (same_source and self.refusals.refused((message.version,), time.monotonic())):
                    self.bus.reject("critic/weights", reason)
                    return
                log.warning(
                    "critic %s: %d versions refused in a row (%s): following its versions again",
                    source,
                    self.refusals.after,
                    reason,
                )
                self.bus.count("critic_version_resyncs")
            if not same_source and self.source is not None:
                log.info("critic session %s replaces %s: versions resynchronized", source, self.source)
                self.bus.count("critic_resyncs")
            self.source = source
            self.refusals.accepted()
            self.held = HeldWeights(
                np.array(message.q_weights),
                np.array(message.v_weights),
                message.version,
                message.trained_step,
                time.monotonic(),
                (message.q_residual, message.v_residual),
            )
            self.marks[self.mark, TRAINED] = message.trained_step
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
        self.true_state: np.ndarray | None = None  # the plant's truth, if it sends it
        self.saturated_commands: int | None = None

    def _keep_truth(self, reply: PlantState) -> np.ndarray:
        self.true_state = None if reply.true_state is None else np.array(reply.true_state)
        self.saturated_commands = reply.saturated_commands
        return np.array(reply.state)

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
        wire = self.settings.wire
        request = wire.reset_request(
            **wire.named, robot=self.robot, episode=self.episode, state=tuple(float(c) for c in state)
        )
        return self._keep_truth(self._query(wire.PLANT_RESET, request))

    def apply(self, action: np.ndarray, duration: float) -> np.ndarray:
        wire = self.settings.wire
        request = wire.step_request(
            **wire.named,
            robot=self.robot,
            episode=self.episode,
            step=self.step_index,
            action=tuple(float(c) for c in action),
            duration=duration,
        )
        reply = self._query(wire.PLANT_STEP, request)
        self.step_index += 1
        return self._keep_truth(reply)


class ZenohCriticPort:
    """Transitions out to the off-board critic; weights back (optionally waited for)."""

    def __init__(self, settings: Settings, bus: Bus, inbox: WeightsInbox, episode: int, sync: bool) -> None:
        self.settings, self.bus, self.inbox, self.episode, self.sync = settings, bus, inbox, episode, sync
        self.robot = settings.transport.robot
        # in batches of one (srl reads transitions only in batches: common.contracts.keys.Batch.on_demand)
        send = bus.round_publisher(
            settings.wire.TRANSITION, cache=settings.transport.transition_cache, robots=[self.robot]
        )
        self.publish: Callable[[Transition], None] = lambda transition: send([transition])
        self.staleness: list[int] = []
        self.timeouts = 0
        self.fits = FitsDue(arrival_tolerances(settings))  # none on a robot held at rest
        # the TD residuals (Q, V) of the fit on the step just recorded, once its weights are held
        # (as common.math.loop.LocalCritic's); nan: no fit on it, or its weights not here yet
        self.last_residuals = (math.nan, math.nan)

    def new_episode(self, settings: Settings, episode: int) -> None:
        """The same port (one cached transition publisher for the process's life) for a new
        episode: its settings and id, staleness and timeouts counted afresh."""
        self.settings, self.episode = settings, episode
        self.staleness, self.timeouts = [], 0
        self.fits = FitsDue(arrival_tolerances(settings))

    def reset(self) -> tuple[np.ndarray, np.ndarray]:
        self.fits.reset()
        held = self.inbox.reset(self.episode)
        return held.q, held.v

    def record(self, sample: Sample) -> tuple[np.ndarray, np.ndarray]:
        self.inbox.published(sample.step)
        wire = self.settings.wire
        self.publish(
            wire.transition(
                **wire.named,
                robot=self.robot,
                episode=self.episode,
                step=sample.step,
                state=tuple(float(c) for c in sample.state),
                action=tuple(float(c) for c in sample.action),
                cost=float(sample.cost),
            )
        )
        # the critic fits when a fit is due, but not on a robot held at rest (no weights come back)
        fitted = self.fits.sent(sample)
        due = fit_due(sample.step, self.settings.critic.update_every)
        needs_fit = fitted and due and learns(self.settings.actor.agent)
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
        self.last_residuals = held.residuals if needs_fit and held.trained_step == sample.step else (math.nan, math.nan)
        # staleness of the weights the NEXT step will use: ideally trained on this step (at rest:
        # on the newest step the critic fits)
        self.staleness.append(self.fits.newest - held.trained_step)
        return held.q, held.v

    def weights(self) -> tuple[np.ndarray, np.ndarray]:
        held = self.inbox.current()
        return held.q, held.v


def wire_weights(settings: Settings, bus: Bus) -> WeightsInbox:
    """One robot's weights inbox on the bus (``settings.transport.robot``'s keys): weights only
    from the live critic session of that robot (its identity watched, common.net.provenance).
    Subscribed with recovery of what it misses (``MISSED``: no history, so none of the critic's
    earlier runs): weights a congested link dropped are fetched from the critic's cache
    (services.critic.service.WEIGHTS_CACHE), so a robot at rest, for which no fit comes, never
    keeps weights older than the critic's last for it."""
    robot = settings.transport.robot
    critic_gate = SourceGate("critic")
    bus.watch_identities(robot, "critic", critic_gate)
    inbox = WeightsInbox(settings, bus, critic_gate)
    weights = settings.wire.WEIGHTS  # the robot's, or another system's
    bus.subscribe(weights, weights.key(robot), inbox.offer, with_source=True, recover=MISSED)
    return inbox
