"""What a run of ``srl up`` measured: each srl process's CPU (its Zenoh threads' apart), wakes and
memory read from /proc, the robot messages routed, and when every robot first stood at rest, which
splits the run's CPU into the robots' drive and their rest (docs/fleets.md, ``srl bench fleet``).

Every reading is bounded in memory: the RSS series halves itself past :data:`RSS_POINTS`, the
per-thread tables (Zenoh's CPU, the wakes) keep one pair per thread ever seen, the statuses one row
per robot.
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import zenoh

from common.config.settings import Settings
from common.contracts.columns import batch_rows
from common.contracts.keys import STATUS, TRANSITION, every_robot, unasked_patterns
from common.contracts.messages import ServiceStatus
from common.contracts.summaries import status_distance
from common.net.transport import zenoh_config
from tools.launch.supervisor import Child, Supervisor


@dataclass
class ProcessUse:
    """CPU and memory of the srl processes over a run, read from /proc."""

    cpu_seconds: float  # over the run (from when every robot was ready to the end)
    rss_mb: float  # sum of every process's resident memory near the end of the run
    peak_rss_mb: float  # sum of every process's peak resident memory (VmHWM)
    processes: int


def _proc_cpu(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as stat:
        fields = stat.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime


# Zenoh's runtime threads: its tokio runtimes name their workers rx-0, tx-0, app-0, acc-0, net-0 (a
# process's other threads are the interpreter's, named after the program)
ZENOH_THREAD = re.compile(r"^(rx|tx|app|acc|net)-\d+$")


class PerThread(ABC):
    """A per-thread reading of each named process (:meth:`value`), summed over its threads since this
    was made: what :class:`ZenohCpu` and :class:`Wakes` read.

    Kept thread by thread: a thread that ends keeps what it had until its last reading, one that
    starts later counts from zero, so the sum never goes back when a runtime retires a worker.
    Memory: one pair per thread ever seen."""

    def __init__(self, pids: dict[str, int]) -> None:
        self.pids = dict(pids)
        self.since: dict[tuple[str, str], float] = {}  # (process, thread id) -> the value when first read
        self.last: dict[tuple[str, str], float] = {}
        for key, value in self._read().items():
            self.since[key] = self.last[key] = value

    @abstractmethod
    def value(self, pid: int, task: str, name: str, stat_fields: list[str]) -> float | None:
        """Thread ``task`` of process ``pid`` (its name, its ``stat`` fields after the name): its
        reading, or None when it is not counted."""

    def totals(self) -> dict[str, float]:
        """Each process's sum since construction (0 for one that is gone)."""
        for key, value in self._read().items():
            self.since.setdefault(key, 0.0)  # a thread started since: all of it is in the span
            self.last[key] = value
        total = dict.fromkeys(self.pids, 0.0)
        for (name, task), value in self.last.items():
            total[name] += value - self.since[(name, task)]
        return total

    def _read(self) -> dict[tuple[str, str], float]:
        now: dict[tuple[str, str], float] = {}
        for name, pid in self.pids.items():
            with contextlib.suppress(OSError):
                for task in os.listdir(f"/proc/{pid}/task"):
                    with contextlib.suppress(OSError, ValueError), open(f"/proc/{pid}/task/{task}/stat") as stat:
                        text = stat.read()
                        thread = text[text.index("(") + 1 : text.rindex(")")]
                        value = self.value(pid, task, thread, text.rsplit(")", 1)[1].split())
                        if value is not None:
                            now[(name, task)] = value
        return now


class ZenohCpu(PerThread):
    """CPU seconds of each named process's Zenoh runtime threads (:data:`ZENOH_THREAD`: the network's
    own work, and the handlers Zenoh calls on its network thread, Bus.subscribe) since this was made.
    Each thread's time is read in nanoseconds (``schedstat``) where the kernel has it, not in clock
    ticks (``stat``): a sum over many threads of tick counts truncated one by one loses up to a tick
    per thread, most of a quiet process's Zenoh time over a few seconds."""

    def value(self, pid: int, task: str, name: str, stat_fields: list[str]) -> float | None:
        return _thread_cpu(pid, task, stat_fields) if ZENOH_THREAD.match(name) else None

    def seconds(self) -> dict[str, float]:
        """Each process's Zenoh thread CPU seconds since construction (0 for one that is gone)."""
        return self.totals()


class Wakes(PerThread):
    """Each named process's wakes since this was made: every thread's voluntary context switches (a
    wait or a sleep that ended; ``/proc/<pid>/task/<tid>/status``). A fleet at rest spends its CPU
    on them more than on its arithmetic: each costs the kernel's switch and a cold cache
    (docs/notes/at-rest-profile.md)."""

    def value(self, pid: int, task: str, name: str, stat_fields: list[str]) -> float | None:
        with open(f"/proc/{pid}/task/{task}/status") as status:
            for line in status:
                if line.startswith("voluntary_ctxt_switches:"):
                    return float(line.split()[1])
        return None


def _thread_cpu(pid: int, task: str, stat_fields: list[str]) -> float:
    """CPU seconds of one thread: its time on a CPU in ns from ``schedstat`` (a kernel with
    scheduler info), else its utime + stime in clock ticks from ``stat``."""
    try:
        with open(f"/proc/{pid}/task/{task}/schedstat") as schedstat:
            return int(schedstat.read().split()[0]) / 1e9
    except (OSError, ValueError, IndexError):
        return (int(stat_fields[11]) + int(stat_fields[12])) / os.sysconf("SC_CLK_TCK")


def _proc_memory(pid: int) -> tuple[float, float]:
    rss = peak = 0.0
    with open(f"/proc/{pid}/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                rss = float(line.split()[1]) / 1024.0
            elif line.startswith("VmHWM:"):
                peak = float(line.split()[1]) / 1024.0
    return rss, peak


def cpu_of(pids: dict[str, int]) -> dict[str, float]:
    """CPU seconds so far of each named process (0 for one that is gone)."""
    seconds = dict.fromkeys(pids, 0.0)
    for name, pid in pids.items():
        with contextlib.suppress(OSError):
            seconds[name] = _proc_cpu(pid)
    return seconds


def message_kind(key: str) -> str:
    """``srl/<robot>/state`` -> ``state``; ``srl/<robot>/status/actor`` -> ``status/actor``; a
    batch's key ``srl/@batch/state`` -> ``state`` (common.contracts.keys.Batch)."""
    return "/".join(key.split("/")[2:]) or key


OUTSIDE_KEYS = (every_robot(TRANSITION),)  # an outside client's subscription (srl bench fleet --outside)


class MessageCounter:
    """Every robot message routed during a run (common.contracts.keys.unasked_patterns: each
    topic's robot keys and the batches, ``srl/@batch/**``; not ``srl/**``, which would make srl
    send the keys it sends on demand), counted (and its bytes) by kind: what ``srl bench capacity``
    reports per robot and second. A batch counts its items, each a robot's message, and its bytes;
    ``batches`` counts the batch samples themselves. It is one more subscriber of everything: the
    router delivers each sample once more to it (said wherever its figures are shown).

    ``keys``: these keys' samples alone, each counted as one message (:data:`OUTSIDE_KEYS`: an
    outside client of every robot's own transition key, which srl sends for it on demand)."""

    def __init__(self, settings: Settings, keys: Sequence[str] = ()) -> None:
        self.counts: dict[str, list[int]] = {}
        self.batches: dict[str, int] = {}
        self.lock = threading.Lock()
        self.session = zenoh.open(zenoh_config(settings.transport))

        def on_sample(sample: Any) -> None:
            kind = message_kind(str(sample.key_expr))
            payload = sample.payload.to_bytes()
            with self.lock:
                count = self.counts.setdefault(kind, [0, 0])
                count[0] += 1
                count[1] += len(payload)

        def on_batch(sample: Any) -> None:
            kind = message_kind(str(sample.key_expr))
            payload = sample.payload.to_bytes()
            # not a batch srl would send: one sample, counted as one
            items = batch_rows(payload) or 1
            with self.lock:
                count = self.counts.setdefault(kind, [0, 0])
                count[0] += items
                count[1] += len(payload)
                self.batches[kind] = self.batches.get(kind, 0) + 1

        if keys:
            self.subscribers = [self.session.declare_subscriber(key, on_sample) for key in keys]
            return
        unasked = unasked_patterns()
        self.subscribers = [self.session.declare_subscriber(key, on_sample) for key in unasked.robot_keys]
        self.subscribers.append(self.session.declare_subscriber(unasked.batches, on_batch))

    def snapshot(self) -> dict[str, list[int]]:
        with self.lock:
            return {kind: list(count) for kind, count in self.counts.items()}

    def close(self) -> None:
        with contextlib.suppress(zenoh.ZError):
            for subscriber in self.subscribers:
                subscriber.undeclare()
        self.session.close()


def memory_of(pids: dict[str, int]) -> dict[str, tuple[float, float]]:
    """Resident and peak memory [MB] of each named process (0 for one that is gone)."""
    memory = dict.fromkeys(pids, (0.0, 0.0))
    for name, pid in pids.items():
        with contextlib.suppress(OSError):
            memory[name] = _proc_memory(pid)
    return memory


RSS_SAMPLE_S = 5.0  # [s] between the points of a run's RSS series
ZENOH_SAMPLE_S = 1.0  # [s] between two readings of every thread's CPU (a file per thread)
RSS_POINTS = 240  # at most (a longer run keeps every other point: bounded whatever the length)
WATCH_S = 0.2  # [s] between two looks at the children, their CPU and memory, and the statuses
WARM_UP_SHARE = 0.1  # the first tenth of a run (at least one RSS sample period) is its warm-up


class RssSeries:
    """The srl processes' summed RSS every :data:`RSS_SAMPLE_S` of a run, bounded in length, and its
    growth from the end of warm-up to the end (what a soak is judged on)."""

    def __init__(self) -> None:
        self.points: list[tuple[float, float]] = []  # (seconds into the run, MB of all)
        self.by_service: list[dict[str, float]] = []  # each point's MB per process
        self.every = RSS_SAMPLE_S

    def add(self, elapsed: float, rss_mb: float, by_service: dict[str, float] | None = None) -> None:
        if self.points and elapsed - self.points[-1][0] < self.every:
            return
        self.points.append((round(elapsed, 1), round(rss_mb, 1)))
        self.by_service.append({name: round(mb, 1) for name, mb in (by_service or {}).items()})
        if len(self.points) > RSS_POINTS:
            self.points, self.by_service = self.points[::2], self.by_service[::2]
            self.every *= 2

    def _after_warm_up(self) -> list[int]:
        if len(self.points) < 2:
            return []
        warm = max(WARM_UP_SHARE * self.points[-1][0], RSS_SAMPLE_S)
        return [i for i, (t, _) in enumerate(self.points) if t >= warm]

    def growth_percent(self) -> float:
        """``100 (last / first after warm-up - 1)``; NaN when the run was too short to tell."""
        after = self._after_warm_up()
        if len(after) < 2 or self.points[after[0]][1] <= 0:
            return math.nan
        return 100.0 * (self.points[after[-1]][1] / self.points[after[0]][1] - 1.0)

    def growth_by_service(self) -> dict[str, list[float]]:
        """Each process's [MB after warm-up, MB at the end]: which one grew."""
        after = self._after_warm_up()
        if len(after) < 2:
            return {}
        first, last = self.by_service[after[0]], self.by_service[after[-1]]
        return {name: [first[name], last.get(name, math.nan)] for name in first}


class RobotStatuses:
    """Each robot's newest actor status (``srl/<robot>/status/actor``), seen from a monitor session.

    ``robot``: that robot's only, with its plant's refusal counters (``srl/<robot>/status/plant``: the
    bridge's refused and resynchronized actions) merged into :attr:`latest` under ``plant.``; ``srl up``
    of one robot and ``srl status`` show them. Without it, every robot's (a fleet's line; its plants'
    statuses are not read: nobody asked for them, and a fleet's router would route them here too)."""

    def __init__(self, settings: Settings, robot: str | None = None) -> None:
        self.robot = robot
        self.actors: dict[str, dict[str, float]] = {}  # one row per robot: bounded by the fleet
        self.plant: dict[str, float] = {}
        self.seen = 0  # actor statuses received
        self.lock = threading.Lock()
        self.session = zenoh.open(zenoh_config(settings.transport))

        def on_sample(sample: Any) -> None:
            try:
                status = ServiceStatus.model_validate_json(sample.payload.to_bytes())
            except ValueError:
                return  # the services' own schema: a bad one is not ours to report
            with self.lock:
                if status.service == "actor":
                    self.actors[status.robot] = dict(status.counters)
                    self.seen += 1
                else:  # only what says whether actions are being refused: the line stays short
                    self.plant = {
                        f"plant.{k}": v
                        for k, v in status.counters.items()
                        if k.startswith("rejected.action") or k == "action_resyncs"
                    }

        services = ("actor",) if robot is None else ("actor", "plant")
        self.subscribers = [
            self.session.declare_subscriber(STATUS.pattern.format(robot=robot or "*", service=service), on_sample)
            for service in services
        ]

    @property
    def latest(self) -> dict[str, float] | None:
        """The one robot's newest actor counters with its plant's ``plant.`` ones; None before the first."""
        with self.lock:
            actor = self.actors.get(self.robot or "")
            return None if actor is None else {**actor, **self.plant}

    def arrived(self) -> int:
        """Robots whose newest status says they have arrived (at rest: no solve, no fit)."""
        with self.lock:
            return sum(c.get("arrived", 0.0) > 0 for c in self.actors.values())

    def line(self, elapsed: float, robots: int) -> str:
        """A fleet's status line: robots reporting and arrived, the farthest, the sums of the alarms."""
        with self.lock:
            seen = list(self.actors.values())
        far = [d for d in map(status_distance, seen) if d is not None]
        unit = f" {far[0][1]}" if far and far[0][1] else ""
        return (
            f"{elapsed:5.1f} s: {len(seen)}/{robots} robots reporting, "
            f"arrived {sum(c.get('arrived', 0.0) > 0 for c in seen)}, "
            f"distance max {max((d for d, _ in far), default=math.nan):.2f}{unit}, "
            f"missed deadlines {sum(c.get('missed_deadlines', 0.0) for c in seen):.0f}, "
            f"staleness max {max((c.get('staleness_steps', 0.0) for c in seen), default=0.0):.0f}, "
            f"solver failures {sum(c.get('solver_failures', 0.0) for c in seen):.0f}"
        )

    def close(self) -> None:
        for subscriber in self.subscribers:
            with contextlib.suppress(zenoh.ZError):
                subscriber.undeclare()
        self.session.close()


def status_monitor(settings: Settings) -> RobotStatuses:
    """The statuses of the robot of ``settings`` (``transport.robot``): what ``srl status`` shows."""
    return RobotStatuses(settings, settings.transport.robot)


@dataclass
class RestMark:
    """When every robot of the fleet had first reported itself arrived, and each process's CPU
    seconds then: it splits the run's CPU into the robots' drive and their rest. At rest an actor
    solves nothing and the critic fits nothing, so the rest's CPU is what the fleet costs for its
    messages and bookkeeping alone. ``fewest_arrived``: the fewest robots arrived at any status
    read after the mark (fewer than all: some left the arrival tolerance, and solved, within the rest)."""

    at: float  # [s] after every robot was ready
    cpu_seconds: dict[str, float]  # each process's CPU seconds at the mark (since the start)
    fewest_arrived: int


def rest_mark(
    mark: RestMark | None, at: float, cpu_seconds: dict[str, float], arrived: int, robots: int
) -> RestMark | None:
    """The run's :class:`RestMark` after a read at ``at`` s of ``arrived`` robots arrived (of
    ``robots``) and the CPU seconds: made at the first read where every robot has arrived, never
    moved after; later reads only lower its ``fewest_arrived``."""
    if mark is None:
        return RestMark(at, cpu_seconds, arrived) if arrived == robots else None
    mark.fewest_arrived = min(mark.fewest_arrived, arrived)
    return mark


def cpu_phase(cpu_seconds: dict[str, float], seconds: float) -> dict[str, Any]:
    """A span's CPU: its length, all processes' CPU [% of a core] and each one's."""

    def percent(cpu: float) -> float:
        return 100.0 * cpu / seconds if seconds > 0 else math.nan

    return {
        "seconds": seconds,
        "cpu_percent": percent(sum(cpu_seconds.values())),
        "cpu_percent_by_service": {name: percent(cpu) for name, cpu in cpu_seconds.items()},
    }


@dataclass
class RunMeasures:
    """What a run measured, from when every robot was ready to the end."""

    cpu_seconds: dict[str, float]  # each process's
    zenoh_seconds: dict[str, float]  # of it, its Zenoh runtime threads'
    memory: tuple[float, float]  # all processes' RSS and peak RSS [MB] near the end
    rss_series: RssSeries
    messages: dict[str, list[int]]  # [count, bytes] of each kind (with count_messages)
    ran: float  # [s] the span over which CPU was measured
    zenoh_ran: float  # [s] the span over which the Zenoh threads' CPU was (sampled less often)
    rest: RestMark | None = None  # None: not every robot arrived while every actor ran
    outside_received: int | None = None  # what the outside subscriber received (``outside``)
    rest_wakes: dict[str, float] | None = None  # each process's wakes a second at rest (:class:`Wakes`)

    def zenoh_percent(self, seconds: float) -> float:
        return 100.0 * seconds / self.zenoh_ran if self.zenoh_ran > 0 else math.nan

    def phases(self) -> dict[str, Any] | None:
        """The run's CPU before and after :class:`RestMark` (``driving``, ``at_rest``), each as
        :func:`cpu_phase`; None without a mark."""
        rest = self.rest
        if rest is None:
            return None
        driving = cpu_phase(rest.cpu_seconds, rest.at)
        at_rest = cpu_phase(
            {name: cpu - rest.cpu_seconds.get(name, 0.0) for name, cpu in self.cpu_seconds.items()}, self.ran - rest.at
        )
        at_rest["fewest_arrived"] = rest.fewest_arrived
        if self.rest_wakes is not None:
            at_rest["wakes_per_second"] = sum(self.rest_wakes.values())
            at_rest["wakes_per_second_by_service"] = dict(self.rest_wakes)
        return {"driving": driving, "at_rest": at_rest}

    def fields(self, processes: int) -> dict[str, Any]:
        """The fleet summary's CPU and memory fields (CPU % of one core over the measured span)."""
        use = ProcessUse(sum(self.cpu_seconds.values()), self.memory[0], self.memory[1], processes)
        ran = self.ran
        return {
            "cpu_percent": 100.0 * use.cpu_seconds / ran if ran > 0 else math.nan,
            "cpu_percent_by_service": {
                name: 100.0 * cpu / ran if ran > 0 else math.nan for name, cpu in self.cpu_seconds.items()
            },
            # of it, Zenoh's runtime threads (the network, and handlers run on its thread)
            "zenoh_cpu_percent": self.zenoh_percent(sum(self.zenoh_seconds.values())),
            "zenoh_cpu_percent_by_service": {name: self.zenoh_percent(cpu) for name, cpu in self.zenoh_seconds.items()},
            "rss_mb": use.rss_mb,
            "rss_growth_percent": self.rss_series.growth_percent(),  # from the end of warm-up to the end (soak)
            "rss_series_mb": self.rss_series.points,
            "rss_growth_by_service_mb": self.rss_series.growth_by_service(),
            "peak_rss_mb": use.peak_rss_mb,
            "processes": use.processes,
            # the CPU while the robots drive and once every one has arrived (RestMark)
            "cpu_phases": self.phases(),
        }


def measure_run(
    supervisor: Supervisor,
    settings: Settings,
    actors: list[Child],
    duration: float,
    robots: list[str],
    show: Callable[[float, RobotStatuses], None] | None,
    count_messages: bool,
    one: bool = False,
    outside: bool = False,
) -> RunMeasures:
    """Watch the run until every actor has ended: CPU, memory and messages sampled while every
    actor still runs (a reaped process has no /proc entry), and the :class:`RestMark` (from the
    robots' statuses, once a second each). ``show`` is handed the seconds since every robot was
    ready and the statuses every :data:`WATCH_S` (``srl up``'s status line); ``one``: the one robot
    of ``robots`` is watched with its plant's refusal counters (:class:`RobotStatuses`);
    ``outside``: a client that is not srl's subscribes to :data:`OUTSIDE_KEYS` for the run (srl
    then sends every robot's transitions on its own key too), and counts what it receives."""
    pids = {name: child.process.pid for name, child in supervisor.children.items()}
    counter = MessageCounter(settings) if count_messages else None
    outsider = MessageCounter(settings, OUTSIDE_KEYS) if outside else None
    ready = time.monotonic()
    cpu_before, zenoh_cpu, wakes = cpu_of(pids), ZenohCpu(pids), Wakes(pids)
    rest_wakes: list[tuple[float, dict[str, float]]] = []  # (when, totals) at the rest mark, and the newest
    monitor = RobotStatuses(settings, robots[0] if one else None)
    rest: RestMark | None = None
    memory, sampled = (0.0, 0.0), ready
    rss_series = RssSeries()
    cpu_seconds = dict.fromkeys(pids, 0.0)
    zenoh_seconds, zenoh_sampled = dict.fromkeys(pids, 0.0), -math.inf
    messages: dict[str, list[int]] = {}
    try:
        actor_names = {a.name for a in actors}
        while any(a.process.poll() is None for a in actors):
            supervisor.check(allowed_to_exit=actor_names)
            now = time.monotonic()
            if all(a.process.poll() is None for a in actors):
                cpu_now, sampled = cpu_of(pids), now
                cpu_seconds = {name: cpu_now[name] - cpu_before[name] for name in pids}
                rest = rest_mark(rest, now - ready, cpu_seconds, monitor.arrived(), len(robots))
                if rest is not None and not rest_wakes:
                    rest_wakes.append((now, wakes.totals()))
                if now - zenoh_sampled >= ZENOH_SAMPLE_S:  # every thread's file: read less often
                    zenoh_seconds, zenoh_sampled = zenoh_cpu.seconds(), now
                    if rest_wakes:
                        rest_wakes[1:] = [(now, wakes.totals())]
                if counter is not None:
                    messages = counter.snapshot()
                if now - ready < duration - 1.0:
                    each = memory_of(pids)  # near the end, while every process still runs
                    memory = (sum(m[0] for m in each.values()), sum(m[1] for m in each.values()))
                    rss_series.add(now - ready, memory[0], {name: m[0] for name, m in each.items()})
            if show is not None:
                show(now - ready, monitor)
            time.sleep(WATCH_S)
    finally:
        monitor.close()
        if counter is not None:
            counter.close()
        received = None
        if outsider is not None:
            received = sum(count for count, _ in outsider.snapshot().values())
            outsider.close()
    return RunMeasures(
        cpu_seconds,
        zenoh_seconds,
        memory,
        rss_series,
        messages,
        sampled - ready,
        zenoh_sampled - ready,
        rest,
        received,
        wake_rates(rest_wakes),
    )


def wake_rates(readings: list[tuple[float, dict[str, float]]]) -> dict[str, float] | None:
    """Each process's wakes a second between the first and the last of ``readings`` ``(when,
    totals)`` (:class:`Wakes`); None without two readings apart in time."""
    if len(readings) < 2 or readings[-1][0] <= readings[0][0]:
        return None
    (first, before), (last, after) = readings[0], readings[-1]
    return {name: (after[name] - before.get(name, 0.0)) / (last - first) for name in after}
