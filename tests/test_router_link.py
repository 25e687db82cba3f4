"""``srl router --connect``: routers linked across hosts (docs/fleets.md), here on loopback.

The multi-host behaviour under faults is tests/test_netns_fleet.py (network namespaces, root);
this checks what any machine can: a router started before the one it connects to links when that
one comes up, samples cross the link both ways, and bad input is refused in one line.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

import pytest
import zenoh

from tests.harness import ROOT, client_config, free_port

pytestmark = pytest.mark.integration

CLI = [sys.executable, "-m", "tools.cli"]


def start_router(endpoint: str, *connect: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [*CLI, "router", "--router", endpoint, *(f"--connect={c}" for c in connect)],
        cwd=ROOT,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
        start_new_session=True,
    )


def first_line(router: subprocess.Popen[str]) -> str:
    assert router.stdout is not None
    return router.stdout.readline().strip()


def crosses(sender: zenoh.Session, receiver: zenoh.Session, key: str, timeout: float) -> float:
    """Seconds until a put on ``sender`` reaches a subscriber on ``receiver`` (bounded)."""
    got = threading.Event()
    subscriber = receiver.declare_subscriber(key, lambda _sample: got.set())
    started = time.monotonic()
    try:
        while time.monotonic() - started < timeout:
            sender.put(key, b"x")
            if got.wait(0.1):
                return time.monotonic() - started
        raise AssertionError(f"nothing crossed the router link on {key} in {timeout} s")
    finally:
        subscriber.undeclare()


def test_a_router_links_to_another_that_comes_up_later_and_samples_cross_both_ways() -> None:
    first, second = (f"tcp/127.0.0.1:{free_port()}" for _ in range(2))
    linking = start_router(first, second)  # the other one is not up yet: Zenoh keeps trying
    other = None
    sessions: list[zenoh.Session] = []
    try:
        assert first_line(linking) == (
            f"srl router: router listening on {first} (multicast scouting off; connecting to {second})"
        )
        time.sleep(1.0)
        other = start_router(second)
        assert first_line(other).startswith(f"srl router: router listening on {second}")
        sessions = [zenoh.open(client_config(first)), zenoh.open(client_config(second))]
        assert crosses(sessions[0], sessions[1], "srl/link/one", 15) < 15
        assert crosses(sessions[1], sessions[0], "srl/link/two", 15) < 15
    finally:
        for session in sessions:
            session.close()  # type: ignore[no-untyped-call]
        for router in (linking, other):
            if router is not None:
                os.killpg(router.pid, signal.SIGINT)
                router.communicate(timeout=30)
    assert linking.returncode == 0 and other is not None and other.returncode == 0


def test_a_bad_connect_endpoint_is_refused_in_one_line() -> None:
    result = subprocess.run(
        [*CLI, "router", "--router", f"tcp/127.0.0.1:{free_port()}", "--connect", "192.168.1.20:7447"],
        cwd=ROOT,
        text=True,
        capture_output=True,
        timeout=60,
    )
    assert result.returncode == 2, result
    assert result.stdout == ""  # never listened
    assert result.stderr.strip().splitlines() == [result.stderr.strip()], result.stderr
    assert "transport.connect" in result.stderr and "192.168.1.20:7447" in result.stderr, result.stderr
