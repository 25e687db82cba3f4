"""``srl up``: the router and every service as separate child processes.

Children are ``python -m services.cli <service> ...`` with the same configuration. Their log
lines are forwarded to stderr prefixed with ``[name]``; each prints one JSON summary as its last
stdout line when it ends. The actor defines the end of the run: when it exits, the others are
stopped (SIGINT, then SIGKILL after a grace period). If any child dies first, everything is
stopped and ``srl up`` exits non-zero naming it. Ctrl-C stops everything cleanly.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import IO, Any

import zenoh

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

    def spawn(self, name: str, argv: list[str]) -> Child:
        command = [sys.executable, "-m", "services.cli", *argv]
        process = subprocess.Popen(
            command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=self.env,
            start_new_session=True,  # our Ctrl-C is forwarded by us, in order
        )
        child = Child(name, process)
        echo = None if self.quiet else sys.stderr
        for stream, sink, keep in ((process.stdout, child.stdout_lines, None),
                                   (process.stderr, child.stderr_tail, 200)):
            thread = threading.Thread(target=_pump, args=(stream, name, sink, echo, keep), daemon=True)
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


def run_up(settings: Settings, settings_args: list[str], mode: str, plant: str, sync_critic: bool,
           duration: float, quiet: bool = False) -> dict[str, Any]:
    """Start everything, run one actor episode/duration, stop everything; the merged summary."""
    if plant != "sim":
        raise ValueError("--plant robot needs the robot bridge, which this build does not have yet")
    env = dict(os.environ)
    env.setdefault("PYTHONUNBUFFERED", "1")
    supervisor = Supervisor(settings_args, env, quiet=quiet)
    common_args = [*settings_args]
    started = time.monotonic()
    try:
        supervisor.spawn("router", ["router", *common_args])
        supervisor.wait_for("router", lambda: router_reachable(settings), timeout=30)
        supervisor.spawn("plant", ["plant-sim", "--mode", mode, *common_args])
        supervisor.spawn("critic", ["critic", *common_args])
        supervisor.wait_for("plant", alive_probe(settings, "plant"), timeout=60)
        supervisor.wait_for("critic", alive_probe(settings, "critic"), timeout=60)
        actor_args = ["actor", "--mode", mode, *common_args]
        if mode == "realtime":
            actor_args += ["--run-seconds", str(duration)]
        if sync_critic:
            actor_args.append("--sync-critic")
        actor = supervisor.spawn("actor", actor_args)
        while actor.process.poll() is None:
            supervisor.check(allowed_to_exit={"actor"})
            time.sleep(0.05)
        if actor.process.returncode != 0:
            raise ServiceDiedError("actor", actor.process.returncode, actor.stderr_tail[-10:])
    finally:
        supervisor.stop_all()
    for name in ("router", "plant", "critic"):
        code = supervisor.children[name].process.returncode
        if code not in (0, -signal.SIGINT):
            raise ServiceDiedError(name, code, supervisor.children[name].stderr_tail[-10:])
    actor_summary = supervisor.children["actor"].summary() or {}
    critic_summary = supervisor.children["critic"].summary() or {}
    merged = dict(actor_summary)
    merged.update({
        "services": {name: child.process.pid for name, child in supervisor.children.items()},
        "exit_codes": {name: child.process.returncode for name, child in supervisor.children.items()},
        "mode": mode,
        "plant": plant,
        "transitions_received": critic_summary.get("transitions_received"),
        "critic_weights_published": critic_summary.get("weights_published"),
        "critic_fit_ms": critic_summary.get("fit_ms"),
        "wall_seconds": time.monotonic() - started,
        "resources": {name: (child.summary() or {}).get("resources") for name, child in supervisor.children.items()},
    })
    return merged
