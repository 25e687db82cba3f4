"""srl's robots as Gymnasium environments, the vector environment, srl's agents as policies and the
environment behind a lockstep plant_sim (tools/gym/, docs/gym.md)."""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterator

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import tools.gym
from common.config.assembly import run_episode
from common.config.settings import Settings
from common.math import physics
from common.math.dynamics import exact_step
from common.math.features import stage_cost
from common.math.loop import Episode
from tests.harness import cluster
from tools.experiment.grid import make_starts
from tools.gym.bench import measure
from tools.gym.envs import ENV_MODELS, SrlEnv, StartDistribution, normalized_actions, system_envs
from tools.gym.policies import SrlPolicy, policy_settings
from tools.gym.vector import SrlVectorEnv

# MuJoCo (srl/TurtleBot3Physics-v0), imported here, outside any test: its first import runs a
# process (GLFW's version probe). The extra srl[physics]: ./srl and CI install it, so it is never skipped
physics.load_mujoco()
# the README's first command: ./srl run --agent rlqv --horizon 12 --start 2,2 --duration 30
README_RUN = {"actor": {"agent": "rlqv", "horizon": 12}, "episode": {"start": [2.0, 2.0], "duration": 30.0}}
README_J = "197.1662"
# what Gymnasium's checker only recommends of a box: unbounded observations (the continuous
# heading), a (v, omega) action box in physical units (normalized_actions gives [-1, 1])
RECOMMENDATIONS = ("infinity", "symmetric and normalized")


# -- registration and the checker -------------------------------------------------------
def test_make_finds_the_ids_through_the_module_prefix_and_after_the_import() -> None:
    env = gymnasium.make("tools.gym:srl/Unicycle-v0")
    assert isinstance(env.unwrapped, SrlEnv) and env.unwrapped.settings.plant.model == "ideal"
    assert env.spec is not None and env.spec.id == "srl/Unicycle-v0"
    for env_id, model in ENV_MODELS.items():
        assert gymnasium.make(env_id).unwrapped.settings.plant.model == model
    ids = sorted([*ENV_MODELS, *system_envs()])  # the robot's, and one per other system
    assert ids == sorted(i for i in gymnasium.registry if i.startswith(f"{tools.gym.NAMESPACE}/")), (
        "every srl id registered, none else"
    )


@pytest.mark.parametrize("env_id", sorted(ENV_MODELS))
def test_each_environment_passes_gymnasiums_checker(env_id: str) -> None:
    env = gymnasium.make(env_id).unwrapped
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, skip_render_check=True)
        check_env(normalized_actions(gymnasium.make(env_id)).unwrapped, skip_render_check=True)
    others = [str(w.message) for w in caught if not any(r in str(w.message) for r in RECOMMENDATIONS)]
    assert not others, others
    settings = env.settings
    assert env.action_space.low.tolist() == [-settings.plant.v_max, -settings.plant.omega_max] == [-0.22, -2.84]
    assert env.action_space.high.tolist() == [0.22, 2.84] and env.action_space.dtype == np.float64
    assert env.observation_space.shape == (3,) and env.observation_space.dtype == np.float64


def test_the_normalized_wrapper_maps_minus_one_to_one_onto_the_robots_limits() -> None:
    plain, scaled = SrlEnv(), normalized_actions(SrlEnv())
    assert scaled.action_space.low.tolist() == [-1.0, -1.0] and scaled.action_space.high.tolist() == [1.0, 1.0]
    plain.reset(options={"start": (1.0, 1.0, 0.0)})
    scaled.reset(options={"start": (1.0, 1.0, 0.0)})
    for normalized, physical in (((1.0, -1.0), (0.22, -2.84)), ((-0.5, 0.25), (-0.11, 0.71)), ((0.0, 0.0), (0.0, 0.0))):
        expected = plain.step(np.array(physical))
        got = scaled.step(np.array(normalized))
        np.testing.assert_allclose(got[0], expected[0], rtol=0, atol=1e-15)
        assert got[1] == pytest.approx(expected[1], rel=1e-12)


# -- observation, action, reward, episode ---------------------------------------------------
def test_the_observation_is_the_goal_frame_state_with_a_continuous_heading() -> None:
    env = SrlEnv()
    obs, info = env.reset(options={"start": (0.5, -0.2, 3.0)})
    assert obs.tolist() == [0.5, -0.2, 3.0] and info["true_state"].tolist() == obs.tolist()
    state = obs.copy()
    for _ in range(10):  # full speed ahead, turning left at 2.84 rad/s: the heading passes pi, unwrapped
        obs, *_ = env.step(np.array([0.22, 2.84]))
        state = exact_step(state, np.array([0.22, 2.84]), 0.1)
        assert obs.tolist() == state.tolist()
    assert obs[2] == pytest.approx(3.0 + 10 * 0.284, abs=1e-12) and obs[2] > math.pi
    # a start given as (x, y) heads away from the target (the paper's alpha_0 = atan2(y, x))
    obs, _ = env.reset(options={"start": (-1.0, 1.0)})
    assert obs[2] == pytest.approx(math.atan2(1.0, -1.0), abs=0)


def test_the_turtlebot_reports_its_odometry_and_the_truth_beside_it() -> None:
    env = SrlEnv(model="actuator")
    obs, _ = env.reset(options={"start": (1.0, 0.0, 0.0)})
    for _ in range(20):
        obs, _, _, _, info = env.step(np.array([0.2, 1.0]))
    robot = env.plant.robot
    assert obs.tolist() == robot.odometry.tolist() and info["true_state"].tolist() == robot.true_pose.tolist()
    assert not np.allclose(obs[:2], info["true_state"][:2], atol=1e-4), "slip: the odometry drifts from the truth"


def test_reward_is_minus_the_stage_cost_of_the_clipped_action_and_bad_actions_move_nothing() -> None:
    env = SrlEnv()
    obs, _ = env.reset(options={"start": (1.0, 2.0, 0.5)})
    r_diag = env.settings.r_diag
    _, reward, _, _, info = env.step(np.array([5.0, -9.0]))  # beyond the box: clipped
    clipped = np.array([0.22, -2.84])
    assert -reward == info["cost"] == 0.1 * float(stage_cost(obs, clipped, r_diag))
    assert env.state is not None and env.state.tolist() == exact_step(obs, clipped, 0.1).tolist()
    held = env.state.copy()
    for bad in ([np.nan, 0.0], [0.0, np.inf], [0.1, 0.2, 0.3]):
        with pytest.raises(ValueError, match=r"not finite|shape"):
            env.step(np.array(bad))
        assert env.state.tolist() == held.tolist() and env.steps == 1


def test_an_episode_is_300_steps_of_delta_then_truncated_never_terminated() -> None:
    env = gymnasium.make("srl/Unicycle-v0")
    env.reset(seed=0)
    ends = []
    for _ in range(300):
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        ends.append((terminated, truncated))
    assert ends[:-1] == [(False, False)] * 299 and ends[-1] == (False, True)
    assert env.unwrapped.delta == 0.1


# -- starts and seeds ----------------------------------------------------------------------
@pytest.mark.parametrize(("kind", "model"), [("paper", "ideal"), ("held-out", "actuator"), ("paper", "physics")])
def test_grid_starts_are_the_experiments_and_a_seed_repeats_an_episode(kind: str, model: str) -> None:
    grid = {(s.x, s.y, s.alpha) for s in make_starts(kind, 5, 2.0, 0)}
    env = SrlEnv(model=model, starts=kind)
    drawn = [tuple(env.reset(seed=seed)[0].tolist()) for seed in range(60)]
    assert set(drawn) <= grid and len(set(drawn)) > 12, "draws among the experiment's 25 starts"
    actions = np.random.default_rng(1).uniform(-1, 1, (30, 2)) * [0.22, 2.84]

    def episode(seed: int) -> list[list[float]]:
        obs, _ = env.reset(seed=seed)
        return [obs.tolist(), *(env.step(a)[0].tolist() for a in actions)]

    assert episode(5) == episode(5)
    assert episode(5) != episode(6) or drawn[5] == drawn[6]


def test_disc_starts_are_uniform_in_the_disc_and_head_away_from_the_target() -> None:
    rng = np.random.default_rng(0)
    starts = np.array([StartDistribution("disc", extent=1.5).draw(rng) for _ in range(4000)])
    radius = np.hypot(starts[:, 0], starts[:, 1])
    assert radius.max() <= 1.5 and np.all(starts[:, 2] == np.arctan2(starts[:, 1], starts[:, 0]))
    # uniform in area: a quarter of the draws within half the radius
    assert abs(float(np.mean(radius < 0.75)) - 0.25) < 0.03
    given = StartDistribution([(1.0, 0.0), (0.0, 1.0, 0.3)])
    assert {tuple(given.draw(rng).tolist()) for _ in range(50)} == {(1.0, 0.0, 0.0), (0.0, 1.0, 0.3)}
    for bad in ("spiral", []):
        with pytest.raises(ValueError, match=r"starts?"):
            StartDistribution(bad)


# -- the vector environment ----------------------------------------------------------------
@pytest.mark.parametrize("model", ["ideal", "actuator"])
def test_the_vector_environment_is_n_single_environments_bit_for_bit(model: str) -> None:
    settings = Settings.load(episode={"duration": 1.0})  # 10 steps: episodes end and restart inside the test
    count, steps = 4, 25
    vector = SrlVectorEnv(num_envs=count, model=model, starts="disc", settings=settings)
    singles = [SrlEnv(model=model, starts="disc", settings=settings) for _ in range(count)]
    obs, _ = vector.reset(seed=11)
    assert obs.tolist() == [env.reset(seed=11 + i)[0].tolist() for i, env in enumerate(singles)]
    actions = np.random.default_rng(2).uniform(-1.2, 1.2, (steps, count, 2)) * [0.22, 2.84]
    ended = [False] * count
    for k in range(steps):
        obs, rewards, terminated, truncated, _ = vector.step(actions[k])
        for i, env in enumerate(singles):
            if ended[i]:  # next-step autoreset: this step is the new start, reward 0
                expected = (env.reset()[0], 0.0, False, False)
            else:
                o, r, te, tr, _ = env.step(actions[k, i])
                expected = (o, r, te, tr)
            got = (obs[i], rewards[i], terminated[i], truncated[i])
            assert got[0].tolist() == expected[0].tolist() and got[1:] == expected[1:], (k, i)
        ended = truncated.tolist()
    assert vector.steps.tolist() == [steps % 11] * count  # two episodes of 10 steps and their restarts


def test_make_vec_builds_the_vector_environment_with_batched_spaces() -> None:
    vector = gymnasium.make_vec("srl/Unicycle-v0", num_envs=3)
    assert isinstance(vector, SrlVectorEnv) and vector.metadata["autoreset_mode"].value == "NextStep"
    assert vector.action_space.shape == (3, 2) and vector.observation_space.shape == (3, 3)
    obs, _ = vector.reset(options={"starts": [(1.0, 1.0), (2.0, 0.0, 0.5), (0.0, -1.0)]})
    assert obs.tolist() == [[1.0, 1.0, math.atan2(1.0, 1.0)], [2.0, 0.0, 0.5], [0.0, -1.0, math.atan2(-1.0, 0.0)]]
    with pytest.raises(ValueError, match="2 starts for 3 robots"):
        vector.reset(options={"starts": [(1.0, 1.0), (2.0, 0.0)]})
    with pytest.raises(ValueError, match="shape"):
        vector.step(np.zeros((2, 2)))
    with pytest.raises(ValueError, match="not finite"):
        vector.step(np.full((3, 2), np.nan))


def test_the_throughput_measurement_counts_robot_steps() -> None:
    one, many = measure(1, 0.02), measure(50, 0.02)
    assert one.calls >= 500 and many.calls >= 500 and one.seconds >= 0.02
    assert many.steps_per_second == pytest.approx(50 * many.calls / many.seconds)
    assert many.steps_per_second > 5 * one.steps_per_second, "50 robots per call: more samples per second"


# -- srl's agents as policies --------------------------------------------------------------
def test_a_policy_refuses_an_unknown_agent_or_method_before_building_anything() -> None:
    with pytest.raises(ValueError, match="unknown agent"):
        policy_settings(None, "sac", 12)
    with pytest.raises(ValueError, match="unknown method"):
        policy_settings(None, "rlqv", 12, method="fast")
    paper = policy_settings(None, "rlq", 6, method="paper")
    assert (paper.actor.agent, paper.actor.horizon, paper.actor.arrival, paper.actor.convex_critics) == (
        "rlq",
        6,
        False,
        False,
    )


@pytest.fixture(scope="module")
def readme_episode() -> Iterator[tuple[Settings, Episode]]:
    settings = Settings.load(**README_RUN)
    yield settings, run_episode(settings)


def replay(env: gymnasium.Env[np.ndarray, np.ndarray], episode: Episode) -> list[float]:
    """``episode``'s actions through ``env`` from its start; each step's observation checked."""
    obs, _ = env.reset(options={"start": tuple(episode.states[0].tolist())})
    costs = []
    for k, action in enumerate(episode.actions):
        assert obs.tolist() == episode.states[k].tolist(), k
        obs, reward, terminated, truncated, _ = env.step(action)
        costs.append(-float(reward))
        assert not terminated and truncated == (k == len(episode.actions) - 1), k
    return costs


@pytest.mark.slow
@pytest.mark.integration  # the actor's JIT build runs the C compiler
def test_the_reward_is_srls_cost_along_the_readme_episode(readme_episode: tuple[Settings, Episode]) -> None:
    _, episode = readme_episode
    assert f"{episode.accumulated_cost:.4f}" == README_J and episode.steps == 300
    costs = replay(gymnasium.make("srl/Unicycle-v0"), episode)
    np.testing.assert_allclose(costs, episode.costs, rtol=0, atol=1e-12)
    assert costs == episode.costs  # the same operations: bit for bit


@pytest.mark.slow
@pytest.mark.integration  # the actor's JIT build runs the C compiler
def test_the_rlqv_policy_in_a_gymnasium_loop_is_srl_run(readme_episode: tuple[Settings, Episode]) -> None:
    _, episode = readme_episode
    env = gymnasium.make("srl/Unicycle-v0")
    policy = SrlPolicy("rlqv", 12, settings=env.unwrapped.settings)
    obs, _ = env.reset(options={"start": (2.0, 2.0)})
    actions, costs, truncated = [], [], False
    while not truncated:
        action = policy.act(obs)
        obs, reward, _, truncated, _ = env.step(action)
        actions.append(action)
        costs.append(-float(reward))
    assert np.array(actions).tolist() == np.array(episode.actions).tolist()
    assert f"{sum(costs):.4f}" == README_J and policy.steps == 300
    assert not np.array_equal(policy.q_weights, policy.settings.initial_q_weights()), "it learned"


@pytest.mark.slow
@pytest.mark.integration  # the actor's JIT build runs the C compiler
@pytest.mark.parametrize("agent", ["mpc", "rlq"])
def test_the_other_agents_as_policies_are_srl_run_too(agent: str) -> None:
    settings = Settings.load(actor={"agent": agent, "horizon": 12}, episode={"start": [-1.0, 2.0], "duration": 3.0})
    episode = run_episode(settings)
    env = SrlEnv(settings=settings)
    policy = SrlPolicy(agent, 12, settings=settings)
    for _ in range(2):  # a reset starts over: the second episode is the first again
        policy.reset()
        obs, _ = env.reset(options={"start": (-1.0, 2.0)})
        actions = []
        for _ in range(episode.steps):
            actions.append(policy.act(obs).tolist())
            obs, *_ = env.step(np.array(actions[-1]))
        assert actions == np.array(episode.actions).tolist()
    learned = not np.array_equal(policy.q_weights, settings.initial_q_weights())
    assert learned == (agent == "rlq")
    with pytest.raises(ValueError, match="3 finite numbers"):
        policy.act(np.array([np.nan, 0.0, 0.0]))


# -- the environment behind a lockstep plant_sim -------------------------------------------
@pytest.mark.integration
def test_the_zenoh_environment_is_the_in_process_one_bit_for_bit() -> None:
    from tools.gym.zenoh_env import ZenohEnv

    actions = np.random.default_rng(3).uniform(-1.1, 1.1, (300, 2)) * [0.22, 2.84]
    local = SrlEnv(starts="held-out")
    with cluster(robot="gym0") as c:
        c.start("plant", "plant-sim", "--mode", "lockstep")
        c.wait_alive("plant")
        remote = ZenohEnv(robot="gym0", router=c.endpoint, starts="held-out")
        try:
            for seed in (4, 5):  # two episodes: a reset starts the plant's next one
                got, expected = [remote.reset(seed=seed)], [local.reset(seed=seed)]
                for action in actions:
                    got.append(remote.step(action))
                    expected.append(local.step(action))
                for k, (a, b) in enumerate(zip(got, expected, strict=True)):
                    assert a[0].tolist() == b[0].tolist() and a[1:-1] == b[1:-1], (seed, k)
                assert got[-1][3] is True
        finally:
            remote.close()


@pytest.mark.integration
def test_another_systems_zenoh_environment_is_its_in_process_one_bit_for_bit() -> None:
    """The cart-pole's lockstep plant_sim as an environment: its messages sized and named by the
    system (common/contracts/wire.py), its episode the in-process one."""
    from tools.gym.zenoh_env import ZenohEnv

    actions = np.random.default_rng(4).uniform(-12.0, 12.0, (50, 1))  # beyond the box: clipped alike
    local = SrlEnv(system="cartpole")
    with cluster(robot="gym1") as c:
        c.start("plant", "plant-sim", "--mode", "lockstep", "--system", "cartpole")
        c.wait_alive("plant")
        remote = ZenohEnv(robot="gym1", router=c.endpoint, system="cartpole")
        try:
            got, expected = [remote.reset(seed=6)], [local.reset(seed=6)]
            for action in actions:
                got.append(remote.step(action))
                expected.append(local.step(action))
            assert got[0][0].shape == (4,)
            for k, (a, b) in enumerate(zip(got, expected, strict=True)):
                assert a[0].tolist() == b[0].tolist() and a[1:-1] == b[1:-1], k
        finally:
            remote.close()
