"""srl up's supervisor stops the services first and the router last (tools/launch/supervisor.py)."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from tools.launch.supervisor import Child, Supervisor

pytestmark = pytest.mark.integration

# Each fake service writes when it got SIGINT, takes 0.3 s to say goodbye, writes when it
# ended and exits 0.
FAKE = """
import signal, sys, time
def on_int(*_):
    got = time.monotonic()
    time.sleep(0.3)
    open(sys.argv[1], "w").write(f"{got} {time.monotonic()}")
    sys.exit(0)
signal.signal(signal.SIGINT, on_int)
time.sleep(60)
"""


def test_router_is_stopped_after_every_service(tmp_path: Path) -> None:
    supervisor = Supervisor([], env={}, quiet=True)
    names = ["router", "plant", "critic", "actor"]
    for name in names:  # in srl up's order: the router first
        process = subprocess.Popen(
            [sys.executable, "-c", FAKE, str(tmp_path / name)], text=True, start_new_session=True
        )
        supervisor.children[name] = Child(name, process)
    time.sleep(0.5)  # the handlers are installed
    try:
        supervisor.stop_all()
    finally:
        for child in supervisor.children.values():
            if child.process.poll() is None:
                child.process.kill()
                child.process.wait()
    got, ended = {}, {}
    for name in names:
        got[name], ended[name] = map(float, (tmp_path / name).read_text().split())
    assert all(child.process.returncode == 0 for child in supervisor.children.values())
    # the router is told to stop only once every service has ended
    assert got["router"] >= max(ended[name] for name in names if name != "router")
