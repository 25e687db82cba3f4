"""``srl`` exits without interpreter finalization once Zenoh ran, and loses nothing by it.

(The reason, in :func:`tools.cli.entry`: a Zenoh thread that wants the GIL while the
interpreter finalizes aborts the process.) The exit must still run the atexit handlers, flush
what was written, and keep the exit code.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from tests.harness import ROOT

pytestmark = pytest.mark.integration

SCRIPT = """
import atexit, sys
from pathlib import Path
{zenoh}
from tools.cli import entry
atexit.register(lambda: Path(sys.argv[1]).write_text("atexit ran"))
sys.stdout.write("unflushed output")  # no newline, no flush: the exit must flush it
entry(sys.argv[2:])
"""


@pytest.mark.parametrize("with_zenoh", [True, False])
@pytest.mark.parametrize(
    ("argv", "code"),
    [(["health", "--help"], 0), (["run", "--horizon", "x"], 2), (["run", "--horizon", "1", "--duration", "1"], 2)],
)
def test_exit_runs_atexit_flushes_and_keeps_the_code(
    tmp_path: Path, argv: list[str], code: int, with_zenoh: bool
) -> None:
    marker = tmp_path / "marker"
    script = SCRIPT.format(zenoh="import zenoh" if with_zenoh else "")
    done = subprocess.run(
        [sys.executable, "-c", script, str(marker), *argv],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == code, done.stderr[-2000:]
    assert done.stdout.startswith("unflushed output")
    assert marker.read_text() == "atexit ran"
    if argv[0] == "health":
        assert "usage: srl health" in done.stdout
    else:
        assert "srl" in done.stderr and "error" in done.stderr
