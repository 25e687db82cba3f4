"""``./srl test`` (tests/tiers.py ``main``) stopped leaves nothing behind: on SIGTERM or SIGHUP its
pytest gets SIGINT (a test's teardown runs) and its directories are removed; the directories of a
runner killed with SIGKILL are removed by the next run."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from tests.harness import ROOT, wait_until

pytestmark = pytest.mark.integration

# the runner without its compiles before the phases (srl build: half a minute), on one worker
RUNNER = "import sys; from tests import tiers; tiers.WARM_PROBLEMS = (); sys.exit(tiers.main(sys.argv[1:]))"

A_TEST = """
import os, pathlib, time
import pytest

@pytest.fixture
def teardown_mark():
    yield
    pathlib.Path(os.environ["SRL_T_MARKS"], "teardown").write_text("ran")

def test_waits(teardown_mark):
    pathlib.Path(os.environ["SRL_T_MARKS"], "started").write_text(str(os.getpid()))
    time.sleep(120)
"""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return Path(f"/proc/{pid}/stat").read_text().split(") ")[-1][0] != "Z"


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP], ids=["SIGTERM", "SIGHUP"])
def test_a_stopped_runner_tears_its_tests_down_and_leaves_no_directory(tmp_path: Path, signum: int) -> None:
    temp, marks = tmp_path / "tmp", tmp_path / "marks"
    temp.mkdir()
    marks.mkdir()
    gone = int(Path("/proc/sys/kernel/pid_max").read_text())  # pids are below it: no process has it
    orphan = temp / f"srl-test-{gone}-jit-abc123"  # a runner's killed with SIGKILL
    orphan.mkdir()
    (orphan / "x.o").write_bytes(b"x")
    other = temp / "srl-test-keep"  # not a runner's name: kept
    other.mkdir()
    (tmp_path / "test_waits.py").write_text(A_TEST)
    env = {**os.environ, "TMPDIR": str(temp), "SRL_T_MARKS": str(marks), "SRL_TEST_WORKERS": "1"}
    runner = subprocess.Popen(
        [sys.executable, "-c", RUNNER, str(tmp_path / "test_waits.py"), "-p", "no:cacheprovider"],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        # started with SIGINT ignored, as a script's background job is (and a pytest-xdist worker,
        # which runs this test in the suite): an ignored signal is inherited, the runner must undo it
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
    )
    group = None
    try:
        wait_until(lambda: (marks / "started").exists(), 60.0, "the test to start under the runner")
        worker = int((marks / "started").read_text())
        group = os.getpgid(worker)  # the runner's pytest and its worker
        assert not orphan.exists()  # removed as the run began
        assert any(p.name.startswith(f"srl-test-{runner.pid}-") for p in temp.iterdir())
        runner.send_signal(signum)
        out, _ = runner.communicate(timeout=45)
    finally:
        if runner.poll() is None:
            runner.kill()
            runner.communicate()
        if group is not None:  # whatever the runner left of its pytest (a failure of this test)
            with contextlib.suppress(ProcessLookupError):
                os.killpg(group, signal.SIGKILL)
    assert runner.returncode != 0, out
    assert (marks / "teardown").read_text() == "ran", out
    assert not _alive(worker), out
    left = sorted(p.name for p in temp.iterdir() if p.name.startswith("srl-"))  # pytest's own: pytest-of-*
    assert left == ["srl-test-keep"], out
