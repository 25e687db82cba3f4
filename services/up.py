"""``srl up``: the router and every service as separate child processes.

Children are ``python -m services.cli <service> ...`` with the same configuration (each gets
only the flags its subcommand takes). Their log lines are forwarded to stderr prefixed with
``[name]``; each prints one JSON summary as its last stdout line when it ends: those are kept,
written to ``<summary_dir>/<name>.json``, never echoed. While the actor runs, its 1 Hz status
(``srl/<robot>/status/actor``) is handed to ``on_status`` (``srl up`` prints a status line).
The actor defines the end of the run: when it exits, the others are stopped (SIGINT, then
SIGKILL after a grace period). If any child dies first, everything is stopped and ``srl up``
exits non-zero naming it. Ctrl-C stops everything cleanly.

``--plant robot`` starts ``robot-bridge`` (and ``tb3-emulator`` unless a robot endpoint is
configured) instead of ``plant-sim``; the bridge is stopped (and has commanded zero velocity)
before everything else.
"""

from __future__ import annotations

import contextlib
import json
import logging
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
from typing import IO, Any

import zenoh

from common.security import write_credentials
from common.settings import Settings
from common.transport import zenoh_config

log = logging.getLogger(__name__)
GRACE_SECONDS = 5.0


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
        from services.cli import child_argv

        command = [sys.executable, "-m", "services.cli", *child_argv(argv)]
        process = subprocess.Popen(
            command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={**self.env, **(env or {})},
            start_new_session=True,  # our Ctrl-C is forwarded by us, in order
        )
        child = Child(name, process)
        echo = None if self.quiet else sys.stderr
        # stdout holds the JSON summary (kilobytes): kept, not echoed; stderr holds the logs
        for stream, sink, keep, shown in ((process.stdout, child.stdout_lines, 1000, None),
                                          (process.stderr, child.stderr_tail, 200, echo)):
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
        """SIGINT every child still running (newest first), then SIGKILL after the grace."""
        alive = [c for c in reversed(list(self.children.values())) if c.process.poll() is None]
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
        for child in self.children.values():
            for thread in child.threads:
                thread.join(timeout=2.0)


def router_reachable(settings: Settings) -> bool:
    try:
        session = zenoh.open(zenoh_config(settings.transport))
    except zenoh.ZError:
        return False
    session.close()
    return True


def alive_probe(settings: Settings, service: str) -> Any:
    from common.transport import Bus

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
    from common.keys import STATE

    seen = threading.Event()
    held: dict[str, Any] = {}

    def probe() -> bool:
        if "session" not in held:
            try:
                held["session"] = zenoh.open(zenoh_config(settings.transport))
            except zenoh.ZError:
                return False
            held["subscriber"] = held["session"].declare_subscriber(
                STATE.key(settings.transport.robot), lambda _: seen.set())
        if seen.wait(0.1):
            held["subscriber"].undeclare()
            held["session"].close()
            return True
        return False

    return probe


class StatusMonitor:
    """The actor's newest 1 Hz status (``srl/<robot>/status/actor``), seen from a monitor session."""

    def __init__(self, settings: Settings) -> None:
        from common.keys import STATUS
        from common.messages import ServiceStatus

        self.latest: dict[str, float] | None = None
        self.seen = 0
        self.session = zenoh.open(zenoh_config(settings.transport))

        def on_sample(sample: Any) -> None:
            try:
                status = ServiceStatus.model_validate_json(sample.payload.to_bytes())
            except ValueError:
                return  # the actor's own schema: a bad one is not ours to report
            self.latest = dict(status.counters)
            self.seen += 1

        self.subscriber = self.session.declare_subscriber(
            STATUS.key(settings.transport.robot, service="actor"), on_sample)

    def close(self) -> None:
        with contextlib.suppress(zenoh.ZError):
            self.subscriber.undeclare()
        self.session.close()


def write_summaries(directory: Path, children: dict[str, Child], merged: dict[str, Any]) -> None:
    """Each child's JSON summary line to ``<name>.json`` and the merged one to ``summary.json``."""
    directory.mkdir(parents=True, exist_ok=True)
    for name, child in children.items():
        summary = child.summary()
        if summary is not None:
            (directory / f"{name}.json").write_text(json.dumps(summary, indent=1) + "\n")
    (directory / "summary.json").write_text(json.dumps(merged, indent=1) + "\n")


def run_up(settings: Settings, settings_args: list[str], mode: str, plant: str, sync_critic: bool,
           duration: float, quiet: bool = False, bridge_args: list[str] | None = None,
           secure: bool = False, on_status: Any = None, summary_dir: Path | None = None) -> dict[str, Any]:
    """Start everything, run one actor episode/duration, stop everything; the merged summary.

    ``plant="robot"``: the robot bridge in place of plant_sim, and the TurtleBot3 emulator as the
    robot unless ``settings.bridge.robot_endpoint`` names a real one. Real time only: a robot
    cannot be stepped by a lockstep query.

    ``secure``: fresh random credentials for every role in a private temporary directory
    (0700, files 0600, removed at exit); the router authenticates users and enforces the role
    rules of common/security.py, each child logs in as its role, this supervisor as ``monitor``.
    """
    if plant not in ("sim", "robot"):
        raise ValueError(f"unknown plant {plant!r} (sim or robot)")
    if plant == "robot" and mode != "realtime":
        raise ValueError("--plant robot runs in real time only: lockstep steps plant_sim through its "
                         "plant/step queryable, and a robot cannot be stepped; use --mode realtime")
    env = dict(os.environ)
    env.setdefault("PYTHONUNBUFFERED", "1")
    supervisor = Supervisor(settings_args, env, quiet=quiet)
    common_args = [*settings_args]
    robot_args = [*common_args, *(bridge_args or [])]
    started = time.monotonic()
    if secure and plant == "robot" and not settings.bridge.robot_endpoint:
        raise ValueError("--secure --plant robot needs the robot on its own Zenoh router (--robot-endpoint): "
                         "the access rules cover srl's keys, not the emulated robot's ROS 2 traffic")
    credentials = write_credentials(Path(tempfile.mkdtemp(prefix="srl-secure-"))) if secure else None
    role: dict[str, dict[str, str]] = {}  # child -> its login environment
    if credentials is not None:
        role = {name: credentials.role_environment(user) for name, user in
                (("plant", "plant"), ("robot_bridge", "plant"), ("critic", "critic"), ("actor", "actor"))}
        role["router"] = credentials.router_environment()
        # this supervisor's own probes log in as the read-only monitor
        settings = settings.model_copy(update={"transport": credentials.transport(settings.transport, "monitor")})
    try:
        supervisor.spawn("router", ["router", *common_args], role.get("router"))
        supervisor.wait_for("router", lambda: router_reachable(settings), timeout=30)
        if plant == "sim":
            supervisor.spawn("plant", ["plant-sim", "--mode", mode, *common_args], role.get("plant"))
        else:
            if not settings.bridge.robot_endpoint:
                supervisor.spawn("tb3_emulator", ["tb3-emulator", *robot_args])
            supervisor.spawn("robot_bridge", ["robot-bridge", *robot_args], role.get("robot_bridge"))
        supervisor.spawn("critic", ["critic", *common_args], role.get("critic"))
        supervisor.wait_for("plant" if plant == "sim" else "robot_bridge", alive_probe(settings, "plant"),
                            timeout=60)
        if plant == "robot":
            supervisor.wait_for(f"the robot's odometry (srl/{settings.transport.robot}/state from the bridge; "
                                f"{settings.bridge.profile}, {settings.bridge.ros_distro}, domain "
                                f"{settings.bridge.domain_id}, namespace '{settings.bridge.namespace}')",
                                state_probe(settings), timeout=60)
        supervisor.wait_for("critic", alive_probe(settings, "critic"), timeout=60)
        actor_args = ["actor", "--mode", mode, *common_args]
        if mode == "realtime":
            actor_args += ["--run-seconds", str(duration)]
        if sync_critic:
            actor_args.append("--sync-critic")
        actor = supervisor.spawn("actor", actor_args, role.get("actor"))
        monitor = StatusMonitor(settings) if on_status is not None else None
        try:
            shown = 0
            while actor.process.poll() is None:
                supervisor.check(allowed_to_exit={"actor"})
                if monitor is not None and monitor.seen > shown and monitor.latest is not None:
                    shown = monitor.seen
                    on_status(monitor.latest)
                time.sleep(0.05)
        finally:
            if monitor is not None:
                monitor.close()
        if actor.process.returncode != 0:
            raise ServiceDiedError("actor", actor.process.returncode, actor.stderr_tail[-10:])
    finally:
        if "robot_bridge" in supervisor.children:  # first, so that its last zero reaches the robot
            supervisor.stop_one("robot_bridge")
        supervisor.stop_all()
        if credentials is not None:
            shutil.rmtree(credentials.directory, ignore_errors=True)
    for name, child in supervisor.children.items():
        code = child.process.returncode
        if name != "actor" and code not in (0, -signal.SIGINT):
            raise ServiceDiedError(name, code, child.stderr_tail[-10:])
    actor_summary = supervisor.children["actor"].summary() or {}
    critic_summary = supervisor.children["critic"].summary() or {}
    merged = dict(actor_summary)
    merged.pop("transitions_tail", None)  # kept in actor.json
    if plant == "robot":
        merged["bridge"] = supervisor.children["robot_bridge"].summary()
        if "tb3_emulator" in supervisor.children:
            merged["emulator"] = supervisor.children["tb3_emulator"].summary()
    merged.update({
        "services": {name: child.process.pid for name, child in supervisor.children.items()},
        "exit_codes": {name: child.process.returncode for name, child in supervisor.children.items()},
        "mode": mode,
        "plant": plant,
        "secure": secure,
        "transitions_received": critic_summary.get("transitions_received"),
        "critic_weights_published": critic_summary.get("weights_published"),
        "critic_fit_ms": critic_summary.get("fit_ms"),
        "critic_checkpoint": critic_summary.get("checkpoint"),
        "critic_restored": critic_summary.get("restored"),
        "wall_seconds": time.monotonic() - started,
        "resources": {name: (child.summary() or {}).get("resources") for name, child in supervisor.children.items()},
    })
    if summary_dir is not None:
        merged["summary_dir"] = str(summary_dir)
        write_summaries(summary_dir, supervisor.children, merged)
    return merged
