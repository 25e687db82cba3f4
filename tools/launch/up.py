"""``srl up``: the router and every service as separate child processes.

Children are ``python -m tools.cli <service> ...`` with the same configuration (each gets
only the flags its subcommand takes). Their log lines are forwarded to stderr prefixed with
``[name]``; each prints one JSON summary as its last stdout line when it ends: those are kept,
written to ``<summary_dir>/<name>.json``, never echoed. While the actor runs, its 1 Hz status
(``srl/<robot>/status/actor``) is handed to ``on_status`` (``srl up`` prints a status line).
The actor defines the end of the run: when it exits, the others are stopped (SIGINT, then
SIGKILL after a grace period). If any child dies first, everything is stopped and ``srl up``
exits non-zero naming it. SIGINT (Ctrl-C), SIGTERM and SIGHUP all stop everything the same
way (children by pid, credentials removed) and ``srl up`` exits with 128 + the signal number
(130, 143, 129). Every child gets ``SRL_PARENT_PID``: it dies with this process even when this
process is killed with SIGKILL (common/system/lifeline.py).

``--plant physics`` is ``plant-sim`` with ``plant.model = "physics"`` (the MuJoCo TurtleBot3,
common/math/physics.py) for every child. ``--plant robot`` starts ``robot-bridge`` (and
``tb3-emulator``, of ``plant.model``, unless a robot endpoint is configured) instead of
``plant-sim``; the bridge is stopped (and has commanded zero velocity) before everything else. The
emulator runs as the robot's own Zenoh router on a free loopback port (as a real robot runs
``rmw_zenohd``) and the bridge talks to it there: when srl's router dies, the
bridge still reaches the robot and stops it (the actor's liveliness token vanishes from the
bridge's srl session within milliseconds).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, TypeVar

import zenoh
from pydantic import TypeAdapter, ValidationError

from common.config.settings import Settings, TransportSettings
from common.contracts.summaries import (
    ACTOR_SUMMARY,
    BridgeSummary,
    CriticSummary,
    EmulatorSummary,
    LockstepActorSummary,
    PlantSummary,
    RealtimeActorSummary,
    RouterSummary,
)
from common.math.frames import Pose2D, to_goal_frame
from common.net.certs import write_tls_material
from common.net.security import ROLES, write_credentials
from common.net.transport import zenoh_config

log = logging.getLogger(__name__)
GRACE_SECONDS = 5.0
T = TypeVar("T")
# the children's contracts besides the actor's and the critic's (common/contracts/summaries.py)
OtherSummary = RouterSummary | PlantSummary | BridgeSummary | EmulatorSummary
CHILD_SUMMARIES: dict[str, type[OtherSummary]] = {
    "router": RouterSummary,
    "plant": PlantSummary,
    "robot_bridge": BridgeSummary,
    "tb3_emulator": EmulatorSummary,
}
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class Stopped(KeyboardInterrupt):
    """``srl up`` was stopped by a signal; everything has been cleaned up as for Ctrl-C.

    A KeyboardInterrupt, so that a caller that handles Ctrl-C handles SIGTERM and SIGHUP alike."""

    def __init__(self, signum: int) -> None:
        self.signum = signum
        super().__init__(signal.Signals(signum).name)

    @property
    def exit_code(self) -> int:
        """The shell's convention: 128 + the signal number (SIGINT 130, SIGTERM 143, SIGHUP 129)."""
        return 128 + self.signum


class SignalGuard:
    """While active, SIGINT, SIGTERM and SIGHUP raise :class:`Stopped` in the main thread, once.

    During cleanup (``cleaning``) a signal is only remembered, never raised: an exception in the
    middle of stopping the children would leave some of them running and the credentials on disk.
    """

    def __init__(self) -> None:
        self.cleaning = False
        self.received: int | None = None
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> SignalGuard:
        if threading.current_thread() is threading.main_thread():  # signals reach the main thread only
            for signum in STOP_SIGNALS:
                self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def _handle(self, signum: int, _frame: Any) -> None:
        first = self.received is None
        self.received = self.received or signum
        if self.cleaning or not first:
            log.warning("srl up: %s while stopping: finishing the cleanup", signal.Signals(signum).name)
            return
        log.warning("srl up: %s: stopping every service", signal.Signals(signum).name)
        raise Stopped(signum)

    def __exit__(self, *exc: object) -> None:
        for signum, previous in self._previous.items():
            signal.signal(signum, previous)

    def raise_if_received(self) -> None:
        """After the cleanup: a signal that came during it still ends the run as stopped."""
        if self.received is not None:
            raise Stopped(self.received)


def physics_plant(settings: Settings, env: dict[str, str]) -> Settings:
    """``--plant physics``: plant_sim (or the plant host) with the MuJoCo TurtleBot3; every child
    sees it through ``env``, and the settings returned say it to this process."""
    env["SRL_PLANT__MODEL"] = "physics"
    return settings.model_copy(update={"plant": settings.plant.model_copy(update={"model": "physics"})})


def _contract_summary(child: Child, contract: TypeAdapter[T]) -> T:
    """A child's JSON summary read through its contract; one line if it has none or does not fit."""
    raw = child.summary()
    if raw is None:
        raise ValueError(f"{child.name} ended without its JSON summary (its last stdout line)")
    try:
        return contract.validate_python(raw)
    except ValidationError as error:
        first = error.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise ValueError(
            f"{child.name}'s summary does not fit common/contracts/summaries.py: {where}: {first['msg']}"
        ) from None


def optional_summary(child: Child, contract: TypeAdapter[T]) -> T | None:
    """A child's summary through its contract, or None if it printed none (a child killed after
    the grace); one that does not fit raises as :func:`_contract_summary` does."""
    return None if child.summary() is None else _contract_summary(child, contract)


def free_loopback_endpoint() -> str:
    """``tcp/127.0.0.1:<port>`` on a port that was free a moment ago (the OS picked it)."""
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{sock.getsockname()[1]}"


class ServiceDiedError(RuntimeError):
    def __init__(self, name: str, code: int | None, tail: list[str]) -> None:
        self.name, self.code, self.tail = name, code, tail
        super().__init__(f"service {name!r} exited with code {code} before the run ended")


@dataclass
class Child:
    name: str
    process: subprocess.Popen[str]
    stdout_lines: list[str] = field(default_factory=list)
    stderr_tail: list[str] = field(default_factory=list)
    threads: list[threading.Thread] = field(default_factory=list)

    def summary(self) -> dict[str, Any] | None:
        for line in reversed(self.stdout_lines):
            if line.startswith("{"):
                try:
                    return json.loads(line)
                except json.JSONDecodeError:
                    return None
        return None


def _pump(stream: IO[str], name: str, sink: list[str], echo: IO[str] | None, keep: int | None) -> None:
    """Keep a child's lines (``keep`` at most); echo them (its logs) if ``echo``."""
    for line in stream:
        line = line.rstrip("\n")
        sink.append(line)
        if keep is not None and len(sink) > keep:
            del sink[0]
        if echo is not None:
            echo.write(f"[{name}] {line}\n")
            echo.flush()


class Supervisor:
    def __init__(self, settings_args: list[str], env: dict[str, str], quiet: bool = False) -> None:
        self.settings_args = settings_args
        self.env = env
        self.quiet = quiet
        self.children: dict[str, Child] = {}

    def spawn(self, name: str, argv: list[str], env: dict[str, str] | None = None) -> Child:
        from common.config.arguments import child_argv

        command = [sys.executable, "-m", "tools.cli", *child_argv(argv)]
        process = subprocess.Popen(
            command,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            # SRL_PARENT_PID: the child stops when this process dies, however it dies (common/system/lifeline.py)
            env={**self.env, **(env or {}), "SRL_PARENT_PID": str(os.getpid())},
            start_new_session=True,  # our Ctrl-C is forwarded by us, in order
        )
        child = Child(name, process)
        echo = None if self.quiet else sys.stderr
        # stdout holds the JSON summary (kilobytes): kept, not echoed; stderr holds the logs
        for stream, sink, keep, shown in (
            (process.stdout, child.stdout_lines, 1000, None),
            (process.stderr, child.stderr_tail, 200, echo),
        ):
            thread = threading.Thread(target=_pump, args=(stream, name, sink, shown, keep), daemon=True)
            thread.start()
            child.threads.append(thread)
        self.children[name] = child
        log.info("started %s (pid %d)", name, process.pid)
        return child

    def check(self, allowed_to_exit: set[str] = frozenset()) -> None:  # type: ignore[assignment]
        for child in self.children.values():
            code = child.process.poll()
            if code is not None and child.name not in allowed_to_exit:
                for thread in child.threads:
                    thread.join(timeout=1.0)
                raise ServiceDiedError(child.name, code, child.stderr_tail[-10:])

    def wait_for(self, what: str, probe: Any, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.check()
            if probe():
                return
            time.sleep(0.05)
        raise TimeoutError(f"{what} not ready after {timeout:.0f} s")

    def stop_one(self, name: str) -> None:
        """SIGINT one child and wait for it (SIGKILL after the grace period)."""
        child = self.children[name]
        if child.process.poll() is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            os.killpg(child.process.pid, signal.SIGINT)
        try:
            child.process.wait(timeout=GRACE_SECONDS)
        except subprocess.TimeoutExpired:
            log.warning("%s did not stop within %.0f s: killing it", name, GRACE_SECONDS)
            os.killpg(child.process.pid, signal.SIGKILL)
            child.process.wait()

    def stop_all(self) -> None:
        """SIGINT every service still running (newest first) and wait for them, SIGKILL after the
        grace; the router last, once nobody is left to say goodbye through it (a router closing
        under its clients' last messages was seen to outlast the grace on a loaded CI machine)."""
        services = [c for c in reversed(list(self.children.values())) if c.name != "router"]
        self._stop_group(services)
        self._stop_group([c for c in self.children.values() if c.name == "router"])
        for child in self.children.values():
            for thread in child.threads:
                thread.join(timeout=2.0)

    def _stop_group(self, children: list[Child]) -> None:
        alive = [c for c in children if c.process.poll() is None]
        for child in alive:
            with contextlib.suppress(ProcessLookupError):  # it ended meanwhile
                os.killpg(child.process.pid, signal.SIGINT)
        deadline = time.monotonic() + GRACE_SECONDS
        for child in alive:
            try:
                child.process.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop within %.0f s: killing it", child.name, GRACE_SECONDS)
                os.killpg(child.process.pid, signal.SIGKILL)
                child.process.wait()


def router_reachable(settings: Settings, endpoint: str | None = None) -> bool:
    """Can a client session open to srl's router (or, without login, to ``endpoint``)?"""
    transport = settings.transport
    if endpoint is not None:
        transport = transport.model_copy(update={"router": endpoint, "connect": [], "secure": False})
    try:
        session = zenoh.open(zenoh_config(transport))
    except zenoh.ZError:
        return False
    session.close()
    return True


def alive_probe(settings: Settings, service: str) -> Any:
    from common.net.transport import Bus

    state: dict[str, Bus | None] = {"bus": None}

    def probe() -> bool:
        if state["bus"] is None:
            try:
                state["bus"] = Bus.open(settings.transport, "up")
            except zenoh.ZError:
                return False
        bus = state["bus"]
        assert bus is not None
        if bus.is_alive(settings.transport.robot, service, timeout=0.5):
            bus.close()
            return True
        return False

    return probe


def state_probe(settings: Settings) -> Any:
    """True once a state sample has been seen (the robot's odometry came through the bridge)."""
    from common.contracts.keys import STATE

    seen = threading.Event()
    held: dict[str, Any] = {}

    def probe() -> bool:
        if "session" not in held:
            try:
                held["session"] = zenoh.open(zenoh_config(settings.transport))
            except zenoh.ZError:
                return False
            held["subscriber"] = held["session"].declare_subscriber(
                STATE.key(settings.transport.robot), lambda _: seen.set()
            )
        if seen.wait(0.1):
            held["subscriber"].undeclare()
            held["session"].close()
            return True
        return False

    return probe


def _tls_endpoint(endpoint: str) -> str | None:
    """``tcp/H:P`` -> ``tls/H:P`` (``srl up --secure``); a tls/ endpoint as is; None for others."""
    if endpoint.startswith("tls/"):
        return endpoint
    return "tls/" + endpoint[len("tcp/") :] if endpoint.startswith("tcp/") else None


@dataclass
class Logins:
    """One secure run's logins (``srl up --secure``, also with ``--robots``): fresh random
    credentials for every role in a private temporary directory, and mutual TLS on the same
    address when the router's endpoint is tcp/. ``environment`` is the login environment of each
    role's children and of the router (``"router"``); ``monitor`` is the transport this process's
    own probes log in with; :meth:`argv` moves the children's ``--router`` to the TLS endpoint;
    :meth:`remove` deletes every secret (the caller's ``finally``)."""

    directory: Path
    environment: dict[str, dict[str, str]]
    monitor: TransportSettings
    tls_router: str | None

    @classmethod
    def create(cls, transport: TransportSettings, *, lockstep: bool, robots: list[str] | None = None) -> Logins:
        """``robots``: the fleet whose keys the router's rules grant (default: transport.robot)."""
        credentials = write_credentials(Path(tempfile.mkdtemp(prefix="srl-secure-")))
        try:
            environment = {user: credentials.role_environment(user) for user in ("actor", "critic", "plant")}
            environment["router"] = credentials.router_environment(lockstep=lockstep)
            if robots is not None:
                environment["router"]["SRL_TRANSPORT__ACL_ROBOTS"] = ",".join(robots)
            monitor = credentials.transport(transport, "monitor")
            tls_router = _tls_endpoint(transport.router)
            if tls_router is not None:  # the same address over mutual TLS (certificates next to the passwords)
                tls = write_tls_material(credentials.directory / "tls", ROLES)
                for user in environment:
                    environment[user] = {
                        **environment[user],
                        **tls.environment(user),
                        "SRL_TRANSPORT__ROUTER": tls_router,
                    }
                monitor = monitor.model_copy(
                    update={
                        "router": tls_router,
                        "tls_ca": str(tls.ca),
                        "tls_cert": str(tls.cert("monitor")),
                        "tls_key": str(tls.key("monitor")),
                    }
                )
        except BaseException:
            shutil.rmtree(credentials.directory, ignore_errors=True)
            raise
        return cls(credentials.directory, environment, monitor, tls_router)

    def argv(self, args: list[str]) -> list[str]:
        if self.tls_router is None:
            return list(args)
        return [f"--router={self.tls_router}" if arg.startswith("--router=") else arg for arg in args]

    def remove(self) -> None:
        shutil.rmtree(self.directory, ignore_errors=True)


class StatusMonitor:
    """The actor's newest 1 Hz status (``srl/<robot>/status/actor``), seen from a monitor session,
    with the plant's refusal counters (``srl/<robot>/status/plant``: the bridge's refused and
    resynchronized actions, issue 13) merged in under ``plant.``."""

    def __init__(self, settings: Settings) -> None:
        from common.contracts.keys import STATUS
        from common.contracts.messages import ServiceStatus

        self.actor: dict[str, float] | None = None
        self.plant: dict[str, float] = {}
        self.seen = 0
        self.session = zenoh.open(zenoh_config(settings.transport))

        def on_sample(sample: Any) -> None:
            try:
                status = ServiceStatus.model_validate_json(sample.payload.to_bytes())
            except ValueError:
                return  # the actor's own schema: a bad one is not ours to report
            if status.service == "actor":
                self.actor = dict(status.counters)
                self.seen += 1
            else:  # only what says whether actions are being refused: the line stays short
                self.plant = {
                    f"plant.{k}": v
                    for k, v in status.counters.items()
                    if k.startswith("rejected.action") or k == "action_resyncs"
                }

        robot = settings.transport.robot
        self.subscribers = [
            self.session.declare_subscriber(STATUS.key(robot, service=service), on_sample)
            for service in ("actor", "plant")
        ]

    @property
    def latest(self) -> dict[str, float] | None:
        return None if self.actor is None else {**self.actor, **self.plant}

    def close(self) -> None:
        for subscriber in self.subscribers:
            with contextlib.suppress(zenoh.ZError):
                subscriber.undeclare()
        self.session.close()


def emulator_truth(emulator: dict[str, Any] | None, settings: Settings) -> dict[str, Any] | None:
    """The emulated robot's true final pose in the goal frame (the actor saw only its odometry,
    so the actor's ``truth`` is null: the emulator is the one that knows)."""
    if not emulator or "final_pose" not in emulator:
        return None
    goal = Pose2D(*settings.bridge.goal)
    true = to_goal_frame(Pose2D(*emulator["final_pose"]), goal)
    reported = to_goal_frame(Pose2D(*emulator.get("final_odometry", emulator["final_pose"])), goal)
    return {
        "model": emulator.get("model", "ideal"),
        "final_state": [true.x, true.y, true.theta],
        "final_distance": float(math.hypot(true.x, true.y)),
        "odometry_final_state": [reported.x, reported.y, reported.theta],
        "saturated_commands": emulator.get("saturated_commands"),
    }


def write_summaries(directory: Path, children: dict[str, Child], merged: dict[str, Any]) -> None:
    """Each child's JSON summary line to ``<name>.json`` and the merged one to ``summary.json``."""
    directory.mkdir(parents=True, exist_ok=True)
    for name, child in children.items():
        summary = child.summary()
        if summary is not None:
            (directory / f"{name}.json").write_text(json.dumps(summary, indent=1) + "\n")
    (directory / "summary.json").write_text(json.dumps(merged, indent=1) + "\n")


def run_up(
    settings: Settings,
    settings_args: list[str],
    mode: str,
    plant: str,
    sync_critic: bool,
    duration: float,
    quiet: bool = False,
    bridge_args: list[str] | None = None,
    secure: bool = False,
    on_status: Any = None,
    summary_dir: Path | None = None,
    record: Path | None = None,
    view_port: int | None = None,
) -> dict[str, Any]:
    """Start everything, run one actor episode/duration, stop everything; the merged summary.

    ``plant="robot"``: the robot bridge in place of plant_sim, and the TurtleBot3 emulator as the
    robot unless ``settings.bridge.robot_endpoint`` names a real one. The emulator is the robot's
    own Zenoh router (``--listen`` on a free loopback port) and the bridge its client, so the
    bridge's path to the robot does not go through srl's router. Real time only: a robot cannot
    be stepped by a lockstep query.

    ``secure``: fresh random credentials for every role in a private temporary directory
    (0700, files 0600, removed at exit); the router authenticates users and enforces the role
    rules of common/net/security.py (plant/step and plant/reset in lockstep only), each child logs in
    as its role, this supervisor as ``monitor``.
    A ``tcp/`` router endpoint becomes ``tls/`` on the same address, with mutual TLS from a
    fresh private CA and one certificate per role in the same directory (common/net/certs.py).

    ``record``: an ``srl record`` child writes every robot to this MCAP file (``--clock steps`` in
    lockstep); ``view_port``: an ``srl view`` child serves the run to Foxglove on that loopback port.
    Both start before the plant and stop after everything but the router, so they see it all.

    SIGINT, SIGTERM and SIGHUP stop everything as Ctrl-C does, then raise :class:`Stopped`.
    """
    if secure and (record is not None or view_port is not None):
        raise ValueError(
            "--record and --view do not run with --secure yet: the read-only monitor role may read "
            "only states and status, not the transitions and weights a recording carries"
        )
    if record is not None:  # a bad path is one line now, before anything starts
        from tools.recording.record import RecordingError, open_for_writing

        try:
            open_for_writing(record).close()
        except RecordingError as error:
            raise ValueError(str(error)) from None
    if plant not in ("sim", "robot", "physics"):
        raise ValueError(f"unknown plant {plant!r} (sim, robot or physics)")
    if plant == "robot" and mode != "realtime":
        raise ValueError(
            "--plant robot runs in real time only: lockstep steps plant_sim through its "
            "plant/step queryable, and a robot cannot be stepped; use --mode realtime"
        )
    env = dict(os.environ)
    env.setdefault("PYTHONUNBUFFERED", "1")
    if plant == "physics":
        settings = physics_plant(settings, env)
    supervisor = Supervisor(settings_args, env, quiet=quiet)
    robot_args = [*settings_args, *(bridge_args or [])]
    started = time.monotonic()
    with SignalGuard() as guard:
        summary = _run_up(
            settings,
            settings_args,
            mode,
            plant,
            sync_critic,
            duration,
            supervisor,
            robot_args,
            secure,
            started,
            guard,
            on_status,
            summary_dir,
            record,
            view_port,
        )
    return summary


def _run_up(
    settings: Settings,
    settings_args: list[str],
    mode: str,
    plant: str,
    sync_critic: bool,
    duration: float,
    supervisor: Supervisor,
    robot_args: list[str],
    secure: bool,
    started: float,
    guard: SignalGuard,
    on_status: Any,
    summary_dir: Path | None,
    record: Path | None = None,
    view_port: int | None = None,
) -> dict[str, Any]:
    common_args = [*settings_args]
    logins = Logins.create(settings.transport, lockstep=mode == "lockstep") if secure else None
    role: dict[str, dict[str, str]] = {}  # child -> its login environment
    if logins is not None:
        users = {"plant": "plant", "robot_bridge": "plant", "critic": "critic", "actor": "actor", "router": "router"}
        role = {name: logins.environment[user] for name, user in users.items()}
        common_args, robot_args = logins.argv(common_args), logins.argv(robot_args)
        # this supervisor's own probes log in as the read-only monitor
        settings = settings.model_copy(update={"transport": logins.monitor})
    try:
        supervisor.spawn("router", ["router", *common_args], role.get("router"))
        supervisor.wait_for("router", lambda: router_reachable(settings), timeout=30)
        observers = []  # srl record / srl view: subscribed before the first state is published
        if record is not None:
            clock = "steps" if mode == "lockstep" else "wall"
            argv = ["record", str(record), "--clock", clock, *common_args]
            observers.append(("recorder", argv, "srl record: recording"))
        if view_port is not None:
            observers.append(("view", ["view", "--port", str(view_port), *common_args], "srl view: serving"))
        for name, argv, ready in observers:
            child = supervisor.spawn(name, argv)
            supervisor.wait_for(name, lambda c=child, r=ready: any(r in line for line in c.stderr_tail), timeout=30)
        if plant in ("sim", "physics"):
            supervisor.spawn("plant", ["plant-sim", "--mode", mode, *common_args], role.get("plant"))
        else:
            robot_endpoint = settings.bridge.robot_endpoint
            if not robot_endpoint:  # the emulated robot runs its own Zenoh router, as a real one does
                robot_endpoint = free_loopback_endpoint()
                supervisor.spawn("tb3_emulator", ["tb3-emulator", *robot_args, "--listen", robot_endpoint])
                log.info("the emulated robot's Zenoh router: %s", robot_endpoint)
                supervisor.wait_for(
                    f"the emulated robot's router ({robot_endpoint})",
                    lambda: router_reachable(settings, robot_endpoint),
                    timeout=30,
                )
            supervisor.spawn(
                "robot_bridge",
                ["robot-bridge", *robot_args, f"--robot-endpoint={robot_endpoint}"],
                role.get("robot_bridge"),
            )
        supervisor.spawn("critic", ["critic", *common_args], role.get("critic"))
        supervisor.wait_for("plant" if plant != "robot" else "robot_bridge", alive_probe(settings, "plant"), timeout=60)
        if plant == "robot":
            supervisor.wait_for(
                f"the robot's odometry (srl/{settings.transport.robot}/state from the bridge; "
                f"{settings.bridge.profile}, {settings.bridge.ros_distro}, domain "
                f"{settings.bridge.domain_id}, namespace '{settings.bridge.namespace}')",
                state_probe(settings),
                timeout=60,
            )
        supervisor.wait_for("critic", alive_probe(settings, "critic"), timeout=60)
        actor_args = ["actor", "--mode", mode, *common_args]
        if mode == "realtime":
            actor_args += ["--run-seconds", str(duration)]
        if sync_critic:
            actor_args.append("--sync-critic")
        actor = supervisor.spawn("actor", actor_args, role.get("actor"))
        status = StatusMonitor(settings) if on_status is not None else None
        try:
            shown = 0
            while actor.process.poll() is None:
                supervisor.check(allowed_to_exit={"actor"})
                if status is not None and status.seen > shown and status.latest is not None:
                    shown = status.seen
                    on_status(status.latest)
                time.sleep(0.05)
        finally:
            if status is not None:
                status.close()
        if actor.process.returncode != 0:
            raise ServiceDiedError("actor", actor.process.returncode, actor.stderr_tail[-10:])
    finally:
        guard.cleaning = True  # a signal from here on is remembered, never raised mid-cleanup
        if "robot_bridge" in supervisor.children:  # first, so that its last zero reaches the robot
            supervisor.stop_one("robot_bridge")
        supervisor.stop_all()
        if logins is not None:
            logins.remove()
    guard.raise_if_received()
    for name, child in supervisor.children.items():
        code = child.process.returncode
        if name != "actor" and code not in (0, -signal.SIGINT):
            raise ServiceDiedError(name, code, child.stderr_tail[-10:])
    # the children's summaries through their contracts (common/contracts/summaries.py): a service that
    # printed none, or one that does not fit, is said here, not met later as a missing key
    actor_summary = _contract_summary(supervisor.children["actor"], ACTOR_SUMMARY)
    critic_summary = _contract_summary(supervisor.children["critic"], TypeAdapter(CriticSummary))
    # the others as far as they printed one (the router's may be cut by its bounded close)
    others: dict[str, OtherSummary] = {
        name: summary
        for name, child in supervisor.children.items()
        if name in CHILD_SUMMARIES
        and (summary := optional_summary(child, TypeAdapter(CHILD_SUMMARIES[name]))) is not None
    }
    parsed: dict[str, OtherSummary | CriticSummary | RealtimeActorSummary | LockstepActorSummary] = {
        "actor": actor_summary,
        "critic": critic_summary,
        **others,
    }
    merged = actor_summary.to_json_dict()
    merged.pop("transitions_tail", None)  # kept in actor.json
    if plant == "robot":
        bridge = others.get("robot_bridge")
        merged["bridge"] = None if bridge is None else bridge.to_json_dict()
        if "tb3_emulator" in supervisor.children:
            emulator = others.get("tb3_emulator")
            merged["emulator"] = None if emulator is None else emulator.to_json_dict()
            merged["emulator_truth"] = None if emulator is None else emulator_truth(merged["emulator"], settings)
    merged.update(
        {
            "services": {name: child.process.pid for name, child in supervisor.children.items()},
            "exit_codes": {name: child.process.returncode for name, child in supervisor.children.items()},
            "mode": mode,
            "plant": plant,
            "plant_model": settings.plant.model,  # the simulated robot's model (the truth line names it)
            "secure": secure,
            "router": settings.transport.router,
            "transitions_received": critic_summary.transitions_received,
            "critic_weights_published": critic_summary.weights_published,
            "critic_fit_ms": critic_summary.fit_ms.to_json_dict(),
            "critic_checkpoint": critic_summary.checkpoint,
            "critic_restored": critic_summary.restored,
            "wall_seconds": time.monotonic() - started,
            "resources": {name: parsed[name].resources if name in parsed else None for name in supervisor.children},
        }
    )
    if record is not None:
        merged["recording"] = str(record)
        merged["recorder"] = next(
            (line for line in supervisor.children["recorder"].stdout_lines if line.startswith("srl record:")), None
        )
    if view_port is not None:
        merged["view"] = supervisor.children["view"].summary()
    if summary_dir is not None:
        merged["summary_dir"] = str(summary_dir)
        write_summaries(summary_dir, supervisor.children, merged)
    return merged
