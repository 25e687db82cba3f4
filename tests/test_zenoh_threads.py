"""Zenoh's runtime threads in srl's processes (``transport.zenoh_threads``, docs/fleets.md).

A service or a recorder runs Zenoh's runtime on one thread by default; a router keeps Zenoh's own
pools (one thread there drops messages under a burst), and nothing a service starts inherits its
choice. Zenoh reads ``ZENOH_RUNTIME`` once per process, when its first session starts the runtime,
so the live case reads the threads of real processes (/proc/<pid>/task/*/comm; Zenoh's runtimes
name theirs rx-N, tx-N, app-N, acc-N, net-N).
"""

from __future__ import annotations

import os
import re

import pytest

from common.net.transport import ZENOH_RUNTIME_PARTS, runtime_spec, zenoh_threads
from tests.harness import Proc, cluster

ZENOH_THREAD = re.compile(r"^(rx|tx|app|acc|net)-\d+$")


def zenoh_pools(proc: Proc) -> set[str]:
    """The runtimes whose threads a process runs ("app" of "app-0": a pool's blocking helpers carry
    its name too, so threads are told apart by pool, not counted one by one)."""
    pools = set()
    for tid in os.listdir(f"/proc/{proc.process.pid}/task"):
        with open(f"/proc/{proc.process.pid}/task/{tid}/comm") as comm:
            name = comm.read().strip()
        if ZENOH_THREAD.match(name):
            pools.add(name.split("-")[0])
    return pools


def test_the_runtime_spec_hands_every_part_to_one_pool() -> None:
    assert runtime_spec(0) is None
    spec = runtime_spec(3)
    assert spec is not None and spec.startswith("(app: (worker_threads: 3)")
    for part in ZENOH_RUNTIME_PARTS:
        assert f"{part}: (handover: app)" in spec


def test_the_runtime_is_set_only_while_the_first_session_opens_and_the_users_wins(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.delenv("ZENOH_RUNTIME", raising=False)
    with zenoh_threads(1):
        assert os.environ["ZENOH_RUNTIME"] == runtime_spec(1)
    assert "ZENOH_RUNTIME" not in os.environ  # nothing started afterwards inherits it
    with zenoh_threads(0):
        assert "ZENOH_RUNTIME" not in os.environ
    monkeypatch.setenv("ZENOH_RUNTIME", "(app: (worker_threads: 3))")
    with zenoh_threads(1):
        assert os.environ["ZENOH_RUNTIME"] == "(app: (worker_threads: 3))"
    assert os.environ["ZENOH_RUNTIME"] == "(app: (worker_threads: 3))"


@pytest.mark.integration
def test_a_service_runs_one_zenoh_pool_the_router_zenohs_and_zero_gives_zenohs(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.delenv("ZENOH_RUNTIME", raising=False)
    with cluster(robot="zt") as c:
        c.start("plant", "plant-sim", "--mode", "realtime")
        c.start("pools", "critic", env={"SRL_TRANSPORT__ZENOH_THREADS": "0"})
        c.wait_alive("plant")
        c.wait_alive("critic")
        assert zenoh_pools(c.procs["plant"]) == {"app"}
        # negative control: the same settings but 0, Zenoh's own pools (send, the network's tasks,
        # ... each its own); and the router's, which no service's choice reaches
        assert zenoh_pools(c.procs["pools"]) >= {"app", "tx", "net"}
        assert zenoh_pools(c.procs["router"]) >= {"app", "tx", "net"}
        assert c.alive("plant") and c.alive("critic")
