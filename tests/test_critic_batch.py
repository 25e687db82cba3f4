"""A fleet's critic fits every robot due in a batch in one stacked solve (docs/fleets.md).

The contract: each robot's weights are those of its fit alone, bit for bit, whatever the batch;
the minimum is the bounded TD least squares (the augmented problem that scipy's BVLS solves);
a wrong guess of the active set costs time, never the answer; the service collects a batch for
at most its window and checkpoints the active sets, so a restored critic fits on exactly."""

from __future__ import annotations

import copy
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import scipy.optimize

import common.math.critic
from common.config.settings import Settings
from common.contracts.columns import batch_payloads
from common.contracts.keys import TRANSITION, TRANSITION_BATCH
from common.contracts.messages import Transition
from common.math.critic import (
    DoubleCritic,
    Replay,
    Sample,
    _solve_each,
    bounded_lstsq,
    fit_gram,
    update_many,
)
from common.net.transport import Bus, Inbox
from common.system.checkpoint import atomic_write_json
from services.critic.service import CriticLearner, collect, drain, load_checkpoint
from tests.harness import FakeSample, buses_on_a_fake_session, random_transitions

BOUNDS = (0.0, 100.0)


def robot_samples(rng: np.random.Generator, steps: int, lost: set[int]) -> list[Sample]:
    """A robot driving toward the origin (states shrink, so weights hit the bounds), with lost steps."""
    state = rng.uniform(-1.5, 1.5, 3)
    samples = []
    for step in range(steps):
        action = rng.uniform(-0.2, 0.2, 2)
        if step not in lost:
            samples.append(Sample(step, state.copy(), action, 0.1 * float(state @ state + action @ action)))
        state = 0.95 * state + rng.normal(scale=0.05, size=3)
    return samples


def fleet(seed: int = 5, robots: int = 6, steps: int = 70) -> list[list[Sample]]:
    rng = np.random.default_rng(seed)
    # robot 1 starts late (few pairs), robot 2 loses steps (gaps), robot 3 loses nearly all
    lost = [set(), set(range(40)), {5, 6, 17, 30, 31, 32}, set(range(0, steps, 2))] + [set()] * robots
    return [robot_samples(rng, steps, lost[i]) for i in range(robots)]


def critic(rng_seed: int, bounds: tuple[float, float] | None = BOUNDS) -> DoubleCritic:
    rng = np.random.default_rng(rng_seed)
    return DoubleCritic(rng.uniform(0.5, 3.0, 15), rng.uniform(0.5, 3.0, 6), 0.9, ridge=1.0, bounds=bounds)


@pytest.mark.parametrize("bounds", [BOUNDS, None])
def test_a_batch_of_robots_fits_each_robot_as_alone_bit_for_bit(bounds: tuple[float, float] | None) -> None:
    streams = fleet()
    batched = [critic(i, bounds) for i in range(len(streams))]
    alone = copy.deepcopy(batched)
    replays = [Replay(30) for _ in streams]
    on_bound_seen = 0
    for step in range(70):
        due = []
        for i, stream in enumerate(streams):
            for sample in (s for s in stream if s.step == step):
                replays[i].add(sample)
                due.append(i)
        if not due:
            continue
        got = update_many([batched[i] for i in due], [replays[i] for i in due])
        for i, fit in zip(due, got, strict=True):
            expected = alone[i].update(replays[i])
            assert np.array_equal(fit.q.weights, expected.q.weights) and np.array_equal(
                fit.v.weights, expected.v.weights
            )
            assert fit.q.residual == expected.q.residual and fit.v.residual == expected.v.residual
            assert fit.q.pairs == expected.q.pairs == fit.v.pairs
            if bounds is None:
                assert fit.q.on_bound is None and fit.v.on_bound is None
            else:
                assert np.array_equal(fit.q.on_bound, expected.q.on_bound)
                on_bound_seen += int(np.any(fit.q.on_bound != 0) or np.any(fit.v.on_bound != 0))
            assert np.array_equal(batched[i].q_weights, alone[i].q_weights)
    if bounds is not None:
        assert on_bound_seen > 50, "the bounds should be active in this fleet"


def augmented_reference(now, following, costs, previous, ridge, bounds, discount=0.9):
    """The TD fit as the augmented least squares that BVLS solves (the critic's earlier way)."""
    targets = costs + discount * following @ previous
    size = previous.size
    a = np.vstack([now, np.sqrt(ridge) * np.eye(size)])
    low, high = bounds
    base = np.clip(previous, low, high)
    b = np.concatenate([targets - now @ previous, np.zeros(size)]) - a @ (base - previous)
    solution = scipy.optimize.lsq_linear(a, b, bounds=(low - base, high - base), method="bvls", tol=1e-12)
    return np.clip(base + solution.x, low, high)


@pytest.mark.parametrize("seed", range(8))
def test_the_stacked_fit_is_the_bounded_td_least_squares(seed: int) -> None:
    rng = np.random.default_rng(seed)
    count, rows, size = 4, 29, 15
    now, following = rng.normal(size=(count, rows, size)), rng.normal(size=(count, rows, size))
    costs = rng.uniform(0, 3, (count, rows))
    previous = rng.uniform(-1, 3, (count, size))  # some outside the bounds: clipped first
    bounds = (0.0, 2.0)
    fits = fit_gram(now, following, costs, previous, [slice(0, size)], 0.9, 1.0, bounds, [[None]] * count, [rows] * 4)
    for i in range(count):
        expected = augmented_reference(now[i], following[i], costs[i], previous[i], 1.0, bounds)
        np.testing.assert_allclose(fits[i][0].weights, expected, rtol=0, atol=1e-9)
        assert np.any(fits[i][0].on_bound != 0), "the bounds should be active"
        targets = costs[i] + 0.9 * following[i] @ previous[i]
        errors = now[i] @ fits[i][0].weights - targets
        assert fits[i][0].residual == pytest.approx(0.5 * errors @ errors, rel=1e-9)


@pytest.mark.parametrize("seed", range(6))
def test_a_wrong_guess_is_mended_by_active_set_steps_without_bvls(seed: int, monkeypatch) -> None:
    rng = np.random.default_rng(seed)
    a = np.vstack([rng.normal(size=(29, 15)), np.eye(15)])
    b = np.concatenate([rng.normal(scale=3.0, size=29), np.zeros(15)])
    low, high = np.full(15, -0.5), np.full(15, 0.5)
    reference = scipy.optimize.lsq_linear(a, b, bounds=(low, high), method="bvls")
    right = np.asarray(reference.active_mask, dtype=float)
    wrong = right.copy()
    flip = int(np.flatnonzero(right != 0)[0])
    wrong[flip] = 0.0  # one bound weight guessed free
    calls: list[object] = []
    original = common.math.critic.lsq_linear
    monkeypatch.setattr(
        common.math.critic, "lsq_linear", lambda *args, **kw: calls.append(args) or original(*args, **kw)
    )
    gram, linear = a.T @ a, a.T @ b
    fits = fit_gram_one(gram, linear, low, high, wrong)
    assert calls == []  # mended by the active-set steps
    np.testing.assert_allclose(fits[0], reference.x, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(fits[1], right)
    # negative control: with no active-set step the same wrong guess needs BVLS
    monkeypatch.setattr(common.math.critic, "ACTIVE_SET_STEPS", 0)
    fits = fit_gram_one(gram, linear, low, high, wrong)
    assert len(calls) == 1
    np.testing.assert_allclose(fits[0], reference.x, rtol=0, atol=1e-12)


def fit_gram_one(gram, linear, low, high, guess):
    """fit_gram's active-set search and fallback on one QP given by its Gram matrix (no ridge
    added: a design whose Gram matrix is ``gram``, i.e. its Cholesky factor, and no data)."""
    upper = np.linalg.cholesky(gram).T
    rhs = np.linalg.solve(upper.T, linear)
    size = gram.shape[0]
    # |upper x - rhs|^2 as a TD fit: now = upper, targets = rhs (following = 0), previous = 0,
    # the ridge as small as fit_gram allows (its effect below the tolerance of the comparison)
    fits = fit_gram(
        upper[None],
        np.zeros((1, size, size)),
        rhs[None],
        np.zeros((1, size)),
        [slice(0, size)],
        0.9,
        1e-300,
        (low[0], high[0]),
        [[guess]],
        [size],
    )
    return fits[0][0].weights, fits[0][0].on_bound


def test_bounded_lstsq_uses_the_same_guess_check() -> None:
    rng = np.random.default_rng(1)
    a = np.vstack([rng.normal(size=(29, 15)), np.eye(15)])
    b = np.concatenate([rng.normal(scale=3.0, size=29), np.zeros(15)])
    low, high = np.full(15, -0.5), np.full(15, 0.5)
    x, on_bound = bounded_lstsq(a, b, low, high)
    warm, warm_bound = bounded_lstsq(a, b, low, high, on_bound)
    np.testing.assert_allclose(warm, x, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(warm_bound, on_bound)


def test_a_singular_problem_in_a_stack_leaves_the_others_be() -> None:
    rng = np.random.default_rng(2)
    good = rng.normal(size=(3, 4, 4)) + 4 * np.eye(4)
    stack = np.concatenate([good[:1], np.zeros((1, 4, 4)), good[1:]])
    rhs = rng.normal(size=(4, 4))
    out = _solve_each(stack, rhs)
    assert np.all(np.isnan(out[1]))
    for k, i in enumerate((0, 2, 3)):
        np.testing.assert_array_equal(out[i], np.linalg.solve(good[k], rhs[i]))


# -- the service: batches, deferred fits, checkpoints -------------------------------------------
def settings(**critic: object) -> Settings:
    return Settings.load(critic={"checkpoint": "", **critic})


def test_deferred_fits_publish_what_fits_one_by_one_publish() -> None:
    stream = random_transitions(40, ("a", "b", "c", "d"), seed=4)
    one_by_one, batched = CriticLearner(settings()), CriticLearner(settings())
    expected = [w for t in stream for w in one_by_one.take(t)]
    got = []
    for start in range(0, len(stream), 7):  # batches cutting across the robots' steps
        for t in stream[start : start + 7]:
            assert batched.take(t, defer=True) == []
        got += batched.flush()
    assert [(w.robot, w.trained_step) for w in got] == [(w.robot, w.trained_step) for w in expected]
    assert [w.q_weights for w in got] == [w.q_weights for w in expected]
    assert [w.v_weights for w in got] == [w.v_weights for w in expected]
    versions = [w.version for w in got]
    assert versions == sorted(set(versions))


def test_a_robot_due_twice_in_a_batch_gets_both_fits_in_order() -> None:
    """Without coalescing every due fit is made, each on the replay as it was at its step."""
    stream = random_transitions(12, ("a", "b"), seed=6)
    one_by_one, batched = CriticLearner(settings()), CriticLearner(settings())
    expected = [w for t in stream for w in one_by_one.take(t)]
    for t in stream:
        batched.take(t, defer=True)
    got = batched.flush()  # one batch holding every step of both robots
    assert [(w.robot, w.trained_step, w.q_weights) for w in got] == [
        (w.robot, w.trained_step, w.q_weights) for w in expected
    ]


def transition(robot: str, step: int = 0) -> Transition:
    return Transition(robot=robot, episode=1, step=step, state=(1.0, 0.0, 0.0), action=(0.0, 0.0), cost=0.1)


def critic_intake(monkeypatch: pytest.MonkeyPatch, limit: int = 1000) -> tuple[Inbox, Callable[..., None]]:
    """A critic's intake (common.net.transport.Inbox, every robot's transitions, as
    services/critic/service.py subscribes them) on a Bus whose Zenoh session is fake, and
    ``put(*messages)``, which hands a message to its robot's key's subscription as Zenoh would
    (one batch of them on the batch key, as every actor host sends them, one robot's too)."""
    subscribed = buses_on_a_fake_session(monkeypatch)
    bus = Bus.open(Settings.load().transport, "critic")
    intake = bus.inbox(limit)
    intake.subscribe(TRANSITION, TRANSITION.pattern.format(robot="*"), recover=True)
    # a robot's own key is for outsiders (Batch.on_demand): the critic reads the batch key alone
    assert list(subscribed) == [TRANSITION_BATCH.pattern]

    def put(*messages: Transition) -> None:
        (callback, _), recover = subscribed[TRANSITION_BATCH.pattern]
        assert recover  # the history the actors' publishers cache
        callback(FakeSample(TRANSITION_BATCH.pattern, one_batch(list(messages))))

    return intake, put


def one_batch(messages: list[Transition]) -> bytes:
    (payload,) = batch_payloads(messages)
    return payload


def test_a_batch_takes_what_waits_and_no_more_without_a_window(monkeypatch: pytest.MonkeyPatch) -> None:
    intake, put = critic_intake(monkeypatch)
    put(transition("a"))
    put(transition("b"), transition("c"))  # a batch of two after a batch of one: one path
    late = threading.Timer(0.05, put, args=(transition("d"),))
    late.start()
    try:
        assert intake.wait(0.0)
        assert collect(intake, deque(), 0.0, robots=4).robots == ["a", "b", "c"]
    finally:
        late.join()
    assert intake.waiting == 1  # d waits for the next batch
    assert collect(intake, deque(), 0.0, robots=4).robots == ["d"]


@pytest.mark.timing
def test_a_batch_window_collects_until_every_robot_is_in_or_the_window_ends(monkeypatch: pytest.MonkeyPatch) -> None:
    intake, put = critic_intake(monkeypatch)
    recovered: deque[Transition] = deque([transition("e")])  # an answer of the actors' caches: taken too
    feeder = threading.Thread(target=lambda: [time.sleep(0.01) or put(transition(r)) for r in "bcd"], daemon=True)
    put(transition("a"))
    feeder.start()
    started = time.monotonic()
    batch = collect(intake, recovered, 1.0, robots=5)
    assert batch.robots == ["a", "e", "b", "c", "d"]
    assert time.monotonic() - started < 0.5  # every robot heard from is in: no wait for the window
    feeder.join()
    put(transition("a", 1))
    started = time.monotonic()
    batch = collect(intake, recovered, 0.05, robots=4)  # nobody else comes
    assert batch.robots == ["a"] and 0.04 <= time.monotonic() - started < 0.5


def test_a_recovered_transition_a_batch_cannot_hold_is_refused_as_the_intake_refuses_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    intake, put = critic_intake(monkeypatch)
    put(transition("a"))
    recovered = deque([transition("b", 2**63), transition("c", 3)])  # a step beyond 64 bits
    batch = drain(intake, recovered)
    assert batch.robots == ["a", "c"] and batch.field("step").tolist() == [0, 3] and not recovered


def test_a_critic_of_many_robots_takes_each_batch_once_and_only_its_robots_rows(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``srl critic --robots``: its intake holds ONE subscription, of the batch key (one per robot
    decoded each batch once per robot: 64 % of a core at rest with 100 robots), and takes a
    batch's rows of its robots once, those of other robots never."""
    subscribed = buses_on_a_fake_session(monkeypatch)
    declared: list[str] = []
    declare = Bus._declare_subscriber
    monkeypatch.setattr(
        Bus, "_declare_subscriber", lambda self, key, *args: declared.append(key) or declare(self, key, *args)
    )
    intake = Bus.open(Settings.load().transport, "critic").inbox(1000)
    intake.subscribe(TRANSITION, [TRANSITION.key(robot) for robot in "abc"], recover=True)
    assert declared == [TRANSITION_BATCH.pattern]  # once; no robot's own key (Batch.on_demand)
    with pytest.raises(ValueError, match="give every key at once"):
        intake.subscribe(TRANSITION, TRANSITION.key("d"))
    (callback, _), _ = subscribed[TRANSITION_BATCH.pattern]
    callback(FakeSample(TRANSITION_BATCH.pattern, one_batch([transition(r) for r in "axbyc"])))
    assert intake.waiting == 5  # the sample's rows, counted once
    assert collect(intake, deque(), 0.0, robots=3).robots == ["a", "b", "c"]


def test_the_intake_wakes_its_consumer_for_what_comes_and_for_what_it_is_told(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    intake, put = critic_intake(monkeypatch)
    assert not intake.wait(0.0)  # nothing came
    put(transition("a"))
    assert intake.wait(0.0)
    assert collect(intake, deque(), 0.0, robots=1).robots == ["a"]
    assert not intake.wait(0.0)  # taken: nothing new
    intake.wake()  # the critic's own (HistoryRecovery's answers)
    assert intake.wait(0.0)
    assert len(collect(intake, deque(), 0.0, robots=1)) == 0 and not intake.wait(0.0)


def test_a_batch_trains_the_critic_as_its_messages_do_bit_for_bit(monkeypatch: pytest.MonkeyPatch) -> None:
    """The critic takes a batch as its columns (CriticLearner.take_batch, no message built): its
    learners, replays, weights and counts are those the same transitions as messages make, one
    by one, a robot at rest included."""
    stream = random_transitions(40, ("a", "b", "c"), seed=5)
    rest = Transition(robot="d", episode=1, step=0, state=(0.004, -0.003, 0.01), action=(0.0, 0.0), cost=1e-7)
    stream += [rest.model_copy(update={"step": k}) for k in range(40)]
    intake, put = critic_intake(monkeypatch, limit=len(stream))
    for first in range(0, len(stream), 7):
        put(*stream[first : first + 7])
    batch = collect(intake, deque(), 0.0, robots=4)
    assert len(batch) == len(stream)
    by_batch, by_messages = CriticLearner(settings()), CriticLearner(settings())
    by_messages.version = by_batch.version  # versions start from the clock
    weights_of_batch = by_batch.take_batch(batch)
    weights_of_messages = [w for message in stream for w in by_messages.take(message)]
    assert weights_of_batch == weights_of_messages and weights_of_batch
    assert by_batch.state() == by_messages.state()
    assert by_batch.fits_at_rest == by_messages.fits_at_rest > 30  # d rested


def test_the_checkpoint_keeps_the_active_sets_and_refuses_bad_ones(tmp_path: Path) -> None:
    stream = random_transitions(30, ("a", "b"), seed=8)
    first = CriticLearner(settings())
    for t in stream:
        first.take(t)
    assert any(x.critic.q_on_bound is not None for x in first.learners.values())
    path = tmp_path / "critic.json"
    atomic_write_json(path, first.state())
    second = CriticLearner(settings())
    assert load_checkpoint(second, path)
    for robot, learner in first.learners.items():
        assert np.array_equal(second.learners[robot].critic.q_on_bound, learner.critic.q_on_bound)
        assert np.array_equal(second.learners[robot].critic.v_on_bound, learner.critic.v_on_bound)
    # an older checkpoint without them: none, found again at the next fit
    payload = first.state()
    for entry in payload["learners"].values():
        del entry["q_on_bound"], entry["v_on_bound"]
    atomic_write_json(path, payload)
    older = CriticLearner(settings())
    assert load_checkpoint(older, path) and older.learners["a"].critic.q_on_bound is None
    # a bad one: the checkpoint is set aside, nothing restored
    payload = first.state()
    payload["learners"]["a"]["q_on_bound"] = [2.0] * 15
    atomic_write_json(path, payload)
    bad = CriticLearner(settings())
    assert not load_checkpoint(bad, path) and bad.learners == {}
    assert not path.exists()
