"""``srl health`` / ``python -m tools.launch.health``: the containers' readiness checks.

Its fast path reads three transport settings itself (see tools/launch/health.py for why): the
oracle is :class:`common.config.settings.Settings` and :func:`common.contracts.keys.liveliness_key`.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from common.config.settings import Settings
from common.contracts.keys import liveliness_key
from tests.harness import ROOT, cluster, free_port
from tools.launch.health import ALIVE_KEY, transport_settings


@pytest.fixture(autouse=True)
def _clean_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in list(os.environ):
        if name.upper().startswith("SRL_TRANSPORT__") or name.upper() == "SRL_CONFIG":
            monkeypatch.delenv(name)


def _expected(config: Path | None = None, **transport: str) -> dict[str, object]:
    t = Settings.load(config, **({"transport": transport} if transport else {})).transport
    return {
        "router": t.router,
        "robot": t.robot,
        "multicast_scouting": t.multicast_scouting,
        "connect": list(t.connect),
        "secure": t.secure,
    }


def test_defaults_are_the_packaged_ones() -> None:
    assert transport_settings() == _expected()


@pytest.mark.parametrize(
    "environment",
    [
        {"SRL_TRANSPORT__ROUTER": "tcp/router:7447", "SRL_TRANSPORT__ROBOT": "tb3_7"},
        {"SRL_TRANSPORT__MULTICAST_SCOUTING": "false"},
        {"SRL_TRANSPORT__MULTICAST_SCOUTING": "True"},
        {"srl_transport__robot": "lower_case_name"},
        {"SRL_TRANSPORT__CONNECT": '["tcp/10.0.0.2:7447"]'},
        {"SRL_TRANSPORT__SECURE": "true", "SRL_TRANSPORT__USER": "monitor"},
    ],
)
def test_environment_overrides_as_settings_do(monkeypatch: pytest.MonkeyPatch, environment: dict[str, str]) -> None:
    for name, value in environment.items():
        monkeypatch.setenv(name, value)
    assert transport_settings() == _expected()


def test_config_file_then_environment_then_flags(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    config = tmp_path / "site.toml"
    config.write_text('[transport]\nrouter = "tcp/192.0.2.1:7447"\nrobot = "from_file"\n')
    assert transport_settings(config) == _expected(config)
    monkeypatch.setenv("SRL_CONFIG", str(config))
    assert transport_settings()["robot"] == "from_file" == _expected()["robot"]
    monkeypatch.setenv("SRL_TRANSPORT__ROBOT", "from_env")
    assert transport_settings() == _expected()
    flags = {"router": "tcp/127.0.0.1:9", "robot": "from_flag"}
    assert transport_settings(None, **flags) == _expected(None, **flags)


def test_bad_robot_id_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SRL_TRANSPORT__ROBOT", "a/b")
    with pytest.raises(ValueError, match="robot id"):
        transport_settings()


def test_client_config_is_zenoh_config_for_a_client(monkeypatch: pytest.MonkeyPatch) -> None:
    from common.net.transport import zenoh_config
    from tools.launch.health import client_config

    monkeypatch.setenv("SRL_TRANSPORT__CONNECT", '["tcp/127.0.0.1:7448"]')
    ours, theirs = client_config(transport_settings()), zenoh_config(Settings.load().transport)
    for key in ("mode", "scouting/multicast/enabled", "listen/endpoints", "connect/endpoints"):
        assert ours.get_json(key) == theirs.get_json(key), key


def test_secure_sessions_are_made_by_zenoh_config(monkeypatch: pytest.MonkeyPatch) -> None:
    from common.net.security import SecurityError
    from tools.launch.health import client_config

    monkeypatch.setenv("SRL_TRANSPORT__SECURE", "true")  # and no user: zenoh_config refuses
    with pytest.raises(SecurityError):
        client_config(transport_settings())


@pytest.mark.parametrize(("robot", "service"), [("tb3_0", "actor"), ("r-1", "robot_bridge"), ("X", "plant")])
def test_alive_key_is_the_liveliness_key(robot: str, service: str) -> None:
    assert ALIVE_KEY.format(robot=robot, service=service) == liveliness_key(robot, service)


def _health(*argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "tools.launch.health", *argv],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


@pytest.mark.integration
@pytest.mark.slow
def test_exit_codes_against_real_services() -> None:
    nobody = f"tcp/127.0.0.1:{free_port()}"
    down = _health("router", "--router", nobody, "--timeout", "0.3")
    assert down.returncode == 1 and down.stdout.startswith("unhealthy: router"), down
    with cluster(robot="hc") as c:
        c.start("critic", "critic")
        c.wait_alive("critic")
        args = ("--router", c.endpoint, "--robot", "hc")
        router = _health("router", *args)
        assert router.returncode == 0, router
        critic = _health("critic", *args)
        assert critic.returncode == 0 and "srl/hc/alive/critic" in critic.stdout, critic
        actor = _health("actor", *args, "--timeout", "0.5")
        assert actor.returncode == 1 and "srl/hc/alive/actor" in actor.stdout, actor
        other_robot = _health("critic", "--router", c.endpoint, "--robot", "other", "--timeout", "0.5")
        assert other_robot.returncode == 1, other_robot
        # the srl subcommand is the same check
        via_cli = subprocess.run(
            [sys.executable, "-m", "tools.cli", "health", "critic", *args],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        assert via_cli.returncode == 0, via_cli
        c.procs["critic"].stop()
        gone = _health("critic", *args, "--timeout", "0.5")
        assert gone.returncode == 1, gone
    bad = _health("a/b", "--router", nobody)
    assert bad.returncode == 2, bad
