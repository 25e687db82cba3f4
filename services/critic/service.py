"""critic: the off-board learner. Transitions in, versioned critic weights out.

One replay of size M and one :class:`~common.math.critic.DoubleCritic` per (robot, episode); a
transition of a new episode starts afresh from the initial weights. After every
``update_every``-th transition both critics are fitted (TD least squares) and published with a
version that increases strictly over the life of the process (so across episodes too), the
step they were trained on and the fit residuals. Non-finite fits are never published.

Nothing is lost across a crash:

* the actor publishes transitions through a Zenoh advanced publisher that caches the last
  ``transport.transition_cache`` of them (an actor host of many robots: one publisher of their
  batches, srl/@batch/transition, that caches as many periods of all of them); the critic
  subscribes with history and recovery, so at (re)start it receives what was published while it
  was down, and after a partition what it missed, in step order. A robot whose stream still
  starts later than the critic needs (the subscription's history query answered after the first
  live transition, which ends its recovery) is asked again: the critic queries the actors'
  caches for the missing steps, one query for every robot waiting (:class:`HistoryRecovery`);
* after every accepted transition the critic writes a checkpoint (``critic.checkpoint``, per
  robot and stack: weights, version, replay, the steps seen) atomically, and reads it at start.
  A learner read from it continues only if the first transition is of its own episode (this
  critic crashed during the run); a new run starts fresh -- its result never depends on what
  ran before -- unless ``critic.resume`` (``--resume``) carries the weights into it. A transition
  it already holds (history overlapping the checkpoint, or a re-delivery) is counted as a
  duplicate and changes nothing, so the recovered fits are exactly those a critic that never
  went down would have made. Restored weights are re-published under a new version.

Steps more than ``retention`` behind the newest step of the episode are refused as too old
(counted): this bounds the memory of seen steps and the checkpoint's size.

``critic.pooled`` (``srl critic --pooled``): ONE learner for every robot
(:class:`~common.math.critic.PooledLearner`). Each robot keeps its stream (episode, replay of M, steps
seen) and TD pairs never leave a stream; the one critic is fitted once per fleet step (as many
transitions due a fit as the fleet has robots since the last fit) and its weights go to every
robot's weights key, one version for all. A robot that starts a new episode restarts its stream
and joins the pool's weights where they are. From a checkpoint, the first robot heard decides:
its episode goes on, so does the pool; a new episode means a new run, and the pool starts from the
initial weights (``critic.resume``: from the checkpoint's) with no robot's old stream.
"""

from __future__ import annotations

import base64
import logging
import math
import os
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from common.config.assembly import arrival_tolerances
from common.config.settings import Settings
from common.contracts.columns import Columns, columns_of, spans
from common.contracts.messages import CriticWeights, MessageError, Transition
from common.contracts.summaries import CriticSummary
from common.math.agents import fit_due
from common.math.critic import (
    DoubleCritic,
    PooledLearner,
    Replay,
    Sample,
    append_each,
    at_rest,
    at_rest_rows,
    load_solver,
    newest_values,
    update_many,
)
from common.math.stats import Window
from common.net.history import HistoryRecovery
from common.net.transport import Bus, Inbox, bus_status, start_status_thread
from common.process.runtime import session_priority
from common.system.checkpoint import (
    CheckpointError,
    CheckpointWriter,
    StepRuns,
    read_json,
    remove_stale_temporaries,
    set_aside,
)

log = logging.getLogger(__name__)
SEEN_SLACK = 100  # steps seen beyond the retention (at most as many again) before the set is pruned to it
# 2: each learner's replay packed (REPLAY_PACKING); 1 (still read): the replay as lists of numbers
CHECKPOINT_SCHEMA = 2
READABLE_SCHEMAS = (1, 2)
MAX_BATCH = 1000  # transitions taken from the inbox at once (then one checkpoint for all of them)
# transitions that may wait for the critic (~200 s of a 100-robot fleet, ~30 MB of batches): past
# it, rows are counted as dropped (transitions_dropped), a gap in their robots' replays
INTAKE_LIMIT = 200_000
# weights rounds (a batch for a critic of a robot list, else one robot's message) the critic's
# advanced publisher keeps: an actor's subscriber that misses one (a congested router link drops
# samples, seen after a partition) detects the gap by sequence number or heartbeat and fetches it
# from this cache. Only the newest weights matter, so the cache need reach back only as far as a
# gap takes to be seen (heartbeats every RECOVERY_HEARTBEAT_S): 64 rounds are >= 6 s of a fleet
# fitting every tick, ~1.3 MB at 100 robots.
WEIGHTS_CACHE = 64


class TransitionRow(Protocol):
    """A transition as the critic takes it: a :class:`~common.contracts.messages.Transition`
    message, or a row of a batch (:class:`Row`)."""

    @property
    def robot(self) -> str: ...

    @property
    def episode(self) -> int: ...

    @property
    def step(self) -> int: ...

    @property
    def state(self) -> Any: ...

    @property
    def action(self) -> Any: ...

    @property
    def cost(self) -> float: ...


@dataclass(frozen=True, slots=True)
class Row:
    """One transition of a batch, read from its columns (validated as the batch was decoded): no
    message built; ``state`` and ``action`` are rows of the batch's arrays."""

    robot: str
    episode: int
    step: int
    state: np.ndarray
    action: np.ndarray
    cost: float


def no_transitions(schema: type[Transition] = Transition) -> Columns[Transition]:
    """A batch of no transitions (of ``schema``: the robot's, or another system's)."""
    laid = spans(schema)
    return Columns(schema, [], np.empty((0, laid.ints), dtype=np.int64), np.empty((0, laid.floats)))


@dataclass
class Learner:
    episode: int
    replay: Replay
    critic: DoubleCritic
    seen: StepRuns
    newest: int = -1
    # the step the last weights published were labelled trained on: a fit never labels older (a
    # transition recovered late, after newer ones were fitted, is fitted with the whole replay)
    fitted: int = -1


def checkpoint_path(settings: Settings) -> Path | None:
    template = settings.critic.checkpoint
    if not template:
        return None
    # per robot AND per stack: a run of another agent or horizon never starts from this one's critic;
    # and per system: another system's critic (its weights of other sizes) never reads the robot's
    path = Path(
        os.path.expanduser(
            template.format(robot=settings.transport.robot, agent=settings.actor.agent, horizon=settings.actor.horizon)
        )
    )
    system = settings.plant.system  # the robot's file is the unicycle's; every other row's its own
    return path if system == "unicycle" else path.with_name(f"{path.stem}-{system}{path.suffix}")


def replay_sample(message: TransitionRow) -> Sample:
    """A transition as its robot's replay holds it (a batch's row: its own arrays, not copied)."""
    return Sample(message.step, np.asarray(message.state, float), np.asarray(message.action, float), message.cost)


class CriticLearner:
    """Transport-free core: feed transitions, get the weight messages to publish.

    ``fleet_size``: the robots a pooled critic serves (its fit is due once per step of all of
    them; None: the robots heard from so far)."""

    def __init__(self, settings: Settings, fleet_size: int | None = None) -> None:
        self.settings = settings
        self.learners: dict[str, Learner] = {}
        self.fleet_size = fleet_size
        self.pool = self._fresh_pool() if settings.critic.pooled else None
        self.fit_pending = False  # a pooled fit came due in this batch, left to its end (coalesce_fits)
        self.pool_run_decided = False  # pooled, from a checkpoint: the first robot heard said whether its run goes on
        # Versions increase strictly over the process's life and across restarts: they start
        # from the wall clock in microseconds, so a restarted critic is never "older".
        self.version = time.time_ns() // 1000
        self.fit_seconds = Window()  # bounded: a critic runs for days
        self.received = 0
        self.duplicates = 0
        self.stale_episode = 0
        self.too_old = 0
        self.accepted = 0  # transitions that entered a replay
        self.fits_coalesced = 0  # due fits left to a newer transition of the same robot in the batch
        self.fits_at_rest = 0  # due fits not made: the robot held at rest (common.math.critic.at_rest)
        self.rest = arrival_tolerances(settings)
        self.due: dict[str, tuple[Learner, int]] = {}  # per-robot fits left to flush(): learner, step
        self.outgoing: list[CriticWeights] = []  # weights of fits made early in a batch, for flush()
        self.resume = settings.critic.resume
        self.pending: set[str] = set()  # robots read from a checkpoint, their run not yet confirmed
        self.continued: set[str] = set()  # robots whose checkpointed learner continued (same run)
        self.heard: set[str] = set()  # robots whose transitions :meth:`take_batch` took since the start
        self.loaded = False  # a checkpoint was restored
        # Seen steps kept per episode: enough to recognise anything the publisher's cache can
        # still deliver again.
        self.retention = 2 * max(settings.transport.transition_cache, settings.critic.replay_size)

    def _fresh_critic(self) -> DoubleCritic:
        s = self.settings
        return DoubleCritic(s.initial_q_weights(), s.initial_v_weights(), s.discount, s.critic.ridge, s.critic.bounds)

    def _fresh_pool(self) -> PooledLearner:
        c = self.settings.critic
        return PooledLearner(self._fresh_critic(), c.replay_size, c.update_every, robots=self.fleet_size)

    def _fresh(self, robot: str, episode: int, pool: PooledLearner | None = None) -> Learner:
        """A robot's new learner: its own critic, or (pooled) a new stream of ``pool`` and its critic."""
        pool = pool or self.pool
        if pool is not None:
            return Learner(episode, pool.replay.restart(robot), pool.critic, StepRuns())
        system = self.settings.system
        replay = Replay(self.settings.critic.replay_size, system.state_dim, system.action_dim)
        return Learner(episode, replay, self._fresh_critic(), StepRuns())

    def initial_weights(self, robot: str, episode: int) -> CriticWeights:
        learner = self._fresh(robot, episode)
        self.learners[robot] = learner
        return self._message(robot, learner, trained_step=-1, q_res=0.0, v_res=0.0, pairs=0)

    def _message(
        self,
        robot: str,
        learner: Learner,
        trained_step: int,
        q_res: float,
        v_res: float,
        pairs: int,
        version: int | None = None,
    ) -> CriticWeights:
        """``version``: the pool's one version for all its robots (None: a new one)."""
        if version is None:
            self.version += 1
        wire = self.settings.wire
        return wire.weights(
            **wire.named,
            robot=robot,
            episode=learner.episode,
            version=self.version if version is None else version,
            trained_step=trained_step,
            q_weights=tuple(learner.critic.q_weights.tolist()),
            v_weights=tuple(learner.critic.v_weights.tolist()),
            q_residual=q_res,
            v_residual=v_res,
            pairs=pairs,
        )

    def confirm(self, message: TransitionRow) -> CriticWeights | None:
        """The first transition of a robot read from the checkpoint: the same run continues
        (the weights held are re-published, under a new version) or a new one starts fresh."""
        if message.robot not in self.pending:
            return None
        self.pending.discard(message.robot)
        learner = self.learners[message.robot]
        decides = self.pool is not None and not self.pool_run_decided
        self.pool_run_decided = True
        if message.episode != learner.episode:
            if decides:
                self._new_pooled_run()
            return None  # on_transition starts the new run (fresh, or resumed weights)
        self.continued.add(message.robot)
        trained = learner.replay.last if len(learner.replay) else -1
        return self._message(message.robot, learner, trained, 0.0, 0.0, 0)

    def missing_before(self, message: TransitionRow) -> range:
        """Steps of ``message``'s episode before it that this critic does not hold, for the first
        transition it hears of a robot since it started: empty when the stream starts where the
        critic is (step 0 of a new run, or the step after its checkpoint's newest). The steps a
        late or restarted critic missed, which the actor's cache may still hold; at most
        ``retention`` of them (older ones would be refused as too old)."""
        learner = self.learners.get(message.robot)
        held = learner is not None and learner.episode == message.episode and message.robot in self.continued
        first = learner.newest + 1 if held and learner is not None else 0
        return range(max(first, message.step - self.retention + 1), message.step)

    def _new_pooled_run(self) -> None:
        """The first robot back from a checkpoint is on a new episode: the pool's run is over.
        No robot's old stream is kept; the weights are the initial ones unless resumed."""
        assert self.pool is not None
        previous, self.pool = self.pool, self._fresh_pool()
        if self.resume:
            self.pool.critic.q_weights = previous.critic.q_weights.copy()
            self.pool.critic.v_weights = previous.critic.v_weights.copy()
        self.learners.clear()
        self.pending.clear()

    @property
    def restored(self) -> bool:
        """A checkpoint's learner is in use: resumed on request, or continued within its run."""
        return bool(self.continued) or (self.resume and self.loaded)

    def resting(self, batch: Sequence[TransitionRow]) -> list[bool]:
        """Per transition of ``batch``, taken in order: will :meth:`take` find its robot at rest
        (:func:`~common.math.critic.at_rest` after the sample before it: the robot's previous one
        in the batch, else its replay's newest) and fit nothing? Never for the pooled learner,
        which fits the fleet as it steps."""
        if self.pool is not None or self.rest is None:
            return [False] * len(batch)
        before: dict[tuple[str, int], Sample] = {}
        resting = []
        for message in batch:
            key = (message.robot, message.episode)
            previous = before.get(key)
            if previous is None and (learner := self.learners.get(message.robot)) is not None:
                previous = learner.replay.newest if learner.episode == message.episode else None
            sample = replay_sample(message)
            resting.append(at_rest(previous, sample, self.rest))
            before[key] = sample
        return resting

    def take_batch(
        self,
        batch: Columns[Transition],
        coalesce: bool = False,
        continued: Callable[[CriticWeights], None] | None = None,
        missing: Callable[[str, int, range], None] | None = None,
    ) -> list[CriticWeights]:
        """A batch of transitions, rows in order: each row as :meth:`take` takes it, then
        :meth:`flush` -- the same decisions, counts, replays, fits, weights and versions -- and
        the weights to publish. A robot's first row since the start (:attr:`heard`) calls
        ``missing(robot, episode, steps)`` with the steps before it that this critic lacks
        (:meth:`missing_before`), when any; a learner read from the checkpoint that continues its
        run calls ``continued`` with its weights (:meth:`confirm`). ``coalesce``
        (critic.coalesce_fits): a robot due a fit again later in the batch is fitted once, on its
        newest transition (:func:`coalesced_fits`); pooled, the fit due is made once, at the end.

        The common rows are taken as arrays (:meth:`_common_rows`): the only row of its robot in
        the batch, of its episode, a step after its learner's newest, and no fit to make (none
        due, or the robot at rest). The rest go through :meth:`take` one by one, in order: a
        robot's first row or its checkpoint's continuation, a new or stale episode, a duplicate,
        a late or too old step, a robot with several rows, a fit due; every row of the pooled
        learner. The two kinds touch different robots and a common row makes no fit, uses no
        version and publishes nothing, so taking the common rows first changes nothing."""
        robots = batch.robots
        episodes, steps, costs = (batch.field(name).tolist() for name in ("episode", "step", "cost"))
        states = batch.field("state")
        values = np.hstack([states, batch.field("action")])  # (s, u) rows: the robot's (x, y, alpha, v, omega)
        n = states.shape[1]
        repeated: set[str] = set()  # robots with several rows in the batch
        if len(set(robots)) < len(robots):
            repeated = {robot for robot, count in Counter(robots).items() if count > 1}
        common = set(self._common_rows(robots, episodes, steps, values, costs, repeated))
        rare = [i for i in range(len(robots)) if i not in common]
        rows = {i: Row(robots[i], episodes[i], steps[i], values[i, :n], values[i, n:], costs[i]) for i in rare}
        superseded: set[int] = set()
        if coalesce and repeated:  # only a robot with several rows in the batch has a fit made redundant
            mine = [i for i in rare if robots[i] in repeated]
            taken = [rows[i] for i in mine]
            update_every = self.settings.critic.update_every
            superseded = {mine[k] for k in coalesced_fits(taken, update_every, self.resting(taken))}
        defer = coalesce and self.pool is not None
        outgoing: list[CriticWeights] = []
        for index in rare:
            row = rows[index]
            weights = self.confirm(row)
            if weights is not None and continued is not None:
                continued(weights)
            if row.robot not in self.heard:
                self.heard.add(row.robot)
                steps_missing = self.missing_before(row)
                if steps_missing and missing is not None:
                    missing(row.robot, row.episode, steps_missing)
            outgoing += self.take(row, fit=not defer and index not in superseded, defer=True)
        return outgoing + self.flush()

    def _common_rows(
        self,
        robots: list[str],
        episodes: list[int],
        steps: list[int],
        values: np.ndarray,
        costs: list[float],
        repeated: set[str],
    ) -> list[int]:
        """Takes the batch's common rows (:meth:`take_batch`) as arrays; which rows they were, in order.

        A common row's robot has one row in the batch, was heard before, is not waiting to confirm
        a checkpoint's run nor for a fit left to :meth:`flush`, and its learner (a per-robot one,
        of the row's episode) holds only earlier steps: its newest, its seen steps, its replay's
        (not empty, keeping rows). Such a row is accepted (neither a duplicate nor too old) and
        appended to the replay; it is taken here when it needs no fit: none due, or the robot at
        rest (:func:`at_rest_rows`). :meth:`take` would do exactly that, counts included."""
        if self.pool is not None:
            return []
        learners, pending, heard, waiting = self.learners, self.pending, self.heard, self.due
        update_every = self.settings.critic.update_every
        picked: list[int] = []  # rows it may take ...
        chosen: list[Learner] = []  # ... their learners
        due: list[int] = []  # ... and of those the ones due a fit (positions in picked)
        for i, robot in enumerate(robots):
            learner = learners.get(robot)
            if learner is None or robot in pending or robot not in heard or robot in repeated or robot in waiting:
                continue
            step, replay, seen_last = steps[i], learner.replay, learner.seen.last
            if (
                episodes[i] != learner.episode
                or step <= learner.newest
                or (seen_last is not None and seen_last >= step)
                or not replay.count
                or replay.last >= step
                or not replay.kept
            ):
                continue
            if step % update_every == 0:  # fit_due
                due.append(len(picked))
            picked.append(i)
            chosen.append(learner)
        if due:  # taken only at rest
            replays = [chosen[k].replay for k in due]
            previous_steps, previous = newest_values(replays)
            rows = [picked[k] for k in due]
            rest = at_rest_rows(previous_steps, previous, np.array([steps[i] for i in rows]), values[rows], self.rest)
            moving = {due[k] for k in np.flatnonzero(~rest).tolist()}
            if moving:
                picked = [i for k, i in enumerate(picked) if k not in moving]
                chosen = [learner for k, learner in enumerate(chosen) if k not in moving]
            self.fits_at_rest += len(due) - len(moving)
        if not picked:
            return picked
        taken_steps = [steps[i] for i in picked]
        append_each([learner.replay for learner in chosen], taken_steps, [costs[i] for i in picked], values[picked])
        limit = self.retention + min(SEEN_SLACK, self.retention)
        for learner, newest in zip(chosen, taken_steps, strict=True):
            learner.newest = newest
            seen = learner.seen
            seen.add(newest)
            if len(seen) > limit:  # pruned often: flat memory
                seen.keep_after(newest - self.retention)
        self.received += len(picked)
        self.accepted += len(picked)
        return picked

    def on_transition(self, message: TransitionRow, fit: bool = True) -> CriticWeights | None:
        """:meth:`take`, and of what it returns the weights for the message's robot."""
        return next((w for w in self.take(message, fit) if w.robot == message.robot), None)

    def take(self, message: TransitionRow, fit: bool = True, defer: bool = False) -> list[CriticWeights]:
        """Into the robot's replay; fitted and the weights returned when a fit is due (and
        ``fit``: False when a newer transition of the robot, due a fit too, is already waiting;
        pooled: when the batch's end will fit, :meth:`flush`). Per robot: its weights; pooled:
        every robot's. ``defer``: a per-robot fit due is left to :meth:`flush`, which fits every
        robot due in the batch at once (a robot due again first has its earlier fit made)."""
        self.received += 1
        learner = self.learners.get(message.robot)
        if learner is None or message.episode > learner.episode:
            previous, learner = learner, self._fresh(message.robot, message.episode)
            if previous is not None and self.resume and self.pool is None:  # learning carried across runs
                learner.critic.q_weights = previous.critic.q_weights.copy()
                learner.critic.v_weights = previous.critic.v_weights.copy()
            self.learners[message.robot] = learner
        elif message.episode < learner.episode:
            self.stale_episode += 1
            return []
        if message.step in learner.seen:
            self.duplicates += 1  # a re-delivered transition: already in the replay
            return []
        if message.step <= learner.newest - self.retention:
            self.too_old += 1
            return []
        learner.seen.add(message.step)
        self.accepted += 1
        if message.step > learner.newest:
            learner.newest = message.step
            if len(learner.seen) > self.retention + min(SEEN_SLACK, self.retention):  # pruned often: flat memory
                floor = learner.newest - self.retention
                learner.seen.keep_after(floor)
        if message.robot in self.due:  # its fit left to the batch's end is made first, on the replay as it was
            self.outgoing += self._fit_due()
        newest = learner.replay.newest
        sample = replay_sample(message)  # a batch's row: a view of its arrays, nothing copied
        learner.replay.add(sample)
        if self.pool is not None:
            if not self.pool.count(message.step):
                return []
            if not fit:
                self.fit_pending = True
                self.fits_coalesced += 1
                return []
            return self._pooled_fit()
        if not fit_due(message.step, self.settings.critic.update_every):
            return []
        if at_rest(newest, sample, self.rest):  # a per-robot learner; the pooled one fits the fleet as it steps
            self.fits_at_rest += 1
            return []
        if not fit:
            self.fits_coalesced += 1
            return []
        self.due[message.robot] = (learner, message.step)
        if defer:
            return []
        outgoing, self.outgoing = self.outgoing, []
        return outgoing + self._fit_due()

    def _fit_due(self) -> list[CriticWeights]:
        """The per-robot fits due, all in one stacked solve (:func:`~common.math.critic.update_many`:
        the designs gathered from the replays' kept rows; each robot's weights are those of its fit
        alone, bit for bit); a fit's time is its share."""
        due, self.due = self.due, {}
        if not due:
            return []
        started = time.perf_counter()
        updates = update_many([x.critic for x, _ in due.values()], [x.replay for x, _ in due.values()])
        share = (time.perf_counter() - started) / len(due)
        outgoing = []
        for (robot, (learner, step)), update in zip(due.items(), updates, strict=True):
            self.fit_seconds.append(share)
            if np.isfinite(update.q.residual) and np.isfinite(update.v.residual):
                # A fit is on the whole replay: a late step's (a transition a partition held back,
                # recovered after newer ones were fitted) is trained on those newer ones too. Labelled
                # with the late step, it would reach the actor under a newer version and freeze the
                # staleness of a robot then at rest (no fit comes to mend it).
                learner.fitted = max(step, learner.fitted)
                outgoing.append(
                    self._message(robot, learner, learner.fitted, update.q.residual, update.v.residual, update.q.pairs)
                )
        return outgoing

    def flush(self) -> list[CriticWeights]:
        """The end of a batch: the fits left to it (``take(..., defer=True)``), per robot in one
        stacked solve, or the pooled fit if one came due; their weights in the order taken."""
        outgoing, self.outgoing = self.outgoing, []
        outgoing += self._fit_due()
        if not self.fit_pending:
            return outgoing
        self.fits_coalesced -= 1  # the last of the batch's due fits is made
        return outgoing + self._pooled_fit()

    def _pooled_fit(self) -> list[CriticWeights]:
        """One fit of the pool; its weights for every robot, under one version."""
        assert self.pool is not None
        self.fit_pending = False
        started = time.perf_counter()
        update = self.pool.fit()
        self.fit_seconds.append(time.perf_counter() - started)
        if not (np.isfinite(update.q.residual) and np.isfinite(update.v.residual)):
            return []
        self.version += 1
        return [
            self._message(robot, x, x.newest, update.q.residual, update.v.residual, update.q.pairs, self.version)
            for robot, x in self.learners.items()
        ]

    # -- checkpoint ---------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        learners = {}
        for robot, learner in self.learners.items():
            learners[robot] = {
                "episode": learner.episode,
                "newest": learner.newest,
                "fitted": learner.fitted,
                "q_weights": learner.critic.q_weights.tolist(),
                "v_weights": learner.critic.v_weights.tolist(),
                **active_sets(learner.critic),
                "replay": pack_rows(learner.replay.table()),
                "seen": learner.seen.runs(),
            }
        payload: dict[str, Any] = {"schema": CHECKPOINT_SCHEMA, "version": self.version, "learners": learners}
        if self.pool is not None:
            payload["pool"] = {
                "q_weights": self.pool.critic.q_weights.tolist(),
                "v_weights": self.pool.critic.v_weights.tolist(),
                **active_sets(self.pool.critic),
                "due": self.pool.due,
            }
        return payload

    def restore(self, payload: dict[str, Any]) -> None:
        """Load :meth:`state` output; raises :class:`CheckpointError` and changes nothing if bad."""
        schema = payload.get("schema")
        if schema not in READABLE_SCHEMAS:
            raise CheckpointError(f"checkpoint schema {schema!r} is not one of {READABLE_SCHEMAS}")
        if ("pool" in payload) != (self.pool is not None):
            kinds = ("per-robot", "pooled")
            raise CheckpointError(
                f"the checkpoint is of a {kinds['pool' in payload]} critic, this one is {kinds[self.pool is not None]}"
            )
        learners: dict[str, Learner] = {}
        pool = self._fresh_pool() if self.pool is not None else None
        try:
            for robot, entry in payload["learners"].items():
                learner = self._fresh(robot, int(entry["episode"]), pool)
                q, v = np.array(entry["q_weights"], dtype=float), np.array(entry["v_weights"], dtype=float)
                if q.shape != learner.critic.q_weights.shape or v.shape != learner.critic.v_weights.shape:
                    raise CheckpointError(f"{robot}: weights of shapes {q.shape}, {v.shape}")
                if not (np.all(np.isfinite(q)) and np.all(np.isfinite(v))):
                    raise CheckpointError(f"{robot}: non-finite weights")
                learner.critic.q_weights, learner.critic.v_weights = q, v
                restore_active_sets(learner.critic, entry, robot)
                n, m = self.settings.system.state_dim, self.settings.system.action_dim
                rows = entry["replay"] if schema == 1 else unpack_rows(entry["replay"], robot, n + m + 2)
                for row in rows:
                    if len(row) != n + m + 2 or not all(np.isfinite(row)):
                        raise CheckpointError(f"{robot}: bad replay row {row}")
                    learner.replay.add(
                        Sample(int(row[0]), np.array(row[1 : 1 + n]), np.array(row[1 + n : 1 + n + m]), float(row[-1]))
                    )
                learner.seen = StepRuns(entry["seen"])
                learner.newest = int(entry["newest"])
                learner.fitted = int(entry.get("fitted", -1))  # absent from checkpoints written before it was kept
                learners[robot] = learner
            version = int(payload["version"])
            if pool is not None:
                q, v = np.array(payload["pool"]["q_weights"], float), np.array(payload["pool"]["v_weights"], float)
                if q.shape != pool.critic.q_weights.shape or v.shape != pool.critic.v_weights.shape:
                    raise CheckpointError(f"pool: weights of shapes {q.shape}, {v.shape}")
                if not (np.all(np.isfinite(q)) and np.all(np.isfinite(v))):
                    raise CheckpointError("pool: non-finite weights")
                pool.critic.q_weights, pool.critic.v_weights = q, v
                restore_active_sets(pool.critic, payload["pool"], "pool")
                pool.due = int(payload["pool"]["due"])
        except (KeyError, TypeError, ValueError) as error:
            if isinstance(error, CheckpointError):
                raise
            raise CheckpointError(f"malformed checkpoint: {error!r}") from error
        self.learners = learners
        if pool is not None:
            self.pool = pool
        self.version = max(self.version, version)
        self.pending = set(learners)
        self.loaded = True

    def current_weights(self) -> list[CriticWeights]:
        """The weights held for every robot, as new versions (to re-publish after a restore)."""
        messages = []
        for robot, learner in self.learners.items():
            trained = learner.replay.last if len(learner.replay) else -1
            messages.append(self._message(robot, learner, trained, 0.0, 0.0, 0))
        return messages


def drain(intake: Inbox, recovered: deque[Transition], schema: type[Transition] = Transition) -> Columns[Transition]:
    """What waits, as one batch of ``schema`` (the robot's transitions, or another system's): the
    intake's batches (a message alone on its robot's key is a batch of one row), then what the
    actors' caches answered (:class:`HistoryRecovery`)."""
    parts: list[Columns[Transition]] = [columns for columns, _ in intake.take()]
    while recovered:
        message = recovered.popleft()
        try:
            parts.append(columns_of(schema, [message]))
        except MessageError as error:  # as the intake refuses it live: an integer beyond a batch's 64 bits
            log.warning("critic: a recovered transition refused: %s", error)
    return Columns.joined(schema, parts) if parts else no_transitions(schema)


def collect(
    intake: Inbox, recovered: deque[Transition], window: float, robots: int, schema: type[Transition] = Transition
) -> Columns[Transition]:
    """What waits (:func:`drain`); with a ``window`` [s], also what comes within it, until a
    transition of each of the ``robots`` heard from is in."""
    batch = drain(intake, recovered, schema)
    if window <= 0 or not len(batch):
        return batch
    parts, heard = [batch], set(batch.robots)
    end = time.monotonic() + window
    while len(heard) < robots and (left := end - time.monotonic()) > 0:
        if intake.wait(left):
            more = drain(intake, recovered, schema)
            parts.append(more)
            heard.update(more.robots)
    return Columns.joined(schema, parts)


REPLAY_PACKING = "<f8"  # a replay in a checkpoint: base64 of little-endian float64 rows (the robot's: 7 numbers)


def pack_rows(table: np.ndarray) -> str:
    """A replay's rows ``(step, s, u, cost)`` (the robot's ``(step, x, y, alpha, v, omega, cost)``) for
    the checkpoint: base64 of their
    float64 bytes (:data:`REPLAY_PACKING`), exact, and ~20 times cheaper to write and read than
    a JSON number each (a fleet's critic writes every learner's replay once a second)."""
    return base64.b64encode(np.ascontiguousarray(table, dtype=REPLAY_PACKING).tobytes()).decode("ascii")


def unpack_rows(text: object, owner: str, width: int = 7) -> list[list[float]]:
    """:func:`pack_rows` back into rows; CheckpointError if it is not such a packing."""
    if not isinstance(text, str):
        raise CheckpointError(f"{owner}: the replay is not a packed table")
    try:
        data = base64.b64decode(text.encode("ascii"), validate=True)
    except (ValueError, UnicodeEncodeError) as error:
        raise CheckpointError(f"{owner}: the replay is not base64: {error}") from None
    if len(data) % (width * 8):
        raise CheckpointError(f"{owner}: a packed replay of {len(data)} bytes is not rows of {width} numbers")
    rows: list[list[float]] = np.frombuffer(data, dtype=REPLAY_PACKING).reshape(-1, width).tolist()
    return rows


def active_sets(critic: DoubleCritic) -> dict[str, list[float] | None]:
    """Each critic's last fit's weights on a bound (its next fit's guess, common.math.critic.fit_gram)
    for the checkpoint: a critic restored with them fits on exactly as one that never stopped."""
    return {
        "q_on_bound": None if critic.q_on_bound is None else critic.q_on_bound.tolist(),
        "v_on_bound": None if critic.v_on_bound is None else critic.v_on_bound.tolist(),
    }


def restore_active_sets(critic: DoubleCritic, entry: dict[str, Any], owner: str) -> None:
    """:func:`active_sets` back into ``critic``; absent (an older checkpoint): none, the next
    fit finds them (the same weights to rounding)."""
    for name, weights in (("q_on_bound", critic.q_weights), ("v_on_bound", critic.v_weights)):
        value = entry.get(name)
        if value is None:
            setattr(critic, name, None)
            continue
        on_bound = np.array(value, dtype=float)
        if on_bound.shape != weights.shape or not np.all(np.isin(on_bound, (-1.0, 0.0, 1.0))):
            raise CheckpointError(f"{owner}: {name} must be {weights.size} values of -1, 0 or 1")
        setattr(critic, name, on_bound)


def coalesced_fits(
    batch: Sequence[TransitionRow], update_every: int, resting: Sequence[bool] | None = None
) -> set[int]:
    """Indices of the batch's transitions whose due fit a later transition of the same robot and
    episode, also fitted, makes redundant. ``resting``: per transition, whether its learner will
    not fit it although due (a robot held at rest, :meth:`CriticLearner.resting`): such a
    transition makes no fit redundant, so a robot's last fit before its rest is made."""
    later: set[tuple[str, int]] = set()
    superseded: set[int] = set()
    for index in range(len(batch) - 1, -1, -1):
        message = batch[index]
        if fit_due(message.step, update_every) and not (resting is not None and resting[index]):
            if (message.robot, message.episode) in later:
                superseded.add(index)
            later.add((message.robot, message.episode))
    return superseded


def load_checkpoint(learner: CriticLearner, path: Path | None) -> bool:
    """Restore from ``path`` if it holds a usable checkpoint; an unusable one is set aside."""
    if path is None:
        return False
    remove_stale_temporaries(path)  # a write killed mid-way (kill -9) leaves its temporary file
    try:
        payload = read_json(path)
        if payload is None:
            return False
        learner.restore(payload)
    except CheckpointError as error:
        moved = set_aside(path, str(error))
        log.error("critic checkpoint %s unusable (%s); moved to %s, starting fresh", path, error, moved)
        return False
    log.info(
        "critic restored from %s: version %d, %s",
        path,
        learner.version,
        ", ".join(f"{r} episode {x.episode} replay {len(x.replay)}" for r, x in learner.learners.items()),
    )
    return True


def run(
    settings: Settings, bus: Bus, stop: threading.Event, duration: float | None, robots: list[str] | None = None
) -> dict:
    session_priority(settings.critic.session_niceness, "critic")  # its fits before the recorder's writing
    load_solver()  # before the critic is alive, so the actors never wait on an import
    learner = CriticLearner(settings, fleet_size=len(robots) if robots else None)
    path = checkpoint_path(settings)
    restored = load_checkpoint(learner, path)
    checkpoint_seconds = Window()
    writer = None if path is None else CheckpointWriter(path, checkpoint_seconds.append)
    batches = Window()  # transitions taken per batch
    waiting = Window()  # transitions waiting when a batch began: the critic's backlog
    # the transitions' samples wait as bytes (Zenoh's threads only queue them); the loop decodes
    # what waits as columns and takes their rows
    intake = bus.inbox(INTAKE_LIMIT)
    wire = settings.wire  # the robot's messages, or another system's
    recovered: deque[Transition] = deque()  # what the actors' caches answered (HistoryRecovery)
    sends: list[Callable[[Sequence[CriticWeights]], None]] = []  # declared at the first round

    def publish(round_: list[CriticWeights]) -> None:
        """A round's weights: batches for a critic of a robot list, else each on its robot's key."""
        if round_:
            if not sends:  # a critic of a robot list sends every round as a batch
                sends.append(
                    bus.round_publisher(
                        wire.WEIGHTS, batches=robots is not None and len(robots) > 1, cache=WEIGHTS_CACHE
                    )
                )
            sends[0](round_)
            bus.count("weights_published", len(round_))

    # a robot whose stream starts later than this critic needs (its subscription's history came
    # too late, or not at all): what the actors' caches hold of the missing steps goes to the
    # inbox, as if it had come in time
    def ask(robots: list[str], answer: Callable[[Transition], None], done: Callable[[], None]) -> None:
        bus.count("history_queries")
        bus.history(wire.TRANSITION, [wire.TRANSITION.key(robot) for robot in robots], answer, done)

    def put_recovered(message: Transition) -> None:
        recovered.append(message)
        intake.wake()

    recovery = HistoryRecovery(ask, put_recovered)

    if restored and learner.resume:  # asked to start from them: the actor may use them from step 0
        publish(list(learner.current_weights()))
    # the transitions of the robots it serves: srl/<id>/transition of each robot of --robots (a
    # critic shard learns only its own robots: critics split a fleet by robot, across processes
    # or hosts), else critic.robots' (srl/*/transition: every robot, the key chunk names it; or
    # one id), with the history the actors' publishers cache (recovery after a restart or a
    # partition).
    keys = (
        [wire.TRANSITION.key(robot) for robot in robots]
        if robots
        else [wire.TRANSITION.pattern.format(robot=settings.critic.robots)]
    )
    intake.subscribe(wire.TRANSITION, keys, recover=True)  # the batch key once, whatever the robots
    # the critic of every robot it serves (a fleet's actors accept weights only from a live critic
    # of their own robot: srl/<robot>/alive/critic/<zid>)
    for robot in robots or [settings.transport.robot]:
        bus.declare_alive(robot)
    own = bus_status(
        bus,
        lambda: {
            "transitions_received": learner.received,
            "duplicates": learner.duplicates,
            "too_old": learner.too_old,
            "transitions_dropped": intake.dropped,
        },
    )
    start_status_thread(bus, [(settings.transport.robot, own)], settings.transport.status_period, stop)
    log.info(
        "critic ready (robots %s, %s, M = %d, beta = %.4f, checkpoint %s)",
        settings.critic.robots,
        "one pooled learner" if learner.pool is not None else "a learner per robot",
        settings.critic.replay_size,
        settings.discount,
        path or "off",
    )
    end = None if duration is None else time.monotonic() + duration
    written, dirty = -math.inf, False  # the last checkpoint write; accepted transitions since

    def continuing(weights: CriticWeights) -> None:
        log.info("critic: continuing %s's episode %d from the checkpoint", weights.robot, weights.episode)
        publish([weights])

    def take_one_batch(batch: Columns[Transition], dirty: bool, written: float) -> tuple[bool, float]:
        """One batch into the learner, its fits made, its checkpoint written when due and its
        weights published; ``dirty``, ``written``: accepted since the last checkpoint, and when."""
        before = learner.accepted
        # critic.coalesce_fits: a critic that fell behind (a batch holds several transitions of a
        # robot) fits each robot once, on its newest: its actor uses only the newest weights anyway.
        # Pooled, the fit due in the batch is made once, at its end, on all of it.
        outgoing = learner.take_batch(batch, settings.critic.coalesce_fits, continuing, recovery.need)
        batches.append(len(batch))
        dirty = dirty or learner.accepted > before
        if dirty and writer is not None and time.monotonic() - written >= settings.critic.checkpoint_period:
            # the state as of this batch, encoded and written by the writer's thread while the
            # next batches are fitted (a restart continues from it; what came after it comes
            # again from the actors' publisher caches)
            writer.submit(learner.state())
            written, dirty = time.monotonic(), False
        publish(outgoing)
        return dirty, written

    dropped, warned = 0, -math.inf  # rows the intake refused, as last counted; when last said
    while not stop.is_set() and (end is None or time.monotonic() < end):
        if not intake.wait(0.05):
            continue
        backlog = intake.waiting + len(recovered)
        # Every transition waiting is taken in one go (a fleet sends one per robot per step), in
        # batches of at most MAX_BATCH: every robot due a fit is fitted at a batch's end, all in
        # one stacked solve, then ONE checkpoint holds them all, then the batch's weights go out.
        # One robot alone gives batches of one: a fit per transition due, as without batching.
        taken = collect(intake, recovered, settings.critic.batch_window, len(learner.learners), wire.transition)
        if intake.dropped > dropped:
            bus.count("transitions_dropped", intake.dropped - dropped)
            dropped = intake.dropped
            if time.monotonic() - warned >= 10.0:
                warned = time.monotonic()
                log.warning("critic: behind by %d transitions: %d dropped so far", INTAKE_LIMIT, dropped)
        if len(taken):
            waiting.append(backlog)
        for first in range(0, len(taken), MAX_BATCH):
            part = taken if len(taken) <= MAX_BATCH else taken.take(range(first, min(first + MAX_BATCH, len(taken))))
            dirty, written = take_one_batch(part, dirty, written)

    if writer is not None:
        if dirty:  # what came after the last periodic write
            writer.submit(learner.state())
        writer.close()
    return CriticSummary.model_validate(
        {
            "transitions_received": learner.received,
            "duplicates": learner.duplicates,
            "too_old": learner.too_old,
            "stale_episode": learner.stale_episode,
            "restored": learner.restored,
            "resume": learner.resume,
            "checkpoint": None if path is None else str(path),
            "checkpoint_ms": checkpoint_seconds.summary(1e3),
            "seen_steps": {robot: x.seen.runs() for robot, x in learner.learners.items()},
            "replay": {
                robot: [[s.step, *s.state.tolist(), *s.action.tolist(), s.cost] for s in x.replay.samples]
                for robot, x in learner.learners.items()
            },
            "weights_published": bus.counters["weights_published"],
            "last_version": learner.version,
            "fit_ms": learner.fit_seconds.summary(1e3),
            "batch_transitions": batches.summary(),
            "waiting_transitions": waiting.summary(),
            "fits_coalesced": learner.fits_coalesced,
            "fits_at_rest": learner.fits_at_rest,
            "pooled": learner.pool is not None,
            "counters": dict(bus.counters),
        }
    ).to_json_dict()
