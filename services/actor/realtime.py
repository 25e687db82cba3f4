"""The real-time actor: the ``delta``-periodic loop as a class with explicit state and ports.

At tick ``k`` (absolute time ``t0 + k delta``, served by services/actor/host.py's
:class:`~services.actor.host.HostScheduler`, one robot or many) it takes the newest
accepted state, solves, publishes the action and one transition. It never waits for the critic:
it uses the newest weights it holds and reports their staleness: the steps between the newest
transition its critic fits and the one they were trained on (a robot held at rest sends
transitions its critic does not fit, common.math.critic.at_rest). It commands zero velocity and
records no transition (the critic sees a gap, never a false pair) when the state is stale
(older than ``(action_timeout_steps - 1) delta``), never came, when the plant's liveliness token
vanished, or while two plant sessions are alive (common.net.provenance).

States are accepted only from the live plant session (its identity token, common.net.provenance),
in order per session and never more than :data:`MAX_SEQ_JUMP` ahead; a new session (a
restarted plant) resynchronizes.

What the loop keeps of its run (costs, latency and staleness windows, what its critic fits, the
published steps and the transitions' tail) is its row of its host's
:class:`~services.actor.ledger.Ledger` (a ledger of its own when it has no host), so that a host
records its robots at rest as array operations (:func:`rest_ticks`). Memory is bounded whatever
the run length: the statistics are fixed windows (the newest 4096 values; max over the whole
run), the costs running sums, the published steps the newest
:data:`~services.actor.ledger.RUNS_KEPT` runs, the transitions' tail the newest ``M``.
``tests/test_realtime_actor.py`` runs it on a fake clock and fake ports.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol

import numpy as np

from common.config.assembly import arrival_tolerances
from common.config.settings import Settings
from common.contracts.columns import Columns
from common.contracts.messages import Action, PlantState, Transition
from common.contracts.summaries import RealtimeActorSummary, TrueView
from common.math.actor import StackedActor
from common.math.actor_problem import ActorCounters, ActorStep
from common.math.agents import learns
from common.math.features import stage_cost
from common.math.stats import Window
from common.net.provenance import RefusalRun, SequenceGuard, SourceGate
from common.system.clock import Ticker
from services.actor.ledger import PUBLISH_TIMES_KEPT, HeldState, Ledger
from services.actor.ports import PUBLISHED, TRAINED, HeldWeights, WeightsInbox

log = logging.getLogger(__name__)
# A state's seq may run at most this far ahead of the last accepted one of its plant session
# (plant_sim publishes at transport.state_rate <= 1000 Hz, the bridge at the odometry rate):
# one forged PlantState(seq=2**62) must not make every real state "old" for the rest of the run.
MAX_SEQ_JUMP = 10_000


class Counts(Protocol):
    """What the loop reports to (common.net.transport.Bus has it): counters and refusals."""

    @property
    def counters(self) -> Any: ...

    def count(self, name: str, amount: int = 1) -> None: ...

    def reject(self, what: str, reason: str) -> None: ...


class Steps(Protocol):
    """The actor a loop steps: a :class:`StackedActor`, or one robot's share of one
    (services/actor/host.py's RobotActor)."""

    @property
    def counters(self) -> ActorCounters: ...

    def step(
        self, state: np.ndarray, q_weights: np.ndarray, v_weights: np.ndarray, hurry: bool = False
    ) -> ActorStep: ...

    def reset(self) -> None: ...


class AtRest(NamedTuple):
    """One robot's tick at rest, decided with its tick group's as arrays (services/actor/host.py
    RestCheck): its actor's arrival rule holds it and still will at ``state``. A tuple: made for
    every robot at rest at every tick (0.26 us to make here, a frozen dataclass 0.72)."""

    held: int  # the newest accepted state it was decided on: its count (services/actor/ledger.py)
    seq: int  # that state's seq
    received: float  # when it came
    state: np.ndarray  # its values
    truth: np.ndarray | None  # its true state (None: the plant sends none)
    cost: float  # delta r(state, 0)
    true_cost: float | None  # delta r(true state, 0); None: the state carries no truth
    inner: bool  # inside the arrival rule's inner tolerances (common.math.critic.at_rest)
    hold: Callable[[], None]  # leaves the actor's memory as its step at rest does


@dataclass(frozen=True, slots=True)
class Rests:
    """Robots' ticks at rest, decided with their tick group's as arrays (services/actor/host.py
    RestCheck), a row each: what :class:`AtRest` is for one, as columns. ``at``: the robots (the
    host's numbers, in the rows' order); ``truths`` and ``true_costs`` NaN where the state carries
    no truth; ``holds``: each robot's :attr:`AtRest.hold`."""

    at: list[int]
    held: np.ndarray  # int64: the newest accepted state each was decided on (its count)
    seq: np.ndarray  # int64: that state's seq
    received: np.ndarray  # when it came
    states: np.ndarray  # (rows, state_dim)
    truths: np.ndarray  # (rows, state_dim), NaN: no truth
    costs: np.ndarray  # delta r(state, 0)
    true_costs: np.ndarray  # delta r(true state, 0), NaN: no truth
    inner: np.ndarray  # bool
    holds: list[Callable[[], None]]

    def __len__(self) -> int:
        return len(self.at)

    def take(self, rows: Sequence[int]) -> Rests:
        """The rows ``rows``, in that order."""
        pick = np.asarray(rows, dtype=np.intp)
        return Rests(
            [self.at[j] for j in rows],
            self.held[pick],
            self.seq[pick],
            self.received[pick],
            self.states[pick],
            self.truths[pick],
            self.costs[pick],
            self.true_costs[pick],
            self.inner[pick],
            [self.holds[j] for j in rows],
        )

    @staticmethod
    def joined(parts: Sequence[Rests]) -> Rests:
        """The rows of ``parts`` (at least one), in order."""
        if len(parts) == 1:
            return parts[0]

        def joined(name: str) -> np.ndarray:
            return np.concatenate([getattr(part, name) for part in parts])

        return Rests(
            [i for part in parts for i in part.at],
            joined("held"),
            joined("seq"),
            joined("received"),
            joined("states"),
            joined("truths"),
            joined("costs"),
            joined("true_costs"),
            joined("inner"),
            [hold for part in parts for hold in part.holds],
        )

    @staticmethod
    def of(at: Sequence[int], rests: Sequence[AtRest], state_dim: int) -> Rests:
        """Robots ``at``'s :class:`AtRest`, as rows."""
        nan = np.full(state_dim, math.nan)
        return Rests(
            list(at),
            np.array([rest.held for rest in rests], dtype=np.int64),
            np.array([rest.seq for rest in rests], dtype=np.int64),
            np.array([rest.received for rest in rests], dtype=float),
            np.array([rest.state for rest in rests], dtype=float).reshape(len(rests), state_dim),
            np.array([nan if rest.truth is None else rest.truth for rest in rests]).reshape(len(rests), state_dim),
            np.array([rest.cost for rest in rests], dtype=float),
            np.array([math.nan if rest.true_cost is None else rest.true_cost for rest in rests], dtype=float),
            np.array([rest.inner for rest in rests], dtype=bool),
            [rest.hold for rest in rests],
        )

    def ready(self, loops: Sequence[RealtimeActor], tick: float) -> np.ndarray:
        """Per row (robot ``loops[j]``): can its tick at ``tick`` be served at rest
        (:meth:`RealtimeActor.ready_at_rest`, for all rows at once: the loops are one host's, of
        one ledger and one staleness bound)."""
        first = loops[0]
        ledger = first.ledger
        rows = np.fromiter((loop.row for loop in loops), dtype=np.intp, count=len(loops))
        conflict = np.fromiter((loop.plant_gate.conflict for loop in loops), dtype=bool, count=len(loops))
        with ledger.lock:
            held, accepted = ledger.held[rows], ledger.accepted[rows]
        ready: np.ndarray = ~conflict & held & (accepted == self.held) & (tick - self.received <= first.stale_after)
        return ready


class ColumnSink(Protocol):
    """Where ticks at rest put their actions and their transitions as columns of their schema,
    no message built (services/actor/host.py Outbox.put_columns): one array, or one value for
    every row, per field (common.contracts.columns.Columns.of)."""

    def put_columns(self, robots: Sequence[str], fields: dict[str, Any]) -> None: ...


class RealtimeActor:
    """One robot's real-time actor. Feed it states (:meth:`on_state`), plant identities and
    tokens; a scheduler (services/actor/host.py HostScheduler, of one robot or many) calls
    :meth:`tick` at each due time and sets :attr:`ticker`; :meth:`status` and :meth:`summary`
    report. Everything it sends goes through ``publish_action`` and ``publish_transition``."""

    def __init__(
        self,
        settings: Settings,
        actor: StackedActor | Steps,
        inbox: WeightsInbox,
        publish_action: Callable[[Action], None],
        publish_transition: Callable[[Transition], None],
        counts: Counts,
        episode_id: int,
        plant_gate: SourceGate | None = None,
        clock: Callable[[], float] = time.monotonic,
        ledger: Ledger | None = None,
        row: int = 0,
    ) -> None:
        self.settings = settings
        self.robot = settings.transport.robot
        # the system's messages (common/contracts/wire.py: the robot's are srl's own) and its zero
        self.system, self.wire = settings.system, settings.wire
        self.zero = (0.0,) * self.system.action_dim
        self.named = self.wire.named  # the fields every message takes beside its own ({} for the robot)
        # what a batch of the system's actions and transitions carries beside their own fields
        self.named_columns = (self.wire.named_columns(self.wire.action), self.wire.named_columns(self.wire.transition))
        self.delta = settings.plant.sampling_time
        self.r_diag = settings.r_diag  # diag(R), resolved once (the system's own if [])
        # A state older than this at a tick means the plant is silent: command zero. The last
        # state seen at t0 is then stale at the first tick after t0 + (n - 1) delta, i.e. the zero
        # goes out within n delta of the state stopping (n = action_timeout_steps >= 2).
        self.stale_after = (settings.transport.action_timeout_steps - 1) * self.delta
        self.actor, self.inbox, self.counts = actor, inbox, counts
        self.publish_action, self.publish_transition = publish_action, publish_transition
        self.episode_id = episode_id
        self.clock = clock
        self.plant_gate = plant_gate or SourceGate("plant")
        self.order = SequenceGuard(MAX_SEQ_JUMP)
        self.episodes: dict[str, int] = {}  # the followed episode of each live plant session
        self.episode_run = RefusalRun()  # states of another episode refused in a row
        self.refused_at = 0.0  # when the live plant's last state was refused (a lockout shows in status)
        # what the loop keeps of its run: its row of its host's ledger (services/actor/ledger.py),
        # or of a ledger of its own; the tick statistics, bounded
        if ledger is None:
            system = self.system
            replay = settings.critic.replay_size
            ledger = Ledger(1, system.state_dim, system.action_dim, replay, arrival_tolerances(settings))
        self.ledger, self.row = ledger, row
        # the newest accepted state is the ledger row's (Ledger.hold), guarded by the ledger's lock
        self.lock = ledger.lock
        inbox.bind(ledger.weights, row)  # its published and trained steps in the ledger's row
        ledger.episode[row] = episode_id
        self.periods = Window()
        self.jitter = Window()
        self.latencies, self.staleness_steps, self.staleness_ms = ledger.windows(row)
        self.learns = learns(settings.actor.agent)
        self.arrived = False  # the actor's arrival rule holds the robot (its last step said "arrived")
        self.stale_state_stops = 0
        self.plant_conflict_stops = 0
        self.start_state: np.ndarray | None = None
        # the truth, when the plant sends it with every state (a simulator; never a real robot)
        self.truth_known = True
        self.true_start: tuple[float, ...] | None = None
        self.ticker: Ticker | None = None
        self.last_step = -1
        # an actor host's outboxes of actions and transitions, which ticks at rest fill with
        # columns (None: every tick builds its messages)
        self.rest_columns: tuple[ColumnSink, ColumnSink] | None = None

    @property
    def steps(self) -> int:
        return int(self.ledger.steps[self.row])

    @property
    def arrived_steps(self) -> int:
        return int(self.ledger.arrived_steps[self.row])

    @property
    def accumulated_cost(self) -> float:
        return float(self.ledger.cost[self.row])

    @property
    def true_accumulated_cost(self) -> float:
        return float(self.ledger.true_cost[self.row])

    @property
    def latest(self) -> tuple[PlantState, float] | None:
        """The newest accepted state and when it came (None: none yet, or forgotten)."""
        with self.lock:
            return self._latest()

    def _latest(self) -> tuple[PlantState, float] | None:
        """:attr:`latest`, the lock held."""
        return self.ledger.newest_state(self.row) if self.ledger.held[self.row] else None

    @property
    def last_accepted(self) -> PlantState | None:
        """The newest accepted state, forgotten or not (the summary's): never a refused one."""
        with self.lock:
            pair = self.ledger.newest_state(self.row)
        return None if pair is None else pair[0]

    def _forget(self) -> None:
        """The held state is no longer the robot's (the lock held): the next tick stops it."""
        self.ledger.held[self.row] = False

    def _settle(self) -> None:
        """Before a state is judged one by one or the plants change (the lock held): the order
        guard's reference as the ledger holds it (batches may have moved it: StateIntake), and no
        batch takes the row's states as arrays until one is accepted again."""
        ledger, i = self.ledger, self.row
        if ledger.follow[i]:
            self.order.last[ledger.follow_source[i]] = ledger.seq.item(i)
            ledger.follow[i] = False

    # -- inputs (Zenoh's threads) ---------------------------------------------------------
    def on_plant_identity(self, zid: str, alive: bool) -> None:
        with self.lock:
            self._settle()
            self.order.forget(set(self.plant_gate.sources()))
            if not alive:
                self.episodes.pop(zid, None)
            if self.plant_gate.conflict:
                self._forget()  # follow neither of two plants
        if self.plant_gate.conflict:
            self.counts.count("plant_conflicts")
            log.error(
                "two plants are alive for robot %s (sessions %s): commanding zero velocity until one is gone",
                self.robot,
                ", ".join(self.plant_gate.sources()),
            )

    def on_state(self, message: PlantState, source: str | None, received: float | None = None) -> None:
        """A state from session ``source``, which arrived at ``received`` (default: now)."""
        verdict = self.plant_gate.verdict(source)
        if verdict != "accept":
            self.counts.reject(
                f"state.{verdict}", f"from session {source} (live plant: {self.plant_gate.sources() or 'none'})"
            )
            return
        assert source is not None
        with self.lock:
            self._settle()
            now = self.clock() if received is None else received
            followed = self.episodes.get(source)
            if followed is None:  # the live plant session's first state: its episode is followed
                self.episodes[source] = followed = message.episode
            if message.episode != followed:
                # A real-time plant never changes its episode within a session (plant_sim serves
                # reset in lockstep only, the bridge's is 0): a state of another episode is forged
                # or stray and refused alone; a run of them that counts on is followed (a plant
                # that did start a new stream), so no forged episode can lock the real one out.
                if not self.episode_run.refused((message.episode, message.seq), now):
                    self.refused_at = now
                    self.counts.reject("state", f"episode {message.episode} is not the live plant's {followed}")
                    return
                log.warning("the live plant's states moved to episode %d: following them", message.episode)
                self.counts.count("state_episode_resyncs")
                self.episodes[source] = message.episode
                self.order.last.pop(source, None)
            resyncs = self.order.resyncs
            refusal = self.order.check(source, message.seq, now)
            if refusal is not None:
                self.refused_at = now
                self.counts.reject("state", f"seq {refusal}")
                return
            if self.order.resyncs != resyncs:
                log.warning("the live plant's seq refused %d times in a row: following it", self.order.restart_after)
                self.counts.count("state_seq_resyncs")
            self.episode_run.accepted()
            self.ledger.hold(self.row, message, now, source)

    def on_plant_token(self, alive: bool) -> None:
        """The plant (simulator or robot bridge) vanished: its last state is no longer the robot's.
        Forget it, so the next tick commands zero velocity instead of waiting for the state to go
        stale; fresh states resume the loop."""
        if not alive:
            with self.lock:
                self._forget()
            self.counts.count("plant_lost")
            log.warning("plant liveliness lost: commanding zero velocity until its state returns")

    # -- the loop ---------------------------------------------------------------------------
    def tick(self, k: int, tick: float, hurry: bool = False, rest: AtRest | None = None) -> None:
        """The work of tick ``k`` (due at ``tick``): an action (zero when it must) and, after a
        solve, one transition. ``hurry``: an actor host serves this tick late (the lighter solve,
        StackedActor.step). ``rest``: the host's tick group found the robot held at rest
        (services/actor/host.py RestCheck): no step, when the state it was decided on is still
        the newest (else a step, as without it)."""
        ledger, i = self.ledger, self.row
        with self.lock:
            at_rest = rest is not None and self.ready_at_rest(rest, tick)  # held and fresh, then
            held = None if at_rest else ledger.fresh_state(i, tick, self.stale_after)  # no message built
        fresh = at_rest or held is not None
        if self.plant_gate.conflict:
            self.plant_conflict_stops += 1
            self.stop_robot(k)
        elif not fresh:
            self.stale_state_stops += 1
            self.stop_robot(k)
        else:
            try:
                if held is None:  # decided at rest on the newest state (no message read)
                    assert rest is not None
                    rest_ticks([self], [k], tick, Rests.of([0], [rest], self.system.state_dim))
                else:
                    self._step(k, tick, held, hurry)
            except Exception:  # never let one bad tick end the loop that keeps the robot safe
                self.counts.count("tick_errors")
                log.exception("actor tick %d failed; commanding zero velocity", k)
                self.stop_robot(k)
        self.last_step = k

    def prime(self) -> bool:
        """One solve from the held state, acting on nothing (no action, no transition): an actor
        host before its first tick, so that tick polishes a plan instead of solving cold (a cold
        solve, with the global phase from scratch, costs several warm ones: services/actor/host.py
        ``prime_plans``). The solve and its
        time are counted as any other. False: no state held yet."""
        held = self.latest
        if held is None:
            return False
        weights = self.inbox.current()
        self.actor.step(np.array(held[0].state), weights.q, weights.v)
        self.counts.count("primed_solves")
        return True

    def send(self, k: int, action: tuple[float, ...], state_seq: int) -> None:
        """Publish the action held over interval ``k`` (answering state ``state_seq``, -1: none)."""
        self.publish_action(
            self.wire.action(
                **self.named,
                robot=self.robot,
                episode=self.episode_id,
                step=k,
                stamp_ns=time.monotonic_ns(),
                action=action,
                state_seq=state_seq,
            )
        )

    def stop_robot(self, k: int) -> None:
        self.send(k, self.zero, -1)
        self.actor.reset()  # the plan no longer matches the robot

    def _step(self, k: int, tick: float, held: HeldState, hurry: bool) -> None:
        values, truth, seq, received = held
        state = np.array(values)
        if self.start_state is None:
            self.start_state = state  # the robot's own start, whatever was requested
        self.note_truth(truth)
        weights = self.inbox.current()
        step = self.actor.step(state, weights.q, weights.v, hurry)  # the arrival rule acts inside (exactly zero)
        arrived = step.status == "arrived"
        if arrived != self.arrived:
            log.info(
                "%s at (%.3f m, %.3f m, %.3f rad): %s",
                "arrived" if arrived else "left the arrival tolerance",
                *state,
                "commanding zero velocity" if arrived else "resuming",
            )
        self.arrived = arrived
        action = tuple(step.action.tolist())
        self.send(k, action, seq)
        done = self.clock()
        r_diag = self.r_diag
        cost = self.delta * float(stage_cost(state, step.action, r_diag))
        true_cost = None
        if truth is not None:
            true_cost = self.delta * float(stage_cost(np.array(truth), step.action, r_diag))
        self._record(k, tick, received, state, action, cost, true_cost, weights, step.solve_seconds, done)

    def ready_at_rest(self, rest: AtRest, tick: float) -> bool:
        """The tick at ``tick`` can be served at ``rest``: one live plant, and the state it was
        decided on still the newest and fresh (else the tick is :meth:`tick`'s, a step or a stop)."""
        ledger, i = self.ledger, self.row
        return (
            not self.plant_gate.conflict
            and ledger.held.item(i)
            and ledger.accepted.item(i) == rest.held
            and tick - rest.received <= self.stale_after
        )

    def note_truth(self, truth: Any) -> None:
        """A state used: its true state (None: none sent; a plant that sends none once is not known
        to tell the truth, and the summary's true view is left out)."""
        if truth is None:
            self.truth_known = False
        elif self.true_start is None:
            self.true_start = tuple(float(c) for c in truth)

    def _record(
        self,
        k: int,
        tick: float,
        received: float,
        state: np.ndarray,
        action: tuple[float, ...],
        cost: float,
        true_cost: float | None,
        weights: HeldWeights,
        solve_seconds: float,
        done: float,
    ) -> None:
        """What a step leaves once its action is out (at ``done``; its state came at ``received``):
        its transition, its cost and statistics, in its row of the ledger (:func:`rest_ticks`
        records many ticks at rest at once)."""
        ledger, i = self.ledger, self.row
        # transport/loop latency: state arrival -> action out, minus the solve itself
        self.latencies.append(max(0.0, done - max(received, tick) - solve_seconds))
        # the step fresh weights would be trained on: the previous one (ideally), or, while the
        # robot rests (the critic fits no transition of a robot at rest), the newest one fitted
        values = [*state.tolist(), *action, cost]
        n = self.system.state_dim
        resting, newest = ledger.record(i, k, values[:n], action, cost, true_cost, self.arrived, None)
        self.inbox.published(k)  # before the transition goes out: weights trained on it may come back at once
        self.publish_transition(
            self.wire.transition(
                **self.named,
                robot=self.robot,
                episode=self.episode_id,
                step=k,
                state=tuple(values[:n]),
                action=action,
                cost=cost,
            )
        )
        ledger.published(i, k, self.clock(), values)
        if self.learns:
            self.staleness_steps.append((newest if resting else k - 1) - weights.trained_step)
            slot = weights.trained_step % PUBLISH_TIMES_KEPT
            # at rest, the weights' age in time grows with the rest: not a delay of the critic's
            trained = weights.trained_step
            if not resting and trained >= 0 and ledger.published_step[i, slot] == trained:
                self.staleness_ms.append((done - float(ledger.published_at[i, slot])) * 1e3)

    # -- reports ------------------------------------------------------------------------------
    def lockout_suspect(self) -> bool:
        """The live plant's states are being refused and none was accepted for over a second:
        the pattern a forged far-ahead sequence number or episode leaves (status)."""
        ledger, i = self.ledger, self.row
        now = self.clock()
        return now - self.refused_at < 1.0 and (not ledger.held.item(i) or now - ledger.received.item(i) > 1.0)

    def status(self) -> dict[str, float]:
        """The 1 Hz status counters (``srl/<robot>/status/actor``; ``srl up``'s live line)."""
        held_weights = self.inbox.current()
        solves = self.actor.counters.solve_seconds
        ledger, i = self.ledger, self.row
        with self.lock:
            shown = ledger.state[i].tolist() if ledger.held.item(i) else None
        return {
            **self.where(shown),
            "accumulated_cost": self.accumulated_cost,
            "steps": self.steps,
            "missed_deadlines": self.ticker.missed if self.ticker is not None else 0,
            "solver_failures": self.actor.counters.failures,
            "hurried_solves": self.actor.counters.hurried_solves,  # served late: the lighter solve
            "weights_version": held_weights.version,
            "staleness_steps": self.staleness_steps.last if self.staleness_steps.count else 0.0,
            "solve_ms_last": solves.last * 1e3 if solves.count else 0.0,
            # the newest tick's distance from its deadline (srl view and srl record plot it)
            "jitter_ms_last": self.jitter.last * 1e3 if self.jitter.count else 0.0,
            "plant_sources": float(len(self.plant_gate.sources())),
            "plant_conflict": float(self.plant_gate.conflict),
            "lockout_suspect": float(self.lockout_suspect()),
            "arrived": float(self.arrived),  # the arrival rule holds the robot (common/math/arrival.py)
            "arrived_steps": float(self.arrived_steps),
        }

    def where(self, state: Any) -> dict[str, float]:
        """The status's view of ``state`` (None: nan, left out): a wheeled robot's pose ``x``, ``y``,
        ``alpha``; another system's ``distance`` to its goal (common/math/systems.py)."""
        if self.system.wheeled:
            x, y, alpha = (math.nan,) * 3 if state is None else state
            return {"x": x, "y": y, "alpha": alpha}
        return {"distance": math.nan if state is None else self.system.distance(np.array(state))}

    def truth(self, last: PlantState | None) -> TrueView | None:
        """The true view, if every state the loop used carried the truth (None: odometry only)."""
        if not self.truth_known or self.true_start is None or last is None or last.true_state is None:
            return None
        final = last.true_state
        return TrueView(
            start_state=list(self.true_start),
            final_state=list(final),
            final_distance=self.system.distance(np.array(final)),
            accumulated_cost=self.true_accumulated_cost,
        )

    def summary(self) -> dict[str, Any]:
        last = self.last_accepted
        ticker = self.ticker
        truth = self.truth(last)
        return RealtimeActorSummary.model_validate(
            {
                "agent": self.settings.actor.agent,
                "horizon": self.settings.actor.horizon,
                "system": self.settings.plant.system,
                "episode_id": self.episode_id,
                "steps": self.steps,
                "accumulated_cost": self.accumulated_cost,
                "start_state": None if self.start_state is None else [float(c) for c in self.start_state],
                "final_state": None if last is None else [float(c) for c in last.state],
                "final_distance": None if last is None else self.system.distance(np.array(last.state)),
                "truth": None if truth is None else truth.model_dump(),
                "saturated_commands": None if last is None else last.saturated_commands,
                "weights_version": self.inbox.current().version,
                "loop": {
                    "period_ms": self.periods.summary(1e3),
                    "jitter_ms": self.jitter.summary(1e3),
                    "missed_deadlines": ticker.missed if ticker is not None else 0,
                    "late_ticks": ticker.late if ticker is not None else 0,
                },
                "solve_ms": self.actor.counters.solve_seconds.summary(1e3),
                "solver_failures": self.actor.counters.failures,
                "latency_ms": self.latencies.summary(1e3),
                "staleness_steps": self.staleness_steps.summary(),
                "staleness_ms": self.staleness_ms.summary(),
                "stale_state_stops": self.stale_state_stops,
                "plant_conflict_stops": self.plant_conflict_stops,
                "plant_sources": self.plant_gate.sources(),
                "transitions_tail": self.ledger.tail_of(self.row),
                "transition_steps": self.ledger.runs_of(self.row),
                "counters": {**self.counts.counters, "hurried_solves": self.actor.counters.hurried_solves},
            }
        ).to_json_dict()


def rest_ticks(loops: Sequence[RealtimeActor], ks: Sequence[int], tick: float, rests: Rests) -> None:
    """Ticks ``ks`` of ``loops`` (each :meth:`RealtimeActor.ready_at_rest`; a host's share a ledger)
    served at ``tick`` at their ``rests`` (a row each, in order): exactly zero, no solve; the
    arrival test and the costs are their tick group's (services/actor/host.py RestCheck), their
    records the ledger's array operations (:meth:`Ledger.record_rows`), their actions and
    transitions one batch each when the loops have their host's outboxes (``rest_columns``), else
    a message each. What each robot sends and keeps is what its own step at rest would, bit for
    bit (``tests/test_host_rest.py``)."""
    first = loops[0]
    ledger = first.ledger
    count = next((j for j, loop in enumerate(loops) if loop.ledger is not ledger), len(loops))
    if count < len(loops):  # loops of several ledgers: each run of one ledger's at once, in order
        rest_ticks(loops[:count], ks[:count], tick, rests.take(range(count)))
        rest_ticks(loops[count:], ks[count:], tick, rests.take(range(count, len(loops))))
        return
    rows = np.array([loop.row for loop in loops], dtype=np.intp)
    ks_array = np.array(ks, dtype=np.int64)
    trained = ledger.weights[rows, TRAINED]  # the held weights' (WeightsInbox.marks)
    truths = rests.truths
    known = ~np.isnan(truths[:, 0])
    for loop, truth, told in zip(loops, truths, known.tolist(), strict=True):
        if not told or loop.true_start is None:  # else note_truth changes nothing
            loop.note_truth(truth if told else None)
    for hold in rests.holds:
        hold()
    seqs, received, costs, true_costs = rests.seq, rests.received, rests.costs, rests.true_costs
    inner, states = rests.inner, rests.states
    arrived = np.fromiter((loop.arrived for loop in loops), dtype=bool, count=count)
    zero = np.zeros((count, first.system.action_dim))
    episodes = ledger.episode[rows]
    sinks = first.rest_columns
    robots = [loop.robot for loop in loops]
    if sinks is not None:
        action_fields = {"episode": episodes, "step": ks_array, "stamp_ns": time.monotonic_ns()}
        action_fields |= {"action": zero, "state_seq": seqs}
        sinks[0].put_columns(robots, first.named_columns[0] | action_fields)
    else:
        for loop, k, seq in zip(loops, ks, seqs.tolist(), strict=True):
            loop.send(k, loop.zero, seq)
    done = first.clock()
    ledger.latencies.append_rows(rows, np.maximum(0.0, done - np.maximum(received, tick)))
    resting, newest = ledger.record_rows(rows, ks_array, states, costs, true_costs, arrived, inner)
    # WeightsInbox.published, before the transitions go out (RealtimeActor._record): only this thread writes it
    published = ledger.weights[rows, PUBLISHED]
    ledger.weights[rows, PUBLISHED] = np.maximum(published, ks_array)
    values = np.column_stack([states, zero, costs])
    if sinks is not None:
        transition_fields = {"episode": episodes, "step": ks_array, "state": states, "action": zero, "cost": costs}
        sinks[1].put_columns(robots, first.named_columns[1] | transition_fields)
    else:
        n = first.system.state_dim
        for loop, k, row in zip(loops, ks, values.tolist(), strict=True):
            loop.publish_transition(
                loop.wire.transition(
                    **loop.named,
                    robot=loop.robot,
                    episode=loop.episode_id,
                    step=k,
                    state=tuple(row[:n]),
                    action=loop.zero,
                    cost=row[-1],
                )
            )
    ledger.published_rows(rows, ks_array, first.clock(), values)
    if first.learns:
        ledger.staleness_steps.append_rows(rows, np.where(resting, newest, ks_array - 1) - trained)
        # at rest, the weights' age in time grows with the rest: not a delay of the critic's
        slots = trained % PUBLISH_TIMES_KEPT
        timed = ~resting & (trained >= 0) & (ledger.published_step[rows, slots] == trained)
        if timed.any():
            ages = (done - ledger.published_at[rows[timed], slots[timed]]) * 1e3
            ledger.staleness_ms.append_rows(rows[timed], ages)
    for loop, k in zip(loops, ks, strict=True):
        loop.last_step = k


class StateIntake:
    """An actor host's states, a batch at once (``loops``: the host's, of one ledger, each robot's
    loop once; made once, refused otherwise). Each state is judged as :meth:`RealtimeActor.on_state`
    judges it, with the same verdicts, counts and order. The common one is taken as arrays: its
    robot's last accepted state came from the batch's source and nothing refused or changed its
    plant since (``Ledger.follow``), it is of the episode followed, its seq newer than that state's
    and at most :data:`MAX_SEQ_JUMP` ahead, its robot once in the batch; it is held without a
    message built (:meth:`Ledger.hold_rows`; a step builds it when it reads it). The others go
    through :meth:`RealtimeActor.on_state` one by one, in order. A batch is judged on the plants
    its robots followed: one that arrives between Zenoh's update of a plant gate and the loop's
    :meth:`RealtimeActor.on_plant_identity` (microseconds) is taken as a state delivered a moment
    earlier would have been, and a second plant stops the robot at its next tick all the same."""

    def __init__(self, loops: Sequence[RealtimeActor]) -> None:
        if not loops:
            raise ValueError("a state intake takes the states of a host's robots: no loop given")
        self.ledger = loops[0].ledger
        if any(loop.ledger is not self.ledger for loop in loops):
            raise ValueError("a state intake holds states in one ledger: its loops must be one host's")
        # robot -> (its loop, its ledger row)
        self.robots = {loop.robot: (loop, loop.row) for loop in loops}
        if len(self.robots) != len(loops) or len({loop.row for loop in loops}) != len(loops):
            raise ValueError("a state intake serves each robot, and each ledger row, once")

    def __call__(self, batch: Columns[Any], source: str | None, received: float) -> None:
        """A batch of states (rows of this host's robots: the bus's subscription of their keys)
        from session ``source``, arrived at ``received``; an empty one changes nothing."""
        ledger, robots = self.ledger, self.robots
        if not len(batch):
            return
        loops, row_list = zip(*(robots[robot] for robot in batch.robots), strict=True)
        rows = np.array(row_list, dtype=np.intp)
        common = np.zeros(len(rows), dtype=bool)
        if source is not None and len(set(row_list)) == len(row_list):
            episodes, seqs = batch.field("episode"), batch.field("seq")
            with ledger.lock:
                last = ledger.seq[rows]
                common = (
                    ledger.follow[rows]
                    & (ledger.follow_source[rows] == source)
                    & (ledger.follow_episode[rows] == episodes)
                    & (seqs > last)
                    & (seqs <= last + MAX_SEQ_JUMP)
                )
                taken = np.flatnonzero(common)
                if len(taken):
                    ledger.hold_rows(rows[taken], batch, taken, received)
        for j in np.flatnonzero(~common).tolist():
            loops[j].on_state(batch.item(j), source, received)

    def alone(self, message: PlantState, source: str | None, received: float) -> None:
        """A state that came alone on its robot's key (a robot bridge's, a plant of one robot's):
        judged by its loop's :meth:`RealtimeActor.on_state`, as a batch of it would be, at the
        cost of one message (no batch of one built)."""
        self.robots[message.robot][0].on_state(message, source, received)
