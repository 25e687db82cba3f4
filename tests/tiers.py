"""The test tiers, the guard that keeps them honest, and the runner of the whole suite.

Markers (registered in pyproject.toml; docs/development.md):

* ``integration``: the test starts a process (the ``srl`` command, a service, a router, the C
  compiler of the actor's JIT build) or opens a socket or a Zenoh session. A test WITHOUT this
  marker may do none of these: the guard below fails it, in every run and naming what it started,
  so a new test is checked by default and the marker can never be missing.
* ``slow``: seconds of CPU in the test's own process (closed-loop episodes, benchmarks in miniature).
* ``timing``: asserts a real-time bound (0 missed deadlines, a latency or period bound, steps done
  within a wall-clock run). These run after everything else, among themselves only: a CPU-bound
  test on the same cores would make them fail for want of CPU, not for a bug.

``pytest --fast`` (``./srl test --fast``): only the tests carrying none of the three markers: no
process, no socket, seconds in all; the edit-test loop. Under ``--fast`` the guard also fails a test
whose code started a process behind Python's back (C's ``system()``): the children's resource usage
of the test process grew.

``python -m tests.tiers`` (``./srl test`` without arguments): the whole suite in phases.
Phase 1 runs every test not marked ``timing`` on ``SRL_TEST_WORKERS`` (default :data:`WORKERS`)
parallel pytest-xdist workers (``--dist worksteal``: each worker starts on a run of whole files, in
order, and a worker that runs out takes tests from another's queue, so the long files of
real-time runs do not leave workers idle). Phase 2 runs the ``timing`` tests one at a time
(:data:`TIMING_WORKERS`): each asserts a real-time bound (deadlines, a stop within a watchdog's
timeout, steps across a router restart) that holds on a quiet machine, and a fleet's timing test
alone takes most of a core. Side by side they broke their bounds in CI: four at a time, three of
them in one run (a deadline, a stop 0.13 s late, 49 of 60 steps after a router restart); two at a
time, once the bridge's watchdog stop (0.443 s against 0.41 s) and once the three-host fleet's
deadlines (2-4 missed per robot against 2, at load 4.3 on 2 cores). One at a time costs about three
minutes more. ``SRL_TEST_TIMING_WORKERS=2`` runs them two at a time on a quicker machine; the tests
marked ``alone`` too (the two above) then run after the others, one at a time, in a third phase.
The last line counts every phase as pytest does; the exit code is non-zero if any phase failed.
Stopped (Ctrl-C, SIGTERM, SIGHUP), the runner sends SIGINT to its pytest's process group (the
tests' teardowns run, as after a Ctrl-C) and removes its directories (``srl-test-PID-*`` in the
temporary directory: the JIT cache, each phase's scratch); a runner killed with SIGKILL leaves
them, and the next run removes them.
Before phase 1 the runner compiles the documented commands' actor problems into the run's JIT cache
(:data:`WARM_PROBLEMS`). After each phase the runner prints its total CPU (tests' processes and
their children: services, ``srl`` commands, the C compiler) and the tests that took the most: on a
machine of two cores the suite's time is its CPU over the cores.

Every test has a time limit (pytest-timeout, ``timeout`` in pyproject.toml; a longer one with
``@pytest.mark.timeout(SECONDS)``): past it the test fails with its stack. A test stuck where
Python's signal handler cannot run (inside C code) is ended :data:`BACKSTOP_S` later by
``faulthandler``, which prints every thread's stack and ends the test process (pytest-xdist then
names the test it was running).
"""

from __future__ import annotations

import faulthandler
import json
import os
import resource
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

from common.system.jit import remove_orphan_build_directories
from common.system.lifeline import stop_group

WORKERS = 4  # two cores: the parallel phase's tests mostly wait on processes and real-time runs
TIMING_WORKERS = 1  # the timing tests one at a time: their bounds assume a quiet machine
RT_PRIORITY = 10  # actor.realtime_priority in common/config/srl.toml
BACKSTOP_S = 60  # past a test's timeout: faulthandler ends a test stuck in C code
TALLY = "SRL_TEST_TALLY"  # where a session writes its counts for the runner (main)
JIT_CACHE = "SRL_TEST_JIT_CACHE"  # the runner's JIT cache, shared by every phase (tests/conftest.py)
CPU_LOG = "SRL_TEST_CPU_LOG"  # a directory where each test process writes its tests' CPU seconds (the runner's table)
CPU_TABLE_ROWS = 15
SCRATCH_PREFIX = "srl-test-"  # + the runner's pid + "-": its JIT cache and each phase's scratch directory
STOP_GRACE_S = 30.0  # a stopped runner's pytest: its teardowns after SIGINT, then SIGKILL
# The actor problems compiled into the run's JIT cache before phase 1 (srl build): those that the
# documented commands and the tests of whole runs build (srl run and srl up: the robot's method at
# N = 12; srl experiment: the paper's at 6 and 12), each under a time limit (a docs block's 120 s)
# and otherwise compiled beside three other workers' tests (N = 12: 15-25 s of one core alone, 40-70
# s there). A problem missing here is compiled by the first test that needs it, once.
WARM_PROBLEMS = (
    ("build", "--agents", "mpc,rlq,rlqv", "--horizons", "12", "--methods", "robot"),
    ("build", "--agents", "mpc,rlq,rlqv", "--horizons", "6,12", "--methods", "paper"),
)
TIER_MARKERS = ("integration", "slow", "timing")
FAST_HINT = (
    "a test without the `integration` marker may start no process and open no socket or Zenoh "
    "session (tests/tiers.py; ./srl test --fast runs only such tests): mark it "
    "@pytest.mark.integration, or the whole file with pytestmark"
)


class NotInFastTierError(RuntimeError):
    """An unmarked test started a process or opened a socket (see :data:`FAST_HINT`)."""


class Guard:
    """Refuses processes, sockets and Zenoh sessions while an unmarked test runs."""

    def __init__(self) -> None:
        self.nodeid: str | None = None
        self.found: list[str] = []

    def check(self, what: str) -> None:
        if self.nodeid is None:
            return
        self.found.append(what)
        raise NotInFastTierError(f"{self.nodeid} {what}; {FAST_HINT}")

    @contextmanager
    def watching(self, item: pytest.Item, strict: bool) -> Iterator[None]:
        if item.get_closest_marker("integration") is not None:
            yield
            return
        self.nodeid, self.found = item.nodeid, []
        children = _children_usage() if strict else None
        try:
            yield
        except (NotInFastTierError, KeyboardInterrupt):
            raise  # its message says it all
        except BaseException:
            self._report(item, children)  # a refusal the code under test caught may be why it failed
            raise
        else:
            self._report(item, children)
        finally:
            self.nodeid = None

    def _report(self, item: pytest.Item, children: tuple[int, float] | None) -> None:
        self.nodeid = None
        found = list(dict.fromkeys(self.found))
        if children is not None and _children_usage() != children:
            found.append("ran a child process (one that Python did not start: C code's system() or fork)")
        if children is not None and _living_children():
            found.append(f"left child processes running: {_living_children()}")
        if found:
            pytest.fail(f"{item.nodeid} {'; '.join(found)}; {FAST_HINT}", pytrace=False)


def _children_usage() -> tuple[int, float]:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_minflt, usage.ru_utime + usage.ru_stime


def _living_children() -> list[int]:
    found: list[int] = []
    for task in Path(f"/proc/{os.getpid()}/task").glob("*/children"):
        try:
            found += [int(pid) for pid in task.read_text().split()]
        except OSError:
            continue
    return found


GUARD = Guard()


def _wrap(owner: Any, name: str, what: Callable[..., str]) -> None:
    original = getattr(owner, name, None)
    if original is None or getattr(original, "_srl_guarded", False):
        return

    def guarded(*args: Any, **kwargs: Any) -> Any:
        GUARD.check(what(*args, **kwargs))
        return original(*args, **kwargs)

    guarded._srl_guarded = True  # type: ignore[attr-defined]
    setattr(owner, name, guarded)


def _install() -> None:
    def started(*args: Any, **kwargs: Any) -> str:
        return "started a process"

    def popen(_self: Any, argv: Any, *args: Any, **kwargs: Any) -> str:
        shown = " ".join(map(str, argv)) if isinstance(argv, (list, tuple)) else str(argv)
        return f"started a process ({shown[:100]})"

    _wrap(subprocess.Popen, "_execute_child", popen)
    for name in ("fork", "forkpty", "posix_spawn", "posix_spawnp", "system"):
        _wrap(os, name, started)
    _wrap(socket.socket, "__init__", lambda *args, **kwargs: "opened a socket")
    try:
        import zenoh
    except ImportError:
        return
    _wrap(zenoh, "open", lambda *args, **kwargs: "opened a Zenoh session")


# -- pytest hooks (tests/conftest.py loads this module as a plugin) ---------------------------------


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.getgroup("srl").addoption(
        "--fast",
        action="store_true",
        help="only the tests marked neither integration, slow nor timing: no process, no socket (tests/tiers.py)",
    )


def pytest_configure(config: pytest.Config) -> None:
    if not config.pluginmanager.hasplugin("timeout"):
        raise pytest.UsageError("pytest-timeout is missing: run the tests with ./srl test (it installs the dev extra)")
    _install()


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if not config.getoption("fast"):
        return
    keep: list[pytest.Item] = []
    drop: list[pytest.Item] = []
    for item in items:
        (drop if any(item.get_closest_marker(name) for name in TIER_MARKERS) else keep).append(item)
    if drop:
        config.hook.pytest_deselected(items=drop)
        items[:] = keep


def _timeout(item: pytest.Item) -> float:
    """The test's limit as pytest-timeout takes it: its marker, else --timeout, else the ini's."""
    marker = item.get_closest_marker("timeout")
    if marker is not None and (marker.args or "timeout" in marker.kwargs):
        return float(marker.args[0] if marker.args else marker.kwargs["timeout"])
    option = item.config.getoption("timeout", None)
    return float(option if option is not None else item.config.getini("timeout") or 0)


def _cpu_seconds() -> float:
    """This process's CPU time and its waited-for children's (a service, a docs block's ``srl``, gcc)."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Any:
    limit = _timeout(item)
    if limit > 0:
        faulthandler.dump_traceback_later(limit + BACKSTOP_S, exit=True, file=sys.__stderr__ or sys.stderr)
    cpu, wall = _cpu_seconds(), time.monotonic()
    try:
        return (yield)
    finally:
        if limit > 0:
            faulthandler.cancel_dump_traceback_later()
        _log_cpu(item.nodeid, _cpu_seconds() - cpu, time.monotonic() - wall)


def _log_cpu(nodeid: str, cpu: float, wall: float) -> None:
    """With ``SRL_TEST_CPU_LOG`` set (by :func:`main`): one line per test, CPU and wall seconds."""
    directory = os.environ.get(CPU_LOG)
    if directory:
        with open(Path(directory) / f"{os.getpid()}.tsv", "a", encoding="utf-8") as log:
            log.write(f"{cpu:.3f}\t{wall:.3f}\t{nodeid}\n")


def cpu_table(directory: Path, rows: int = CPU_TABLE_ROWS) -> str:
    """The tests that took the most CPU (their processes' and their children's), and the total:
    on a machine of few cores the suite's time is its CPU divided by the cores."""
    tests = [
        (float(cpu), float(wall), nodeid)
        for path in directory.glob("*.tsv")
        for cpu, wall, nodeid in (
            line.split("\t", 2) for line in path.read_text().splitlines() if line.count("\t") >= 2
        )
    ]
    if not tests:
        return ""
    tests.sort(reverse=True)
    total = sum(cpu for cpu, _, _ in tests)
    lines = [f"CPU of {len(tests)} tests: {total:.0f} s; the {min(rows, len(tests))} most (CPU s, wall s, share):"]
    lines += [f"{cpu:8.1f} {wall:8.1f} {cpu / total:6.1%}  {nodeid}" for cpu, wall, nodeid in tests[:rows]]
    return "\n".join(lines)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_setup(item: pytest.Item) -> Any:
    with GUARD.watching(item, item.config.getoption("fast")):
        return (yield)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item: pytest.Item) -> Any:
    with GUARD.watching(item, item.config.getoption("fast")):
        return (yield)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_teardown(item: pytest.Item, nextitem: pytest.Item | None) -> Any:
    with GUARD.watching(item, item.config.getoption("fast")):
        return (yield)


@pytest.hookimpl(trylast=True)
def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """With ``SRL_TEST_TALLY`` set (by :func:`main`), the controlling session writes its counts."""
    path = os.environ.get(TALLY)
    if not path or hasattr(session.config, "workerinput"):
        return
    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    stats = reporter.stats if reporter is not None else {}
    counts = {
        key: sum(1 for report in reports if getattr(report, "count_towards_summary", True))
        for key, reports in stats.items()
        if key
    }
    Path(path).write_text(json.dumps({"counts": counts, "exitstatus": int(session.exitstatus)}))


# -- the runner: ./srl test without arguments ---------------------------------------------------------

ORDER = ("failed", "passed", "skipped", "deselected", "xfailed", "xpassed", "warnings", "error")
NOTHING_COLLECTED = 5


def _phase(args: list[str], jit_cache: Path) -> tuple[int, dict[str, int], float]:
    with tempfile.TemporaryDirectory(prefix=f"{SCRATCH_PREFIX}{os.getpid()}-") as scratch:
        tally = Path(scratch) / "tally.json"
        started = time.monotonic()
        cpu_log = Path(scratch) / "cpu"
        cpu_log.mkdir()
        env = {**os.environ, TALLY: str(tally), JIT_CACHE: str(jit_cache), CPU_LOG: str(cpu_log)}
        if env.pop("PYTHONDONTWRITEBYTECODE", ""):
            # the suite starts hundreds of Python processes: without bytecode each would compile
            # srl's modules again. Kept beside the JIT cache, so the tree stays as the user keeps it
            # and the run leaves nothing behind.
            env["PYTHONPYCACHEPREFIX"] = str(jit_cache / "bytecode")
        code = _call([sys.executable, "-m", "pytest", *args], env)
        took = time.monotonic() - started
        counts = json.loads(tally.read_text())["counts"] if tally.exists() else {}
        table = cpu_table(cpu_log)
        if table:  # where the suite's time goes
            compiled = sum(1 for _ in jit_cache.glob("*.o"))
            print(f"{table}\nJIT cache: {compiled} compiled objects after this phase", flush=True)
    return code, counts, took


def _call(argv: list[str], env: dict[str, str]) -> int:
    """``argv``'s exit code. The runner stopped (Ctrl-C, or SIGTERM or SIGHUP: :func:`_stop`):
    pytest gets SIGINT, so its teardowns run as after a Ctrl-C (the services a test started
    stopped, its files removed), and SIGKILL if it is not done within :data:`STOP_GRACE_S`."""
    # its own process group: the SIGINT reaches the xdist workers too, as a terminal's Ctrl-C would
    child = subprocess.Popen(argv, env=env, process_group=0)
    try:
        return child.wait()
    finally:
        stop_group(child, STOP_GRACE_S)  # nothing to do once it ended


def _stop(signum: int, _frame: object) -> None:
    """SIGTERM or SIGHUP: the runner stops as on Ctrl-C (its pytest stopped, its directories removed)."""
    raise KeyboardInterrupt(f"srl test: {signal.Signals(signum).name}")


def _line(counts: dict[str, int], seconds: float) -> str:
    keys = [k for k in ORDER if counts.get(k)] + sorted(k for k in counts if k not in ORDER and counts[k])
    parts = []
    for key in keys:
        n = counts[key]
        name = {"warnings": "warning" if n == 1 else "warnings", "error": "error" if n == 1 else "errors"}.get(key, key)
        parts.append(f"{n} {name}")
    minutes, rest = divmod(int(seconds), 60)
    return f"{', '.join(parts) or 'no tests ran'} in {seconds:.2f}s (0:{minutes:02d}:{rest:02d})"


def realtime_allowed() -> bool:
    """Whether this user's processes may ask for SCHED_FIFO at the actor's priority (root, or an
    rtprio limit that high): the actor's tick thread then keeps its deadlines beside other work."""
    return os.geteuid() == 0 or resource.getrlimit(resource.RLIMIT_RTPRIO)[0] >= RT_PRIORITY


def main(extra: list[str]) -> int:
    """The phases, each on ``extra`` (paths; none: the whole suite)."""
    workers = int(os.environ.get("SRL_TEST_WORKERS", WORKERS))
    timing = int(os.environ.get("SRL_TEST_TIMING_WORKERS", TIMING_WORKERS))
    phases = [
        ("parallel", ["-n", str(workers), "--dist", "worksteal", "-m", "not timing", *extra]),
        (
            ("timing, alone", ["-p", "no:xdist", "-m", "timing", *extra])
            if timing <= 1
            else (
                f"timing, {timing} at a time",
                ["-n", str(timing), "--dist", "worksteal", "-m", "timing and not alone", *extra],
            )
        ),
    ]
    if timing > 1:  # the tests whose bound assumes the machine to themselves: after, one at a time
        phases.append(("timing, alone", ["-p", "no:xdist", "-m", "timing and alone", *extra]))
    code, seconds = 0, 0.0
    total: dict[str, int] = {}
    done: list[str] = []
    for signum in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(signum, _stop)
    # Ctrl-C heard even when started with SIGINT ignored (a background job of a script, a pytest-xdist
    # worker); a handler, unlike an ignored signal, is not inherited: pytest then hears the SIGINT of _call
    signal.signal(signal.SIGINT, signal.default_int_handler)
    # a runner killed with SIGKILL (no handler runs) left its directories: the next run removes them
    remove_orphan_build_directories(prefix=SCRATCH_PREFIX)
    # private (0700): a problem compiles once per run
    jit_cache = Path(tempfile.mkdtemp(prefix=f"{SCRATCH_PREFIX}{os.getpid()}-jit-"))
    try:
        seconds = _warm(jit_cache)
        done.append(f"compiles before: {seconds:.0f}s")
        for number, (name, args) in enumerate(phases, start=1):
            phase_code, counts, took = _run(name, args, number, len(phases), jit_cache)
            seconds += took
            done.append(f"{name}: {_line(counts, took)}")
            for key, n in counts.items():
                total[key] = total.get(key, 0) + n
            if phase_code not in (0, NOTHING_COLLECTED) and code == 0:
                code = phase_code
            if phase_code not in (0, 1, NOTHING_COLLECTED):  # interrupted, internal or usage error
                break
    finally:
        shutil.rmtree(jit_cache, ignore_errors=True)
    print(f"===== {_line(total, seconds)} [{'; '.join(done)}] =====", flush=True)
    return code


def _warm(jit_cache: Path) -> float:
    """:data:`WARM_PROBLEMS` compiled into ``jit_cache``, one per core; the seconds it took. Not a
    phase: without a compiler (or on a failure) the tests compile what they need themselves."""
    started = time.monotonic()
    env = {**os.environ, "SRL_ACTOR__JIT_CACHE": str(jit_cache)}
    for argv in WARM_PROBLEMS:
        print(f"===== srl test, before the phases: srl {' '.join(argv)} =====", flush=True)
        code = subprocess.call([sys.executable, "-m", "tools.cli", *argv], env=env)
        if code != 0:
            print(f"srl test: srl build exited with {code}; the tests compile their problems themselves", flush=True)
    return time.monotonic() - started


def _run(name: str, args: list[str], number: int, of: int, jit_cache: Path) -> tuple[int, dict[str, int], float]:
    print(f"===== srl test, phase {number} of {of}: {name} (pytest {' '.join(args)}) =====", flush=True)
    phase_code, counts, took = _phase(args, jit_cache)
    counts.pop("deselected", None)  # each phase deselects the other's tests
    return phase_code, counts, took


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
