"""The pooled fleet critic (docs/fleets.md): one learner on every robot's transitions, TD pairs only
within one robot's consecutive steps; a pool of one is the per-robot learner bit for bit."""

from __future__ import annotations

import itertools
import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest

from common.config.assembly import build_actor, fleet_learners, run_episode, run_fleet_episode
from common.config.settings import Settings
from common.contracts.messages import Transition
from common.math.critic import DoubleCritic, PooledLearner, PooledReplay, Replay, Sample
from common.math.features import phi_q_rows
from common.math.loop import Episode
from common.system.checkpoint import atomic_write_json
from services.critic.service import CriticLearner, load_checkpoint
from tests.harness import random_transitions

ROBOTS = ("a", "b", "c")


def tagged(robot: int, step: int) -> Sample:
    """A sample whose state says whose and which step it is (robot id, step, 0)."""
    return Sample(step, np.array([float(robot), float(step), 0.0]), np.zeros(2), cost=float(100 * robot + step))


def identity(states: np.ndarray, _: np.ndarray) -> np.ndarray:
    return states


def cross_robot_or_gap_pairs(now: np.ndarray, nxt: np.ndarray) -> int:
    """Rows of a design (states as features) that join two robots or skip a step."""
    return int(np.sum((now[:, 0] != nxt[:, 0]) | (nxt[:, 1] != now[:, 1] + 1)))


def interleaved_fleet() -> list[tuple[int, Sample]]:
    """Three robots stepping together, robot 1 started 3 steps later, robot 2 lost step 4."""
    stream = []
    for k in range(8):
        for robot in range(3):
            step = k - 3 if robot == 1 else k
            if step < 0 or (robot == 2 and step == 4):
                continue
            stream.append((robot, tagged(robot, step)))
    return stream


def test_pooled_pairs_never_cross_robots_or_gaps() -> None:
    pool = PooledReplay(capacity=100)
    for robot, sample in interleaved_fleet():
        pool.add(ROBOTS[robot], sample)
    now, nxt, costs = pool.design(identity)
    assert cross_robot_or_gap_pairs(now, nxt) == 0
    # the oracle: a plain loop over each robot's own steps
    expected = []
    for robot, steps in ((0, range(8)), (1, range(5)), (2, [0, 1, 2, 3, 5, 6, 7])):
        steps = list(steps)
        expected += [(robot, s) for s, t in itertools.pairwise(steps) if t == s + 1]
    got = [(int(r), int(s)) for r, s, _ in now]
    assert sorted(got) == expected  # stream after stream, in the order the robots joined
    assert costs.tolist() == [100.0 * r + s for r, s in got]


def test_negative_control_one_stream_for_the_fleet_pairs_across_robots() -> None:
    """The check above can fail: the same stream kept as ONE robot's replay (keyed by arrival)
    joins robots, and the checker sees it."""
    replay = Replay(capacity=100)
    for index, (_, sample) in enumerate(interleaved_fleet()):
        replay.add(Sample(index, sample.state, sample.action, sample.cost))
    now, nxt, _ = replay.design(identity)
    assert cross_robot_or_gap_pairs(now, nxt) == len(now) > 0


def test_a_new_episode_restarts_only_that_robots_stream() -> None:
    pool = PooledReplay(capacity=10)
    for step in range(5):
        pool.add("a", tagged(0, step))
        pool.add("b", tagged(1, step))
    pool.restart("a")
    pool.add("a", tagged(0, 0))  # the new episode's step 0 is no duplicate
    now, nxt, _ = pool.design(identity)
    assert cross_robot_or_gap_pairs(now, nxt) == 0
    assert set(now[:, 0].tolist()) == {1.0} and len(now) == 4


def random_stream(rng: np.random.Generator, length: int, gap_every: int) -> list[Sample]:
    steps = [k for k in range(length) if k % gap_every != gap_every - 1]
    return [Sample(k, rng.normal(size=3), rng.normal(size=2) * 0.2, float(rng.uniform(0.0, 2.0))) for k in steps]


@pytest.mark.parametrize("bounds", [None, (0.0, 100.0)])
def test_a_pool_of_one_is_the_per_robot_learner_bit_for_bit(bounds: tuple[float, float] | None) -> None:
    rng = np.random.default_rng(3)
    q0, v0 = rng.uniform(0.5, 2.0, 15), rng.uniform(0.5, 2.0, 6)
    per_robot, replay = DoubleCritic(q0, v0, 0.9, 1.0, bounds), Replay(30)
    pool = PooledLearner(DoubleCritic(q0, v0, 0.9, 1.0, bounds), 30, update_every=2)
    fits = 0
    for sample in random_stream(rng, 120, gap_every=17):
        replay.add(sample)
        due = sample.step % 2 == 0
        assert pool.record("only", sample) == due
        if due:
            expected = per_robot.update(replay)
            got = pool.fit()
            fits += 1
            assert got.q.residual == expected.q.residual and got.v.residual == expected.v.residual
            assert np.array_equal(pool.critic.q_weights, per_robot.q_weights)
            assert np.array_equal(pool.critic.v_weights, per_robot.v_weights)
    assert fits > 40 and not np.array_equal(pool.critic.q_weights, q0)  # it learned


def test_pooled_fit_is_the_least_squares_fit_of_every_robots_pairs() -> None:
    """Oracle: the ridge's normal equations over the union of the robots' own pairs, built by hand."""
    rng = np.random.default_rng(5)
    q0, v0 = rng.uniform(0.5, 2.0, 15), rng.uniform(0.5, 2.0, 6)
    beta, ridge = 0.95, 0.5
    pool = PooledLearner(DoubleCritic(q0, v0, beta, ridge), 30, update_every=1, robots=3)
    streams = {robot: random_stream(rng, 40, gap_every=9) for robot in ROBOTS}
    for robot, samples in streams.items():
        for sample in samples:
            pool.replay.add(robot, sample)
    rows_now, rows_next, costs = [], [], []
    for samples in streams.values():
        kept = samples[-30:]
        for s, t in itertools.pairwise(kept):
            if t.step == s.step + 1:
                rows_now.append(phi_q_rows(s.state[None], s.action[None])[0])
                rows_next.append(phi_q_rows(t.state[None], t.action[None])[0])
                costs.append(s.cost)
    a, b, c = np.array(rows_now), np.array(rows_next), np.array(costs)
    rhs = c + beta * b @ q0 - a @ q0
    expected = q0 + np.linalg.solve(a.T @ a + ridge * np.eye(15), a.T @ rhs)
    update = pool.fit()
    assert update.q.pairs == len(c) > 3 * 20
    np.testing.assert_allclose(pool.critic.q_weights, expected, rtol=1e-9, atol=1e-9)


def test_the_pool_fits_once_per_fleet_step() -> None:
    fresh = PooledLearner(DoubleCritic(np.ones(15), np.ones(6), 0.9), 10, update_every=2, robots=3)
    fits = []
    for k in range(6):
        for i, robot in enumerate(ROBOTS):
            if fresh.record(robot, tagged(i, k)):
                fresh.fit()
                fits.append((k, robot))
    assert fits == [(0, "c"), (2, "c"), (4, "c")]  # after the last robot of every due step
    # unknown fleet size: the robots heard from so far
    growing = PooledLearner(DoubleCritic(np.ones(15), np.ones(6), 0.9), 10, update_every=1)
    assert growing.record("a", tagged(0, 0)) is True
    growing.fit()
    assert growing.record("b", tagged(1, 0)) is False and growing.record("a", tagged(0, 1)) is True


def test_pooled_memory_is_bounded_per_robot() -> None:
    pool = PooledLearner(DoubleCritic(np.ones(15), np.ones(6), 0.9), 12, update_every=50, robots=3)
    for k in range(2000):
        for i, robot in enumerate(ROBOTS):
            if pool.record(robot, tagged(i, k)):
                pool.fit()
    assert len(pool.replay) == 3 * 12
    assert all(len(replay) == 12 for replay in pool.replay.streams.values())
    now, _, _ = pool.replay.design(identity)
    assert len(now) == 3 * 11


@pytest.mark.parametrize("kwargs", [{"update_every": 0}, {"robots": 0}])
def test_pooled_learner_rejects_bad_arguments(kwargs: dict) -> None:
    args = {"update_every": 1, "robots": 2, **kwargs}
    with pytest.raises(ValueError):
        PooledLearner(DoubleCritic(np.ones(15), np.ones(6), 0.9), 10, **args)
    with pytest.raises(ValueError):
        PooledReplay(1)


# -- the fleet in lockstep (common.math.loop.run_algorithm1 of K robots) --------------------------
STARTS = [np.array([1.0, -0.5, 0.3]), np.array([-0.8, 0.6, 2.5])]


def short_settings(agent: str = "rlqv") -> Settings:
    return Settings.load(actor={"agent": agent, "horizon": 6, "jit": False}, episode={"duration": 2.0})


def assert_same_episode(got: Episode, expected: Episode) -> None:
    assert got.steps == expected.steps > 0
    for name in ("states", "actions", "costs", "q_weights", "v_weights"):
        assert np.array_equal(np.array(getattr(got, name)), np.array(getattr(expected, name))), name


def test_a_per_robot_fleet_is_one_run_per_robot_bit_for_bit() -> None:
    settings = short_settings()
    actor = build_actor(settings)
    fleet = run_fleet_episode(settings, STARTS, "per-robot", actor=actor)
    for start, got in zip(STARTS, fleet, strict=True):
        alone = run_episode(
            settings.model_copy(update={"episode": settings.episode.model_copy(update={"start": list(start)})}),
            actor=actor,
        )
        assert_same_episode(got, alone)


def test_a_pooled_fleet_of_one_is_the_per_robot_run_bit_for_bit() -> None:
    settings = short_settings()
    actor = build_actor(settings)
    (pooled,) = run_fleet_episode(settings, STARTS[:1], "pooled", actor=actor)
    (per_robot,) = run_fleet_episode(settings, STARTS[:1], "per-robot", actor=actor)
    assert_same_episode(pooled, per_robot)


def test_a_pooled_fleet_shares_one_critic_fitted_once_per_step() -> None:
    settings = short_settings()
    learners = fleet_learners(settings, 2, "pooled")
    assert learners[0] is learners[1]
    fleet = run_fleet_episode(settings, STARTS, "pooled")
    # every robot acts on the same weights at every step; they change (it learns)
    assert np.array_equal(np.array(fleet[0].q_weights), np.array(fleet[1].q_weights))
    assert not np.array_equal(fleet[0].q_weights[0], fleet[0].q_weights[-1])
    # one fit per step, after the fleet's last robot: robot 1's rows carry the residuals
    assert all(np.isnan(r[0]) for r in fleet[0].td_residuals)
    assert not any(np.isnan(r[0]) for r in fleet[1].td_residuals[1:])
    per_robot = run_fleet_episode(settings, STARTS, "per-robot")
    assert not np.array_equal(np.array(per_robot[0].q_weights), np.array(fleet[0].q_weights))
    with pytest.raises(ValueError, match="critic layout"):
        fleet_learners(settings, 2, "shared")  # type: ignore[arg-type]


# -- the critic service (services/critic/service.py) ------------------------------------------
def pooled_settings(**critic: object) -> Settings:
    return Settings.load(critic={"pooled": True, "checkpoint": "", **critic})


def fleet_stream(steps: int, robots: Sequence[str] = ROBOTS, episode: int = 7, seed: int = 3) -> list[Transition]:
    return random_transitions(steps, robots, episode, seed)


def pool_oracle(settings: Settings, stream: Sequence[Transition], robots: int) -> PooledLearner:
    c = settings.critic
    double = DoubleCritic(
        settings.initial_q_weights(), settings.initial_v_weights(), settings.discount, c.ridge, c.bounds
    )
    pool = PooledLearner(double, c.replay_size, c.update_every, robots=robots)
    for t in stream:
        if pool.record(t.robot, Sample(t.step, np.array(t.state), np.array(t.action), t.cost)):
            pool.fit()
    return pool


def test_the_pooled_service_fits_once_per_fleet_step_and_sends_every_robot_the_same_version() -> None:
    settings = pooled_settings()
    learner = CriticLearner(settings, fleet_size=3)
    stream = fleet_stream(40)
    sent = [learner.take(t) for t in stream]
    fits = [weights for weights in sent if weights]
    assert len(fits) == 40 and all(len(sent[3 * k + 2]) == 3 for k in range(40))  # after the fleet's last robot
    for k, weights in enumerate(fits):
        assert [w.robot for w in weights] == list(ROBOTS)
        assert len({w.version for w in weights}) == 1 and len({w.q_weights for w in weights}) == 1
        assert all(w.trained_step == k and w.episode == 7 for w in weights)
    assert [w[0].version for w in fits] == sorted({w[0].version for w in fits})
    oracle = pool_oracle(settings, stream, robots=3)
    assert np.array_equal(np.array(fits[-1][0].q_weights), oracle.critic.q_weights)
    assert np.array_equal(np.array(fits[-1][0].v_weights), oracle.critic.v_weights)
    assert learner.learners["a"].critic is learner.learners["c"].critic  # one learner
    assert len(learner.pool.replay) == 3 * settings.critic.replay_size  # type: ignore[union-attr]


def test_a_pooled_service_behind_fits_once_at_the_end_of_the_batch() -> None:
    learner = CriticLearner(pooled_settings(), fleet_size=3)
    batch = fleet_stream(4)  # four fleet steps waiting at once
    assert all(learner.take(t, fit=False) == [] for t in batch)
    weights = learner.flush()
    assert len(weights) == 3 and all(w.trained_step == 3 for w in weights)
    assert learner.fits_coalesced == 3 and learner.flush() == []
    assert learner.learners["a"].critic.update(learner.pool.replay).q.pairs == 3 * 3  # type: ignore[union-attr]


def test_a_pooled_checkpoint_restores_the_pool_and_it_continues_as_if_never_stopped(tmp_path: Path) -> None:
    settings = pooled_settings()
    stream = fleet_stream(30)
    oracle = CriticLearner(settings, fleet_size=3)
    for t in stream:
        oracle.take(t)
    first = CriticLearner(settings, fleet_size=3)
    for t in stream[:50]:  # mid-step: the pool's count of due transitions is part of the state
        first.take(t)
    path = tmp_path / "critic.json"
    atomic_write_json(path, first.state())
    second = CriticLearner(settings, fleet_size=3)
    assert load_checkpoint(second, path)
    sent = [second.confirm(t) for t in stream[30:33]]  # the robots come back: the same episode
    assert [w.robot for w in sent if w is not None] == ["a", "b", "c"] and second.restored
    for t in stream[30:]:  # the publishers' caches re-deliver 30..49: duplicates
        second.take(t)
    assert second.duplicates == 20
    np.testing.assert_array_equal(second.pool.critic.q_weights, oracle.pool.critic.q_weights)  # type: ignore[union-attr]
    np.testing.assert_array_equal(second.pool.critic.v_weights, oracle.pool.critic.v_weights)  # type: ignore[union-attr]


def test_a_pooled_checkpoint_of_an_earlier_run_starts_the_pool_fresh(tmp_path: Path) -> None:
    settings = pooled_settings()
    first = CriticLearner(settings, fleet_size=3)
    for t in fleet_stream(20):
        first.take(t)
    path = tmp_path / "critic.json"
    atomic_write_json(path, first.state())
    second = CriticLearner(settings, fleet_size=3)
    assert load_checkpoint(second, path)
    new_run = fleet_stream(1, episode=8, seed=4)
    for t in new_run:
        assert second.confirm(t) is None
        second.take(t)
    assert sorted(second.learners) == list(ROBOTS) and all(x.episode == 8 for x in second.learners.values())
    assert len(second.pool.replay) == 3  # type: ignore[union-attr]  # no old stream left
    fresh = CriticLearner(settings, fleet_size=3)
    for t in new_run:
        fresh.take(t)
    np.testing.assert_array_equal(second.pool.critic.q_weights, fresh.pool.critic.q_weights)  # type: ignore[union-attr]


@pytest.mark.parametrize("pooled_first", [True, False])
def test_a_checkpoint_of_the_other_kind_of_critic_is_set_aside(tmp_path: Path, pooled_first: bool) -> None:
    kinds = {True: pooled_settings(), False: Settings.load(critic={"checkpoint": ""})}
    first = CriticLearner(kinds[pooled_first])
    for t in fleet_stream(3):
        first.take(t)
    path = tmp_path / "critic.json"
    atomic_write_json(path, first.state())
    second = CriticLearner(kinds[not pooled_first])
    assert not load_checkpoint(second, path)
    assert not path.exists() and second.learners == {}


def test_the_critic_command_takes_pooled_and_srl_up_a_critic_layout() -> None:
    from tools.cli import build_parser

    args = build_parser().parse_args(["critic", "--robots", "3", "--pooled"])
    assert args.pooled is True
    args = build_parser().parse_args(["up", "--robots", "3", "--critic", "pooled"])
    assert args.critic == "pooled"


class AliveProbe:
    """A bus that records the critic's calls up to its declaring itself alive, then stops it."""

    class AliveError(Exception):
        pass

    def __init__(self) -> None:
        self.calls: list[str] = []

    def inbox(self, limit: int) -> AliveProbe:
        return self  # its subscriptions are the bus's

    def subscribe(self, *args: object, **kwargs: object) -> None:
        self.calls.append("subscribe")

    def declare_alive(self, robot: str) -> None:
        self.calls.append("alive")
        raise self.AliveError


def test_the_critic_loads_its_solver_before_it_is_alive(monkeypatch: pytest.MonkeyPatch) -> None:
    """The launcher starts the actors once the critic is alive: an import in its first fit would
    make every actor's weights seconds stale (a loaded machine, 0.15-0.4 s of CPU quiet)."""
    import threading

    from services.critic import service

    bus = AliveProbe()
    monkeypatch.setattr(service, "load_solver", lambda: bus.calls.append("solver"))
    settings = Settings.load(critic={"checkpoint": ""})
    with pytest.raises(AliveProbe.AliveError):
        service.run(settings, bus, threading.Event(), 1.0)  # type: ignore[arg-type]
    assert bus.calls.index("solver") < bus.calls.index("alive"), bus.calls


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.timing  # staleness <= 5 steps: a latency bound
def test_a_fleet_with_a_pooled_critic_gets_the_pools_weights_and_approaches() -> None:
    """The real services (srl up --robots 3 --critic pooled): one learner, every robot served."""
    from tools.launch.up import UpOptions, run_up

    summary = run_up(Settings.load(), UpOptions([], duration=8.0, robots=["pa", "pb", "pc"], quiet=True, pooled=True))
    critic, fleet = summary["critic"], summary["fleet"]
    assert critic["pooled"] is True
    # one fit per fleet step (~80 in 8 s), its weights to each of the 3 robots
    assert critic["weights_published"] >= 3 * 60
    for row in fleet["rows"]:
        assert row["steps"] >= 40 and row["staleness_max_steps"] <= 5, row
        assert row["final_distance_m"] < 1.5 - 0.5, row  # from 1.5 m: approached


@pytest.mark.integration
@pytest.mark.slow
def test_experiment_fleet_per_robot_gives_the_paper_experiments_j_and_pooled_beside_it(tmp_path: Path) -> None:
    """``srl experiment fleet`` on a reduced grid: its per-robot fleet is ``srl experiment paper``
    run for run (the same J), the pooled fleet is reported beside it, and bad input is refused."""
    import csv

    from tests.harness import srl

    grid = ["--grid", "2", "--duration", "2", "--horizons", "6", "--agents", "mpc,rlqv", "--workers", "1"]
    paper = srl(
        "experiment", "paper", *grid, "--no-plots", "--no-progress", "--out", str(tmp_path / "paper"), timeout=300
    )
    assert paper.returncode == 0, paper.stderr[-2000:]
    fleet = srl("experiment", "fleet", *grid, "--out", str(tmp_path / "fleet"), timeout=300)
    assert fleet.returncode == 0, fleet.stderr[-2000:]
    assert "| RL-QV | 6 | per-robot |" in fleet.stdout and "| RL-QV | 6 | pooled |" in fleet.stdout
    marks = json.loads((tmp_path / "fleet" / "fleet.json").read_text())
    runs = list(csv.DictReader((tmp_path / "paper" / "runs.csv").open()))
    j = {(r["agent"], int(r["start_index"])): float(r["accumulated_cost"]) for r in runs}
    assert marks["mpc_costs"]["6"] == [j[("mpc", i)] for i in range(4)]
    groups = {g["critic"]: g for g in marks["groups"]}
    per_robot = [
        r / 100 * jm for r, jm in zip(groups["per-robot"]["ratio_percent"], marks["mpc_costs"]["6"], strict=True)
    ]
    np.testing.assert_allclose(per_robot, [j[("rlqv", i)] for i in range(4)], rtol=1e-12)
    assert groups["pooled"]["ratio_percent"] != groups["per-robot"]["ratio_percent"]  # it learned otherwise
    refused = srl("experiment", "fleet", "--critic", "shared", timeout=60)
    assert refused.returncode == 2 and refused.stderr.strip().count("\n") == 0 and "--critic" in refused.stderr
