"""The supervisor of srl's child processes, shared by ``srl up``, the fleet, the experiment and the
benchmarks: children started and stopped, their output kept, their readiness probed, a secure
run's logins, and the stop signals.

Children are ``python -m tools.cli <command> ...`` (each gets only the flags its subcommand
takes). Their log lines are forwarded to stderr prefixed with ``[name]``; each prints one JSON
summary as its last stdout line when it ends: those are kept, never echoed. A child is stopped by
SIGINT to its process group, SIGKILL after a grace period. Every child gets ``SRL_PARENT_PID``: it
dies with this process even when this process is killed with SIGKILL (common/system/lifeline.py).
SIGINT (Ctrl-C), SIGTERM and SIGHUP all stop a run the same way (:class:`StopSignals`): children
by pid, credentials removed, then :class:`Stopped` (exit 128 + the signal number: 130, 143, 129).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, TypeVar

import zenoh
from pydantic import TypeAdapter, ValidationError

from common.config.settings import Settings, TransportSettings
from common.contracts.summaries import BridgeSummary, EmulatorSummary, PlantSummary, RouterSummary
from common.net.certs import write_tls_material
from common.net.security import ROLES, write_credentials
from common.net.transport import zenoh_config
from common.process.runtime import SignalWatch
from common.system.jit import remove_orphan_build_directories
from common.system.lifeline import stop_group
from common.system.ports import free_port

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
# SignalWatch hands one signal over twice (its wakeup fd and its handler): a repeat of the same
# signal this soon after it is that one signal, not a second Ctrl-C
SAME_SIGNAL_SECONDS = 0.2


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


class StopSignals:
    """While active, SIGINT, SIGTERM and SIGHUP stop the run: the first is kept, and :meth:`check`
    (called by :meth:`Supervisor.check`, so by every wait and poll of a run) raises
    :class:`Stopped` in the main thread.

    The signal is taken by common.process.runtime.SignalWatch: its handler only writes to a pipe
    and a thread of its own records it here, so a signal never raises inside a lock or native
    code. During cleanup (``cleaning``) a signal is only remembered, never raised: an exception in
    the middle of stopping the children would leave some of them running and the credentials on
    disk; :meth:`raise_if_received` ends the run as stopped after it. Signals reach the main
    thread only: elsewhere the guard does nothing.
    """

    def __init__(self) -> None:
        self.cleaning = False
        self.received: int | None = None
        self._received_at = 0.0
        self._said_cleaning = False
        self._watch: SignalWatch | None = None

    def __enter__(self) -> StopSignals:
        if threading.current_thread() is threading.main_thread():
            self._watch = SignalWatch(self._on_signal, STOP_SIGNALS).start()
        return self

    def _on_signal(self, signum: int) -> None:
        """On the watch's thread: remember the first signal; say a later one once."""
        name = signal.Signals(signum).name
        if self.received is None:
            self.received, self._received_at = signum, time.monotonic()
            log.warning("srl up: %s: stopping every service", name)
        elif signum == self.received and time.monotonic() - self._received_at < SAME_SIGNAL_SECONDS:
            return
        elif self.cleaning and not self._said_cleaning:
            self._said_cleaning = True
            log.warning("srl up: %s while stopping: finishing the cleanup", name)

    def check(self) -> None:
        """In the main thread, between two steps of a run: :class:`Stopped` once a signal came."""
        if self.received is not None and not self.cleaning:
            raise Stopped(self.received)

    def __exit__(self, *exc: object) -> None:
        if self._watch is not None:
            self._watch.close()
            self._watch = None

    def raise_if_received(self) -> None:
        """After the cleanup: a signal that came during it still ends the run as stopped."""
        if self.received is not None:
            raise Stopped(self.received)


def contract_summary(child: Child, contract: TypeAdapter[T]) -> T:
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
    the grace); one that does not fit raises as :func:`contract_summary` does."""
    return None if child.summary() is None else contract_summary(child, contract)


def free_loopback_endpoint() -> str:
    """``tcp/127.0.0.1:<port>`` on a port that was free a moment ago (common/system/ports.py)."""
    return f"tcp/127.0.0.1:{free_port()}"


LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1", "[::1]")


def loopback_endpoint_free(endpoint: str) -> bool:
    """Whether ``endpoint`` is a ``tcp/`` address of this machine's loopback on which nothing
    listens now (a router started here could listen there)."""
    protocol, _, address = endpoint.partition("/")
    host, _, port = address.rpartition(":")
    if protocol != "tcp" or host not in LOOPBACK_HOSTS or not port.isdigit():
        return False
    family = socket.AF_INET6 if ":" in host.strip("[]") else socket.AF_INET
    with socket.socket(family) as sock:
        # as a listener binds (SO_REUSEADDR): a port only in TIME_WAIT is free, one listened on is not
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host.strip("[]"), int(port)))
        except OSError:
            return False
    return True


def local_router_endpoint(wanted: str, given: bool) -> str:
    """Where a router this process starts listens: ``wanted`` if the user ``given`` it (a taken
    port is then the router's own one-line error), else ``wanted`` (transport.router, where every
    other srl command looks by default) if it is free on loopback, else a free loopback port."""
    if given or loopback_endpoint_free(wanted):
        return wanted
    return free_loopback_endpoint()


class ServiceDiedError(RuntimeError):
    def __init__(self, name: str, code: int | None, tail: list[str]) -> None:
        self.name, self.code, self.tail = name, code, tail
        super().__init__(f"service {name!r} exited with code {code} before the run ended")

    def say(self, who: str) -> int:
        """On stderr, as ``who`` (``srl up``) says it: one line and the service's last log lines; exit code 1."""
        print(f"{who}: error: {self}", file=sys.stderr)
        for line in self.tail:
            print(f"  [{self.name}] {line}", file=sys.stderr)
        return 1


@dataclass
class Child:
    name: str
    process: subprocess.Popen[str]
    stdout_lines: list[str] = field(default_factory=list)
    stderr_tail: list[str] = field(default_factory=list)
    threads: list[threading.Thread] = field(default_factory=list)
    observer: bool = False  # srl record, srl view: stopped after every service, so they see the last messages

    def summary(self) -> dict[str, Any] | None:
        for line in reversed(self.stdout_lines):
            if line.startswith("{"):
                try:
                    return json.loads(line)
                except json.JSONDecodeError:
                    return None
        return None


def said(child: Child, text: str) -> Callable[[], bool]:
    """A readiness probe: ``child`` has logged a line containing ``text``."""
    return lambda: any(text in line for line in child.stderr_tail)


def write_child_summaries(directory: Path, children: dict[str, Child]) -> None:
    """Each child's JSON summary line to ``<directory>/<name>.json`` (a child that printed none: no file)."""
    directory.mkdir(parents=True, exist_ok=True)
    for name, child in children.items():
        summary = child.summary()
        if summary is not None:
            (directory / f"{name}.json").write_text(json.dumps(summary, indent=1) + "\n")


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
    def __init__(
        self, settings_args: list[str], env: dict[str, str], quiet: bool = False, signals: StopSignals | None = None
    ) -> None:
        self.settings_args = settings_args
        self.env = env
        self.quiet = quiet
        self.signals = signals  # checked by every check(): a stop signal ends the run there
        self.children: dict[str, Child] = {}

    def spawn(self, name: str, argv: list[str], env: dict[str, str] | None = None, observer: bool = False) -> Child:
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
        child = Child(name, process, observer=observer)
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
        """:class:`Stopped` if a stop signal came; :class:`ServiceDiedError` if a child ended that was
        not ``allowed_to_exit``."""
        if self.signals is not None:
            self.signals.check()
        for child in self.children.values():
            code = child.process.poll()
            if code is not None and child.name not in allowed_to_exit:
                for thread in child.threads:
                    thread.join(timeout=1.0)
                raise ServiceDiedError(child.name, code, child.stderr_tail[-10:])

    def wait_for(self, what: str, probe: Callable[[], bool], timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.check()
            if probe():
                return
            time.sleep(0.05)
        raise TimeoutError(f"{what} not ready after {timeout:.0f} s")

    def stop_one(self, name: str) -> None:
        """SIGINT one child and wait for it (SIGKILL after the grace period)."""
        if stop_group(self.children[name].process, GRACE_SECONDS):
            log.warning("%s did not stop within %.0f s: killed", name, GRACE_SECONDS)

    def stop_all(self) -> None:
        """SIGINT every service still running (newest first) and wait for them, SIGKILL after the
        grace; then the observers (:attr:`Child.observer`: a recorder still subscribed while the
        services' last messages come through); the router last, once nobody is left to say
        goodbye through it (a router closing under its clients' last messages can outlast the
        grace). Then the JIT build directories of processes that are gone (a child killed
        mid-build) are removed."""
        newest_first = list(reversed(list(self.children.values())))
        self._stop_group([c for c in newest_first if c.name != "router" and not c.observer])
        self._stop_group([c for c in newest_first if c.observer])
        self._stop_group([c for c in self.children.values() if c.name == "router"])
        for child in self.children.values():
            for thread in child.threads:
                thread.join(timeout=2.0)
        if (removed := remove_orphan_build_directories()) > 0:
            log.info("removed %d JIT build directories of stopped services", removed)

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


def tls_endpoint(endpoint: str) -> str | None:
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
            tls_router = tls_endpoint(transport.router)
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
