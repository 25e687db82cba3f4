"""The status line (``srl status``, ``srl up``) shows the lockout-like patterns.

The actor computes ``plant_conflict`` and ``lockout_suspect``; the bridge counts the actions it
refuses and the resyncs. A quiet line when nothing is wrong, one word per alarm when it is; the
monitor merges the plant's refusal counters into the actor's status it shows.
"""

from __future__ import annotations

import itertools
import time

import pytest

from common.config.settings import Settings
from common.contracts.keys import STATUS
from common.contracts.messages import ServiceStatus
from common.contracts.summaries import format_status_line
from tests.harness import cluster, wait_until
from tools.launch.measure import status_monitor

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
        monitor = status_monitor(Settings.load(transport={"router": c.endpoint, "robot": robot}))
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
        monitor = status_monitor(Settings.load(transport={"router": c.endpoint, "robot": robot}))
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
@pytest.mark.timing  # the statuses' arrival 0.1-0.4 s apart: a real-time bound, run alone
def test_one_status_loop_sends_every_robots_status_spread_over_the_period() -> None:
    """One status loop for one robot and for a host of K (here 2): each robot's status once a
    period, one robot every period / K (never both in one burst), NaN counters left out; nothing
    after stop."""
    import threading

    import zenoh

    from common.net.transport import Bus, start_status_thread
    from tests.harness import client_config

    robots = ("st_a", "st_b")
    built = {robot: 0 for robot in robots}
    seen: list[tuple[float, ServiceStatus]] = []

    def counters(robot: str):  # type: ignore[no-untyped-def]
        def read() -> dict[str, float]:
            built[robot] += 1
            return {"steps": float(built[robot]), "bad": float("nan")}

        return read

    with cluster(robot=robots[0]) as c:
        assert c.session is not None
        subscriber = c.session.declare_subscriber(
            "srl/*/status/plant",
            lambda sample: seen.append(
                (time.monotonic(), ServiceStatus.model_validate_json(sample.payload.to_bytes()))
            ),
        )
        bus = Bus(zenoh.open(client_config(c.endpoint)), "plant")
        stop = threading.Event()
        try:
            time.sleep(0.5)  # the subscription reaches the router
            start_status_thread(bus, [(robot, counters(robot)) for robot in robots], 0.4, stop)
            wait_until(lambda: len(seen) >= 6, 10, "three statuses of each robot")
            stop.set()
            time.sleep(0.5)
            count = len(seen)
            time.sleep(1.0)  # two periods after stop
            assert len(seen) == count
        finally:
            stop.set()
            subscriber.undeclare()
            bus.close()
    order = [status.robot for _, status in seen]
    assert order[:6] == ["st_a", "st_b"] * 3  # one robot at a time, in turn
    gaps = [later - earlier for (earlier, _), (later, _) in itertools.pairwise(seen)][:5]
    assert all(0.1 <= gap <= 0.4 for gap in gaps), gaps  # period / K = 0.2 s apart, not a burst
    assert all("bad" not in status.counters for _, status in seen)
    assert [status.counters["steps"] for _, status in seen if status.robot == "st_b"][:3] == [1.0, 2.0, 3.0]


class _Closing:
    """A bus's ``closing`` event that never sleeps: each wait is noted; after ``waits`` it says closed."""

    def __init__(self, waits: int, log: list[tuple[str, object]]) -> None:
        self.left, self.log = waits, log

    def wait(self, gap: float) -> bool:
        self.log.append(("wake", gap))
        self.left -= 1
        return self.left < 0


class _StatusBus:
    """What start_status_thread uses of a Bus, with puts noted in order beside the wakes."""

    service = "plant"

    def __init__(self, waits: int) -> None:
        self.log: list[tuple[str, object]] = []
        self.closing = _Closing(waits, self.log)
        self.counters: dict[str, int] = {}
        self.thread: object = None

    def publisher(self, topic: object, robot: str, **chunks: str):  # type: ignore[no-untyped-def]
        return lambda message: self.log.append(("put", message.robot))

    def count(self, name: str, amount: int = 1) -> None:
        self.counters[name] = self.counters.get(name, 0) + amount

    def adopt(self, thread: object) -> None:
        self.thread = thread


@pytest.mark.parametrize(("robots", "wakes", "most"), [(25, 10, 3), (10, 10, 1), (3, 3, 1)])
def test_a_status_loop_wakes_at_most_ten_times_a_period(robots: int, wakes: int, most: int) -> None:
    """K <= 10 robots: one status a wake, period / K apart; more: every robot's status once a
    period in 10 wakes of ceil(K / 10) (puts due together leave in one Zenoh batch)."""
    import threading

    from common.net.transport import start_status_thread

    names = [f"r{i}" for i in range(robots)]
    bus = _StatusBus(waits=2 * wakes)
    start_status_thread(bus, [(r, lambda: {"steps": 1.0}) for r in names], 1.0, threading.Event())  # type: ignore[arg-type]
    assert isinstance(bus.thread, threading.Thread)
    bus.thread.join(5)
    gaps = [gap for what, gap in bus.log if what == "wake"]
    assert gaps == [pytest.approx(1.0 / wakes)] * (2 * wakes + 1)  # the last wake: closed
    bursts: list[list[object]] = []
    for what, item in bus.log:
        if what == "wake":
            bursts.append([])
        else:
            bursts[-1].append(item)
    period = [robot for burst in bursts[:wakes] for robot in burst]
    assert period == names  # every robot once a period, in order
    assert [robot for burst in bursts[wakes : 2 * wakes] for robot in burst] == names
    assert max(len(burst) for burst in bursts) == most
    assert bus.counters["statuses_published"] == 2 * robots


def test_a_status_says_how_far_its_robot_is_in_the_robots_metres_or_the_systems_terms() -> None:
    """One reading of a status's distance (``status_distance``) for the one robot's line and the
    fleet's: the robot's pose gives hypot(x, y) in m, another system's status its ``distance``."""
    import threading

    from common.contracts.summaries import status_distance
    from tools.launch.measure import RobotStatuses

    robot, system = {**QUIET, "x": 3.0, "y": -4.0}, {"steps": 10.0, "distance": 0.0123}
    assert status_distance(robot) == (5.0, "m") and status_distance(system) == (0.0123, "")
    assert status_distance({"steps": 1.0}) is None  # no state yet
    assert "distance 5.00 m" in format_status_line(robot, 1.0, [])
    line = format_status_line(system, 1.0, [])
    assert "distance to the goal 0.0123" in line and " x " not in line
    fleet = object.__new__(RobotStatuses)  # its table alone, without the monitor's session
    fleet.actors, fleet.lock = {"a": robot, "b": {**QUIET, "x": 0.3, "y": 0.4}}, threading.Lock()
    assert "distance max 5.00 m," in fleet.line(1.0, 2)
    fleet.actors = {"a": system, "b": {"distance": 0.5}}
    assert "distance max 0.50," in fleet.line(1.0, 2)
