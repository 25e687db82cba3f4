"""What ``srl up --plant`` starts is a row of tools/launch/plants.py ``LAUNCH_PLANTS``: the command
line offers the rows, the launchers read the row (not the name), and a row's model reaches every
child through the environment."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from common.config.settings import Settings
from tools.cli import build_parser
from tools.launch import plants
from tools.launch.plants import LAUNCH_PLANTS, LaunchPlant, launch_plant, with_launch_plant
from tools.launch.up import UpOptions, run_up


def test_the_command_line_offers_every_row_and_refuses_another(capsys: pytest.CaptureFixture[str]) -> None:
    parser = build_parser()
    for name in LAUNCH_PLANTS:
        assert parser.parse_args(["up", "--plant", name]).plant == name
    with pytest.raises(SystemExit):
        parser.parse_args(["up", "--plant", "gazebo"])
    assert "invalid choice: 'gazebo'" in capsys.readouterr().err
    with pytest.raises(ValueError, match=r"unknown plant 'gazebo' \(sim, physics, robot\)"):
        launch_plant("gazebo")


def test_a_rows_model_goes_to_every_child_and_to_this_process() -> None:
    settings = Settings.load()
    env: dict[str, str] = {}
    physics = with_launch_plant(settings, env, "physics")
    assert physics.plant.model == "physics" and env == {"SRL_PLANT__MODEL": "physics"}
    for name, row in LAUNCH_PLANTS.items():  # a row without a model leaves the settings' own
        if row.model is None:
            untouched: dict[str, str] = {}
            assert with_launch_plant(settings, untouched, name) is settings and untouched == {}


class StartedError(Exception):
    """The launcher got past its checks and would start processes now."""


def test_lockstep_is_refused_for_every_plant_behind_the_bridge(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    def no_processes(*args: object, **kwargs: object) -> None:
        raise StartedError

    monkeypatch.setattr("tools.launch.up.Supervisor", no_processes)
    # a row of the test's own: the launcher reads behind_bridge, not the name "robot"
    monkeypatch.setitem(plants.LAUNCH_PLANTS, "rosbot", LaunchPlant("a robot of the test", behind_bridge=True))
    settings = Settings.load()
    for name in ("robot", "rosbot"):
        with pytest.raises(ValueError, match="runs in real time only"):
            run_up(settings, UpOptions(settings_args=[], mode="lockstep", plant=name, duration=1.0))
    # negative controls: a simulator in lockstep, and a robot in real time, get past the checks
    for name, mode in (("sim", "lockstep"), ("rosbot", "realtime")):
        with pytest.raises(StartedError):
            run_up(settings, UpOptions(settings_args=[], mode=mode, plant=name, duration=1.0))
    # a name no row has: one line, before anything starts
    with pytest.raises(ValueError, match="unknown plant 'nowhere'"):
        run_up(settings, UpOptions(settings_args=[], mode="realtime", plant="nowhere", duration=1.0))
    with pytest.raises(ValueError, match="unknown plant 'nowhere'"):
        run_up(settings, UpOptions([], duration=1.0, robots=["r1"], plant="nowhere", summary_dir=tmp_path))


def test_the_plant_host_sends_states_as_its_actors_read_them_and_every_state_tick_to_a_live_view(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """srl up's plant host sends a robot's state just before its actor's tick (transport.state_sync),
    one robot as a fleet's; with --view, every state tick (the view draws them), unless the user's
    environment names state_sync (every child inherits it). What the children are given is what
    their settings read."""
    from tools.launch.up import run_environment

    def state_sync(options: UpOptions) -> bool:
        env = run_environment(options)
        with monkeypatch.context() as child:
            for name in [name for name in os.environ if name.startswith("SRL_")]:
                child.delenv(name)
            for name, value in env.items():
                if name.startswith("SRL_"):
                    child.setenv(name, value)
            return Settings.load().transport.state_sync

    monkeypatch.delenv("SRL_TRANSPORT__STATE_SYNC", raising=False)
    assert state_sync(UpOptions([]))  # the settings' sync, one robot
    assert state_sync(UpOptions([], robots=["a", "b"]))  # and a fleet
    assert not state_sync(UpOptions([], view_port=8765))
    assert not state_sync(UpOptions([], robots=["a", "b"], view_port=8765))
    monkeypatch.setenv("SRL_TRANSPORT__STATE_SYNC", "true")
    assert state_sync(UpOptions([], view_port=8765))  # the user's word wins
