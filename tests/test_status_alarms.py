"""The status line (``srl status``, ``srl up``) shows the lockout-like patterns.

The actor computes ``plant_conflict`` and ``lockout_suspect``; the bridge counts the actions it
refuses and the resyncs. A quiet line when nothing is wrong, one word per alarm when it is; the
monitor merges the plant's refusal counters into the actor's status it shows.
"""

from __future__ import annotations

import time

import pytest

from common.config.settings import Settings
from common.contracts.keys import STATUS
from common.contracts.messages import ServiceStatus
from common.contracts.summaries import format_status_line
from tests.harness import cluster, wait_until
from tools.launch.up import StatusMonitor

QUIET = {"x": 0.5, "y": 0.0, "alpha": 0.0, "steps": 10.0, "plant_sources": 1.0}


def test_a_quiet_status_line_has_no_alarm() -> None:
    line = format_status_line({**QUIET, "plant_conflict": 0.0, "lockout_suspect": 0.0}, 1.0, [])
    assert "LOCKOUT" not in line and "CONFLICT" not in line and "refused" not in line


def test_the_status_line_shows_a_lockout_a_conflict_and_the_bridge_refusals() -> None:
    line = format_status_line({**QUIET, "lockout_suspect": 1.0}, 1.0, [])
    assert "LOCKOUT SUSPECT" in line and "CONFLICT" not in line
    line = format_status_line({**QUIET, "plant_conflict": 1.0, "plant_sources": 2.0}, 1.0, [])
    assert "PLANT CONFLICT (2 plants alive)" in line and "LOCKOUT" not in line
    refusals = {"plant.rejected.action": 7.0, "plant.rejected.action.foreign": 3.0, "plant.action_resyncs": 2.0}
    line = format_status_line({**QUIET, **refusals}, 1.0, [])
    assert "bridge refused 10 actions (2 resyncs)" in line


@pytest.mark.integration
def test_the_monitor_merges_the_plant_refusals_into_the_actor_status() -> None:
    robot = "st_m"
    with cluster(robot=robot) as c:
        assert c.session is not None
        monitor = StatusMonitor(Settings.load(transport={"router": c.endpoint, "robot": robot}))
        try:
            publishers = {
                service: c.session.declare_publisher(STATUS.key(robot, service=service))
                for service in ("actor", "plant")
            }

            def put(service: str, counters: dict[str, float]) -> None:
                publishers[service].put(
                    ServiceStatus(
                        robot=robot, service=service, stamp_ns=time.monotonic_ns(), counters=counters
                    ).encode()
                )

            deadline = time.monotonic() + 20
            while monitor.latest is None or "plant.rejected.action" not in monitor.latest:
                assert time.monotonic() < deadline, f"the monitor saw {monitor.latest}"
                put("plant", {"rejected.action": 4.0, "action_resyncs": 1.0, "states_published": 99.0})
                put("actor", {**QUIET, "lockout_suspect": 1.0})
                time.sleep(0.05)
            seen = monitor.latest
        finally:
            monitor.close()
    assert seen["lockout_suspect"] == 1.0 and seen["plant.action_resyncs"] == 1.0
    assert "plant.states_published" not in seen  # only the refusal counters: the line stays short
    line = format_status_line(seen, 1.0, [])
    assert "LOCKOUT SUSPECT" in line and "bridge refused 4 actions (1 resyncs)" in line


@pytest.mark.integration
def test_a_monitor_without_an_actor_status_shows_nothing() -> None:
    robot = "st_n"
    with cluster(robot=robot) as c:
        assert c.session is not None
        monitor = StatusMonitor(Settings.load(transport={"router": c.endpoint, "robot": robot}))
        try:
            publisher = c.session.declare_publisher(STATUS.key(robot, service="plant"))
            for _ in range(20):
                publisher.put(
                    ServiceStatus(robot=robot, service="plant", stamp_ns=0, counters={"rejected.action": 1.0}).encode()
                )
                time.sleep(0.02)
            wait_until(lambda: bool(monitor.plant), 10, "the plant's status")
            assert monitor.latest is None and monitor.seen == 0  # a line needs the actor's status
        finally:
            monitor.close()


@pytest.mark.integration
def test_a_status_is_built_and_sent_only_while_someone_subscribes_to_it() -> None:
    """One status loop for one robot and for a host of K (here 2): a robot's status costs nothing
    until a subscriber matches its key, then comes within a period; the other robot's stays unbuilt."""
    import threading

    import zenoh

    from common.net.transport import Bus, start_status_thread
    from tests.harness import client_config

    robots = ("st_a", "st_b")
    built = {robot: 0 for robot in robots}
    seen: list[ServiceStatus] = []

    def counters(robot: str):  # type: ignore[no-untyped-def]
        def read() -> dict[str, float]:
            built[robot] += 1
            return {"steps": float(built[robot]), "bad": float("nan")}

        return read

    with cluster(robot=robots[0]) as c:
        assert c.session is not None
        bus = Bus(zenoh.open(client_config(c.endpoint)), "plant")
        stop = threading.Event()
        try:
            start_status_thread(bus, [(robot, counters(robot)) for robot in robots], 0.2, stop)
            time.sleep(1.0)  # five periods, nobody subscribed
            assert built == {"st_a": 0, "st_b": 0} and bus.counters.get("statuses_published", 0) == 0
            subscriber = c.session.declare_subscriber(
                STATUS.key("st_a", service="plant"),
                lambda sample: seen.append(ServiceStatus.model_validate_json(sample.payload.to_bytes())),
            )
            wait_until(lambda: len(seen) >= 3, 10, "three of st_a's statuses")
            assert built["st_b"] == 0 and {s.robot for s in seen} == {"st_a"}
            assert "bad" not in seen[-1].counters and seen[-1].counters["steps"] >= 3
            subscriber.undeclare()
            time.sleep(0.5)
            published = bus.counters["statuses_published"]
            time.sleep(1.0)  # five periods after the subscriber left
            assert bus.counters["statuses_published"] == published and built["st_b"] == 0
        finally:
            stop.set()
            bus.close()
