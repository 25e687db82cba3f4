"""A robot held at rest by the arrival rule costs its critic no fit (common.math.critic.at_rest):
the rule itself, the per-robot critic service, the in-process critic (the same decisions), the
lockstep port (which then waits for no weights) and the real-time actor's staleness (over the
ticks that use weights)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

from common.config.assembly import local_critic
from common.config.settings import Settings
from common.contracts.messages import Transition
from common.math.arrival import ArrivalTolerances
from common.math.critic import FitsDue, Sample, at_rest, at_rest_rows
from services.actor.ports import HeldWeights, ZenohCriticPort
from services.critic.service import CriticLearner, coalesced_fits
from tests.test_realtime_actor import DELTA, FakeStep, Loop, weights

TOLERANCES = ArrivalTolerances(position=0.03, heading=0.1, hysteresis=1.5)
PARKED = np.array([0.01, -0.02, 0.05])  # inside the inner tolerances
ZERO = np.zeros(2)


def sample(step: int, state: np.ndarray = PARKED, action: np.ndarray = ZERO, cost: float = 1e-5) -> Sample:
    return Sample(step, np.array(state, dtype=float), np.array(action, dtype=float), cost)


def test_at_rest_is_the_same_state_held_at_zero_inside_the_tolerances() -> None:
    assert at_rest(sample(4), sample(5), TOLERANCES)
    inner = np.array([0.029, 0.0, 0.099])
    assert at_rest(sample(4, inner), sample(5, inner), TOLERANCES)
    # between the inner and the outer tolerances (0.03 and 1.5 x 0.03 m) a zero command may be the
    # wheel deadband's on a robot that has not arrived: its fits go on (the next solve may move it)
    annulus = np.array([0.04, 0.0, 0.0])
    assert not at_rest(sample(4, annulus), sample(5, annulus), TOLERANCES)
    turned = np.array([0.0, 0.0, 0.12])  # heading beyond 0.1 rad
    assert not at_rest(sample(4, turned), sample(5, turned), TOLERANCES)
    # each condition alone breaks it
    assert not at_rest(sample(4), sample(5), None)  # no arrival rule (the paper's method)
    assert not at_rest(None, sample(5), TOLERANCES)  # nothing before it
    assert not at_rest(sample(3), sample(5), TOLERANCES)  # a gap: not the step after
    assert not at_rest(sample(4, action=np.array([0.0, 1e-12])), sample(5), TOLERANCES)  # it moved
    assert not at_rest(sample(4), sample(5, action=np.array([1e-12, 0.0])), TOLERANCES)  # it moves now
    moved = PARKED + np.array([0.0, 0.0, 1e-15])
    assert not at_rest(sample(4), sample(5, moved), TOLERANCES)  # another state (pushed, noise)


def robot_run(approach: int = 8, rest: int = 12, leave: int = 6) -> list[Sample]:
    """A robot that drives in, is held at rest, then is pushed and drives again."""
    out, state = [], np.array([0.6, 0.3, 0.4])
    for k in range(approach):
        action = np.array([-0.2, 0.1])
        out.append(sample(k, state, action, cost=0.01 * (approach - k)))
        state = state * 0.6
    state = PARKED
    for k in range(approach, approach + rest):
        out.append(sample(k, state))
    for k in range(approach + rest, approach + rest + leave):
        state = state + np.array([0.02, 0.01, -0.03])  # pushed away, then driving back
        out.append(sample(k, state, np.array([0.1, -0.2]), cost=0.005))
    return out


def message(robot: str, s: Sample) -> Transition:
    return Transition(
        robot=robot,
        episode=1,
        step=s.step,
        state=(float(s.state[0]), float(s.state[1]), float(s.state[2])),
        action=(float(s.action[0]), float(s.action[1])),
        cost=s.cost,
    )


def settings(arrival: bool = True) -> Settings:
    return Settings.load(critic={"checkpoint": ""}, actor={"arrival": arrival})


def test_at_rest_rows_is_at_rest_of_each_row() -> None:
    tolerances = ArrivalTolerances(0.03, 0.1, 1.5)
    rng = np.random.default_rng(7)
    count = 4000
    previous = rng.choice([0.0, 0.01, -0.02, 0.029999, 0.03, 0.2], size=(count, 5))
    previous[:, 2] = rng.choice([0.0, 0.1, -0.1, 0.0999, 2 * np.pi, 2 * np.pi + 0.05, -np.pi], size=count)
    values = previous.copy()
    changed = rng.random(count) < 0.2
    values[changed, rng.integers(0, 5, changed.sum())] += 1e-12  # a state or an action apart by a hair
    previous_steps = rng.integers(0, 5, count)
    steps = previous_steps + rng.choice([1, 1, 1, 2, 0], size=count)
    got = at_rest_rows(previous_steps, previous, steps, values, tolerances)
    expected = [
        at_rest(
            Sample(int(previous_steps[i]), previous[i, :3], previous[i, 3:], 0.0),
            Sample(int(steps[i]), values[i, :3], values[i, 3:], 0.0),
            tolerances,
        )
        for i in range(count)
    ]
    assert got.tolist() == expected
    assert 0 < sum(expected) < count  # both answers occur
    assert not at_rest_rows(previous_steps, previous, steps, values, None).any()


@pytest.mark.parametrize("arrival", [True, False])
def test_the_critic_makes_no_fit_while_the_robot_is_held_at_rest_and_fits_again_when_it_moves(arrival: bool) -> None:
    run = robot_run()
    learner = CriticLearner(settings(arrival))
    fitted = [s.step for s in run if learner.on_transition(message("r1", s)) is not None]
    if not arrival:  # the negative control: without the rule every due fit is made
        assert fitted == [s.step for s in run] and learner.fits_at_rest == 0
        return
    # the first transition at the target is fitted (the robot came from elsewhere), the 11 after it
    # repeat it and are not; the push is fitted at once, on the whole replay, the rests included
    assert fitted == list(range(0, 9)) + list(range(20, 26))
    assert learner.fits_at_rest == 11
    assert learner.accepted == len(run)  # every transition entered the replay
    replay = learner.learners["r1"].replay
    assert [s.step for s in replay.samples] == [s.step for s in run]


def test_a_critic_behind_still_makes_the_last_fit_before_a_rest() -> None:
    """A critic that fell behind (``critic.coalesce_fits``) takes a robot's approach, its arrival
    and its first rests in one batch. The rests are not fitted, so they make no fit redundant: the
    arrival's fit is made, on the step the robot's actor counts its weights' staleness from
    (FitsDue.newest). Without the rests known (the negative control) the rests superseded it, no
    fit was made, and the actor's staleness stayed at its value of then for the whole rest."""
    run = robot_run()  # steps 0-7 approach, 8 the arrival (fitted), 9-19 at rest, then pushed
    batch = [message("r1", s) for s in run[:12]]
    learner = CriticLearner(settings())
    resting = learner.resting(batch)
    assert resting == [False] * 9 + [True] * 3
    superseded = coalesced_fits(batch, 1, resting)
    assert superseded == set(range(8))  # the approach's fits, made redundant by the arrival's
    outgoing = [w for i, m in enumerate(batch) for w in learner.take(m, fit=i not in superseded, defer=True)]
    outgoing += learner.flush()
    assert [w.trained_step for w in outgoing] == [8]
    assert learner.fits_coalesced == 8 and learner.fits_at_rest == 3
    actor = FitsDue(TOLERANCES)
    for s in run[:12]:
        actor.sent(s)
    assert actor.resting and actor.newest == 8  # what the weights the actor waits for are trained on

    unaware = CriticLearner(settings())
    superseded = coalesced_fits(batch, 1)
    assert superseded == set(range(11))
    outgoing = [w for i, m in enumerate(batch) for w in unaware.take(m, fit=i not in superseded, defer=True)]
    assert outgoing + unaware.flush() == []


def test_the_in_process_critic_makes_the_same_fits_as_the_critic_service() -> None:
    run = robot_run()
    learner, local = CriticLearner(settings()), local_critic(settings())
    local.reset()
    for s in run:
        weights = learner.on_transition(message("r1", s))
        q, v = local.record(s)
        fitted_locally = not np.isnan(local.last_residuals[0])
        assert fitted_locally == (weights is not None), s.step
        if weights is not None:
            np.testing.assert_array_equal(q, np.array(weights.q_weights))
            np.testing.assert_array_equal(v, np.array(weights.v_weights))
    assert local.updates == len(run) - 11


@dataclass
class FakeInbox:
    held: HeldWeights = field(default_factory=lambda: HeldWeights(np.ones(15), np.ones(6), 1, -1, 0.0))
    waited: list[int] = field(default_factory=list)

    def reset(self, episode: int) -> HeldWeights:
        return self.held

    def published(self, step: int) -> None:
        pass

    def wait_trained(self, step: int, timeout: float) -> bool:
        self.waited.append(step)
        self.held = HeldWeights(self.held.q, self.held.v, self.held.version + 1, step, 0.0)
        return True

    def current(self) -> HeldWeights:
        return self.held


class FakeBus:
    def __init__(self) -> None:
        self.sent: list[Any] = []

    def round_publisher(self, topic: Any, batches: bool = True, cache: int = 0, robots: Any = ()) -> Any:
        return self.sent.extend

    def count(self, name: str, amount: int = 1) -> None:
        pass


@pytest.mark.parametrize("arrival", [True, False])
def test_the_lockstep_port_waits_for_no_fit_at_rest(arrival: bool) -> None:
    own = Settings.load(critic={"checkpoint": ""}, actor={"arrival": arrival}, transport={"robot": "r1"})
    inbox, bus = FakeInbox(), FakeBus()
    port = ZenohCriticPort(own, bus, inbox, episode=1, sync=True)  # type: ignore[arg-type]
    port.reset()
    run = robot_run()
    for s in run:
        port.record(s)
    assert len(bus.sent) == len(run)  # every transition is published
    rests = set(range(9, 20)) if arrival else set()
    assert inbox.waited == [s.step for s in run if s.step not in rests]
    # the weights are as fresh as the critic makes them at every step, the rests too
    assert port.staleness == [0] * len(run)


def test_the_real_time_actor_counts_staleness_from_the_newest_transition_its_critic_fits() -> None:
    t = Loop()
    held = {"arrived": False}
    step = t.actor.step

    def arriving(*args: Any, **kwargs: Any) -> FakeStep:
        done = step(*args, **kwargs)
        return FakeStep(np.zeros(2), status="arrived") if held["arrived"] else done

    t.actor.step = arriving  # type: ignore[method-assign]
    t.loop.on_state = parked(t.loop.on_state)  # type: ignore[method-assign]

    def ticks(steps: range) -> None:
        for k in steps:
            t.publish_state()
            t.fake.now += DELTA
            t.loop.tick(k, t.fake.now)

    ticks(range(0, 3))  # driving on the initial weights (trained_step -1): staleness k
    held["arrived"] = True
    ticks(range(3, 8))  # held at rest from step 4 on: the critic fits step 3 (the arrival), none after
    assert list(t.loop.staleness_steps.values()) == [0, 1, 2, 3, 4, 4, 4, 4]
    assert len(t.transitions) == 8  # its transitions still go out (the critic's replay)
    t.inbox.offer(weights(3, version=13), "c1")  # the critic fitted the arrival: as fresh as it gets
    ticks(range(8, 10))
    assert list(t.loop.staleness_steps.values())[-2:] == [0, 0]
    assert t.loop.staleness_ms.count == 0  # at rest, the weights' age in time is not a delay
    held["arrived"] = False
    ticks(range(10, 12))  # moves at step 10: the transition of step 10 is due a fit, so step 11's
    assert list(t.loop.staleness_steps.values())[-2:] == [0, 10 - 3]  # weights lag 7 behind it
    assert t.loop.staleness_ms.count == 1


def parked(on_state: Any) -> Any:
    """The loop's state intake with every state at the target (the arrival rule's inner tolerances)."""

    def intake(message: Any, source: Any, received: float | None = None) -> None:
        on_state(message.model_copy(update={"state": (0.01, 0.0, 0.0)}), source, received)

    return intake


def test_a_step_recovered_late_is_fitted_but_never_labels_the_weights_older() -> None:
    """A partition holds back one of a robot's transitions; Zenoh recovers it from the actor's
    cache after newer ones, the robot then at rest. Its fit is on the whole replay, so its weights
    are trained on the newest fitted step: labelled with the late step, they would reach the actor
    under a newer version with a staleness no fit mends while the robot rests (seen once in CI:
    48 steps to the end of a partition test's run)."""
    run = robot_run(leave=0)  # 0-7 approach, 8 the arrival, 9-19 at rest
    late = 5
    learner = CriticLearner(settings())
    published = [w for s in run if s.step != late for w in learner.take(message("r1", s))]
    assert [w.trained_step for w in published] == [0, 1, 2, 3, 4, 6, 7, 8]  # 6: the gap is no rest
    recovered = learner.take(message("r1", run[late]))
    assert len(recovered) == 1 and recovered[0].version > published[-1].version  # fitted: new data
    actor = FitsDue(TOLERANCES)
    for s in run:
        actor.sent(s)
    assert actor.resting and actor.newest == 8
    assert recovered[0].trained_step == 8  # what the actor counts its staleness from: 0 steps stale


def test_a_restored_critic_still_never_labels_the_weights_older() -> None:
    """The label's floor (Learner.fitted) is in the checkpoint: a critic restarted mid-run that
    then fits a transition recovered late labels it with the newest step it had fitted before,
    not the late one (and a checkpoint written before the floor was kept restores it as -1)."""
    run = robot_run(leave=0)
    late = 5
    learner = CriticLearner(settings())
    for s in run:
        if s.step != late:
            learner.take(message("r1", s))
    state = learner.state()
    assert state["learners"]["r1"]["fitted"] == 8
    restored = CriticLearner(settings())
    restored.restore(state)
    recovered = restored.take(message("r1", run[late]))
    assert len(recovered) == 1 and recovered[0].trained_step == 8
    del state["learners"]["r1"]["fitted"]  # an older checkpoint: the late step labels its fit
    older = CriticLearner(settings())
    older.restore(state)
    assert [w.trained_step for w in older.take(message("r1", run[late]))] == [late]


@pytest.mark.parametrize("arrival", [True, False])
def test_the_lockstep_port_reports_the_residuals_of_the_fit_on_each_step(arrival: bool) -> None:
    """As the in-process critic (LocalCritic.last_residuals), the lockstep port over Zenoh says the
    TD residuals of the fit on the step it just recorded: those its weights message carried, once
    the weights trained on that step are held; nan on a step with no fit (a robot at rest)."""
    own = Settings.load(critic={"checkpoint": ""}, actor={"arrival": arrival}, transport={"robot": "r1"})

    class ResidualInbox(FakeInbox):
        def wait_trained(self, step: int, timeout: float) -> bool:
            self.waited.append(step)
            self.held = HeldWeights(
                self.held.q, self.held.v, self.held.version + 1, step, 0.0, (step + 0.5, step + 0.25)
            )
            return True

    inbox = ResidualInbox()
    port = ZenohCriticPort(own, FakeBus(), inbox, episode=1, sync=True)  # type: ignore[arg-type]
    port.reset()
    residuals = []
    for s in robot_run():
        port.record(s)
        residuals.append(port.last_residuals)
    fitted = set(inbox.waited)
    assert fitted and len(fitted) < len(residuals) if arrival else fitted
    for s, (q, v) in zip(robot_run(), residuals, strict=True):
        if s.step in fitted:
            assert (q, v) == (s.step + 0.5, s.step + 0.25)
        else:
            assert np.isnan(q) and np.isnan(v)
