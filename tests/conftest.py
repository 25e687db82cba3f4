"""Test-wide rules.

* Isolation: no test reads or writes the user's real critic checkpoint, nor the user's JIT cache
  (``actor.jit_cache``: one private directory for the run, so a problem compiles once per run),
  nor meets a router it did not start: ``transport.router`` is a free loopback port of its own
  per test process.
* Machine requirements: a test that needs more than python3 (root, iproute2 and iptables for
  network namespaces; a C compiler for the actor's JIT build; the right to real-time scheduling)
  carries a marker (``needs_root``, ``needs_compiler``, ``needs_rtprio``); where the machine lacks
  it, the test is
  SKIPPED with one line saying what it needs and how to run it, so that ``./srl test`` passes on a
  fresh machine with only python3. ``SRL_TEST_REQUIRE_ALL=1`` (CI, ``.ci/run``) turns every such
  skip into a failure, and fails the session if any test at all was skipped.
* Tiers: the markers ``integration`` (starts a process or opens a socket), ``slow`` and ``timing``,
  ``--fast``, the guard that fails an unmarked test that starts a process, the per-test time
  limit and the two phases of ``./srl test``: tests/tiers.py (docs/development.md).
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from common.system.ports import free_port

pytest_plugins = ("tests.tiers",)

REQUIRE_ALL = "SRL_TEST_REQUIRE_ALL"


def _netns_missing() -> list[str]:
    from tests import netns  # imported when a marked test runs (it imports zenoh)

    return netns.missing_requirements()


def _compiler_missing() -> list[str]:
    # the actor builds without JIT when there is none (common/math/actor_nlp.py), so only the tests of the
    # JIT build itself need one
    return [] if shutil.which("gcc") or shutil.which("cc") else ["no C compiler (gcc or cc) on PATH"]


def _baselines_missing() -> list[str]:
    import importlib.util

    absent = [name for name in ("stable_baselines3", "torch") if importlib.util.find_spec(name) is None]
    return [f"{' and '.join(absent)} not installed (the baselines extra)"] if absent else []


def _rtprio_missing() -> list[str]:
    from tests.tiers import realtime_allowed

    if realtime_allowed():
        return []
    return ["this user may not ask for SCHED_FIFO 10 (not root, `ulimit -r` below 10)"]


# marker -> (what is missing on this machine (empty: nothing), how to run these tests)
REQUIREMENTS: dict[str, tuple[Callable[[], list[str]], str]] = {
    "needs_root": (_netns_missing, "run as root on Debian with iproute2 and iptables: sudo ./srl test {path}"),
    "needs_compiler": (_compiler_missing, "install a C compiler (Debian: apt-get install gcc), then ./srl test {path}"),
    "needs_baselines": (
        _baselines_missing,
        "SRL_BASELINES=1 ./srl test {path} (installs the baselines extra: stable-baselines3 and torch, ~1 GB "
        "with torch's CPU build)",
    ),
    "needs_rtprio": (
        _rtprio_missing,
        "run as root (sudo ./srl test {path}) or with an rtprio limit of 10 or more (docs/fleets.md)",
    ),
}


def require_all() -> bool:
    return os.environ.get(REQUIRE_ALL, "").strip().lower() not in ("", "0", "false", "no")


def unmet(item: pytest.Item) -> str | None:
    """One line naming what this test needs and how to run it, or None when the machine has it."""
    for marker, (missing, how) in REQUIREMENTS.items():
        if item.get_closest_marker(marker) is None:
            continue
        reasons = missing()
        if reasons:
            path = (
                item.path.relative_to(item.config.rootpath)
                if item.path.is_relative_to(item.config.rootpath)
                else item.path
            )
            return f"{marker}: {'; '.join(reasons)}; {how.format(path=path)}"
    return None


def pytest_runtest_setup(item: pytest.Item) -> None:
    reason = unmet(item)
    if reason is None:
        return
    if require_all():  # CI: the machine must run every test
        pytest.fail(f"{REQUIRE_ALL} is set and this test cannot run: {reason}", pytrace=False)
    pytest.skip(reason)


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    # any skip at all (a marker above, importorskip, pytest.skip in a test) fails a session that
    # must run everything
    if not require_all():
        return
    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    skipped = len(reporter.stats.get("skipped", [])) if reporter is not None else 0
    if skipped and session.exitstatus == pytest.ExitCode.OK:
        if reporter is not None:
            reporter.write_line(f"{REQUIRE_ALL} is set: {skipped} test(s) skipped, failing the run", red=True)
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


def pytest_configure(config: pytest.Config) -> None:
    # transport.router of this test process (each parallel worker has its own): a router, service
    # or srl up that a test starts without --router meets that test's own, never one of a test
    # running in another worker, nor a router the machine itself runs on the packaged 7447
    # (common/system/ports.py: below the ephemeral range, so no outgoing connection takes it meanwhile).
    port = free_port()
    os.environ["SRL_TRANSPORT__ROUTER"] = f"tcp/127.0.0.1:{port}"
    _build_font_cache()


def _build_font_cache() -> None:
    """Matplotlib builds its font cache once per user, running ``fc-list`` to find the fonts:
    built here, before any test, so a test's first plot on a new account starts no process (the
    fast tier's guard, tests/tiers.py, would fail it). A cache already there is left alone."""
    import matplotlib

    if not any(Path(matplotlib.get_cachedir()).glob("fontlist-v*.json")):
        import matplotlib.font_manager  # builds and stores the cache


@pytest.fixture(autouse=True, scope="session")
def jit_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """The run's JIT cache (service processes started by a test inherit it). Parallel workers
    (pytest-xdist) share one, beside their own temporary directories: its objects are stored by
    an atomic rename (common/system/jit.py), so a problem compiles once per run, not per worker."""
    from tests.tiers import JIT_CACHE

    if os.environ.get(JIT_CACHE):  # ./srl test: its two phases share one too
        path = Path(os.environ[JIT_CACHE])
    elif os.environ.get("PYTEST_XDIST_WORKER"):
        path = tmp_path_factory.getbasetemp().parent / "jit-cache"
        path.mkdir(exist_ok=True)
    else:
        path = tmp_path_factory.mktemp("jit-cache")
    path.chmod(0o700)
    before = os.environ.get("SRL_ACTOR__JIT_CACHE")
    os.environ["SRL_ACTOR__JIT_CACHE"] = str(path)
    yield path
    if before is None:
        os.environ.pop("SRL_ACTOR__JIT_CACHE", None)
    else:
        os.environ["SRL_ACTOR__JIT_CACHE"] = before


@pytest.fixture(autouse=True)
def critic_checkpoint(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    # Settings read SRL_<SECTION>__<NAME>; service processes started by a test inherit it.
    """The checkpoint template of this test (``{robot}`` = robot id)."""
    path = tmp_path / "critic-{robot}.json"
    monkeypatch.setenv("SRL_CRITIC__CHECKPOINT", str(path))
    monkeypatch.setenv("SRL_RUNS_DIR", str(tmp_path / "runs"))  # srl up's JSON summaries
    yield path


@pytest.fixture
def no_srl_environment(monkeypatch: pytest.MonkeyPatch, jit_cache: Path) -> None:
    """No ``SRL_*`` variable set (tests of how settings are resolved, from files and flags only).
    ``actor.jit_cache`` is then ``auto``: ``$XDG_CACHE_HOME`` points into the session's cache, so
    these tests do not write the user's ``~/.cache/srl/jit`` either."""
    import os

    for name in list(os.environ):
        if name.upper().startswith("SRL_"):
            monkeypatch.delenv(name)
    monkeypatch.setenv("XDG_CACHE_HOME", str(jit_cache / "xdg"))
