"""A plant model is one row (common/math/plant_models.py): a class that satisfies
:class:`common.math.turtlebot.SimulatedRobot`, registered, runs wherever a plant model runs --
the settings, the in-process episode (``srl run``, the experiment), plant_sim, the TurtleBot3
emulator, and through ``SRL_PLUGINS`` every process of ``srl run`` and ``srl up`` -- with no
change to srl's modules. The model is examples/lagged_unicycle.py, a user's file."""

from __future__ import annotations

import json
import math
import subprocess
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from common.config.settings import Settings
from common.math.dynamics import FloatArray
from common.math.frames import Pose2D
from common.math.plant_models import (
    BUILT_IN_PLANT_MODELS,
    PLANT_MODELS,
    plant_model_row,
    register_plant_model,
    simulated_robot,
)
from common.process.plugins import PluginError, load_plugins
from examples import lagged_unicycle
from examples.lagged_unicycle import NAME, LaggedUnicycle

ROOT = Path(__file__).resolve().parents[1]
PLUGIN = "examples/lagged_unicycle.py"
build_lagged = lagged_unicycle.build


@pytest.fixture
def registered() -> Iterator[str]:
    lagged_unicycle.register()  # what SRL_PLUGINS does in each process
    try:
        yield NAME
    finally:
        del PLANT_MODELS[NAME]  # other tests of this process see srl's rows only


def oracle(settings: Settings, start: FloatArray, actions: list[FloatArray], duration: float) -> list[FloatArray]:
    """The user's model alone, driven by ``actions``: its odometry after each."""
    robot = LaggedUnicycle(settings.turtlebot_params(), start)
    return [robot.step(action, duration) for action in actions]


def test_registering_a_model_makes_it_a_setting_and_a_choice_and_a_bad_one_is_refused(registered: str) -> None:
    from tools.cli import build_parser

    assert Settings.load(plant={"model": registered}).plant.model == registered
    assert plant_model_row(registered).build is build_lagged
    with pytest.raises(ValidationError, match=r"unknown plant model 'gazebo' \(ideal, actuator, physics, lagged"):
        Settings.load(plant={"model": "gazebo"})
    with pytest.raises(ValueError, match="exists already"):
        register_plant_model(registered, "again", build_lagged)
    with pytest.raises(ValueError, match="a-z 0-9 _"):
        register_plant_model("Bad Name", "a name no setting can hold", build_lagged)
    assert tuple(PLANT_MODELS)[: len(BUILT_IN_PLANT_MODELS)] == BUILT_IN_PLANT_MODELS
    model_choices = [
        list(action.choices)
        for sub in build_parser()._subparsers._group_actions[0].choices.values()  # type: ignore[union-attr]
        for action in sub._actions
        if "--model" in action.option_strings and action.choices is not None
    ]  # the parser is built after the registration: every --model offers the model
    assert model_choices and all(registered in choices for choices in model_choices)


def test_a_model_unregistered_is_refused_by_the_settings() -> None:
    assert NAME not in PLANT_MODELS  # the negative control of the test above: without the row, no setting
    with pytest.raises(ValidationError, match=f"unknown plant model '{NAME}'"):
        Settings.load(plant={"model": NAME})


@pytest.mark.slow
def test_the_in_process_episode_runs_the_users_model(registered: str) -> None:
    """``srl run``'s episode (common.config.assembly.run_episode) on the user's model: the actor
    saw its odometry, the truth is its true pose, and the model alone, driven by the episode's
    actions, gives the same states bit for bit."""
    from common.config.assembly import episode_summary, run_episode

    settings = Settings.load(
        plant={"model": registered},
        actor={"agent": "mpc", "horizon": 6, "jit": False},
        episode={"start": [1.0, 0.5], "duration": 3.0},
    )
    episode = run_episode(settings)
    start = settings.start_state()
    expected = oracle(settings, start, episode.actions, settings.plant.sampling_time)
    np.testing.assert_array_equal(np.array(episode.states[1:]), np.array(expected))
    assert episode.truth_known and not np.allclose(episode.true_states[-1], episode.states[-1])
    assert np.hypot(*episode.true_states[-1][:2]) < np.hypot(*start[:2])  # the MPC drove it towards the target
    summary = episode_summary(episode, settings)
    assert summary["plant_model"] == registered and summary["truth"] is not None


def test_plant_sim_runs_the_users_model_in_lockstep(registered: str) -> None:
    from common.contracts.messages import ResetRequest, StepRequest
    from services.plant_sim.service import SimulatedPlant

    settings = Settings.load(plant={"model": registered})
    plant = SimulatedPlant(settings)
    start = np.array([1.0, -0.5, 0.3])
    plant.reset(ResetRequest(robot="robot1", episode=1, state=(1.0, -0.5, 0.3)))
    actions = [np.array([0.2, 0.5]), np.array([0.22, -1.0]), np.array([0.0, 0.0])] * 3
    replies = [
        plant.step(StepRequest(robot="robot1", episode=1, step=k, action=(float(a[0]), float(a[1])), duration=0.1))
        for k, a in enumerate(actions)
    ]
    np.testing.assert_array_equal(np.array([r.state for r in replies]), np.array(oracle(settings, start, actions, 0.1)))
    assert all(r.true_state is not None and r.true_state != r.state for r in replies)


def test_the_emulator_runs_the_users_model_behind_its_latency(registered: str) -> None:
    from services.tb3_emulator.service import Tb3Model

    settings = Settings.load()
    model = Tb3Model(
        Pose2D(0.5, 0.0, 0.0), 0.22, 2.84, 0.0, 0.0, (0.0, 0.0), 0, 0.0,
        registered, settings.turtlebot_params(), settings.physics_params(),
    )  # fmt: skip
    assert model.kind == registered and isinstance(model.robot, LaggedUnicycle)
    assert model.robot.params.v_max == 0.22  # the emulated robot's limits, not the settings'
    model.command(0.5, 0.0, now=0.0)  # beyond its limit: clamped by the model
    pose, velocity = model.sample(1.0)
    robot = LaggedUnicycle(model.robot.params, np.array([0.5, 0.0, 0.0]))
    robot.command(0.5, 0.0)
    robot.advance(1.0)
    np.testing.assert_array_equal(pose, robot.odometry)
    assert velocity == robot.velocity and 0.0 < velocity[0] < 0.22  # the encoders' speed, still lagging
    assert model.robot.saturated_commands == 1


def test_the_built_in_rows_build_what_they_name() -> None:
    settings = Settings.load()
    args = (settings.turtlebot_params(), settings.physics_params(), np.zeros(3))
    assert simulated_robot("ideal", *args) is None  # the exact unicycle: no robot model
    assert type(simulated_robot("actuator", *args)).__name__ == "TurtleBot"


def test_srl_plugins_loads_each_file_once_and_refuses_a_bad_one_with_one_line(tmp_path: Path) -> None:
    try:
        assert load_plugins(f" {ROOT / PLUGIN} ,") == [str(ROOT / PLUGIN)]
        assert plant_model_row(NAME).build is not None
        assert load_plugins(str(ROOT / PLUGIN)) == [str(ROOT / PLUGIN)]  # again: nothing registered twice
    finally:
        PLANT_MODELS.pop(NAME, None)
    assert load_plugins(None) == [] and load_plugins("") == []
    no_register = tmp_path / "no_register.py"
    no_register.write_text("X = 1\n")
    broken = tmp_path / "broken.py"
    broken.write_text("import not_a_module_anywhere\n")
    failing = tmp_path / "failing.py"
    failing.write_text("def register():\n    raise RuntimeError('no licence')\n")
    for entry, says in [
        (str(tmp_path / "absent.py"), "no file"),
        (str(no_register), "has no register"),
        (str(broken), "cannot import .*ModuleNotFoundError"),
        (str(failing), "register\\(\\) failed: RuntimeError: no licence"),
        ("not_a_module_anywhere", "cannot import 'not_a_module_anywhere'"),
    ]:
        with pytest.raises(PluginError, match=says) as refused:
            load_plugins(entry)
        assert "\n" not in str(refused.value)


def srl_with(*args: str, plugins: str = PLUGIN, timeout: float = 240, **env: str) -> subprocess.CompletedProcess[str]:
    """``srl ARGS`` with the model chosen, ``SRL_PLUGINS=plugins`` ("": none) and ``env``."""
    from tests.harness import srl

    return srl(*args, env={"SRL_PLANT__MODEL": NAME, "SRL_PLUGINS": plugins, **env}, timeout=timeout)


@pytest.mark.integration
@pytest.mark.slow
def test_srl_run_and_srl_up_run_the_plugins_model_in_every_process() -> None:
    """``SRL_PLUGINS``: ``srl run`` (in process) and ``srl up`` (plant_sim, the critic and the actor
    as processes, in lockstep, which reproduces the in-process run bit for bit) run the user's
    model; without the plugin the same command is refused with one line."""
    common = ["--agent", "mpc", "--horizon", "6", "--no-jit", "--start", "1,0.5", "--duration", "3", "--json"]
    local = srl_with("run", *common)
    assert local.returncode == 0, local.stderr[-2000:]
    in_process = json.loads(local.stdout.strip().splitlines()[-1])
    assert in_process["plant_model"] == NAME and in_process["truth"] is not None
    from tests.harness import free_port

    distributed = srl_with("up", "--mode", "lockstep", "--router", f"tcp/127.0.0.1:{free_port()}", *common)
    assert distributed.returncode == 0, distributed.stderr[-2000:]
    up = json.loads(distributed.stdout.strip().splitlines()[-1])
    assert up["plant_model"] == NAME
    assert up["accumulated_cost"] == in_process["accumulated_cost"]  # the same model, the same run
    assert up["final_state"] == in_process["final_state"]
    refused = srl_with("run", *common, plugins="")
    assert refused.returncode == 2 and f"unknown plant model '{NAME}'" in refused.stderr
    assert len([line for line in refused.stderr.splitlines() if line.startswith("srl: error")]) == 1
    bad = srl_with("run", *common, plugins="examples/absent.py")
    assert bad.returncode == 2 and bad.stderr.strip().splitlines()[-1].startswith("srl: error: SRL_PLUGINS: no file")


def test_the_gymnasium_environment_runs_the_users_model(registered: str) -> None:
    """``gymnasium.make("srl/Unicycle-v0", model=NAME)``: the user's model behind srl's
    environment, which passes Gymnasium's checker; its observations are the model's odometry."""
    import gymnasium
    from gymnasium.utils.env_checker import check_env

    import tools.gym  # noqa: F401  (registers srl's ids)

    env = gymnasium.make("srl/Unicycle-v0", model=registered)
    check_env(env.unwrapped, skip_render_check=True)
    first, _ = env.reset(options={"start": (1.0, -0.5, 0.3)})
    np.testing.assert_array_equal(first, (1.0, -0.5, 0.3))
    actions = [np.array([0.2, 0.5]), np.array([0.22, -1.0]), np.array([0.1, 0.0])]
    observations = [env.step(action)[0] for action in actions]
    settings = env.unwrapped.settings  # type: ignore[attr-defined]
    expected = oracle(settings, np.array([1.0, -0.5, 0.3]), actions, settings.plant.sampling_time)
    np.testing.assert_array_equal(np.array(observations), np.array(expected))
    env.close()


@pytest.mark.integration
@pytest.mark.slow
def test_the_paper_experiment_runs_a_plugins_model_and_agent_in_its_spawned_workers(tmp_path: Path) -> None:
    """``srl experiment paper`` spreads its runs over spawned worker processes, each a fresh
    interpreter: they load ``SRL_PLUGINS`` as every srl process does, so the user's plant model
    and the user's agent (examples/mpc_with_value.py) run there, J / J_MPC and all."""
    import csv

    plugins = f"{PLUGIN},examples/mpc_with_value.py"
    grid = ["--grid", "1", "--duration", "2", "--horizons", "6", "--agents", "mpc,mpcv", "--workers", "2"]
    out = tmp_path / "paper"
    run = srl_with(
        "experiment", "paper", "--plant", NAME, *grid, "--no-plots", "--no-progress", "--out", str(out),
        plugins=plugins, SRL_ACTOR__JIT="false",
    )  # fmt: skip
    assert run.returncode == 0, run.stderr[-2000:]
    rows = list(csv.DictReader((out / "runs.csv").open()))
    assert sorted({r["agent"] for r in rows}) == ["mpc", "mpcv"] and len(rows) == 2
    assert all(math.isfinite(float(r["accumulated_cost"])) for r in rows)
    summary = (out / "summary.md").read_text()
    assert f"plant {NAME}" in summary and "| mpcv | 6 | 1 |" in summary  # J / J_mpc of the user's agent
