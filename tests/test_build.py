"""``srl build``: actor problems compiled into the JIT cache ahead of the runs that need them."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from tests.harness import ROOT, srl, srl_as_from_a_terminal, wait_until


def objects(cache: Path) -> set[str]:
    return {p.name for p in cache.glob("*.o")}


@pytest.mark.integration
@pytest.mark.slow
def test_build_compiles_each_problem_once_and_a_run_then_finds_it(tmp_path: Path) -> None:
    """Two problems (mpc at N = 3, the robot's and the paper's method: the wheel box makes them two
    shapes) compiled into a fresh cache; again, nothing is added; a run of one of them compiles
    nothing (its objects' modification times are the cache's use marks, nothing new appears)."""
    cache = tmp_path / "jit"
    cache.mkdir(mode=0o700)
    env = {"SRL_ACTOR__JIT_CACHE": str(cache)}
    first = srl("build", "--agents", "mpc", "--horizons", "3", env=env, timeout=300)
    assert first.returncode == 0, first.stderr[-2000:]
    lines = [line for line in first.stdout.splitlines() if line.startswith("mpc")]
    assert len(lines) == 2 and {"(wheel box)" in line for line in lines} == {True, False}, first.stdout
    built = objects(cache)
    assert len(built) >= 4, built  # per problem: the solver, the merit and the argmin's tick
    assert f"{len(built)} compiled objects added to the JIT cache {cache}" in first.stdout

    again = srl("build", "--agents", "mpc", "--horizons", "3", env=env, timeout=300)
    assert again.returncode == 0, again.stderr[-2000:]
    assert "0 compiled objects added" in again.stdout and objects(cache) == built

    run = srl("run", "--agent", "mpc", "--horizon", "3", "--duration", "0.5", env=env, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert objects(cache) == built, "the run compiled a problem srl build had compiled"


@pytest.mark.integration
@pytest.mark.parametrize(
    ("argv", "env", "message"),
    [
        (["--agents", "mpc,nope"], {}, "--agents: unknown agent(s) nope"),
        (["--horizons", "1"], {}, "--horizons"),
        (["--methods", "robot,fast"], {}, "--methods: unknown method(s) fast"),
        (["--jobs", "-1"], {}, "--jobs must be >= 0"),
        ([], {"SRL_ACTOR__JIT_CACHE": "off"}, "actor.jit_cache is off"),
        ([], {"SRL_ACTOR__JIT": "false"}, "actor.jit is off"),
    ],
)
def test_build_refuses_what_it_cannot_do_in_one_line_and_compiles_nothing(
    argv: list[str], env: dict[str, str], message: str, tmp_path: Path
) -> None:
    cache = tmp_path / "jit"
    cache.mkdir(mode=0o700)
    result = srl("build", *argv, env={"SRL_ACTOR__JIT_CACHE": str(cache), **env})
    assert result.returncode == 2, (result.stdout, result.stderr)
    errors = [line for line in result.stderr.splitlines() if line.startswith("srl")]
    assert len(errors) == 1 and message in errors[0], result.stderr
    assert os.listdir(cache) == []


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.needs_compiler
def test_two_builds_of_one_problem_at_once_compile_each_source_once(tmp_path: Path) -> None:
    """Two ``srl build`` of the same problem started together on one cache: each generated source
    reaches the C compiler once (a compiler on PATH that logs each source it is given); the other
    process waits for its object. The control: the two builds together produce the objects one
    build alone does."""
    cache, bin_dir, log = tmp_path / "jit", tmp_path / "bin", tmp_path / "compiles.log"
    cache.mkdir(mode=0o700)
    bin_dir.mkdir()
    real = shutil.which("gcc") or shutil.which("cc")
    assert real is not None
    logger = bin_dir / "gcc"
    logger.write_text(
        f'#!/bin/sh\nfor a in "$@"; do case "$a" in *.c) echo "$a" >> "{log}";; esac; done\nexec {real} "$@"\n'
    )
    logger.chmod(0o755)
    env = {
        **os.environ,
        "SRL_ACTOR__JIT_CACHE": str(cache),
        "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}",
    }
    argv = [sys.executable, "-m", "tools.cli", "build", "--agents", "mpc", "--horizons", "3", "--methods", "robot"]
    runs = [
        subprocess.Popen(argv, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for _ in range(2)
    ]
    try:
        outputs = [run.communicate(timeout=300) for run in runs]
    finally:
        for run in runs:
            if run.poll() is None:
                run.kill()
                run.wait()
    assert [run.returncode for run in runs] == [0, 0], [err[-2000:] for _, err in outputs]
    compiled = log.read_text().splitlines()
    stored = objects(cache)
    assert len(stored) >= 2 and len(compiled) == len(stored), (compiled, stored)


def processes_with(marker: str) -> list[int]:
    """The pids whose environment holds ``marker`` (a test's own TMPDIR: srl, its workers, gcc)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            if marker.encode() in (entry / "environ").read_bytes().split(b"\0"):
                found.append(int(entry.name))
        except OSError:
            continue
    return found


@pytest.mark.integration
@pytest.mark.needs_compiler
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_signal_stops_the_build_at_once_and_leaves_nothing_behind(sig: signal.Signals, tmp_path: Path) -> None:
    """Three problems two at a time; the signal to srl alone once the first compile has begun: srl
    exits 128 + the signal within 30 s, the third problem never starts (nothing "ready"), and no
    process, build directory or compiled object of the run is left."""
    cache, scratch = tmp_path / "jit", tmp_path / "tmp"
    cache.mkdir(mode=0o700)
    scratch.mkdir()
    env = {**os.environ, "SRL_ACTOR__JIT_CACHE": str(cache), "TMPDIR": str(scratch)}
    argv = [sys.executable, "-m", "tools.cli", "build", "--agents", "mpc,rlq,rlqv", "--horizons", "12"]
    argv += ["--methods", "robot", "--jobs", "2"]
    run = srl_as_from_a_terminal(argv, env)
    try:
        wait_until(lambda: any(scratch.glob("srl-jit-*")), 120, "a JIT build directory")
        run.send_signal(sig)
        out, err = run.communicate(timeout=30)
    finally:
        if run.poll() is None:
            os.killpg(run.pid, signal.SIGKILL)
            run.wait()
    assert run.returncode == 128 + sig, (run.returncode, err[-2000:])
    assert "ready in" not in out, out
    marker = f"TMPDIR={scratch}"
    wait_until(lambda: not processes_with(marker), 15, "srl's workers and compilers gone")
    wait_until(lambda: not any(scratch.iterdir()), 15, f"nothing left in TMPDIR: {list(scratch.iterdir())}")
    assert not list(cache.glob("*.o")), "a compile finished after the signal"
