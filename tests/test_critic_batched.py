"""A fleet's critic fits the robots due in a batch from the replays' kept arrays (docs/concepts.md,
"The critic update").

The contract, on replays recorded from real closed-loop runs (rlqv driving the ideal plant):
the design read from a replay's kept ring buffers is the design built from its samples, bit for
bit (full or not, with gaps, late arrivals, a pool's streams); the batched fit of K robots gives
every robot the weights of today's per-robot fit -- its design rebuilt from its samples, one robot
per call -- to 1e-9, including fits whose active set changes (the fallback to BVLS) and replays
not yet full, and both are the bounded TD least squares; the critic service publishes the same
weights, bit for bit, whether it fits a batch of robots at once or each robot alone."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import scipy.optimize

import common.math.critic
import services.critic.service
from common.config.assembly import run_fleet_episode
from common.config.settings import Settings
from common.contracts.messages import CriticWeights, Transition
from common.math.critic import (
    DoubleCritic,
    PooledReplay,
    Replay,
    Sample,
    _phi_qv_rows,
    kept_designs,
    padded_designs,
    update_many,
)
from services.critic.service import CriticLearner

STARTS = [np.array([2.0, 2.0, 0.0]), np.array([-1.0, -2.0, 1.0]), np.array([2.0, -1.0, -2.0])]
STEPS = 40  # 4 s at delta = 0.1 s: the replay of M = 30 fills and wraps
BOUNDS = (0.0, 100.0)


@pytest.fixture(scope="module")
def recorded() -> list[list[Sample]]:
    """Three robots' closed-loop transitions (rlqv, N = 6, each with its own per-robot critic)."""
    settings = Settings.load(actor={"agent": "rlqv", "horizon": 6, "jit": False}, episode={"duration": STEPS / 10})
    episodes = run_fleet_episode(settings, STARTS, "per-robot")
    return [
        [Sample(k, episode.states[k], episode.actions[k], episode.costs[k]) for k in range(episode.steps)]
        for episode in episodes
    ]


def fleet(recorded: list[list[Sample]], robots: int) -> list[list[Sample]]:
    """``robots`` streams from the recordings: one in four joins late (its replay not yet full for
    most of the run), one loses steps (gaps), one every other step (no pair at all)."""
    lost = [set(), set(range(25)), {5, 6, 17, 30, 31, 32}, set(range(0, STEPS, 2))]
    return [[s for s in recorded[i % len(recorded)] if s.step not in lost[i % len(lost)]] for i in range(robots)]


def critics(robots: int, seed: int = 4) -> list[DoubleCritic]:
    """Each robot's critic from its own initial weights around the default ones: the fits differ
    and their active sets change from fit to fit."""
    settings, rng = Settings.load(), np.random.default_rng(seed)
    q0, v0 = settings.initial_q_weights(), settings.initial_v_weights()
    return [
        DoubleCritic(q0 * rng.uniform(0.3, 3.0, q0.size), v0 * rng.uniform(0.3, 3.0, v0.size), 0.9, 1.0, BOUNDS)
        for _ in range(robots)
    ]


def bounded_td_reference(replay: Replay, previous_q: np.ndarray, previous_v: np.ndarray) -> np.ndarray:
    """Both critics' fit as the augmented least squares scipy's BVLS solves (eq. (14) with the ridge
    and the box), from the samples: an answer computed without the critic's own code."""
    now, following, costs = replay.design(_phi_qv_rows)
    out = []
    for columns, previous in ((slice(0, 15), previous_q), (slice(15, 21), previous_v)):
        a, b = now[:, columns], following[:, columns]
        size = previous.size
        base = np.clip(previous, *BOUNDS)
        targets = costs + 0.9 * b @ previous
        augmented = np.vstack([a, np.eye(size)])
        rhs = np.concatenate([targets - a @ previous, np.zeros(size)]) - augmented @ (base - previous)
        bounds = (BOUNDS[0] - base, BOUNDS[1] - base)
        step = scipy.optimize.lsq_linear(augmented, rhs, bounds=bounds, method="bvls", tol=1e-12).x
        out.append(np.clip(base + step, *BOUNDS))
    return np.concatenate(out)


@pytest.mark.parametrize("robots", [1, 3, 50])
@pytest.mark.parametrize("active_set_steps", [common.math.critic.ACTIVE_SET_STEPS, 0])
def test_the_batched_fit_is_todays_per_robot_fit(recorded, robots, active_set_steps, monkeypatch) -> None:
    """``active_set_steps = 0``: every rejected guess goes to the per-robot BVLS (the fallback)."""
    monkeypatch.setattr(common.math.critic, "ACTIVE_SET_STEPS", active_set_steps)
    bvls_calls: list[int] = []
    original = common.math.critic.lsq_linear
    monkeypatch.setattr(
        common.math.critic, "lsq_linear", lambda *args, **kw: bvls_calls.append(1) or original(*args, **kw)
    )
    streams = fleet(recorded, robots)
    batched = critics(robots)
    alone = copy.deepcopy(batched)
    kept, rebuilt = [Replay(30) for _ in streams], [Replay(30) for _ in streams]
    changed = not_full = checked = batched_bvls = 0
    for step in range(STEPS):
        due = [i for i, stream in enumerate(streams) if any(s.step == step for s in stream)]
        for i in due:
            sample = next(s for s in streams[i] if s.step == step)
            kept[i].add(sample)
            rebuilt[i].add(sample)
        previous = [(batched[i].q_weights.copy(), batched[i].v_weights.copy(), batched[i].q_on_bound) for i in due]
        before = len(bvls_calls)
        got = update_many([batched[i] for i in due], [kept[i] for i in due])
        batched_bvls += len(bvls_calls) - before
        for i, fit, (q_before, v_before, bound_before) in zip(due, got, previous, strict=True):
            expected = update_many([alone[i]], [rebuilt[i]], rebuild=True)[0]  # today's: one robot, from samples
            for name in ("q", "v"):
                mine, theirs = getattr(fit, name), getattr(expected, name)
                np.testing.assert_allclose(mine.weights, theirs.weights, rtol=0, atol=1e-9)
                np.testing.assert_array_equal(mine.on_bound, theirs.on_bound)
                assert mine.pairs == theirs.pairs and mine.residual == pytest.approx(theirs.residual, rel=1e-9)
            changed += bound_before is not None and not np.array_equal(bound_before, fit.q.on_bound)
            not_full += fit.q.pairs and len(kept[i]) < kept[i].capacity
            if fit.q.pairs and (step % 10 == 9 or robots == 1):  # and both are the bounded TD least squares
                weights = np.concatenate([fit.q.weights, fit.v.weights])
                reference = bounded_td_reference(kept[i], q_before, v_before)
                np.testing.assert_allclose(weights, reference, rtol=0, atol=1e-9)
                checked += 1
    assert changed > 0, "the active sets should change during the run"
    assert not_full > 0 and checked > 0
    if active_set_steps == 0:
        assert batched_bvls > 0, "the fallback to BVLS should be taken"


def test_the_kept_design_is_the_design_built_from_the_samples(recorded) -> None:
    """Bit for bit after every sample, for replays filling up, wrapping, with gaps, late arrivals and
    a clear, and for a pool's streams with a restart; stacked as a batch of any size."""
    streams = fleet(recorded, 8)
    replays = [Replay(capacity) for capacity in (30, 30, 30, 30, 5, 5, 2, 2)]
    late = {0: [12, 13], 4: [20]}  # robot -> steps held back and delivered three steps late
    pool = PooledReplay(30)
    for step in range(STEPS):
        for i, stream in enumerate(streams):
            held = late.get(i, [])
            for sample in stream:
                if (sample.step == step and sample.step not in held) or (
                    sample.step in held and sample.step + 3 == step
                ):
                    replays[i].add(sample)
                    pool.add(f"r{i}", sample)
        if step == 30:
            replays[1].clear()
            pool.restart("r1")
        for group in (replays[:4], replays[4:6], replays[6:], replays[:1]):
            rows = group[0].max_pairs
            got = kept_designs([r.replays() for r in group], rows)
            assert got is not None
            expected = padded_designs([r.sample_streams() for r in group], rows, _phi_qv_rows)
            assert got[3] == expected[3]
            if any(expected[3]):
                for mine, theirs in zip(got[:3], expected[:3], strict=True):
                    assert mine.shape == theirs.shape and np.array_equal(mine, theirs)
        pooled = kept_designs([pool.replays()], pool.max_pairs)
        expected = padded_designs([pool.sample_streams()], pool.max_pairs, _phi_qv_rows)
        assert pooled is not None and pooled[3] == expected[3]
        assert not any(expected[3]) or all(
            np.array_equal(mine, theirs) for mine, theirs in zip(pooled[:3], expected[:3], strict=True)
        )
    assert [s.step for s in replays[0].samples] == list(range(STEPS - 30, STEPS))  # the late ones in order


@pytest.mark.parametrize("bounds", [BOUNDS, None])
def test_without_a_ridge_the_kept_design_fits_as_the_samples_design(recorded, bounds) -> None:
    """The minimum-norm fits (no ridge: td_fit per critic) from the kept rows, bit for bit."""
    streams = fleet(recorded, 4)
    kept = [DoubleCritic(c.q_weights, c.v_weights, 0.9, 0.0, bounds) for c in critics(4)]
    rebuilt = copy.deepcopy(kept)
    replays = [Replay(30) for _ in streams]
    for step in range(STEPS):
        for replay, stream in zip(replays, streams, strict=True):
            for sample in (s for s in stream if s.step == step):
                replay.add(sample)
        for mine, theirs in zip(update_many(kept, replays), update_many(rebuilt, replays, rebuild=True), strict=True):
            assert np.array_equal(mine.q.weights, theirs.q.weights) and np.array_equal(mine.v.weights, theirs.v.weights)
            assert mine.q.pairs == theirs.q.pairs


def test_a_replay_of_other_shapes_keeps_no_rows_and_its_design_comes_from_the_samples() -> None:
    replay = Replay(5)
    for step in range(3):
        replay.add(Sample(step, np.array([float(step), 1.0]), np.array([0.0]), 1.0))
    assert not replay.kept and kept_designs([replay.replays()], None) is None
    now, _, _ = replay.design(lambda states, _: states[:, :1])
    np.testing.assert_array_equal(now.ravel(), [0.0, 1.0])
    replay.clear()
    assert replay.kept


def transitions(recorded: list[list[Sample]], robots: int) -> list[Transition]:
    """The fleet's transitions as the actors send them: every robot's step k, then step k + 1."""
    streams = fleet(recorded, robots)
    by_step = sorted((s.step, i, s) for i, stream in enumerate(streams) for s in stream)
    return [
        Transition(
            robot=f"robot{i}",
            episode=1,
            step=s.step,
            state=tuple(float(x) for x in s.state),
            action=tuple(float(x) for x in s.action),
            cost=float(s.cost),
        )
        for _, i, s in by_step
    ]


def published(message: CriticWeights) -> tuple:
    return (
        message.robot,
        message.trained_step,
        message.q_weights,
        message.v_weights,
        message.q_residual,
        message.v_residual,
        message.pairs,
    )


def test_the_service_publishes_the_same_weights_batched_as_one_robot_at_a_time(recorded, monkeypatch) -> None:
    """The critic service fed the same transition stream: today's way (each transition's fit made at
    once, the design rebuilt from the samples) and batched as its run loop does (every robot due in
    a batch of transitions fitted in one stacked solve, at the batch's end)."""
    stream = transitions(recorded, 12)
    settings = Settings.load(critic={"checkpoint": ""})
    with monkeypatch.context() as patch:
        patch.setattr(
            services.critic.service, "update_many", lambda critics, replays: update_many(critics, replays, rebuild=True)
        )
        alone = CriticLearner(settings)
        expected = [w for t in stream for w in alone.take(t)]
    batched = CriticLearner(settings)
    got = []
    for start in range(0, len(stream), 12):  # a batch holds one fleet step, as collect() takes it
        for t in stream[start : start + 12]:
            assert batched.take(t, defer=True) == []
        got += batched.flush()
    assert len(got) == len(expected) > 12 * (STEPS - 25)
    assert [published(w) for w in got] == [published(w) for w in expected]
    versions = [w.version for w in got]
    assert versions == sorted(set(versions))
