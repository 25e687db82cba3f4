"""``srl experiment baselines`` (tools/experiment/baselines.py): SAC and PPO from stable-baselines3
on srl's Gymnasium environments, beside srl's agents. A tiny training of each (a few hundred
steps) through the command's own code path keeps that path alive; the full budgets are
``srl experiment baselines`` (docs/gym.md)."""

from __future__ import annotations

import csv
import json
import math
import os
import tempfile
import warnings
from dataclasses import replace
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import pytest

from common.config.settings import Settings
from common.math import physics
from common.math.systems import SYSTEMS
from tools.cli import main as srl
from tools.experiment.baselines import (
    DEFAULT_BUDGETS,
    DEFAULT_ENVS,
    DEFAULT_SEEDS,
    QUICK_BUDGETS,
    ZOO,
    BaselineOptions,
    Row,
    evaluation_starts,
    hyperparameters,
    parse_budgets,
    parse_envs,
    parse_hyper,
    run_baselines,
    system_environments,
    table_markdown,
    train,
)
from tools.experiment.output import experiment_settings
from tools.gym.envs import ENV_MODELS, normalized_actions, system_envs

# MuJoCo (srl/TurtleBot3Physics-v0), imported here, outside any test: its first import runs a
# process (GLFW's version probe); as tests/test_gym.py
physics.load_mujoco()
# what stable-baselines3's checker only recommends: a [-1, 1] action box (normalized_actions gives
# one) and float32 actions (srl's actions are float64, as the actor computes them)
RECOMMENDATIONS = ("symmetric and normalized", "np.float32")
# a few hundred steps: SAC past its 100 learning-free steps, PPO two rollouts of 4 x 64 steps
TINY = BaselineOptions(
    algos=("sac", "ppo"),
    envs=("srl/Unicycle-v0",),
    budgets=(150, 300),
    seeds=1,
    grid=1,  # one start of each set: the paper's centre and one held-out start
    agents=("mpc", "rlqv"),
    horizons=(12,),
    hyper={"ppo": {"n_steps": 64}},
    progress=False,
)


# -- options (pure) -----------------------------------------------------------------------
def test_the_options_parse_and_refuse_in_one_line() -> None:
    assert parse_budgets("50000,10000,1e4") == (10_000, 50_000)
    assert parse_envs("Unicycle-v0,srl/TurtleBot3-v0") == ("srl/Unicycle-v0", "srl/TurtleBot3-v0")
    assert parse_hyper(["ppo.n_steps=64", "sac.ent_coef=auto_0.1"]) == {
        "ppo": {"n_steps": 64},
        "sac": {"ent_coef": "auto_0.1"},
    }
    assert hyperparameters("ppo", {"ppo": {"n_steps": 64}}) == {**ZOO["ppo"], "n_steps": 64}
    assert hyperparameters("sac") == {"policy": "MlpPolicy", "learning_rate": 1e-3}  # the Zoo's Pendulum-v1
    for bad, call in [
        ("0,10", lambda: parse_budgets("0,10")),
        ("x", lambda: parse_budgets("x")),
        ("Pendulum-v1", lambda: parse_envs("Pendulum-v1")),
        ("td3.x=1", lambda: parse_hyper(["td3.x=1"])),
    ]:
        with pytest.raises(ValueError) as raised:
            call()
        assert "\n" not in str(raised.value), bad


def test_the_help_states_the_defaults_the_code_uses(capsys: pytest.CaptureFixture[str]) -> None:
    """The CLI cannot import this module (its extra's gymnasium), so its help repeats them."""
    with pytest.raises(SystemExit):
        srl(["experiment", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    budgets = f"(default: {','.join(map(str, DEFAULT_BUDGETS))}; --quick: {','.join(map(str, QUICK_BUDGETS))})"
    assert budgets in text and f"(default: {DEFAULT_SEEDS}; --quick: 1)" in text, text


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--seeds", "0"], "--seeds must be >= 1"),
        (["--algos", "td3"], "unknown algorithm td3"),
        (["--transport", "zenoh"], "runs in process"),
        (["--plant", "actuator"], "--envs"),
    ],
)
def test_the_command_refuses_bad_options_before_any_training(
    flags: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert srl(["experiment", "baselines", *flags, "--out", str(tmp_path / "out")]) == 2
    error = capsys.readouterr().err.strip()
    assert message in error and len(error.splitlines()) == 1, error
    assert not (tmp_path / "out").exists(), "nothing written"


# -- the second checker -------------------------------------------------------------------
@pytest.mark.needs_baselines
@pytest.mark.parametrize("env_id", [*sorted(ENV_MODELS), *sorted(system_envs())])
def test_each_environment_passes_stable_baselines3s_checker(env_id: str) -> None:
    from stable_baselines3.common.env_checker import check_env

    for env in (gymnasium.make(env_id), normalized_actions(gymnasium.make(env_id))):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            check_env(env, warn=True)
        others = [str(w.message) for w in caught if not any(r in str(w.message) for r in RECOMMENDATIONS)]
        assert not others, others


# -- a tiny training of each baseline, end to end --------------------------------------------
@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], list[Row], Path]:
    out = tmp_path_factory.mktemp("baselines")
    options = replace(TINY, out=out)
    summary, rows = run_baselines(options, experiment_settings(Settings.load()))
    return summary, rows, out


@pytest.mark.needs_baselines
@pytest.mark.slow
@pytest.mark.integration  # srl's actor (J_mpc) is JIT-built with the C compiler
def test_a_tiny_training_of_each_baseline_writes_every_output(tiny: tuple[dict[str, Any], list[Row], Path]) -> None:
    summary, rows, out = tiny
    labels = [(r["controller"], r["horizon"], r["budget"], r["steps"]) for r in summary["rows"]]
    assert labels == [
        ("mpc", 12, None, 300),
        ("rlqv", 12, None, 300),
        ("sac", None, 150, 150),
        ("sac", None, 300, 300),
        ("ppo", None, 150, 256),  # whole rollouts of 4 environments x 64 steps
        ("ppo", None, 300, 512),
    ]
    for r in summary["rows"]:
        assert r["paper"]["episodes"] == r["held-out"]["episodes"] == 1
        assert r["wall_seconds"] > 0 and r["cpu_seconds"] > 0
    assert summary["rows"][0]["paper"]["median_ratio_percent"] == 100.0  # MPC is the reference
    assert summary["hyperparameters"]["ppo"] == {**ZOO["ppo"], "n_steps": 64}
    assert "Pendulum-v1" in summary["hyperparameter_source"]["sac"]
    assert (out / "baselines.png").stat().st_size > 0
    assert json.loads((out / "baselines.json").read_text())["rows"] == json.loads(json.dumps(summary["rows"]))
    with (out / "baselines.csv").open() as handle:
        records = list(csv.DictReader(handle))
    assert len(records) == 2 * len(rows)  # (row, start): two starts, one seed
    table = (out / "baselines.md").read_text()
    assert table_markdown(summary) in table
    assert len([line for line in table.splitlines() if line.startswith("| Unicycle-v0 |")]) == len(rows)


@pytest.mark.needs_baselines
@pytest.mark.slow
@pytest.mark.integration  # srl's actor (J_mpc) is JIT-built with the C compiler
def test_every_j_is_finite_and_the_sum_of_the_environments_costs(tiny: tuple[dict[str, Any], list[Row], Path]) -> None:
    _, rows, _ = tiny
    env = gymnasium.make("srl/Unicycle-v0", settings=experiment_settings(Settings.load()))
    for row in rows:
        for _, e in row.episodes:
            assert math.isfinite(e.cost) and len(e.actions) == len(e.costs) == 300
            env.reset(options={"start": (e.start.x, e.start.y, e.start.alpha)})
            costs = []
            for action in e.actions:  # the episode's actions again, on a fresh environment
                _, reward, _, _, info = env.step(action)
                assert info["cost"] == -reward
                costs.append(info["cost"])
            assert costs == e.costs.tolist() and float(np.sum(costs)) == e.cost, row.label


@pytest.mark.needs_baselines
@pytest.mark.parametrize("algo", ["sac", "ppo"])
def test_a_training_leaves_nothing_in_the_temporary_directory(
    algo: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # stable-baselines3 makes an SB3-<date> folder in the temporary directory at each learn()
    # unless the model has a logger of its own (the control shows where its default would go),
    # and torch its compiler's cache torchinductor_<user> unless told another place: srl's cache.
    from stable_baselines3.common.utils import configure_logger

    temporary, cache = tmp_path / "tmp", tmp_path / "cache"
    temporary.mkdir()
    for name in ("SB3_LOGDIR", "TORCHINDUCTOR_CACHE_DIR"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(cache))
    monkeypatch.setattr(tempfile, "tempdir", str(temporary))
    train("srl/Unicycle-v0", algo, (64, 128), 3, experiment_settings(Settings.load()))
    assert list(temporary.iterdir()) == []
    assert os.environ["TORCHINDUCTOR_CACHE_DIR"] == str(cache / "srl" / "torchinductor")
    configure_logger()  # the negative control: SB3's default logger
    assert [p.name[:4] for p in temporary.iterdir()] == ["SB3-"]


@pytest.mark.needs_baselines
@pytest.mark.slow
def test_a_training_seed_repeats_the_training() -> None:
    settings = experiment_settings(Settings.load())
    first, second = (train("srl/Unicycle-v0", "sac", (120,), 7, settings)[0] for _ in range(2))
    other = train("srl/Unicycle-v0", "sac", (120,), 8, settings)[0]
    weights = [[p.detach().numpy().copy() for p in snapshot.policy.parameters()] for snapshot in (first, second, other)]
    assert all(np.array_equal(a, b) for a, b in zip(weights[0], weights[1], strict=True))
    assert not all(np.array_equal(a, b) for a, b in zip(weights[0], weights[2], strict=True))


@pytest.mark.needs_baselines
@pytest.mark.slow
@pytest.mark.integration  # worker processes, and srl's actor JIT-built with the C compiler
def test_trainings_in_worker_processes_give_the_same_table_as_one_after_another(
    tiny: tuple[dict[str, Any], list[Row], Path], tmp_path: Path
) -> None:
    # --workers 2: the four trainings (sac, ppo; two budgets each) in two spawned processes; each
    # is seeded on its own, so every J and every action is what the one-process run gave
    summary, rows, _ = tiny
    parallel, parallel_rows = run_baselines(
        replace(TINY, out=tmp_path, workers=2), experiment_settings(Settings.load())
    )
    assert [r.label for r in parallel_rows] == [r.label for r in rows]
    for one, other in zip(rows, parallel_rows, strict=True):
        assert [e.cost for _, e in one.episodes] == [e.cost for _, e in other.episodes], one.label
        assert all(
            np.array_equal(a.actions, b.actions) for (_, a), (_, b) in zip(one.episodes, other.episodes, strict=True)
        )
    assert [r["paper"] for r in parallel["rows"]] == [r["paper"] for r in summary["rows"]]


# -- another system's environment ------------------------------------------------------------
@pytest.mark.needs_baselines
@pytest.mark.slow
@pytest.mark.integration  # srl's actor (J_mpc) is JIT-built with the C compiler
def test_sac_and_ppo_train_on_every_other_system_beside_srls_agents(tmp_path: Path) -> None:
    """A tiny training of each on each built-in system's environment: its starts are the lattice
    over the system's start box (the goal left out), its actions of the system's size and in its
    box, "parked" is stabilized in the system's terms, and every J is the sum of the costs the
    environment gives for the episode's actions, again."""
    envs = tuple(sorted(system_envs()))
    base = experiment_settings(Settings.load(episode={"duration": 2.0}))
    options = replace(TINY, envs=envs, grid=2, agents=("mpc",), out=tmp_path)
    summary, rows = run_baselines(options, base)
    for env_id in envs:
        system = SYSTEMS[system_envs()[env_id]]
        labels = [(r.controller, r.budget) for r in rows if r.env_id == env_id]
        assert labels == [("mpc", None), ("sac", 150), ("sac", 300), ("ppo", 150), ("ppo", 300)], env_id
        starts = evaluation_starts(2, 2.0, 0, system_envs()[env_id])
        assert starts["paper"] and all(any(s.values) for s in starts["paper"])  # never the goal itself
        assert summary["tolerances"][env_id] == system.stabilized
        env = gymnasium.make(env_id, settings=base)
        for row in (r for r in rows if r.env_id == env_id):
            assert len(row.episodes) == sum(len(points) for points in starts.values()), row.label
            for _, e in row.episodes:
                assert e.actions.shape == (20, system.action_dim), row.label
                assert np.all(np.abs(e.actions) <= np.array(system.action_max)), row.label
                assert e.parked == (e.final_distance <= system.stabilized)
                env.reset(options={"start": e.start.values})
                costs = [env.step(action)[4]["cost"] for action in e.actions]
                assert costs == e.costs.tolist() and float(np.sum(costs)) == e.cost, row.label
    mpc = [r for r in summary["rows"] if r["controller"] == "mpc"]
    assert [r["paper"]["median_ratio_percent"] for r in mpc] == [100.0] * len(envs)  # the reference
    assert "Another system: parked is stabilized" in (tmp_path / "baselines.md").read_text()
    assert "start box" in summary["training_starts"]


def test_system_names_the_environment_of_baselines(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert system_environments("pendulum") == ("srl/Pendulum-v0",)
    assert system_environments("unicycle") == DEFAULT_ENVS
    assert parse_envs("Cartpole-v0,srl/TwoTank-v0") == ("srl/Cartpole-v0", "srl/TwoTank-v0")
    flags = ["--system", "pendulum", "--envs", "Unicycle-v0", "--out", str(tmp_path / "out")]
    assert srl(["experiment", "baselines", *flags]) == 2
    error = capsys.readouterr().err.strip()
    assert "--system or --envs, not both" in error and len(error.splitlines()) == 1, error
    assert not (tmp_path / "out").exists()
