"""A fleet's router is findable: ``srl up --robots`` listens where every other command looks by
default (transport.router) unless that port is taken or ``--router`` was given, prints its
endpoint at start, and ``srl record`` run exactly as it says records every robot of the fleet;
``srl up --robots K --record FILE`` records every robot itself.

Everything on loopback; every wait is bounded; every process is stopped by its pid.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from tests.harness import ROOT, free_port
from tools.recording.record import read_episodes

pytestmark = pytest.mark.integration

ROBOTS = ("robot1", "robot2")
START_LINE = "srl up: the fleet's router listens on "
UP_SECONDS = 240.0  # [s] start-up on a loaded 2-core machine, the 15 s run and the stop


def srl_argv(command: str) -> list[str]:
    """``srl ARGS`` as printed, run through this interpreter (``python -m tools.cli ARGS``)."""
    words = shlex.split(command)
    assert words[0] == "srl", command
    return [sys.executable, "-m", "tools.cli", *words[1:]]


def stop(process: subprocess.Popen[str], signum: int = signal.SIGINT, timeout: float = 20.0) -> None:
    """``signum`` to the process by its pid, SIGKILL after ``timeout``."""
    if process.poll() is None:
        os.kill(process.pid, signum)
        try:
            process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.kill(process.pid, signal.SIGKILL)
            process.wait(timeout=10)


def start_line(lines: list[str], process: subprocess.Popen[str], timeout: float = 60.0) -> str:
    """The fleet's first line, the one that says where its router listens."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = [line for line in lines if line.startswith(START_LINE)]
        if found:
            return found[0]
        assert process.poll() is None, "srl up ended before saying where its router listens:\n" + "\n".join(lines)
        time.sleep(0.05)
    raise AssertionError(f"no {START_LINE!r} line within {timeout:.0f} s:\n" + "\n".join(lines))


@pytest.mark.integration
@pytest.mark.timeout(UP_SECONDS + 180)
@pytest.mark.parametrize("default_port", ["free", "taken"])
def test_srl_record_beside_a_fleet_records_both_robots(tmp_path: Path, default_port: str) -> None:
    default = f"tcp/127.0.0.1:{free_port()}"  # this test's transport.router: never the machine's 7447
    env = {**os.environ, "SRL_TRANSPORT__ROUTER": default, "PYTHONUNBUFFERED": "1"}
    recording = tmp_path / "fleet.mcap"
    blocker = None
    if default_port == "taken":  # something else listens on the default: the fleet must go elsewhere
        blocker = socket.socket()
        blocker.bind(("127.0.0.1", int(default.rsplit(":", 1)[1])))
        blocker.listen()
    up: subprocess.Popen[str] | None = None
    record: subprocess.Popen[str] | None = None
    try:
        # 1. what srl up says to a user who asks a fleet for --view: the exact commands beside it
        hint = subprocess.run(
            [sys.executable, "-m", "tools.cli", "up", "--robots", "2", "--view"],
            cwd=ROOT, env=env, capture_output=True, text=True, timeout=60, check=False,
        )  # fmt: skip
        assert hint.returncode == 2, hint.stderr
        commands = re.findall(r"`([^`]+)`", hint.stderr)
        again = [c for c in commands if c.startswith("--router ")]
        assert bool(again) == (default_port == "taken"), hint.stderr
        told_record = next(c for c in commands if c.startswith("srl record "))
        assert ("--router" in told_record) == (default_port == "taken"), hint.stderr
        # 2. the fleet as the hint says, and its start line saying the same command
        up_argv = ["up", "--robots", "2", "--duration", "15", "--no-jit", *shlex.split(again[0] if again else "")]
        up = subprocess.Popen(
            [sys.executable, "-m", "tools.cli", *up_argv],
            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
        )  # fmt: skip
        lines: list[str] = []
        reader = threading.Thread(target=lambda: lines.extend(line.rstrip("\n") for line in up.stderr), daemon=True)
        reader.start()
        line = start_line(lines, up)
        endpoint = line[len(START_LINE) :].split(";", 1)[0]
        assert (endpoint == default) == (default_port == "free"), line
        said_record = next(c for c in re.findall(r"`([^`]+)`", line) if c.startswith("srl record "))
        assert said_record == told_record.replace(str(recording), "FILE.mcap")
        # 3. srl record beside it, exactly as said
        record = subprocess.Popen(
            srl_argv(said_record.replace("FILE.mcap", str(recording))),
            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
        )  # fmt: skip
        up.wait(timeout=UP_SECONDS)
        reader.join(timeout=10)
        assert up.returncode == 0, "\n".join(lines[-30:])
        stop(record)
        record_out, record_err = record.communicate(timeout=10)
        assert record.returncode in (0, 130), record_err[-2000:]
        episodes, _ = read_episodes(recording)
        assert set(ROBOTS) <= set(episodes), f"robots recorded: {sorted(episodes)}; {record_out} {record_err[-500:]}"
        assert all(episodes[robot].steps > 10 for robot in ROBOTS), {r: e.steps for r, e in episodes.items()}
    finally:
        for process in (record, up):
            if process is not None:
                stop(process)
        if blocker is not None:
            blocker.close()


@pytest.mark.integration
@pytest.mark.timeout(UP_SECONDS + 60)
def test_srl_up_fleet_records_every_robot_itself(tmp_path: Path) -> None:
    env = {**os.environ, "SRL_TRANSPORT__ROUTER": f"tcp/127.0.0.1:{free_port()}", "PYTHONUNBUFFERED": "1"}
    recording = tmp_path / "fleet.mcap"
    argv = ["up", "--robots", ",".join(ROBOTS), "--duration", "8", "--no-jit", "--record", str(recording), "--json"]
    up = subprocess.Popen(
        [sys.executable, "-m", "tools.cli", *argv],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
    )  # fmt: skip
    try:
        out, err = up.communicate(timeout=UP_SECONDS)
    finally:
        stop(up)
    assert up.returncode == 0, err[-3000:]
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["recording"] == str(recording)
    assert summary["recorder"] and summary["recorder"].startswith("srl record:"), summary.get("recorder")
    assert summary["exit_codes"]["recorder"] == 0
    episodes, _ = read_episodes(recording)
    assert set(episodes) == set(ROBOTS), sorted(episodes)
    assert all(episodes[robot].steps >= 60 for robot in ROBOTS), {r: e.steps for r, e in episodes.items()}
    # a bad path changes nothing: one line, exit 2, before anything starts
    bad = subprocess.run(
        [sys.executable, "-m", "tools.cli", *argv[:-2], str(tmp_path / "missing" / "x.mcap")],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1, bad.stderr
    assert "missing" in bad.stderr and not (tmp_path / "missing").exists(), bad.stderr
