"""The command line "out of the box": negative numbers, help, refused options,
errors that name the cause and the fix, signals and pipes, bounds, checkpoints, status, plot.

Every process test runs the real ``srl`` as a user does (``python -m tools.cli``) on free
loopback ports, waits on what the process prints, bounds every wait and kills by pid.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from common.config.arguments import COMMAND_SETTINGS, child_argv
from common.config.settings import Settings
from common.contracts.messages import Transition
from common.net.security import write_credentials
from services.critic.service import CriticLearner, checkpoint_path, load_checkpoint
from tests.harness import ROOT, free_port, srl
from tools.cli import build_parser

CLI = [sys.executable, "-m", "tools.cli"]


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """Every (sub)command's parser by its words ("run", "bench actor", ...), nested ones too."""
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    found: dict[str, argparse.ArgumentParser] = {}
    for name, sub in action.choices.items():
        found[name] = sub
        if any(isinstance(a, argparse._SubParsersAction) for a in sub._actions):
            found.update({f"{name} {inner}": p for inner, p in _subparsers(sub).items()})
    return found


# -- point 5: negative numbers -------------------------------------------------------------
@pytest.mark.parametrize(
    ("argv", "name", "value"),
    [
        (["run", "--start", "-1.2,0.7"], "start", (-1.2, 0.7)),
        (["run", "--start=-1.2,0.7"], "start", (-1.2, 0.7)),
        (["run", "--start", "-1,-0.5,-3.1"], "start", (-1.0, -0.5, -3.1)),
        (["run", "--start", "-1e3,2E-1"], "start", (-1e3, 0.2)),
        (["up", "--start", "-0.5,-.5"], "start", (-0.5, -0.5)),
        (["tb3-emulator", "--initial-pose", "-1.5,-2,-0.3"], "initial_pose", (-1.5, -2.0, -0.3)),
        (["tb3-emulator", "--noise", "-0,0.01"], "noise", (0.0, 0.01)),
    ],
)
def test_negative_numbers_are_values_everywhere(argv: list[str], name: str, value: tuple[float, ...]) -> None:
    args = build_parser().parse_args(argv)
    assert getattr(args, name) == pytest.approx(value)


@pytest.mark.integration
def test_a_negative_start_runs_an_episode() -> None:
    done = srl("run", "--start", "-1.2,0.7", "--horizon", "4", "--duration", "0.3", "--no-jit", "--json")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout.splitlines()[-1])["start_state"][:2] == [-1.2, 0.7]


# -- point 10: help and refused options ----------------------------------------------------
def test_every_subcommand_has_a_description_and_every_option_its_default() -> None:
    parser = build_parser()
    top = parser.format_help()
    assert "``" not in top and "COMMAND" in top
    missing = []
    for name, sub in _subparsers(parser).items():
        assert sub.description, f"srl {name} has no description"
        for action in sub._actions:
            if not action.option_strings or isinstance(action, argparse._HelpAction):
                continue
            if action.nargs == 0:  # an on/off flag: off unless given, says its help
                assert action.help, f"srl {name} {action.option_strings[0]} has no help"
                continue
            if "default" not in (action.help or "").lower():
                missing.append(f"srl {name} {action.option_strings[0]}")
    assert not missing, f"options whose help shows no default: {missing}"


@pytest.mark.integration
@pytest.mark.parametrize(
    ("command", "flag"),
    [
        ("router", "--agent=mpc"),
        ("router", "--horizon=6"),
        ("critic", "--start=1,1"),
        ("plant-sim", "--solver=ipopt"),
        ("robot-bridge", "--duration=5"),
        ("bench actor", "--seconds=5"),
        ("bench actor", "--profile=ros2dds"),
        ("bench actor", "--router=tcp/127.0.0.1:1"),
        ("bench loop", "--agents=mpc"),
        ("bench bridge", "--critic-load"),
        ("bench parking", "--baseline-steps=3"),
    ],
)
def test_options_a_command_ignores_are_refused_in_one_line(command: str, flag: str) -> None:
    done = srl(*command.split(), flag, timeout=60)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "unrecognized arguments" in lines[0] and flag in lines[0], done.stderr


def test_children_get_only_the_flags_their_command_takes() -> None:
    given = [
        "--config=c.toml",
        "--system=unicycle",
        "--agent=mpc",
        "--horizon=6",
        "--solver=ipopt",
        "--predictor=rk4",
        "--start=-1.0,1.0",
        "--duration=5.0",
        "--router=tcp/127.0.0.1:1",
        "--robot=r",
        "--no-jit",
        "--resume",
    ]
    parser = build_parser()
    for command, takes in COMMAND_SETTINGS.items():
        if command.startswith("bench "):  # never a child of srl up: its parser takes what it lists
            words = command.split()
            parser.parse_args([*words, *(a for a in given if a.split("=")[0][2:].replace("-", "_") in takes)])
            continue
        argv = child_argv([command, *given])
        assert {a.split("=")[0][2:].replace("-", "_") for a in argv[1:]} == set(takes) - {"resume"} | (
            {"resume"} & set(takes)
        ), command
        parser.parse_args(argv)  # accepted as a whole


# -- point 9 / 6: errors that name the cause and the fix ----------------------------------
@pytest.mark.integration
def test_settings_errors_name_the_file_the_variable_and_the_bound(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[actor]\nhorizon = [\n")
    cases = [
        (srl("run", "--config", str(bad)), [str(bad), "TOML syntax error"]),
        (srl("run", env={"SRL_ACTOR__HORIZON": "foo"}), ["actor.horizon", "SRL_ACTOR__HORIZON", "'foo'"]),
        (srl("run", "--router", "garbage"), ["transport.router", "tcp/127.0.0.1:7447", "'garbage'"]),
        (srl("critic", "--router", "garbage"), ["transport.router"]),
        (srl("run", "--horizon", "10000"), ["actor.horizon", "2 .. 100", "10000"]),
        (srl("run", "--start", "1e9,0"), ["episode.start", "10000 m"]),
    ]
    for done, expected in cases:
        assert done.returncode == 2, done.stderr
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1, done.stderr
        assert all(e in lines[0] for e in expected), (expected, lines[0])
        assert "Json5Err" not in done.stderr and "Traceback" not in done.stderr


@pytest.mark.integration
def test_a_start_far_outside_the_workspace_warns_once() -> None:
    done = srl("run", "--start", "20,0", "--horizon", "4", "--duration", "0.2", "--no-jit")
    assert done.returncode == 0, done.stderr
    assert done.stderr.count("more than 10 m from the target") == 1


def test_a_readable_password_file_warns_once(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    from common.net.security import client_credentials

    password = tmp_path / "pw"
    password.write_text("secret\n")
    password.chmod(0o644)
    transport = Settings.load(transport={"user": "critic", "password_file": str(password)}).transport
    with caplog.at_level(logging.WARNING, logger="common.net.security"):
        for _ in range(150):  # as a client retrying its login every 200 ms for 30 s
            assert client_credentials(transport) == ("critic", "secret")
    warnings = [r for r in caplog.records if "readable by others" in r.getMessage()]
    print(f"\nfigures: 150 logins with a 0644 password file: {len(warnings)} warning(s) (before: 150)")
    assert len(warnings) == 1


@pytest.mark.integration
def test_router_unreachable_and_wrong_password_are_told_apart(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    started = time.monotonic()
    unreachable = srl("critic", "--router", endpoint, "--connect-timeout", "2")
    unreachable_s = time.monotonic() - started
    lines = unreachable.stderr.strip().splitlines()
    assert unreachable.returncode == 2
    assert "waiting for the Zenoh router at " + endpoint in lines[0]  # said at once, before the timeout
    assert f"cannot reach the Zenoh router at {endpoint} after 2 s (is `srl router` running?" in lines[-1]
    assert ".rs:" not in unreachable.stderr and "Traceback" not in unreachable.stderr

    credentials = write_credentials(tmp_path / "secure")
    router = subprocess.Popen(
        [*CLI, "router", "--router", endpoint],
        cwd=ROOT,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,
        env={**os.environ, **credentials.router_environment()},
    )
    try:
        wrong = tmp_path / "wrong"
        wrong.write_text("not-the-password\n")
        wrong.chmod(0o600)
        started = time.monotonic()
        refused = srl(
            "critic",
            "--router",
            endpoint,
            env={**credentials.role_environment("critic"), "SRL_TRANSPORT__PASSWORD_FILE": str(wrong)},
        )
        refused_s = time.monotonic() - started
    finally:
        os.killpg(router.pid, signal.SIGKILL)
        router.wait(timeout=10)
    assert refused.returncode == 2
    last = refused.stderr.strip().splitlines()[-1]
    assert f"the router at {endpoint} refused the login of user 'critic': wrong password" in last, refused.stderr
    assert refused_s < 15, f"the refusal took {refused_s:.1f} s"  # not the 30 s connect timeout
    print(
        f"\nfigures: unreachable router reported after {unreachable_s:.1f} s (timeout 2 s), "
        f"wrong password reported after {refused_s:.1f} s (before: 33 s, as 'cannot reach')"
    )


# -- point 7: signals and pipes during srl run ---------------------------------------------
def _start_run(*extra: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [*CLI, "--log-level", "INFO", "run", "--horizon", "6", "--no-jit", *extra],
        cwd=ROOT,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )


def _wait_for_line(stream: object, needle: str, timeout: float) -> list[str]:
    seen: list[str] = []
    done = threading.Event()

    def read() -> None:
        for line in stream:  # type: ignore[attr-defined]
            seen.append(line)
            if needle in line:
                done.set()
                return

    threading.Thread(target=read, daemon=True).start()
    assert done.wait(timeout), f"no {needle!r} within {timeout} s: {seen[-5:]}"
    return seen


@pytest.mark.integration
@pytest.mark.parametrize(("signum", "code"), [(signal.SIGINT, 130)] * 5 + [(signal.SIGTERM, 143)])
def test_a_signal_during_srl_run_ends_it_in_one_line(signum: int, code: int, tmp_path: Path) -> None:
    # 6000 steps, every one solved: without the arrival rule (the paper's actor) the robot never
    # rests, so neither the solves nor the critic's fits stop (a parked robot's steps take microseconds)
    paper = tmp_path / "paper.toml"
    paper.write_text("[actor]\narrival = false\n")
    process = _start_run("--duration", "600", "--config", str(paper))
    try:
        _wait_for_line(process.stderr, "episode started", 60)
        time.sleep(random.uniform(0.0, 1.0))
        os.killpg(process.pid, signum)  # as a terminal does: the whole process group
        _, err = process.communicate(timeout=30)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    assert process.returncode == code, err
    assert "Traceback" not in err and "SystemError" not in err
    assert err.strip().splitlines() == [f"srl: interrupted ({signal.Signals(signum).name}): stopped"]


@pytest.mark.integration
def test_a_closed_pipe_ends_srl_run_quietly() -> None:
    read, write = os.pipe()
    os.close(read)  # `srl run | head` once head has gone
    done = subprocess.run(
        [*CLI, "run", "--horizon", "4", "--duration", "0.3", "--no-jit"],
        cwd=ROOT,
        stdout=write,
        stderr=subprocess.PIPE,
        text=True,
        timeout=120,
        check=False,
    )
    os.close(write)
    assert done.returncode == 141, done.stderr
    assert done.stderr == ""


# -- point 6: the horizon's JIT build ends promptly on a signal, leaving nothing -----------
def _running(pid: int) -> bool:
    """Alive and not a zombie (a killed process whose parent has not reaped it yet holds nothing)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


def _build_processes(owner: int) -> list[int]:
    """Processes of srl ``owner``'s JIT build (the wrapper, gcc, cc1, as): they carry its pid."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            environ = (entry / "environ").read_bytes()
        except OSError:
            continue
        if f"SRL_JIT_OWNER={owner}".encode() in environ.split(b"\0"):
            found.append(int(entry.name))
    return found


def _cmdline(pid: int) -> bytes:
    """A process's command line; empty once it has ended (it may end between listing and reading:
    a short-lived gcc child raised ProcessLookupError here once)."""
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return b""


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.needs_compiler
@pytest.mark.parametrize(
    ("signum", "group", "code"), [(signal.SIGTERM, False, 143), (signal.SIGINT, True, 130), (signal.SIGINT, False, 130)]
)
def test_a_signal_during_the_jit_build_kills_the_compiler_and_removes_its_directory(
    tmp_path: Path, signum: int, group: bool, code: int
) -> None:
    env = {**os.environ, "TMPDIR": str(tmp_path), "SRL_ACTOR__JIT_CACHE": "off"}  # gcc runs: nothing cached
    process = subprocess.Popen(
        [*CLI, "run", "--horizon", "60", "--duration", "1"],
        cwd=ROOT,
        text=True,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )
    try:
        _wait_for_line(process.stderr, "building the actor problem (N = 60", 60)
        deadline = time.monotonic() + 120
        while not any(b"cc1" in _cmdline(p) for p in _build_processes(process.pid)):
            assert time.monotonic() < deadline and process.poll() is None, "gcc never started"
            time.sleep(0.1)
        compilers = _build_processes(process.pid)
        assert list(tmp_path.glob("srl-jit-*")), "no build directory"
        sent = time.monotonic()
        if group:
            os.killpg(process.pid, signum)  # Ctrl-C at a terminal
        else:
            os.kill(process.pid, signum)  # docker stop, systemd, kill
        _, err = process.communicate(timeout=30)  # its stderr's end: no compiler holds it any more
        ended = time.monotonic() - sent
        deadline = time.monotonic() + 1
        while any(_running(p) for p in compilers) and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    left = [p for p in compilers if _running(p)]
    print(
        f"\nfigures: {signal.Signals(signum).name} during gcc at N = 60: srl ended after {ended:.2f} s "
        f"(exit {process.returncode}), {len(compilers)} compiler processes, {len(left)} left, "
        f"build directories left {len(list(tmp_path.glob('srl-jit-*')))} (before: gcc orphaned, directory left)"
    )
    assert process.returncode == code, err
    assert ended < 10
    assert not left
    assert not list(tmp_path.glob("srl-jit-*"))
    assert "Traceback" not in err


# -- point 11: checkpoints ------------------------------------------------------------------
def _transitions(episode: int, steps: range, robot: str = "r1") -> list[Transition]:
    return [
        Transition(
            robot=robot,
            episode=episode,
            step=k,
            state=(1.0 - 0.01 * k, 0.5, 0.1),
            action=(0.1, -0.2),
            cost=0.1 * (1.0 - 0.01 * k),
        )
        for k in steps
    ]


def test_checkpoint_path_is_per_robot_and_stack() -> None:
    import tomllib

    from common.config.settings import DEFAULT_CONFIG

    default = tomllib.loads(DEFAULT_CONFIG.read_text())["critic"]["checkpoint"]  # not the test's own
    settings = Settings.load(
        critic={"checkpoint": default}, actor={"agent": "rlqv+", "horizon": 6}, transport={"robot": "tb3_7"}
    )
    path = checkpoint_path(settings)
    assert path is not None and path.name == "critic-tb3_7-rlqv+-N6.json"


def test_a_new_run_starts_fresh_and_a_crash_in_the_same_run_continues(tmp_path: Path) -> None:
    settings = Settings.load()
    path = tmp_path / "critic.json"
    first = CriticLearner(settings)
    for t in _transitions(1, range(20)):
        first.on_transition(t)
    from common.system.checkpoint import atomic_write_json

    atomic_write_json(path, first.state())

    # a later run (new episode): fresh initial weights, "restored" false
    later = CriticLearner(settings)
    assert load_checkpoint(later, path)
    assert later.confirm(_transitions(2, range(1))[0]) is None
    later.on_transition(_transitions(2, range(1))[0])
    np.testing.assert_array_equal(later.learners["r1"].critic.q_weights, settings.initial_q_weights())
    assert later.restored is False

    # the same run after a crash: the checkpointed learner continues, its weights re-published
    again = CriticLearner(settings)
    assert load_checkpoint(again, path)
    republished = again.confirm(_transitions(1, range(20, 21))[0])
    assert republished is not None and republished.q_weights == tuple(first.learners["r1"].critic.q_weights)
    assert again.restored is True

    # --resume: a new run starts from the checkpoint's weights
    resumed = CriticLearner(Settings.load(critic={"resume": True}))
    assert load_checkpoint(resumed, path)
    resumed.confirm(_transitions(2, range(1))[0])
    resumed.on_transition(_transitions(2, range(1))[0])
    np.testing.assert_array_equal(resumed.learners["r1"].critic.q_weights, first.learners["r1"].critic.q_weights)
    assert resumed.restored is True


# -- points 8 and 11: srl up's status line, summaries and checkpoints -----------------------
@pytest.mark.timing
@pytest.mark.integration
@pytest.mark.slow
def test_srl_up_shows_a_status_line_keeps_json_off_the_console_and_starts_a_fresh_critic(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    runs = []
    # `srl status`: the same line from any running system (a monitor session), e.g. the containers
    watcher = subprocess.Popen(
        [*CLI, "status", "--router", endpoint, "--robot", "h5up", "--seconds", "20", "--connect-timeout", "60"],
        cwd=ROOT,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )
    for extra in ([], [], ["--resume", "--json"]):
        summaries = tmp_path / f"run{len(runs)}"
        done = srl(
            "up",
            "--router",
            endpoint,
            "--robot",
            "h5up",
            "--duration",
            "4",
            "--summary-dir",
            str(summaries),
            *extra,
            timeout=180,
        )
        assert done.returncode == 0, done.stderr[-3000:]
        runs.append((done, summaries))
        if watcher.poll() is None and len(runs) == 1:
            os.killpg(watcher.pid, signal.SIGINT)
    try:
        watched, watcher_err = watcher.communicate(timeout=30)
    finally:
        if watcher.poll() is None:
            os.killpg(watcher.pid, signal.SIGKILL)
            watcher.wait()
    assert watcher.returncode in (0, 130), watcher_err
    assert len([line for line in watched.splitlines() if line.startswith("h5up ") and ": step " in line]) >= 2
    first, second, resumed = runs
    status = [line for line in first[0].stderr.splitlines() if line.startswith("srl up ") and ": step " in line]
    assert len(status) >= 2, first[0].stderr
    assert all(
        " distance " in line and " J " in line and " weights " in line and " missed deadlines " in line
        for line in status
    )
    assert "{" not in first[0].stdout and len(first[0].stderr) < 4000, "JSON on the console"
    assert not [line for line in first[0].stderr.splitlines() if " WARNING " in line], first[0].stderr
    for _done, summaries in runs:
        assert {"actor.json", "critic.json", "plant.json", "router.json", "summary.json"} <= {
            p.name for p in summaries.iterdir()
        }
    critic = json.loads((first[1] / "critic.json").read_text())
    assert "replay" in critic  # kept in the file, for whoever needs it
    assert "(fresh critic; --resume to restore)" in second[0].stdout  # not "restored" by an earlier run
    assert json.loads((second[1] / "critic.json").read_text())["restored"] is False
    merged = json.loads(resumed[0].stdout.splitlines()[-1])
    assert merged["critic"]["restored"] is True
    # one summary whatever the size: the robot's own figures at the top, beside them the per-robot
    # table and the run's CPU that a fleet's summary has (tools/launch/up.py run_summary)
    assert merged["robots"] == ["h5up"] and [row["robot"] for row in merged["fleet"]["rows"]] == ["h5up"]
    assert merged["fleet"]["steps"] == merged["steps"] and merged["cpu_percent"] > 0 and merged["processes"] == 4
    assert merged["plant_model"] == "ideal" and "(plant ideal: the states above" in first[0].stdout  # the model's name
    assert merged["critic"]["checkpoint"].endswith("critic-h5up.json") or "h5up" in merged["critic"]["checkpoint"]
    print(
        f"\nfigures: srl up --duration 4: {len(status)} status lines, stdout {len(first[0].stdout)} B, "
        f"stderr {len(first[0].stderr)} B (before: 9 KB of JSON); second run restored "
        f"{json.loads((second[1] / 'critic.json').read_text())['restored']} (before: true)"
    )


# -- point 13: the plot ---------------------------------------------------------------------
def test_the_plot_records_and_shows_the_learning(tmp_path: Path) -> None:
    from common.config.assembly import run_episode
    from tools.recording.plots import plot_episode

    settings = Settings.load(actor={"horizon": 4, "jit": False}, episode={"duration": 2.0, "start": (-1.2, 0.7)})
    episode = run_episode(settings)
    assert len(episode.q_weights) == len(episode.v_weights) == len(episode.td_residuals) == episode.steps
    assert np.isfinite(np.array(episode.td_residuals)[1:]).all()  # a fit after every step but the first
    path = tmp_path / "run.png"
    plot_episode(episode, settings.plant.sampling_time, path)
    assert path.stat().st_size > 20_000


def test_the_path_plot_keeps_its_arrows_in_the_axes_and_the_end_above_the_target() -> None:
    """Point 13: the end marker used to hide under the target star, and the heading arrows ran
    out of the axes."""
    import matplotlib.pyplot as plt

    from tools.recording.plots import plot_path

    # a run that ends on the target, heading outward, with a long last arrow
    t = np.linspace(0.0, 1.0, 60)
    states = np.column_stack([2.0 * (1 - t), 2.0 * (1 - t) ** 2, np.full_like(t, np.pi / 4)])
    fig, ax = plt.subplots()
    try:
        plot_path(ax, states)
        (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
        arrows = ax.collections[0]  # the quiver
        tips = arrows.get_offsets() + np.column_stack([arrows.U, arrows.V])
        assert (tips[:, 0] >= x0).all() and (tips[:, 0] <= x1).all()
        assert (tips[:, 1] >= y0).all() and (tips[:, 1] <= y1).all()
        markers = {line.get_label().split(" ")[0]: line for line in ax.get_lines()}
        assert markers["end"].get_zorder() > markers["target"].get_zorder()
        assert markers["end"].get_markerfacecolor() == "none"  # hollow: the target shows through
    finally:
        plt.close(fig)


# -- point 8: log levels that mean something; point 9: no Rust internals --------------------
@pytest.mark.integration
def test_the_router_says_it_listens_on_stdout_and_a_taken_port_in_one_line() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = subprocess.Popen(
        [*CLI, "router", "--router", endpoint],
        cwd=ROOT,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )
    try:
        lines = _wait_for_line(router.stdout, "router listening on " + endpoint, 60)
        taken = srl("router", "--router", endpoint, timeout=60)
    finally:
        os.killpg(router.pid, signal.SIGINT)
        _, err = router.communicate(timeout=30)
    assert lines[-1].startswith("srl router: router listening on")
    assert err == "", "a normal start logged on stderr"
    assert taken.returncode == 2
    assert taken.stderr.strip().splitlines() == [taken.stderr.strip()]
    assert "Address already in use" in taken.stderr and ".rs:" not in taken.stderr and "--router" in taken.stderr


@pytest.mark.integration
def test_an_srl_process_runs_one_openblas_thread_unless_the_user_sets_more() -> None:
    # tools/__init__.py: importing srl's tools before numpy and scipy load OpenBLAS leaves the
    # process its main thread alone (an OpenBLAS worker spins on a core after each call); a user's
    # OPENBLAS_NUM_THREADS wins, and with 2 each OpenBLAS starts a worker (the negative control,
    # on a machine of more than one core).
    probe = (
        "import os, tools.cli, numpy, scipy.linalg; "
        "print(os.environ['OPENBLAS_NUM_THREADS'], len(os.listdir('/proc/self/task')))"
    )
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    default = subprocess.run(
        [sys.executable, "-c", probe], env=env, cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert default.returncode == 0, default.stderr
    assert default.stdout.split() == ["1", "1"], default.stdout
    env["OPENBLAS_NUM_THREADS"] = "2"
    chosen = subprocess.run(
        [sys.executable, "-c", probe], env=env, cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert chosen.returncode == 0, chosen.stderr
    value, threads = chosen.stdout.split()
    assert value == "2"
    if (os.cpu_count() or 1) > 1:
        assert int(threads) > 1, chosen.stdout
