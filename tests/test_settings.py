"""Settings layering (packaged TOML < user TOML < environment < explicit) and the CLI contract.

Oracle for the defaults: the packaged ``srl.toml`` parsed with ``tomllib`` directly.
"""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

import common
from common.config.settings import Settings, parse_start, start_state

TOML_PATH = Path(common.__file__).parent / "config" / "srl.toml"
RAW = tomllib.loads(TOML_PATH.read_text())


pytestmark = pytest.mark.usefixtures("no_srl_environment")


def test_load_reads_packaged_toml() -> None:
    s = Settings.load()
    assert s.plant.sampling_time == RAW["plant"]["sampling_time"]
    assert s.plant.v_max == RAW["plant"]["v_max"]
    assert s.plant.omega_max == RAW["plant"]["omega_max"]
    assert list(s.cost.r_diag) == RAW["cost"]["r_diag"] == []  # the system's own:
    assert s.r_diag == (1.0, 10.0, 1.0, 0.01, 0.01) and s.plant.system == RAW["plant"]["system"] == "unicycle"
    assert s.critic.replay_size == RAW["critic"]["replay_size"]
    assert s.critic.ridge == RAW["critic"]["ridge"]
    assert s.critic.discount_rate == RAW["critic"]["discount_rate"]
    assert s.actor.agent == RAW["actor"]["agent"]
    assert RAW["actor"]["horizon"] == 0 and s.actor.horizon == 12  # the system's own: the robot's N = 12
    assert s.actor.solver == RAW["actor"]["solver"]
    assert s.episode.duration == RAW["episode"]["duration"]
    assert list(s.episode.start) == RAW["episode"]["start"] == []  # the system's own: (2, 2) heading away
    assert np.array_equal(s.start_state(), [2.0, 2.0, math.atan2(2.0, 2.0)])
    # every key of the file is a setting, and every setting comes from the file
    dumped = s.model_dump(mode="json")
    assert set(dumped) == set(RAW)
    for section, values in RAW.items():
        assert set(dumped[section]) == set(values), section


def test_derived_quantities() -> None:
    s = Settings.load()
    delta, gamma = RAW["plant"]["sampling_time"], RAW["critic"]["discount_rate"]
    assert s.discount == pytest.approx(math.exp(-gamma * delta), rel=1e-15)
    assert s.steps == round(RAW["episode"]["duration"] / delta)
    data = s.as_dict()
    assert data["derived"]["discount_beta"] == pytest.approx(math.exp(-gamma * delta))
    json.dumps(data)  # JSON-ready


def test_initial_weights_from_stage_cost() -> None:
    s = Settings.load(critic={"q_init": "stage_cost", "v_init": "stage_cost"})
    delta = s.plant.sampling_time
    r = list(s.r_diag)  # srl.toml's [] is the system's own: the robot's (1, 10, 1, 0.01, 0.01)
    assert r == [1.0, 10.0, 1.0, 0.01, 0.01]
    np.testing.assert_allclose(s.initial_q_weights(), delta * np.array([*r, *[0.0] * 10]), rtol=1e-15)
    np.testing.assert_allclose(s.initial_v_weights(), delta * np.array([*r[:3], 0.0, 0.0, 0.0]), rtol=1e-15)


def test_initial_weights_explicit_lists() -> None:
    s = Settings.load(critic={"q_init": list(range(15)), "v_init": [1, 2, 3, 4, 5, 6]})
    np.testing.assert_array_equal(s.initial_q_weights(), np.arange(15.0))
    np.testing.assert_array_equal(s.initial_v_weights(), [1, 2, 3, 4, 5, 6])


def test_env_overrides_toml(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SRL_CRITIC__REPLAY_SIZE", "40")
    s = Settings.load()
    assert s.critic.replay_size == 40
    # the rest of the section still comes from the file
    assert s.critic.ridge == RAW["critic"]["ridge"]
    assert s.critic.q_init == RAW["critic"]["q_init"]


def test_user_file_overrides_a_subset(tmp_path: Path) -> None:
    user = tmp_path / "mine.toml"
    user.write_text("[actor]\nhorizon = 6\n\n[plant]\nv_max = 0.5\n")
    s = Settings.load(user)
    assert s.actor.horizon == 6
    assert s.plant.v_max == 0.5
    assert s.actor.agent == RAW["actor"]["agent"]  # same section, untouched key
    assert s.plant.sampling_time == RAW["plant"]["sampling_time"]
    assert s.critic.replay_size == RAW["critic"]["replay_size"]


def test_user_file_from_env_variable(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    user = tmp_path / "mine.toml"
    user.write_text("[critic]\nreplay_size = 17\n")
    monkeypatch.setenv("SRL_CONFIG", str(user))
    assert Settings.load().critic.replay_size == 17


def test_missing_user_file_raises(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        Settings.load(tmp_path / "absent.toml")


def test_env_beats_user_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    user = tmp_path / "mine.toml"
    user.write_text("[critic]\nreplay_size = 17\n")
    monkeypatch.setenv("SRL_CRITIC__REPLAY_SIZE", "40")
    assert Settings.load(user).critic.replay_size == 40


def test_explicit_overrides_beat_env_and_files(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    user = tmp_path / "mine.toml"
    user.write_text("[actor]\nhorizon = 6\n")
    monkeypatch.setenv("SRL_ACTOR__HORIZON", "7")
    s = Settings.load(user, actor={"horizon": 5})
    assert s.actor.horizon == 5
    assert s.actor.agent == RAW["actor"]["agent"]  # deep merge: the rest of [actor] stays
    assert s.actor.predictor == RAW["actor"]["predictor"]


@pytest.mark.parametrize(
    "overrides",
    [
        {"actor": {"horizon": 1}},
        {"actor": {"agent": "dqn"}},
        {"plant": {"sampling_time": -0.1}},
        {"plant": {"sampling_time": float("nan")}},
        {"plant": {"v_max": float("inf")}},
        {"episode": {"start": [float("nan"), 1.0]}},
        {"episode": {"start": [1.0]}},
        {"episode": {"duration": 0.0}},
        {"critic": {"q_init": [0.0] * 14}},
        {"critic": {"v_init": [0.0] * 5 + [float("nan")]}},
        {"critic": {"replay_size": 1}},
        {"critic": {"weight_bounds": [1.0, -1.0]}},
        {"critic": {"discount_rate": -1.0}},
        {"critic": {"robots": "a/b"}},  # one key chunk: "*" or a robot id, never a path
        {"critic": {"robots": "**"}},
        {"critic": {"robots": ""}},
        {"cost": {"r_diag": [1.0, 10.0, -1.0, 0.01, 0.01]}},
        {"cost": {"r_diag": [1.0, 10.0, 1.0, 0.01]}},
        {"actor": {"unknown_key": 3}},
    ],
)
def test_invalid_values_raise(overrides: dict) -> None:
    with pytest.raises(ValidationError):
        Settings.load(**overrides)


@pytest.mark.parametrize(
    "overrides",
    [
        {"episode": {"duration": float("inf")}},  # steps = round(inf / delta) cannot exist
        {"critic": {"ridge": float("inf")}},  # sqrt(inf) rows: every fit is NaN, silently dropped
    ],
)
def test_infinite_values_raise(overrides: dict) -> None:
    with pytest.raises(ValidationError):
        Settings.load(**overrides)


def test_invalid_env_value_raises(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SRL_ACTOR__HORIZON", "1")
    with pytest.raises(ValidationError):
        Settings.load()


def test_start_state_heading_away_from_target() -> None:
    np.testing.assert_allclose(start_state((2.0, 2.0)), [2.0, 2.0, math.pi / 4], rtol=1e-15)
    np.testing.assert_allclose(start_state([-1.0, 0.0]), [-1.0, 0.0, math.pi], rtol=1e-15)
    np.testing.assert_allclose(start_state([0.0, -2.0]), [0.0, -2.0, -math.pi / 2], rtol=1e-15)
    np.testing.assert_allclose(start_state([0.0, 0.0]), [0.0, 0.0, math.pi], rtol=1e-15)
    np.testing.assert_array_equal(start_state([1.0, 2.0, 0.25]), [1.0, 2.0, 0.25])
    s = Settings.load(episode={"start": [-3.0, 3.0]})
    np.testing.assert_allclose(s.start_state(), [-3.0, 3.0, 3 * math.pi / 4], rtol=1e-15)


@pytest.mark.parametrize("bad", [(1.0,), (1.0, 2.0, 3.0, 4.0), (1.0, float("inf"))])
def test_start_state_rejects_bad(bad) -> None:
    with pytest.raises(ValueError):
        start_state(bad)


def test_parse_start() -> None:
    assert parse_start("1,2") == (1.0, 2.0)
    assert parse_start("-1.5, 2e-1, 3") == (-1.5, 0.2, 3.0)
    for bad in ("1,nan", "a,b", "", "1,inf"):
        with pytest.raises(ValueError):
            parse_start(bad)
    # how many numbers a start has is the system's: the robot's settings refuse what a cart-pole's take
    for count in (1, 4):
        start = parse_start(",".join(["0.1"] * count))
        with pytest.raises(ValidationError, match="X,Y or X,Y,ALPHA"):
            Settings.load(episode={"start": start})
    assert Settings.load(plant={"system": "cartpole"}, episode={"start": parse_start("0.1,0.1,0.1,0.1")})
    with pytest.raises(ValidationError, match=r"episode\.start: 4 numbers, cartpole's state"):
        Settings.load(plant={"system": "cartpole"}, episode={"start": parse_start("1,2")})


# -- the CLI ------------------------------------------------------------------------------
def test_cli_rejects_horizon_one(capsys: pytest.CaptureFixture[str]) -> None:
    from tools.cli import main

    assert main(["run", "--horizon", "1"]) == 2
    err = capsys.readouterr().err
    assert "horizon" in err
    assert "Traceback" not in err


def test_cli_config_file_and_flags(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from common.config.arguments import settings_from_args
    from tools.cli import build_parser

    user = tmp_path / "mine.toml"
    user.write_text('[actor]\nhorizon = 6\nagent = "rlq"\n\n[plant]\nv_max = 0.5\n')
    monkeypatch.setenv("SRL_ACTOR__AGENT", "mpc")
    args = build_parser().parse_args(["run", "--config", str(user), "--horizon", "4", "--start", "1,-1"])
    s = settings_from_args(args)
    assert s.actor.horizon == 4  # flag > file
    assert s.actor.agent == "mpc"  # env > file
    assert s.plant.v_max == 0.5  # file > packaged
    assert s.plant.omega_max == RAW["plant"]["omega_max"]
    np.testing.assert_allclose(s.start_state(), [1.0, -1.0, -math.pi / 4], rtol=1e-15)


def test_cli_rejects_infinite_duration(capsys: pytest.CaptureFixture[str]) -> None:
    from tools.cli import main

    assert main(["run", "--duration", "inf", "--no-jit"]) == 2
    capsys.readouterr()


def test_cli_rejects_bad_start(capsys: pytest.CaptureFixture[str]) -> None:
    from tools.cli import main

    with pytest.raises(SystemExit) as info:
        main(["run", "--start", "1,nan"])
    assert info.value.code == 2
    capsys.readouterr()


def test_cli_run_json_contract(capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    import common.config.assembly
    from tools.cli import main

    captured = []
    original = common.config.assembly.run_episode

    def spy(*args, **kwargs):
        episode = original(*args, **kwargs)
        captured.append(episode)
        return episode

    monkeypatch.setattr(common.config.assembly, "run_episode", spy)
    assert main(["run", "--agent", "mpc", "--duration", "1", "--json", "--no-jit"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    summary = json.loads(out[-1])
    for key in ("agent", "horizon", "steps", "accumulated_cost", "final_state", "solve_ms",
                "solver_failures", "settings"):  # fmt: skip
        assert key in summary, key
    assert set(summary["solve_ms"]) >= {"median", "p99", "max"}
    assert summary["agent"] == "mpc"
    assert summary["horizon"] == 12  # the robot's own (srl.toml: 0, the system's)
    assert summary["steps"] == 10
    assert summary["solver_failures"] == 0
    assert summary["settings"]["actor"]["agent"] == "mpc"
    assert summary["settings"]["episode"]["duration"] == 1.0
    cost = summary["accumulated_cost"]
    assert math.isfinite(cost) and cost > 0

    # recompute J = sum_k delta r(s_k, u_k) and the plant's states by hand
    (episode,) = captured
    states, actions = np.array(episode.states), np.array(episode.actions)
    assert states.shape == (11, 3) and actions.shape == (10, 2)
    x0, y0 = 2.0, 2.0  # srl.toml's start and R are [], the robot's own: (2, 2) heading away, (1, 10, 1, ...)
    np.testing.assert_allclose(states[0], [x0, y0, math.atan2(y0, x0)], rtol=1e-15)
    delta = RAW["plant"]["sampling_time"]
    r = np.array([1.0, 10.0, 1.0, 0.01, 0.01])
    chi = np.hstack([states[:-1], actions])
    assert cost == pytest.approx(float(np.sum(delta * (chi**2 @ r))), rel=1e-12)
    for k in range(10):
        x, y, a = states[k]
        v, w = actions[k]
        assert abs(v) <= RAW["plant"]["v_max"] and abs(w) <= RAW["plant"]["omega_max"]
        if w == 0.0:
            expected = [x + v * delta * math.cos(a), y + v * delta * math.sin(a), a]
        else:  # the textbook closed form of sample-and-hold integration
            expected = [
                x + v / w * (math.sin(a + w * delta) - math.sin(a)),
                y - v / w * (math.cos(a + w * delta) - math.cos(a)),
                a + w * delta,
            ]
        np.testing.assert_allclose(states[k + 1], expected, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(summary["final_state"], states[-1], rtol=1e-15)
    # the robot moved towards the target (the MPC does its job)
    assert np.hypot(*states[-1][:2]) < np.hypot(*states[0][:2])


def test_the_plant_models_are_one_table_that_the_settings_and_the_command_lines_read() -> None:
    """common.math.plant_models.PLANT_MODELS, one row per model: the settings accept exactly its
    names, and every command-line option that chooses a plant model offers exactly them."""
    import argparse

    from common.math.plant_models import BUILT_IN_PLANT_MODELS, PLANT_MODELS
    from tools.cli import build_parser

    assert tuple(PLANT_MODELS) == BUILT_IN_PLANT_MODELS == ("ideal", "actuator", "physics")
    for name in PLANT_MODELS:
        assert Settings.load(plant={"model": name}).plant.model == name
    with pytest.raises(ValidationError):
        Settings.load(plant={"model": "slipping"})  # the parking bench's own plant, not a model

    def choices(parser: argparse.ArgumentParser, path: str = "srl") -> dict[str, list[str]]:
        found: dict[str, list[str]] = {}
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    found |= choices(sub, f"{path} {name}")
            elif action.choices is not None and "actuator" in action.choices:  # srl up --plant is not a model
                found[f"{path} {action.option_strings}"] = list(action.choices)
        return found

    found = choices(build_parser())
    assert {"srl experiment ['--plant']", "srl tb3-emulator ['--model']"} <= set(found), found
    assert all(offered == list(PLANT_MODELS) for offered in found.values()), found


def test_a_horizon_of_zero_is_the_systems_own_and_a_named_one_wins(monkeypatch: pytest.MonkeyPatch) -> None:
    """``actor.horizon = 0`` (srl.toml's) is the row's N: the robot's 12, the dynamic robot's 20,
    whether the system comes from a flag or the environment; an N given anywhere wins, and 0 given
    anywhere is the system's own again. Every reader sees the N the run takes."""
    from common.math.systems import SYSTEMS

    assert SYSTEMS["unicycle"].horizon == 12 and SYSTEMS["dynamic_unicycle"].horizon == 20
    assert Settings.load().actor.horizon == 12
    assert Settings.load(plant={"system": "dynamic_unicycle"}).actor.horizon == 20
    assert Settings.load(plant={"system": "dynamic_unicycle"}, actor={"horizon": 6}).actor.horizon == 6
    monkeypatch.setenv("SRL_PLANT__SYSTEM", "dynamic_unicycle")
    assert Settings.load().actor.horizon == 20
    monkeypatch.setenv("SRL_ACTOR__HORIZON", "8")
    assert Settings.load().actor.horizon == 8
    assert Settings.load(actor={"horizon": 0}).actor.horizon == 20
    with pytest.raises(ValueError, match=r"the horizon N must be 2 \.\. 100"):
        Settings.load(actor={"horizon": 1})


def test_a_horizon_of_zero_in_a_section_given_as_its_model_is_the_systems_own_too() -> None:
    """A caller building ``Settings`` from sections passes models, not dicts: ``horizon = 0`` in an
    ``ActorSettings`` is the system's own N as it is in a file (it stayed 0 before)."""
    s = Settings.load(plant={"system": "dynamic_unicycle"})
    dumped = s.model_dump()
    built = Settings(**{**dumped, "actor": s.actor.model_copy(update={"horizon": 0}), "plant": s.plant})
    assert built.actor.horizon == 20
    robot = Settings.load()
    unnamed = robot.actor.model_copy(update={"horizon": 0})
    assert Settings(**{**robot.model_dump(), "actor": unnamed}).actor.horizon == 12
