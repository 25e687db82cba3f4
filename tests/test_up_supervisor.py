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


def stop_fakes(tmp_path: Path, names: list[str], observers: tuple[str, ...] = ()) -> dict[str, tuple[float, float]]:
    """A fake of each name (spawned in this order), stopped by ``stop_all``: when each got SIGINT, and ended."""
    supervisor = Supervisor([], env={}, quiet=True)
    for name in names:
        process = subprocess.Popen(
            [sys.executable, "-c", FAKE, str(tmp_path / name)], text=True, start_new_session=True
        )
        supervisor.children[name] = Child(name, process, observer=name in observers)
    time.sleep(0.5)  # the handlers are installed
    try:
        supervisor.stop_all()
    finally:
        for child in supervisor.children.values():
            if child.process.poll() is None:
                child.process.kill()
                child.process.wait()
    assert all(child.process.returncode == 0 for child in supervisor.children.values())
    times = {name: (tmp_path / name).read_text().split() for name in names}
    return {name: (float(got), float(ended)) for name, (got, ended) in times.items()}


def test_router_is_stopped_after_every_service(tmp_path: Path) -> None:
    names = ["router", "plant", "critic", "actor"]  # in srl up's order: the router first
    times = stop_fakes(tmp_path, names)
    # the router is told to stop only once every service has ended
    assert times["router"][0] >= max(times[name][1] for name in names if name != "router")


def test_observers_are_stopped_after_the_services_and_before_the_router(tmp_path: Path) -> None:
    """A recorder (an observer) hears the services' last messages: told to stop once they ended."""
    services = ["plant", "critic", "actor"]
    times = stop_fakes(tmp_path, ["router", "recorder", *services], observers=("recorder",))
    assert times["recorder"][0] >= max(times[name][1] for name in services)
    assert times["router"][0] >= times["recorder"][1]
    assert max(times[name][0] for name in services) < times["plant"][1]  # the services told together (the control)
