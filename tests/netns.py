"""Several hosts on one machine: network namespaces on a bridge, and faults between them.

:class:`Topology` (a context manager) builds, for one test run:

* one namespace per host, ``srl<pid><rand><role>`` (e.g. ``srl4242kr`` for the router's), each
  with ``lo`` up and one interface ``eth0`` holding ``10.213.<rand>.<i>/24``;
* a bridge ``br0`` in a namespace of its own (``...b``), never on the host (where dockerd may
  own the bridges and their netfilter rules), one veth pair per host created straight between
  the bridge's namespace and the host's: nothing is added to the machine's own namespace;
* processes started inside a namespace (``ip netns exec`` execs the program: the pid of the
  :class:`NsProc` is the program's), stopped by that pid at the end;
* faults on one host's link: random loss (iptables ``statistic``) and a partition (silent
  drop, or the interface taken down and up again), each reversible and counted.

Loss and silent drops are applied where packets are *received*: on the host's ``eth0`` INPUT
and, for what it sends, on its peers' INPUT matched by its source address. Dropping in the
sender's own OUTPUT chain is not loss on the wire: the sender's TCP stack sees a local error
(EPERM) and simply sends again, so the fault would be milder than the one under test.

``close()`` (also on exceptions, and at interpreter exit) stops every process by pid, kills by
pid anything left in the namespaces, deletes every namespace (their veths and iptables rules
go with them) and checks that ``ip netns list`` holds none of them any more.
"""

from __future__ import annotations

import atexit
import contextlib
import functools
import json
import os
import random
import shutil
import signal
import string
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from types import TracebackType
from typing import Any

from tests.harness import ROOT

BRIDGE = "br0"
IFACE = "eth0"
LOSS_TAG = "srl-loss"
CUT_TAG = "srl-cut"


class NetnsError(RuntimeError):
    """The machine cannot host the topology, or a command that builds or faults it failed."""


def missing_requirements() -> list[str]:
    """Why this machine cannot run the topology (empty: it can)."""
    reasons = []
    if os.geteuid() != 0:
        reasons.append(f"network namespaces and iptables need root (running as uid {os.geteuid()})")
    for tool, package in (("ip", "iproute2"), ("ss", "iproute2"), ("iptables", "iptables")):
        if shutil.which(tool) is None:
            reasons.append(f"`{tool}` not found on PATH (apt-get install -y {package})")
    return reasons


def sh(*argv: str, check: bool = True, timeout: float = 15.0) -> subprocess.CompletedProcess[str]:
    result = subprocess.run(argv, capture_output=True, text=True, timeout=timeout)
    if check and result.returncode != 0:
        raise NetnsError(f"`{' '.join(argv)}` failed ({result.returncode}): {result.stderr.strip()}")
    return result


def wait_for(predicate: Callable[[], bool], timeout: float, what: str, poll: float = 0.05) -> float:
    """Wait (bounded) until ``predicate()``; the seconds it took."""
    started = time.monotonic()
    while time.monotonic() - started < timeout:
        if predicate():
            return time.monotonic() - started
        time.sleep(poll)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def _host_env() -> dict[str, str]:
    """The environment of a program on a namespace's host: the test process's, without the
    router that tests/conftest.py gives each test process on the machine's loopback. Inside a
    namespace, a service without --router meets its own host's router on the packaged port, as
    on a real robot."""
    return {key: value for key, value in os.environ.items() if key != "SRL_TRANSPORT__ROUTER"}


class NsProc:
    """A program running inside a network namespace; output collected line by line."""

    def __init__(self, name: str, ns: str, argv: Sequence[str], env: dict[str, str] | None = None) -> None:
        self.name = name
        self.ns = ns
        self.argv = list(argv)
        self.process = subprocess.Popen(
            ["ip", "netns", "exec", ns, *argv],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=ROOT,
            env={**_host_env(), "PYTHONUNBUFFERED": "1", **(env or {})},
            start_new_session=True,
        )
        self.stdout: list[str] = []
        self.stderr: list[str] = []
        self.records: list[dict[str, Any]] = []  # stdout lines that are JSON objects
        self._readers = [
            threading.Thread(target=self._read, args=(self.process.stdout, self.stdout, True), daemon=True),
            threading.Thread(target=self._read, args=(self.process.stderr, self.stderr, False), daemon=True),
        ]
        for reader in self._readers:
            reader.start()

    def _read(self, stream: Any, sink: list[str], parse: bool) -> None:
        for raw in stream:
            line = raw.rstrip()
            sink.append(line)
            if parse and line.startswith("{"):
                with contextlib.suppress(json.JSONDecodeError):  # not JSON after all: stays in stdout
                    self.records.append(json.loads(line))

    @property
    def pid(self) -> int:
        return self.process.pid

    def running(self) -> bool:
        return self.process.poll() is None

    def wait(self, timeout: float) -> int:
        try:
            code = self.process.wait(timeout=timeout)
        except subprocess.TimeoutExpired as error:
            raise AssertionError(f"{self.name} still running after {timeout} s; stderr: {self.stderr[-10:]}") from error
        self._drain()
        return int(code)

    def stop(self, sig: int = signal.SIGINT, timeout: float = 10.0) -> int:
        """Signal the process (its own process group, id = its pid), then SIGKILL if it lingers."""
        if self.process.poll() is None:
            try:
                os.killpg(self.pid, sig)
                self.process.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                os.killpg(self.pid, signal.SIGKILL)
                self.process.wait(timeout=5)
            except ProcessLookupError:
                self.process.wait(timeout=5)
        self._drain()
        return int(self.process.returncode)

    def _drain(self) -> None:
        for reader in self._readers:
            reader.join(timeout=2)

    def wait_record(self, predicate: Callable[[dict[str, Any]], bool], timeout: float, what: str) -> dict[str, Any]:
        """The first JSON line that satisfies ``predicate``, waited for (bounded)."""
        found: list[dict[str, Any]] = []

        def seen() -> bool:
            exited = self.process.poll() is not None
            if exited:
                self._drain()
            found.extend(r for r in list(self.records) if predicate(r))
            if not found and exited:
                raise AssertionError(f"{self.name} exited {self.process.returncode} before {what}: {self.stderr[-10:]}")
            return bool(found)

        wait_for(seen, timeout, f"{what} ({self.name})")
        return found[0]

    def wait_output(self, text: str, timeout: float) -> None:
        """Wait (bounded) for a line of stdout or stderr that contains ``text``."""

        def seen() -> bool:
            if any(text in line for line in [*self.stdout, *self.stderr]):
                return True
            if self.process.poll() is not None:
                raise AssertionError(
                    f"{self.name} exited {self.process.returncode} before printing {text!r}: {self.stderr[-10:]}"
                )
            return False

        wait_for(seen, timeout, f"{text!r} from {self.name}")

    def summary(self) -> dict[str, Any]:
        for record in reversed(self.records):
            if "kind" not in record or record["kind"] == "summary":
                return record
        raise AssertionError(f"{self.name} printed no JSON summary; stderr: {self.stderr[-10:]}")

    def tail(self, lines: int = 15) -> str:
        return "\n".join(
            f"  [{self.name} {stream}] {line}"
            for stream, sink in (("out", self.stdout), ("err", self.stderr))
            for line in sink[-lines:]
        )


@dataclass(frozen=True)
class Host:
    role: str
    ns: str
    ip: str
    port: str  # its veth's end on the bridge (in the bridge's namespace)


@dataclass
class Faults:
    """What one fault injected: packets its rules saw and dropped, to the host and from it."""

    seen_in: int = 0
    dropped_in: int = 0
    seen_out: int = 0
    dropped_out: int = 0

    @property
    def seen(self) -> int:
        return self.seen_in + self.seen_out

    @property
    def dropped(self) -> int:
        return self.dropped_in + self.dropped_out


class Topology:
    """Hosts (one namespace each) on a bridge in its own namespace; see the module docstring."""

    def __init__(self, roles: Sequence[str] = ("r", "a", "c", "p")) -> None:
        if len(set(roles)) != len(roles) or "b" in roles or not all(len(r) == 1 for r in roles):
            raise ValueError(f"roles must be distinct single letters other than 'b', got {roles}")
        rand = random.Random()
        self.tag = f"srl{os.getpid()}{''.join(rand.choices(string.ascii_lowercase, k=2))}"
        self.prefix = f"10.213.{rand.randint(1, 254)}"
        self.bridge_ns = f"{self.tag}b"
        self.hosts = {
            role: Host(role, f"{self.tag}{role}", f"{self.prefix}.{i + 1}", f"v{role}") for i, role in enumerate(roles)
        }
        self.namespaces: list[str] = []  # created, in order
        self.procs: list[NsProc] = []
        self._loss_rules: list[tuple[str, list[str]]] = []
        self._cut_rules: list[tuple[str, list[str]]] = []
        self._closed = False

    # -- life ---------------------------------------------------------------------------
    def __enter__(self) -> Topology:
        atexit.register(self.close)
        try:
            self._build()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None, tb: TracebackType | None) -> None:
        if error is not None:
            print(f"\n--- {self.tag}: last output of every process ---", file=sys.stderr)
            for proc in self.procs:
                print(proc.tail(), file=sys.stderr)
        leftovers = self.close()
        if leftovers and error is None:
            raise NetnsError(f"namespaces left after cleanup: {leftovers}")

    def _add_ns(self, ns: str) -> None:
        existing = self.list_namespaces()
        if ns in existing:
            raise NetnsError(f"namespace {ns} already exists: not ours, refusing to touch it")
        sh("ip", "netns", "add", ns)
        self.namespaces.append(ns)
        sh("ip", "-n", ns, "link", "set", "lo", "up")

    def _build(self) -> None:
        self._add_ns(self.bridge_ns)
        sh("ip", "-n", self.bridge_ns, "link", "add", BRIDGE, "type", "bridge")
        sh("ip", "-n", self.bridge_ns, "link", "set", BRIDGE, "up")
        for host in self.hosts.values():
            self._add_ns(host.ns)
            # the pair is created between the two namespaces directly: the machine's own
            # namespace never holds either end, so no name there can collide
            sh(
                "ip",
                "-n",
                self.bridge_ns,
                "link",
                "add",
                host.port,
                "type",
                "veth",
                "peer",
                "name",
                IFACE,
                "netns",
                host.ns,
            )
            sh("ip", "-n", self.bridge_ns, "link", "set", host.port, "master", BRIDGE, "up")
            sh("ip", "-n", host.ns, "addr", "add", f"{host.ip}/24", "dev", IFACE)
            sh("ip", "-n", host.ns, "link", "set", IFACE, "up")
        for host in self.hosts.values():
            wait_for(functools.partial(self.is_up, host.role), 10, f"{host.ns} {IFACE} up")

    @staticmethod
    def list_namespaces() -> set[str]:
        out = sh("ip", "-j", "netns", "list").stdout.strip()
        return {entry["name"] for entry in json.loads(out)} if out else set()

    def close(self) -> list[str]:
        """Stop every process by pid, delete every namespace; the names still listed (should be none)."""
        if self._closed:
            return []
        self._closed = True
        atexit.unregister(self.close)
        for proc in reversed(self.procs):
            proc.stop(signal.SIGINT, timeout=5)
        for ns in reversed(self.namespaces):
            # anything still inside one of our namespaces was started there by this run
            for pid in sh("ip", "netns", "pids", ns, check=False).stdout.split():
                with contextlib.suppress(ProcessLookupError):
                    os.kill(int(pid), signal.SIGKILL)
            sh("ip", "netns", "del", ns, check=False)
        return sorted(self.list_namespaces() & set(self.namespaces))

    # -- processes ----------------------------------------------------------------------
    def spawn(self, role: str, name: str, argv: Sequence[str], env: dict[str, str] | None = None) -> NsProc:
        proc = NsProc(name, self.hosts[role].ns, argv, env)
        self.procs.append(proc)
        return proc

    def stop_all(self) -> dict[str, int]:
        """Stop every process (SIGINT, last started first): their exit codes by name."""
        return {proc.name: proc.stop() for proc in reversed(self.procs)}

    def python(self, role: str, name: str, module: str, *args: str) -> NsProc:
        return self.spawn(role, name, [sys.executable, "-m", module, *args])

    def run(self, role: str, argv: Sequence[str], timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
        """A short program inside ``role``'s namespace, run to completion (bounded)."""
        return sh("ip", "netns", "exec", self.hosts[role].ns, *argv, timeout=timeout)

    def tcp_peers(self, role: str) -> list[str]:
        """Remote ``address:port`` of every established TCP connection in ``role``'s namespace."""
        out = sh("ip", "netns", "exec", self.hosts[role].ns, "ss", "-Htn", "state", "established").stdout
        return [line.split()[-1] for line in out.splitlines() if line.strip()]

    # -- link state ---------------------------------------------------------------------
    def operstate(self, role: str) -> str:
        info = json.loads(sh("ip", "-n", self.hosts[role].ns, "-j", "link", "show", IFACE).stdout)
        return str(info[0].get("operstate", "UNKNOWN"))

    def is_up(self, role: str) -> bool:
        return self.operstate(role) == "UP"

    # -- iptables -----------------------------------------------------------------------
    def _iptables(self, role: str, *argv: str) -> None:
        sh("ip", "netns", "exec", self.hosts[role].ns, "iptables", "-w", "5", *argv)

    def _rules(self, role: str, tag: str, drop: list[str]) -> list[tuple[str, list[str]]]:
        """(namespace role, rule) pairs that drop what ``role``'s link carries, where it is received:
        on its own INPUT, and on its peers' INPUT matched by its address. Each drop rule comes
        after a rule without target that only counts the packets it sees."""
        host = self.hosts[role]
        matches = [(role, ["INPUT", "-i", IFACE], f"{tag}-in")]
        matches += [
            (peer.role, ["INPUT", "-i", IFACE, "-s", host.ip], f"{tag}-out")
            for peer in self.hosts.values()
            if peer.role != role
        ]
        rules = []
        for ns_role, match, comment in matches:
            rules.append((ns_role, [*match, "-m", "comment", "--comment", f"{comment}-seen"]))
            rules.append((ns_role, [*match, *drop, "-m", "comment", "--comment", comment]))
        return rules

    def _counters(self, tag: str) -> Faults:
        faults = Faults()
        for host in self.hosts.values():
            out = sh("ip", "netns", "exec", host.ns, "iptables", "-w", "5", "-nvx", "-L", "INPUT").stdout
            for line in out.splitlines():
                for way in ("in", "out"):
                    if f"/* {tag}-{way}-seen */" in line:
                        setattr(faults, f"seen_{way}", getattr(faults, f"seen_{way}") + int(line.split()[0]))
                    elif f"/* {tag}-{way} */" in line:
                        setattr(faults, f"dropped_{way}", getattr(faults, f"dropped_{way}") + int(line.split()[0]))
        return faults

    def set_loss(self, role: str, probability: float) -> None:
        """Drop each packet ``role``'s link carries, either way, with ``probability`` (independently)."""
        if not 0 < probability < 1:
            raise ValueError(f"probability must be in (0, 1), got {probability}")
        drop = ["-m", "statistic", "--mode", "random", "--probability", f"{probability}", "-j", "DROP"]
        self._loss_rules = self._rules(role, LOSS_TAG, drop)
        for ns_role, rule in self._loss_rules:
            self._iptables(ns_role, "-A", *rule)

    def clear_loss(self) -> Faults:
        """Remove the loss rules; what they saw and dropped."""
        counted = self._counters(LOSS_TAG)
        for ns_role, rule in self._loss_rules:
            self._iptables(ns_role, "-D", *rule)
        self._loss_rules = []
        return counted

    def cut(self, role: str, method: str = "drop") -> None:
        """Partition ``role`` from every other host.

        ``drop``: every packet of its link silently dropped where it arrives (a dead switch
        port, a radio out of range: neither end's stack notices). ``link``: its interface goes
        down (a pulled cable: its own stack knows, the peers do not)."""
        if method == "drop":
            self._cut_rules = self._rules(role, CUT_TAG, ["-j", "DROP"])
            for ns_role, rule in reversed(self._cut_rules):  # first in their chains, in this order
                self._iptables(ns_role, "-I", rule[0], "1", *rule[1:])
        elif method == "link":
            sh("ip", "-n", self.hosts[role].ns, "link", "set", IFACE, "down")
        else:
            raise ValueError(f"unknown partition method {method!r}")

    def restore(self, role: str, method: str = "drop") -> Faults:
        """Undo :meth:`cut`; for ``drop`` the packets its rules saw and dropped."""
        host = self.hosts[role]
        if method == "drop":
            counted = self._counters(CUT_TAG)
            for ns_role, rule in self._cut_rules:
                self._iptables(ns_role, "-D", *rule)
            self._cut_rules = []
            return counted
        sh("ip", "-n", host.ns, "link", "set", IFACE, "up")
        wait_for(functools.partial(self.is_up, role), 10, f"{host.ns} {IFACE} up again")
        # the kernel drops a downed interface's routes; the connected one comes back with the
        # address, anything else would not: put the subnet's route back explicitly
        sh(
            "ip",
            "-n",
            host.ns,
            "route",
            "replace",
            f"{self.prefix}.0/24",
            "dev",
            IFACE,
            "proto",
            "kernel",
            "scope",
            "link",
            "src",
            host.ip,
        )
        return Faults()
