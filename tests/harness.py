"""Start real service processes on free loopback ports, wait on readiness, clean up by pid.

Why :class:`Proc` and :class:`Cluster` do not reuse ``tools.launch.supervisor.Supervisor``:

* Tests do not set up with the code they test: the Supervisor is under test itself
  (test_up_supervisor.py, and the ``srl up`` runs of test_services.py and test_security.py). A
  harness built on it would carry its bugs (stop order, signal forwarding, grace) into every
  integration test, as leaked or wrongly stopped processes, instead of failing the test that
  checks that one thing.
* Tests need other controls than a launcher meant to run for days: any signal to any one process
  (SIGKILL, SIGTERM to provoke the failure paths) with a per-call timeout, where the Supervisor
  sends SIGINT with one fixed grace; every stdout and stderr line kept for assertions, where the
  Supervisor keeps the newest 1000/200 and echoes the logs; a missing summary as an
  AssertionError carrying the stderr tail, where the Supervisor's is None.

What the two share is the Popen call and two reader threads: kept twice, small, on purpose.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from common.config.settings import Settings
from common.contracts.messages import PlantState, Transition
from common.contracts.ros_wire import Odometry
from common.math.frames import quaternion_from_yaw
from common.net.transport import plain_config
from common.system.ports import free_port
from services.robot_bridge.bridge import RobotBridge

ROOT = Path(__file__).resolve().parents[1]


def run_bench(kind: str, robot: str, seconds: float = 4) -> dict[str, Any]:
    """``srl bench <kind> --json`` on a free router port, as a user runs it: its JSON result
    (plus ``"stdout"``, the printed table); fails the test on a non-zero exit."""
    router = f"tcp/127.0.0.1:{free_port()}"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "tools.cli",
            "bench",
            kind,
            "--seconds",
            str(seconds),
            "--json",
            "--router",
            router,
            "--robot",
            robot,
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=180,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return {**json.loads(done.stdout.strip().splitlines()[-1]), "stdout": done.stdout}


class FakeCounts:
    """The counters a service keeps (common.net.transport.Bus.count / reject), in memory, for the
    transport-free logic under test (the robot bridge, the real-time actor, the order gates)."""

    def __init__(self) -> None:
        self.counters: Counter[str] = Counter()

    def count(self, name: str, amount: int = 1) -> None:
        self.counters[name] += amount

    def reject(self, what: str, reason: str) -> None:
        self.counters[f"rejected.{what}"] += 1


def fake_bridge(**bridge: Any) -> tuple[RobotBridge, list[PlantState], list[tuple[float, float]], FakeCounts]:
    """A :class:`RobotBridge` of robot ``u0`` with ``[bridge]`` settings ``bridge``, on fake ports:
    the states it publishes, the (v, omega) it commands, its counters."""
    settings = Settings.load(transport={"robot": "u0"}, bridge=bridge)
    states: list[PlantState] = []
    commands: list[tuple[float, float]] = []
    counts = FakeCounts()
    return RobotBridge(settings, states.append, lambda v, w: commands.append((v, w)), counts), states, commands, counts


def odom_sample(stamp: int, x: float = 0.0, y: float = 0.0, yaw: float = 0.0) -> Odometry:
    """An odometry sample at rest in ``odom``: pose (x, y, yaw), ROS stamp ``stamp`` [ns]."""
    return Odometry(stamp, "odom", "base_footprint", x, y, quaternion_from_yaw(yaw), 0.0, 0.0)


def client_config(endpoint: str) -> zenoh.Config:
    """A client of the srl router at ``endpoint`` as every srl session is configured (its samples
    carry its own id: common.net.provenance), without a login."""
    return plain_config(Settings.load().transport, endpoint)


def declare_service_tokens(session: zenoh.Session, robot: str, service: str) -> list[Any]:
    """Make ``session`` look alive as ``service`` of ``robot``: its liveliness token and its
    identity token (common.contracts.keys.identity_key), as common.net.transport.Bus.declare_alive does."""
    from common.contracts.keys import identity_key, liveliness_key

    liveliness = session.liveliness()
    return [
        liveliness.declare_token(liveliness_key(robot, service)),
        liveliness.declare_token(identity_key(robot, service, str(session.info.zid()))),
    ]


class Proc:
    def __init__(self, name: str, argv: list[str], env: dict[str, str] | None = None) -> None:
        self.name = name
        self.process = subprocess.Popen(
            [sys.executable, "-m", "tools.cli", *argv],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=ROOT,
            env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
            start_new_session=True,
        )
        self.stdout: list[str] = []
        self.stderr: list[str] = []
        self.readers = [
            threading.Thread(target=lambda st=stream, sk=sink: [sk.append(x.rstrip()) for x in st], daemon=True)
            for stream, sink in ((self.process.stdout, self.stdout), (self.process.stderr, self.stderr))
        ]
        for reader in self.readers:
            reader.start()

    def stop(self, sig: int = signal.SIGINT, timeout: float = 10.0) -> int:
        if self.process.poll() is None:
            os.killpg(self.process.pid, sig)
            try:
                self.process.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                os.killpg(self.process.pid, signal.SIGKILL)
                self.process.wait()
        for reader in self.readers:  # every line read: the pipes end when the process group has ended
            reader.join(timeout=2.0)
        return int(self.process.returncode)

    def summary(self) -> dict[str, Any]:
        for line in reversed(self.stdout):
            if line.startswith("{"):
                return dict(json.loads(line))
        raise AssertionError(f"{self.name} printed no JSON summary; stderr: {self.stderr[-10:]}")


def srl_as_from_a_terminal(argv: Sequence[str], env: dict[str, str] | None = None) -> subprocess.Popen[str]:
    """``argv`` (a command line) started in a session of its own, its output piped, with Ctrl-C's
    default action as from a terminal, even when this test runs with SIGINT ignored (a background
    job of a non-interactive shell, ``nohup ... &``, which children inherit)."""
    return subprocess.Popen(
        list(argv),
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )


def srl(*argv: str, env: dict[str, str] | None = None, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    """``srl ARGV`` as a user types it (from the checkout, its output captured; never raises on
    the exit code: the test reads it)."""
    return subprocess.run(
        [sys.executable, "-m", "tools.cli", *argv],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
        env={**os.environ, **(env or {})},
    )


def open_session(endpoint: str, timeout: float = 60, what: str | None = None) -> zenoh.Session:
    """A client session to ``endpoint``, once its router accepts one (it was just started)."""
    held: list[zenoh.Session] = []

    def opened() -> bool:
        try:
            held.append(zenoh.open(client_config(endpoint)))
        except zenoh.ZError:
            return False
        return True

    wait_until(opened, timeout, what or f"the router at {endpoint}")
    return held[0]


def wait_until(predicate: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


class Cluster:
    """A router on a free port plus services started on demand; everything stopped on exit."""

    def __init__(self, robot: str = "t0", extra: list[str] | None = None) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.robot = robot
        self.common = ["--router", self.endpoint, "--robot", robot, *(extra or [])]
        self.procs: dict[str, Proc] = {}
        self.session: zenoh.Session | None = None

    def start(self, name: str, command: str, *args: str, env: dict[str, str] | None = None) -> Proc:
        proc = Proc(name, [command, *self.common, *args], env)
        self.procs[name] = proc
        return proc

    def start_plant_and_critic(self) -> None:
        """A real-time plant_sim and a critic, both alive (the usual ground under an actor)."""
        self.start("plant", "plant-sim", "--mode", "realtime")
        self.start("critic", "critic")
        self.wait_alive("plant")
        self.wait_alive("critic")

    def connect(self) -> zenoh.Session:
        self.session = open_session(self.endpoint, 30, "the router")
        return self.session

    def alive(self, service: str) -> bool:
        assert self.session is not None
        replies = self.session.liveliness().get(f"srl/{self.robot}/alive/{service}", timeout=0.5)
        return any(r.ok is not None for r in replies)

    def wait_alive(self, service: str, timeout: float = 60) -> None:
        proc = self.procs.get(service)

        def ready() -> bool:
            if proc is not None and proc.process.poll() is not None:
                raise AssertionError(f"{service} exited {proc.process.returncode}: {proc.stderr[-10:]}")
            return self.alive(service)

        wait_until(ready, timeout, f"liveliness of {service}")

    def close(self) -> None:
        if self.session is not None:
            self.session.close()
        for proc in reversed(list(self.procs.values())):
            proc.stop()


@contextmanager
def cluster(robot: str = "t0", extra: list[str] | None = None) -> Iterator[Cluster]:
    c = Cluster(robot, extra)
    try:
        c.start("router", "router")
        c.connect()
        yield c
    finally:
        c.close()


def random_transitions(
    steps: int, robots: Sequence[str] = ("r1",), episode: int = 7, seed: int = 3
) -> list[Transition]:
    """Random transitions of robots stepping together: every robot's step k, then step k + 1, ..."""
    rng = np.random.default_rng(seed)
    return [
        Transition(
            robot=robot,
            episode=episode,
            step=k,
            state=tuple(rng.uniform(-2, 2, 3)),
            action=tuple(rng.uniform(-0.2, 0.2, 2)),
            cost=float(rng.uniform(0, 1)),
        )
        for k in range(steps)
        for robot in robots
    ]


class FakeSample:
    """What an Inbox reads of a Zenoh sample: its payload, key and (no) timestamp."""

    def __init__(self, key: str, payload: bytes) -> None:
        self.key_expr, self.timestamp = key, None
        # a new bytes object per call, as Zenoh makes one (the backlog test counts what it holds)
        self.payload = type("Payload", (), {"to_bytes": lambda _: bytes(bytearray(payload))})()


def buses_on_a_fake_session(monkeypatch: Any) -> dict[str, Any]:
    """Every :class:`~common.net.transport.Bus` opened from here on (``Bus.open``) is on a Zenoh
    session that only notes its subscriptions: the dict returned maps a subscribed key to the
    callback Zenoh would call with a sample and whether it recovers. No Zenoh, no thread."""
    from common.net.transport import Bus

    subscribed: dict[str, Any] = {}

    class Session:
        def close(self) -> None:
            pass

    class Subscriber:
        def undeclare(self) -> None:
            pass

    def declare(self: Bus, key: str, callback: Any, recover: bool) -> Subscriber:
        subscribed[key] = (callback, recover)
        return Subscriber()

    monkeypatch.setattr(Bus, "_callback", lambda self, handler, threaded=None: (handler, threaded))
    monkeypatch.setattr(Bus, "_declare_subscriber", declare)
    monkeypatch.setattr(Bus, "open", classmethod(lambda cls, transport, service: cls(Session(), service)))
    return subscribed
