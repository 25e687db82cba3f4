"""critic: the off-board learner. Transitions in, versioned critic weights out.

One replay of size M and one :class:`~common.critic.DoubleCritic` per (robot, episode); a
transition of a new episode starts afresh from the initial weights. After every
``update_every``-th transition both critics are fitted (TD least squares) and published with a
version that increases strictly over the life of the process (so across episodes too), the
step they were trained on and the fit residuals. Non-finite fits are never published.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass

import numpy as np

from common.critic import DoubleCritic, Replay, Sample
from common.keys import TRANSITION, WEIGHTS
from common.messages import CriticWeights, Transition
from common.settings import Settings
from common.transport import Bus, start_status_thread

log = logging.getLogger(__name__)


@dataclass
class Learner:
    episode: int
    replay: Replay
    critic: DoubleCritic
    seen: set[int]


class CriticLearner:
    """Transport-free core: feed transitions, get the weight messages to publish."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.learners: dict[str, Learner] = {}
        # Versions increase strictly over the process's life and across restarts: they start
        # from the wall clock in microseconds, so a restarted critic is never "older".
        self.version = time.time_ns() // 1000
        self.fit_seconds: list[float] = []
        self.received = 0
        self.duplicates = 0
        self.stale_episode = 0

    def _fresh(self, episode: int) -> Learner:
        s = self.settings
        critic = DoubleCritic(s.initial_q_weights(), s.initial_v_weights(), s.discount,
                              s.critic.ridge, s.critic.bounds)
        return Learner(episode, Replay(s.critic.replay_size), critic, set())

    def initial_weights(self, robot: str, episode: int) -> CriticWeights:
        learner = self._fresh(episode)
        self.learners[robot] = learner
        return self._message(robot, learner, trained_step=-1, q_res=0.0, v_res=0.0, pairs=0)

    def _message(self, robot: str, learner: Learner, trained_step: int, q_res: float, v_res: float,
                 pairs: int) -> CriticWeights:
        self.version += 1
        return CriticWeights(
            robot=robot, episode=learner.episode, version=self.version, trained_step=trained_step,
            q_weights=tuple(float(w) for w in learner.critic.q_weights),
            v_weights=tuple(float(w) for w in learner.critic.v_weights),
            q_residual=q_res, v_residual=v_res, pairs=pairs,
        )

    def on_transition(self, message: Transition) -> CriticWeights | None:
        self.received += 1
        learner = self.learners.get(message.robot)
        if learner is None or message.episode > learner.episode:
            learner = self._fresh(message.episode)
            self.learners[message.robot] = learner
        elif message.episode < learner.episode:
            self.stale_episode += 1
            return None
        if message.step in learner.seen:
            self.duplicates += 1  # a re-delivered transition: already in the replay
            return None
        learner.seen.add(message.step)
        learner.replay.add(Sample(message.step, np.array(message.state), np.array(message.action),
                                  message.cost))
        if message.step % self.settings.critic.update_every != 0:
            return None
        started = time.perf_counter()
        update = learner.critic.update(learner.replay)
        self.fit_seconds.append(time.perf_counter() - started)
        if not (np.isfinite(update.q.residual) and np.isfinite(update.v.residual)):
            return None
        return self._message(message.robot, learner, message.step, update.q.residual,
                             update.v.residual, update.q.pairs)


def run(settings: Settings, bus: Bus, stop: threading.Event, duration: float | None) -> dict:
    learner = CriticLearner(settings)
    publishers: dict[str, object] = {}
    inbox: queue.Queue[Transition] = queue.Queue()
    # Every robot's transitions: srl/*/transition (the key chunk names the robot).
    bus.subscribe(TRANSITION, TRANSITION.pattern.format(robot="*"), inbox.put)
    bus.declare_alive(settings.transport.robot)
    start_status_thread(bus, settings.transport.robot, settings.transport.status_period, stop,
                        lambda: {"transitions_received": learner.received, "duplicates": learner.duplicates})
    log.info("critic ready (M = %d, beta = %.4f)", settings.critic.replay_size, settings.discount)
    end = None if duration is None else time.monotonic() + duration
    while not stop.is_set() and (end is None or time.monotonic() < end):
        try:
            message = inbox.get(timeout=0.05)
        except queue.Empty:
            continue
        weights = learner.on_transition(message)
        if weights is None:
            continue
        publish = publishers.get(message.robot)
        if publish is None:
            publish = publishers[message.robot] = bus.publisher(WEIGHTS, message.robot)
        publish(weights)  # type: ignore[operator]
        bus.count("weights_published")
    from common.stats import summarize

    return {
        "service": "critic",
        "transitions_received": learner.received,
        "duplicates": learner.duplicates,
        "weights_published": bus.counters["weights_published"],
        "last_version": learner.version,
        "fit_ms": summarize(learner.fit_seconds, 1e3),
        "counters": dict(bus.counters),
    }
