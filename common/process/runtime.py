"""The life cycle every srl process shares: signals, the parent watch, the Zenoh session with
retry and readable errors, one JSON summary line, exit codes, and the exit that skips the
interpreter's finalization once Zenoh ran.

A service's ``__main__`` (and ``srl <service>``) parses its arguments with the helpers here and
in :mod:`common.config.arguments`, resolves its settings and hands its ``run`` to :func:`serve`; the
``srl`` command (tools/cli.py) and ``python -m services.<name>`` run the same code. Zenoh is
imported only inside functions (through common.net.transport), so importing this module stays pure.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import re
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from common.config.arguments import Parser, UsageError, add_log_level
from common.config.settings import Settings
from common.net.provenance import PlantConflictError
from common.net.security import SecurityError
from common.system.lifeline import die_with_parent, end_if_stuck

log = logging.getLogger(__name__)


class SignalledError(Exception):
    """Ended by a signal: one line, exit 128 + the signal's number (130 Ctrl-C, 143 SIGTERM)."""

    def __init__(self, signum: int) -> None:
        self.signum = signum
        super().__init__(f"{signal.Signals(signum).name}")


class SignalStop(threading.Event):
    """A stop event that remembers the signal that set it."""

    signum: int | None = None

    def stop_by(self, signum: int) -> None:
        if self.signum is None:
            self.signum = signum
        self.set()


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class SignalWatch:
    """Signals handed to ``callback(signum)`` on a thread of their own, never inside the handler.

    A Python signal handler runs in the main thread between two bytecodes, possibly inside
    ``threading.Event.wait`` while that thread holds the event's (non-reentrant) lock: a handler
    that calls ``stop.set()`` then waits for a lock its own thread holds, forever: the process
    never stops. Here the handler only writes
    the signal's number to a pipe (``os.write``, no lock), and so does Python's C-level handler
    (``signal.set_wakeup_fd``) the moment the signal arrives, even while the main thread is
    blocked in native code; a daemon thread reads the pipe and calls ``callback``. ``callback``
    may see one signal twice (both writes) and must be idempotent (``Event.set``,
    :meth:`SignalStop.stop_by`, :func:`stop_within_bounds` are).

    Use it as a context manager (the handlers and wakeup fd before it are restored after), or
    :meth:`start` it for the rest of the process. Main thread only, like ``signal.signal``.
    """

    def __init__(self, callback: Callable[[int], None], signals: Sequence[int] = STOP_SIGNALS) -> None:
        self.callback = callback
        self.signals = tuple(signals)
        self._read = self._write = -1
        self._previous: dict[int, Any] = {}
        self._old_wakeup = -1
        self._thread: threading.Thread | None = None

    def start(self) -> SignalWatch:
        self._read, self._write = os.pipe()  # not inherited by children (PEP 446)
        os.set_blocking(self._write, False)  # a full pipe drops a byte, never blocks a handler
        self._thread = threading.Thread(target=self._watch, name="signals", daemon=True)
        self._thread.start()
        self._old_wakeup = signal.set_wakeup_fd(self._write, warn_on_full_buffer=False)
        self._previous = {signum: signal.signal(signum, self._handle) for signum in self.signals}
        return self

    def _handle(self, signum: int, _frame: object) -> None:
        with contextlib.suppress(OSError):  # full pipe: a byte for this signal is already there
            os.write(self._write, bytes([signum]))

    def _watch(self) -> None:
        while True:
            try:
                received = os.read(self._read, 64)
            except OSError:
                return
            if not received:  # the write end closed: the watch is over
                return
            for signum in received:
                if signum in self.signals:  # the wakeup fd hears every signal with a Python handler
                    self.callback(signum)

    def close(self) -> None:
        for signum, previous in self._previous.items():
            signal.signal(signum, previous)
        self._previous = {}
        if self._write >= 0:
            signal.set_wakeup_fd(self._old_wakeup)
            os.close(self._write)
            self._write = -1
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            self._thread = None
        if self._read >= 0:
            os.close(self._read)
            self._read = -1

    def __enter__(self) -> SignalWatch:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


@contextlib.contextmanager
def stop_on_signals() -> Iterator[SignalStop]:
    """SIGINT and SIGTERM set an event (checked between steps) instead of raising inside native
    code: a KeyboardInterrupt raised in a CasADi callback surfaces as ``SystemError ... returned a
    result with an exception set``. Set from :class:`SignalWatch`'s thread, never inside the
    handler. The previous handlers are restored after."""
    stop = SignalStop()
    with SignalWatch(stop.stop_by):
        yield stop


def serve(
    settings: Settings,
    service: str,
    connect_timeout: float,
    body: Callable[..., dict[str, Any]],
    any_system: bool = False,
) -> int:
    """The one life cycle of a service process: signals, parent watch, session (with retry),
    ``body(settings, bus, stop)``, the session closed, the summary as the last stdout line.
    ``any_system``: the service carries any system's messages (settings.wire: the actor, the
    simulated plant, the critic); else the robot's only (the robot bridge, the TurtleBot3
    emulator), and another system is refused in one line."""
    from common.net.transport import Bus

    if not any_system:
        try:
            settings.robot_only(f"srl {service}")  # ROS 2's odom and cmd_vel are the robot's
        except ValueError as error:
            raise UsageError(str(error)) from error
    stop = service_stop()
    bus = connect_with_retry(lambda: Bus.open(settings.transport, service), settings, service, connect_timeout, stop)
    try:
        result = body(settings, bus, stop)
    finally:
        bus.close()
    result["resources"] = own_resources()
    print(json.dumps(result), flush=True)
    return 0


def service_stop() -> threading.Event:
    """A service process's stop, for its life: set by SIGINT and SIGTERM (through
    :class:`SignalWatch`, the stop bounded by :func:`stop_within_bounds`) and by the death of the
    ``srl up`` that started it, even by SIGKILL (common.system.lifeline)."""
    stop = threading.Event()
    SignalWatch(lambda _signum: stop_within_bounds(stop)).start()
    die_with_parent(stop)
    return stop


def stop_within_bounds(stop: threading.Event) -> None:
    """A service's stop on a signal: ``stop`` set, and the stop bounded even if the process then
    hangs holding the GIL (common.system.lifeline.end_if_stuck: ended after HARD_EXIT_SECONDS)."""
    end_if_stuck()
    stop.set()


def lower_priority(niceness: int, who: str) -> None:
    """Lower this process's CPU priority by ``niceness`` (nice, capped at 19). Linux keeps a
    niceness per thread, and a thread inherits its creator's: every thread already running
    (BLAS's pool) is lowered as well as the calling one, so Zenoh's threads, started later,
    inherit it. Needs no root (only raising a priority does); where it is refused, a warning and
    the normal priority. With the kernel's autogroups on (``/proc/sys/kernel/sched_autogroup_enabled``)
    it orders threads within one session only: ``srl up`` starts each service in a session of
    its own, so a niced service does not yield to another service (docs/fleets.md)."""
    if niceness <= 0:
        return
    try:
        tasks = [int(tid) for tid in os.listdir("/proc/self/task")]
    except OSError:  # no /proc: the calling thread only
        tasks = [0]
    try:
        for tid in tasks:
            os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + niceness))
    except ProcessLookupError:  # a thread that ended meanwhile
        pass
    except OSError as error:
        log.warning("%s: cannot lower its CPU priority (nice +%d): %s", who, niceness, error)
    session_priority(min(19, niceness), who)


AUTOGROUP_ATTEMPTS = 5  # session_priority: writes refused with EAGAIN (one change per 0.1 s) tried again


def session_priority(niceness: int, who: str) -> bool:
    """With the kernel's autogroups on, the CPU is shared between sessions before threads, and
    ``srl up`` starts each service in a session of its own: set this session's autogroup
    niceness (``/proc/self/autogroup``), so under contention it yields to the other services'
    (``niceness`` > 0, the recorder) or comes before them (< 0, the critic: needs root or
    ``CAP_SYS_NICE``; refused, one INFO line). Only when this process leads its session, as a
    service ``srl up`` or ``srl bench`` starts does -- started from a shell the autogroup is the
    shell's, whose other processes are left as they are. True if set; 0 changes nothing.

    Without ``CAP_SYS_ADMIN`` the kernel takes one autogroup change per 0.1 s, machine-wide, and
    refuses the others with EAGAIN: services that start together (``srl up``) try again, up to
    AUTOGROUP_ATTEMPTS times, 0.11 s apart."""
    if niceness == 0:
        return False
    try:
        if os.getsid(0) != os.getpid():
            return False
        for attempt in range(AUTOGROUP_ATTEMPTS):
            try:
                with open("/proc/self/autogroup", "w") as autogroup:
                    autogroup.write(str(niceness))
                break
            except BlockingIOError:  # EAGAIN: another change within the kernel's 0.1 s
                if attempt == AUTOGROUP_ATTEMPTS - 1:
                    raise
                time.sleep(0.11)
    except (PermissionError, BlockingIOError) as error:  # not allowed, or still busy after every try
        log.info("%s: its session keeps its CPU share (niceness %d refused: %s)", who, niceness, error.strerror)
        return False
    except OSError as error:  # no autogroups (or no /proc)
        log.debug("%s: autogroup kept (%s)", who, error)
        return False
    log.info("%s: its session's niceness is %d", who, niceness)
    return True


@contextlib.contextmanager
def realtime_priority(priority: int, who: str) -> Iterator[int]:
    """Run the calling thread under ``SCHED_FIFO`` at ``priority`` (1-99; 0: leave it as it is)
    until the block ends, then give it back its policy. Yields the priority granted, 0 if none.
    The threads it may wait for on the GIL run one step below it for as long
    (:func:`realtime_helpers`).

    A real-time thread is given a core before any thread of the normal class, whatever their
    sessions and autogroups: an actor's tick thread is not made to wait behind a critic's fit
    or another service's burst (docs/fleets.md). It needs ``CAP_SYS_NICE``
    (root, or ``cap_add: [SYS_NICE]`` in compose) or a ``rtprio`` limit (``ulimit -r``, e.g.
    ``@realtime - rtprio 20`` in /etc/security/limits.conf); where refused, one INFO line and
    the normal class. ``SCHED_RESET_ON_FORK``: threads and processes it starts are normal. The
    kernel's RT throttling (``/proc/sys/kernel/sched_rt_runtime_us``, 95 % by default) keeps a
    runaway from taking a whole core."""
    if priority <= 0 or not hasattr(os, "sched_setscheduler"):
        yield 0
        return
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, os.sched_param(priority))
    except OSError as error:
        log.info(
            "%s: ticks at normal priority (SCHED_FIFO %d refused: %s; it needs CAP_SYS_NICE or "
            "an rtprio limit, docs/fleets.md)",
            who,
            priority,
            error.strerror or error,
        )
        yield 0
        return
    log.info("%s: ticks under SCHED_FIFO %d", who, priority)
    helpers = realtime_helpers(max(1, priority - 1), who)
    try:
        yield priority
    finally:
        with contextlib.suppress(OSError):  # giving a priority back is always allowed
            os.sched_setscheduler(0, policy, param)
        for tid in helpers:
            with contextlib.suppress(OSError):  # a thread that ended meanwhile
                os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))


# Zenoh's runtime threads (their names as the kernel knows them): the receiving ones run the
# subscriptions' Python callbacks
ZENOH_THREAD = re.compile(r"^(rx|tx|net|acc|app)-\d+$")


def realtime_helpers(priority: int, who: str) -> list[int]:
    """``SCHED_FIFO`` at ``priority`` for the threads of this process a real-time thread may wait
    for: every other Python thread and Zenoh's runtime threads, all of which take the GIL. A
    real-time thread that needs the GIL waits for whichever thread holds it; in the normal class
    that thread may wait for a core behind other processes' threads for tens of ms (an actor host
    of 150 robots beside a loaded critic and recorder: ticks 25-65 ms late, a solve of 0.25 ms
    stretched to 40). One step below the waiting thread they take the core at once, and they use
    little of it (an actor host's receive threads: ~5 % of a core at 150 robots). Threads started
    later are not included, nor native pools that never take the GIL (BLAS). Returns their ids."""
    me = threading.get_native_id()
    python = {t.native_id for t in threading.enumerate() if t.native_id is not None}
    try:
        tids = [int(tid) for tid in os.listdir("/proc/self/task")]
    except OSError:
        return []
    promoted = []
    for tid in tids:
        if tid == me:
            continue
        try:
            with open(f"/proc/self/task/{tid}/comm") as comm:
                name = comm.read().strip()
        except OSError:  # ended meanwhile
            continue
        if tid not in python and not ZENOH_THREAD.match(name):
            continue
        try:
            os.sched_setscheduler(tid, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, os.sched_param(priority))
        except OSError as error:
            log.debug("%s: thread %d (%s) kept in the normal class: %s", who, tid, name, error)
            continue
        promoted.append(tid)
    log.info("%s: the threads it may wait for under SCHED_FIFO %d: %d", who, priority, len(promoted))
    return promoted


# A router that accepts TCP but refuses the session this long is refusing the login (a wrong
# password does not become right); shorter, it may still be starting.
LOGIN_REFUSED_AFTER = 2.0


@dataclass(frozen=True)
class RouterWait:
    """The router :func:`connect_with_retry` waits for, as its lines name it: srl's own router
    (:meth:`of_srl`), or another, e.g. a robot's own router (services/robot_bridge/robot_router.py).
    ``user``: who logs in there (None: no login, so a refused session is never called a login
    refusal); ``login_setting`` turns a login on; the hints say where to look when the login is
    refused or the router never comes."""

    endpoint: str
    name: str
    user: str | None
    login_setting: str
    credentials_hint: str
    start_hint: str

    @classmethod
    def of_srl(cls, settings: Settings) -> RouterWait:
        transport = settings.transport
        return cls(
            transport.router,
            "the Zenoh router",
            transport.user if transport.secure else None,
            "transport.secure",
            "check transport.password_file or SRL_TRANSPORT__PASSWORD against the router's users file",
            "is `srl router` running? see --router, --connect-timeout",
        )


def connect_with_retry(
    opener: Callable[[], Any],
    settings: Settings | None,
    service: str,
    timeout: float,
    stop: threading.Event,
    router: RouterWait | None = None,
) -> Any:
    """Open the Zenoh session, retrying every 0.2 s for ``timeout`` s, and say why it failed.

    "waiting for the router" is said at once; at the end a router that listens but refuses the
    session (a login is configured: the login) is told apart from one that is not there at all,
    without Zenoh's Rust internals (those go to DEBUG). ``router``: which router (default srl's,
    from ``settings``)."""
    from common.net.transport import session_errors  # zenoh only through the transport, and only here

    refused = session_errors()
    if router is None:
        if settings is None:
            raise ValueError("connect_with_retry: neither settings nor a router to wait for")
        router = RouterWait.of_srl(settings)
    short = router.name.replace(" Zenoh", "")  # "the router", "the robot's router"
    deadline = time.monotonic() + timeout
    refused_since: float | None = None
    said = False
    while True:
        try:
            return opener()
        except refused as error:
            log.debug("%s: zenoh.open: %s", service, error)
            now = time.monotonic()
            listening = _endpoint_listening(router.endpoint)
            refused_since = (refused_since or now) if listening else None
            if router.user is not None and refused_since is not None and now - refused_since >= LOGIN_REFUSED_AFTER:
                raise UsageError(
                    f"{service}: {short} at {router.endpoint} refused the login of user "
                    f"{router.user!r}: wrong password or unknown user ({router.credentials_hint})"
                ) from None
            if now > deadline or stop.is_set():
                if listening:
                    raise UsageError(
                        f"{service}: something listens at {router.endpoint} but refused a Zenoh "
                        f"session (not a Zenoh router, or it requires a login: {router.login_setting})"
                    ) from None
                raise UsageError(
                    f"{service}: cannot reach {router.name} at {router.endpoint} after "
                    f"{timeout:.0f} s ({router.start_hint})"
                ) from None
            if not said:
                log.warning("%s: waiting for %s at %s (up to %.0f s)", service, router.name, router.endpoint, timeout)
                said = True
            time.sleep(0.2)


def zenoh_reason(error: Exception) -> str:
    """Zenoh's error text without its Rust source location (`` at /root/.cargo/...rs:447.``)."""
    return re.sub(r"\s+at /\S+\.rs:\d+\.?", "", str(error)).strip()


def _endpoint_listening(endpoint: str) -> bool:
    """Whether a TCP-based endpoint (tcp/, tls/, ws/) accepts a plain connection."""
    import socket

    protocol, _, address = endpoint.partition("/")
    if protocol not in ("tcp", "tls", "ws"):
        return False
    host, _, port = address.split("?")[0].split("#")[0].rpartition(":")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=0.5):
            return True
    except (OSError, ValueError):
        return False


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity, e.g. a container's cpuset), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def own_resources() -> dict[str, float]:
    """CPU seconds and peak resident memory of this process (for benchmarks)."""
    import resource

    usage = resource.getrusage(resource.RUSAGE_SELF)
    return {"cpu_seconds": usage.ru_utime + usage.ru_stime, "peak_rss_mb": usage.ru_maxrss / 1024.0}


def fleet_hosts(option: str, size: int, flag: str) -> int:
    """How many actor host processes serve ``size`` robots (common.math.fleet.host_count over this
    process's cores), from the option ``flag`` (``srl up --actor-hosts``, ``srl actor --hosts``);
    a bad value is a :class:`UsageError` (one line)."""
    from common.math.fleet import FleetError, host_count

    try:
        return host_count(option, size, usable_cores(), flag)
    except FleetError as error:
        raise UsageError(str(error)) from None


def main(parser: argparse.ArgumentParser, argv: Sequence[str] | None = None) -> int:
    """Parse, configure logging once, run the chosen ``func``; errors as one line and an exit code."""
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=getattr(logging, str(args.log_level).upper(), logging.WARNING),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        code = func(args)
        # what is still buffered goes now, so a reader that went away (srl run | head) shows as
        # the BrokenPipeError below, not as "Exception ignored" and exit 120 at the interpreter's exit
        sys.stdout.flush()
        return code
    except (UsageError, SecurityError, PlantConflictError) as error:
        print(f"srl: error: {error}", file=sys.stderr)
        return 2
    except SignalledError as stopped:
        print(f"srl: interrupted ({stopped}): stopped", file=sys.stderr)
        return 128 + stopped.signum
    except KeyboardInterrupt as error:  # also common.system.jit.BuildInterrupted (a signal during the JIT build)
        signum = getattr(error, "signum", signal.SIGINT)
        print(f"srl: interrupted ({signal.Signals(signum).name}): stopped", file=sys.stderr)
        return 128 + signum
    except BrokenPipeError:
        # the reader went away (srl run | head): no traceback; as a shell reports SIGPIPE
        with contextlib.suppress(OSError):
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        return 141


def entry(build_parser: Callable[[], argparse.ArgumentParser], argv: Sequence[str] | None = None) -> None:
    """A process's whole life: :func:`main`, then, in a process that used Zenoh, an exit that
    skips the interpreter's finalization.

    Zenoh runs Python callbacks on its own native (Rust) threads. A thread that asks for the
    GIL while the interpreter finalizes is ended by CPython with ``pthread_exit``, and that
    forced unwinding through Rust frames aborts the whole process (SIGABRT, exit -6) after its
    work is done and reported. Such a process therefore runs its ``atexit`` handlers (logging,
    multiprocessing), flushes its streams and leaves with ``os._exit``: nothing of ours is left to
    finalize (every service has closed its Zenoh session by then).
    """
    import os

    from common.process.plugins import PluginError, load_from_environment

    try:
        load_from_environment()  # before the parser: its choices offer the plugins' rows
    except PluginError as error:
        print(f"srl: error: {error}", file=sys.stderr)
        raise SystemExit(2) from None
    try:
        code: int | str | None = main(build_parser(), argv)
    except SystemExit as done:
        code = done.code
    if "zenoh" in sys.modules and (code is None or isinstance(code, int)):
        import atexit
        import contextlib

        atexit._run_exitfuncs()
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(OSError, ValueError):  # closed, or a broken pipe: nothing more to say
                stream.flush()
        os._exit(code or 0)
    sys.exit(code)


def service_parser(command: Any) -> argparse.ArgumentParser:
    """The parser of one service run as ``python -m services.<name>``: the same options as
    ``srl <name>`` (the service's ``command`` module: ``NAME``, ``HELP``, ``add_arguments``)."""
    parser = Parser(prog=f"srl {command.NAME}", description=command.HELP[:1].upper() + command.HELP[1:] + ".")
    add_log_level(parser)
    command.add_arguments(parser)
    return parser
