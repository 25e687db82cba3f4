"""Recovering the steps a subscriber missed from the actors' transition caches.

The actors publish transitions through advanced publishers that cache their last
``transport.transition_cache`` periods (common.net.transport.Bus.publisher). A subscriber with
recovery gets that history when it starts, but only if the answer to its history query comes
before the publisher's next live sample: a sample delivered live ends the recovery of everything
older. A consumer that sees a robot's stream start later than it should (the critic, the
recorder) asks the caches again for the missing steps with :class:`HistoryRecovery`.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from common.contracts.messages import Transition

log = logging.getLogger(__name__)


class HistoryRecovery:
    """The robots whose transitions start later than a consumer (``who``: the critic, the recorder)
    needs, recovered from the actors' caches (common.net.transport.Bus.history): one query at a
    time, for every robot waiting when it is asked, so a critic that restarts beside a fleet asks
    an actor host's batch cache (its robots' last ``transport.transition_cache`` periods,
    srl/@batch/transition) once, not once per robot. A
    robot that starts waiting while a query is out is asked for in the next one (the answer of
    one asked before it may have passed its steps over). What comes back goes to ``put`` if it is
    a missing step of a waiting robot's episode. ``ask(robots, handler, done)`` is the query;
    ``done`` is called once when it ends. Thread-safe: ``need`` runs on the consumer's loop, the
    answers on Zenoh's threads; :meth:`pending` says whether a robot's steps may still come."""

    def __init__(
        self,
        ask: Callable[[list[str], Callable[[Transition], None], Callable[[], None]], None],
        put: Callable[[Transition], None],
        who: str = "critic",
    ) -> None:
        self.ask, self.put, self.who = ask, put, who
        self.lock = threading.Lock()
        self.waiting: dict[str, tuple[int, range]] = {}  # robot -> (episode, its missing steps)
        self.asked: dict[str, tuple[int, range]] = {}  # what the query out asks for
        self.queries = 0

    def need(self, robot: str, episode: int, missing: range) -> None:
        """The first transition the consumer got of ``robot`` is of ``episode``; ``missing``: the
        steps before it that it needs."""
        with self.lock:
            self.waiting[robot] = (episode, missing)
            if self.asked:
                return  # asked for in the next query, when this one ends
        self._next()

    def _next(self) -> None:
        with self.lock:
            self.asked = dict(self.waiting)
            if not self.asked:
                return
            self.queries += 1
        log.info(
            "%s: asking the actors' caches for the missing steps of %d robots (%s)",
            self.who,
            len(self.asked),
            ", ".join(f"{robot} {steps.start}-{steps.stop - 1}" for robot, (_, steps) in list(self.asked.items())[:5])
            + (", ..." if len(self.asked) > 5 else ""),
        )
        self.ask(list(self.asked), self._answer, self._done)

    def _answer(self, message: Transition) -> None:
        wanted = self.waiting.get(message.robot)
        if wanted is not None and message.episode == wanted[0] and message.step in wanted[1]:
            self.put(message)

    def _done(self) -> None:
        with self.lock:
            for robot, wanted in self.asked.items():
                if self.waiting.get(robot) == wanted:  # not waiting for more since it was asked
                    del self.waiting[robot]
            self.asked = {}
        self._next()

    def pending(self, robot: str) -> bool:
        """Whether ``robot``'s missing steps are still asked for (waiting, or in the query out)."""
        with self.lock:
            return robot in self.waiting or robot in self.asked
