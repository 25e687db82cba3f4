"""``srl up --robots K``: a simulated fleet, every robot on one router, one run of ``duration`` s.

Two layouts, the same robots, keys and critic:

* ``host`` (the default): ONE actor host (``srl actor --robots``), ONE plant host
  (``srl plant-sim --robots``) and the critic: four processes, whatever the fleet's size;
* ``process`` (the baseline of ``srl bench fleet``): one ``srl plant-sim`` and one
  ``srl actor`` per robot, and the critic.

Robots start evenly on a circle around the target (common/math/fleet.py), heading away from it. The
run is bounded: readiness waits time out, the actors stop after ``duration`` seconds, and every
child is stopped (SIGINT, SIGKILL after a grace) whatever happens (tools/launch/supervisor.py). CPU
and memory of every srl process are read from /proc over the run itself (after start-up).
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import shutil
import signal
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh
from pydantic import TypeAdapter

from common.config.settings import Settings
from common.contracts.columns import batch_rows
from common.contracts.keys import BATCH_CHUNK, STATUS
from common.contracts.messages import ServiceStatus
from common.contracts.summaries import CriticSummary, FleetActorSummary, FleetView, RealtimeActorSummary, fleet_view
from common.math.fleet import circle_starts, split_evenly
from common.net.transport import zenoh_config
from common.process.runtime import fleet_hosts
from tools.launch.plants import launch_plant, with_launch_plant
from tools.launch.supervisor import (
    Child,
    Logins,
    ServiceDiedError,
    StopSignals,
    Supervisor,
    free_loopback_endpoint,
    router_reachable,
    said,
    write_child_summaries,
)

LAYOUTS = ("host", "process")
# settings flags a fleet sets per child itself (the router is fresh, robots and starts its own)
OWN_FLAGS = ("--router", "--robot", "--start", "--duration")
FLEET_TRANSITION_CACHE = 600  # transitions per robot kept for a late critic (60 s at delta = 0.1 s)
# [s] the slowest start seen here: 100 robots' subscriptions and tokens on a loaded 2-core machine
READY_TIMEOUT = 120.0


def actor_hosts(option: str, size: int) -> int:
    """``--actor-hosts``: a number, or ``auto`` (common.process.runtime.fleet_hosts)."""
    return fleet_hosts(option, size, "--actor-hosts")


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


class ZenohCpu:
    """CPU seconds of each named process's Zenoh runtime threads (:data:`ZENOH_THREAD`: the network's
    own work, and the handlers Zenoh calls on its network thread, Bus.subscribe) since this was made.

    Kept thread by thread: a thread that ends keeps what it ran until its last reading, one that starts
    later counts from zero, so the sum never goes back when a runtime retires a worker. Each thread's
    time is read in nanoseconds (``schedstat``) where the kernel has it, not in clock ticks (``stat``):
    a sum over many threads of tick counts truncated one by one loses up to a tick per thread, most of
    a quiet process's Zenoh time over a few seconds. Memory: one pair per thread ever seen."""

    def __init__(self, pids: dict[str, int]) -> None:
        self.pids = dict(pids)
        self.since: dict[tuple[str, str], float] = {}  # (process, thread id) -> seconds when first read
        self.last: dict[tuple[str, str], float] = {}
        for key, seconds in self._read().items():
            self.since[key] = self.last[key] = seconds

    def seconds(self) -> dict[str, float]:
        """Each process's Zenoh thread CPU seconds since construction (0 for one that is gone)."""
        for key, seconds in self._read().items():
            self.since.setdefault(key, 0.0)  # a thread started since: all its time is in the span
            self.last[key] = seconds
        total = dict.fromkeys(self.pids, 0.0)
        for (name, task), seconds in self.last.items():
            total[name] += seconds - self.since[(name, task)]
        return total

    def _read(self) -> dict[tuple[str, str], float]:
        now: dict[tuple[str, str], float] = {}
        for name, pid in self.pids.items():
            with contextlib.suppress(OSError):
                for task in os.listdir(f"/proc/{pid}/task"):
                    with contextlib.suppress(OSError, ValueError), open(f"/proc/{pid}/task/{task}/stat") as stat:
                        text = stat.read()
                        if ZENOH_THREAD.match(text[text.index("(") + 1 : text.rindex(")")]):
                            now[(name, task)] = _thread_cpu(pid, task, text.rsplit(")", 1)[1].split())
        return now


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


class MessageCounter:
    """Every robot message routed during a run (``srl/**`` and the batches, ``srl/@batch/**``),
    counted (and its bytes) by kind: what ``srl bench capacity`` reports per robot and second. A
    batch counts its items, each a robot's message, and its bytes; ``batches`` counts the batch
    samples themselves. It is one more subscriber of everything: the router delivers each sample
    once more to it (said wherever its figures are shown)."""

    def __init__(self, settings: Settings) -> None:
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

        self.subscriber = self.session.declare_subscriber("srl/**", on_sample)
        self.batch_subscriber = self.session.declare_subscriber(f"srl/{BATCH_CHUNK}/**", on_batch)

    def snapshot(self) -> dict[str, list[int]]:
        with self.lock:
            return {kind: list(count) for kind, count in self.counts.items()}

    def close(self) -> None:
        with contextlib.suppress(zenoh.ZError):
            self.subscriber.undeclare()
            self.batch_subscriber.undeclare()
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


class FleetMonitor:
    """Every robot's newest actor status (``srl/*/status/actor``), from a monitor session."""

    def __init__(self, settings: Settings) -> None:
        self.latest: dict[str, dict[str, float]] = {}
        self.lock = threading.Lock()
        self.session = zenoh.open(zenoh_config(settings.transport))

        def on_sample(sample: Any) -> None:
            try:
                status = ServiceStatus.model_validate_json(sample.payload.to_bytes())
            except ValueError:
                return
            with self.lock:
                self.latest[status.robot] = dict(status.counters)

        self.subscriber = self.session.declare_subscriber(STATUS.pattern.format(robot="*", service="actor"), on_sample)

    def arrived(self) -> int:
        """Robots whose newest status says they have arrived (at rest: no solve, no fit)."""
        with self.lock:
            return sum(c.get("arrived", 0.0) > 0 for c in self.latest.values())

    def line(self, elapsed: float, robots: int) -> str:
        with self.lock:
            seen = list(self.latest.values())
        distances = [math.hypot(c["x"], c["y"]) for c in seen if "x" in c and "y" in c]
        return (
            f"{elapsed:5.1f} s: {len(seen)}/{robots} robots reporting, "
            f"arrived {sum(c.get('arrived', 0.0) > 0 for c in seen)}, "
            f"distance max {max(distances, default=math.nan):.2f} m, "
            f"missed deadlines {sum(c.get('missed_deadlines', 0.0) for c in seen):.0f}, "
            f"staleness max {max((c.get('staleness_steps', 0.0) for c in seen), default=0.0):.0f}, "
            f"solver failures {sum(c.get('solver_failures', 0.0) for c in seen):.0f}"
        )

    def close(self) -> None:
        with contextlib.suppress(zenoh.ZError):
            self.subscriber.undeclare()
        self.session.close()


def _alive_robots(session: Any, service: str) -> set[str]:
    replies = session.liveliness().get(f"srl/*/alive/{service}", timeout=2.0)
    return {str(reply.ok.key_expr).split("/")[1] for reply in replies if reply.ok is not None}


def wait_fleet_alive(supervisor: Supervisor, settings: Settings, robots: list[str], service: str) -> None:
    """Until every robot's ``service`` token is live (bounded by READY_TIMEOUT)."""
    session = zenoh.open(zenoh_config(settings.transport))
    try:
        wanted = set(robots)
        supervisor.wait_for(
            f"{service} of {len(robots)} robots", lambda: wanted <= _alive_robots(session, service), READY_TIMEOUT
        )
    finally:
        session.close()


def exit_code(code: int | None) -> int | None:
    """A child's exit code, its stop by our SIGINT counted as a clean end (0), as srl up does."""
    return 0 if code == -signal.SIGINT else code


def host_shares(robots: list[str], hosts: int) -> dict[str, list[str]]:
    """The robots of each actor host (common.math.fleet.split_evenly): ``actor`` alone, else
    ``actor-1`` .. ``actor-H`` (one per core: one host's solves run in one thread)."""
    shares = split_evenly(robots, hosts)
    return {"actor": shares[0]} if hosts == 1 else {f"actor-{h + 1}": share for h, share in enumerate(shares)}


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
class FleetMeasures:
    """What a fleet's run measured, from when every robot was ready to the end."""

    cpu_seconds: dict[str, float]  # each process's
    zenoh_seconds: dict[str, float]  # of it, its Zenoh runtime threads'
    memory: tuple[float, float]  # all processes' RSS and peak RSS [MB] near the end
    rss_series: RssSeries
    messages: dict[str, list[int]]  # [count, bytes] of each kind (with count_messages)
    ran: float  # [s] the span over which CPU was measured
    zenoh_ran: float  # [s] the span over which the Zenoh threads' CPU was (sampled less often)
    rest: RestMark | None = None  # None: not every robot arrived while every actor ran

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
        return {"driving": driving, "at_rest": {**at_rest, "fewest_arrived": rest.fewest_arrived}}

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


def measure_fleet(
    supervisor: Supervisor,
    settings: Settings,
    actors: list[Child],
    duration: float,
    robots: int,
    on_status: Callable[[str], None] | None,
    count_messages: bool,
) -> FleetMeasures:
    """Watch the fleet until every actor has ended: CPU, memory and messages sampled while every
    actor still runs (a reaped process has no /proc entry), a status line a second, and the
    :class:`RestMark` (from the robots' statuses, once a second each)."""
    pids = {name: child.process.pid for name, child in supervisor.children.items()}
    counter = MessageCounter(settings) if count_messages else None
    ready = time.monotonic()
    cpu_before, zenoh_cpu = cpu_of(pids), ZenohCpu(pids)
    monitor = FleetMonitor(settings)
    rest: RestMark | None = None
    memory, sampled = (0.0, 0.0), ready
    rss_series = RssSeries()
    cpu_seconds = dict.fromkeys(pids, 0.0)
    zenoh_seconds, zenoh_sampled = dict.fromkeys(pids, 0.0), -math.inf
    messages: dict[str, list[int]] = {}
    try:
        shown = 0
        actor_names = {a.name for a in actors}
        while any(a.process.poll() is None for a in actors):
            supervisor.check(allowed_to_exit=actor_names)
            now = time.monotonic()
            if all(a.process.poll() is None for a in actors):
                cpu_now, sampled = cpu_of(pids), now
                cpu_seconds = {name: cpu_now[name] - cpu_before[name] for name in pids}
                rest = rest_mark(rest, now - ready, cpu_seconds, monitor.arrived(), robots)
                if now - zenoh_sampled >= ZENOH_SAMPLE_S:  # every thread's file: read less often
                    zenoh_seconds, zenoh_sampled = zenoh_cpu.seconds(), now
                if counter is not None:
                    messages = counter.snapshot()
                if now - ready < duration - 1.0:
                    each = memory_of(pids)  # near the end, while every process still runs
                    memory = (sum(m[0] for m in each.values()), sum(m[1] for m in each.values()))
                    rss_series.add(now - ready, memory[0], {name: m[0] for name, m in each.items()})
            if on_status is not None and int(now - ready) > shown:
                shown = int(now - ready)
                on_status(monitor.line(now - ready, robots))
            time.sleep(0.2)
    finally:
        monitor.close()
        if counter is not None:
            counter.close()
    return FleetMeasures(
        cpu_seconds, zenoh_seconds, memory, rss_series, messages, sampled - ready, zenoh_sampled - ready, rest
    )


def spawn_sim_plants(
    supervisor: Supervisor,
    common: list[str],
    robots: list[str],
    layout: str,
    circle: float,
    login: dict[str, str] | None,
) -> None:
    """The simulated robots: one plant host for all (``host``) or a plant_sim each (``process``),
    starting evenly on the circle (common.math.fleet.circle_starts)."""
    if layout == "host":
        supervisor.spawn("plant", ["plant-sim", *common, f"--robots={','.join(robots)}", f"--circle={circle!r}"], login)
        return
    for robot, start in zip(robots, circle_starts(len(robots), circle), strict=True):
        supervisor.spawn(
            f"plant-{robot}",
            ["plant-sim", *common, f"--robot={robot}", "--start=" + ",".join(repr(c) for c in start)],
            login,
        )


def spawn_actors(
    supervisor: Supervisor,
    common: list[str],
    robots: list[str],
    layout: str,
    actor_hosts: int,
    duration: float,
    login: dict[str, str] | None,
) -> list[Child]:
    """The actors, each running ``duration`` seconds: ``actor_hosts`` hosts (``host``) or one per robot."""
    run = ["--run-seconds", repr(duration)]
    if layout == "host":
        return [
            supervisor.spawn(name, ["actor", *common, f"--robots={','.join(share)}", *run], login)
            for name, share in host_shares(robots, actor_hosts).items()
        ]
    return [supervisor.spawn(f"actor-{robot}", ["actor", *common, f"--robot={robot}", *run], login) for robot in robots]


def actor_summaries(
    supervisor: Supervisor, robots: list[str], layout: str, actor_hosts: int
) -> tuple[dict[str, RealtimeActorSummary], list[dict[str, float]]]:
    """Each robot's actor summary, and each actor process's own counters (a host's: its tick
    thread's priority), from the actor processes of either layout."""
    if layout == "host":
        per_robot: dict[str, RealtimeActorSummary] = {}
        process_counters = []
        for name in host_shares(robots, actor_hosts):
            host_summary = FleetActorSummary.model_validate(supervisor.children[name].summary())
            per_robot.update(host_summary.per_robot)
            process_counters.append(host_summary.counters)
        return per_robot, process_counters
    per_robot = {
        robot: RealtimeActorSummary.model_validate(supervisor.children[f"actor-{robot}"].summary()) for robot in robots
    }
    return per_robot, [summary.counters for summary in per_robot.values()]


def fleet_args(settings_args: list[str], router: str) -> list[str]:
    """The user's settings flags, without those the fleet sets per child, and the fleet's router."""
    return [a for a in settings_args if a.split("=", 1)[0] not in OWN_FLAGS] + [f"--router={router}"]


def fleet_environment(pooled: bool) -> dict[str, str]:
    """Every child's environment: this process's, with the settings a fleet runs its critic and
    actors with (an ``SRL_`` variable the user set wins) and one BLAS thread per process."""
    env = dict(os.environ)
    env.setdefault("PYTHONUNBUFFERED", "1")
    # one checkpoint write a second (all learners in each), not one per batch: a big fleet's critic
    # would spend its time writing
    env.setdefault("SRL_CRITIC__CHECKPOINT_PERIOD", "1.0")
    env.setdefault("SRL_CRITIC__COALESCE_FITS", "true")  # a critic behind fits each robot's newest only
    env.setdefault("SRL_CRITIC__BATCH_WINDOW", "0.02")  # ~20 robots' fits in one stacked solve at 100 robots
    # each actor keeps this many transitions per robot for a late critic (Zenoh's publisher cache):
    # 60 s at delta = 0.1 s covers a critic's restart (it checkpoints every second here) and
    # partitions up to a minute; the single robot's 3000 would hold ~0.6 MB per robot, filled
    # over the first 5 minutes: a fleet's memory would grow for that long
    env.setdefault("SRL_TRANSPORT__TRANSITION_CACHE", str(FLEET_TRANSITION_CACHE))
    env["SRL_CRITIC__POOLED"] = "true" if pooled else "false"
    # one BLAS thread per process: a pooled fit (25 robots: ~750 rows) is big enough for a BLAS to
    # start threads, which spin on a busy machine and slow every fit. OPENBLAS_NUM_THREADS is already
    # in this process's environment (tools/__init__.py); the children's other BLAS libraries too:
    for variable in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        env.setdefault(variable, "1")
    return env


def run_fleet(
    settings: Settings,
    settings_args: list[str],
    robots: list[str],
    duration: float,
    layout: str = "host",
    circle: float = 1.5,
    quiet: bool = False,
    on_status: Callable[[str], None] | None = None,
    summary_dir: Path | None = None,
    actor_hosts: int = 1,
    count_messages: bool = False,
    plant: str = "sim",
    robot_endpoints: dict[str, str] | None = None,
    bridge_args: list[str] | None = None,
    pooled: bool = False,
    secure: bool = False,
    router: str | None = None,
    record: Path | None = None,
) -> dict[str, Any]:
    """Start the fleet, run it ``duration`` seconds, stop everything; the fleet's summary.

    ``plant="robot"``: ROS 2 robots behind robot bridges (tools/launch/fleet_robot.py), each robot's id
    its namespace; emulated TurtleBot3s for the robots without an entry in ``robot_endpoints``.
    ``plant="physics"``: simulated robots as for ``sim``, each the MuJoCo TurtleBot3
    (``plant.model = physics``: lag, deadband, slip, odometry) instead of the ideal unicycle.
    ``pooled``: one critic learner for every robot (critic.pooled), else one per robot.
    ``secure``: as ``srl up --secure`` (tools.launch.supervisor.Logins): every child logs in as its role over
    mutual TLS, and the router's rules grant the roles the keys of every robot of the fleet; with
    ``plant="robot"`` each emulated robot's own router is secured too (tools/launch/fleet_robot.py).
    ``router``: where the fleet's router listens (``srl up`` chooses it: tools/launch/fleet_cli.py);
    default: a free loopback port, so that fleets side by side never meet. ``record``: an ``srl record``
    child writes every robot to this MCAP file for the whole run (subscribed before the first state;
    its CPU and memory count with the fleet's); refused with ``secure`` (the read-only monitor role may
    not read the transitions and weights a recording carries)."""
    if layout not in LAYOUTS:
        raise ValueError(f"unknown layout {layout!r} ({' or '.join(LAYOUTS)})")
    bridged = launch_plant(plant).behind_bridge
    if not 1 <= actor_hosts <= len(robots):
        raise ValueError(f"{actor_hosts} actor hosts for {len(robots)} robots: 1 to one per robot")
    if secure and record is not None:
        raise ValueError("--record does not run with --secure: no role may read the transitions and weights")
    if secure and count_messages:
        raise ValueError("counting every message needs to read srl/**, which no role may do with secure")
    router = router or free_loopback_endpoint()
    settings = settings.model_copy(update={"transport": settings.transport.model_copy(update={"router": router})})
    env = fleet_environment(pooled)
    settings = with_launch_plant(settings, env, plant)  # physics: one MuJoCo TurtleBot3 per robot
    common = fleet_args(settings_args, router)
    ids = ",".join(robots)
    started = time.monotonic()
    logins: Logins | None = None
    scratch: Path | None = None
    with StopSignals() as signals:
        supervisor = Supervisor(common, env, quiet=quiet, signals=signals)
        try:
            # made while the signals are watched: a signal from here on still removes them (the finally below)
            scratch = Path(tempfile.mkdtemp(prefix="srl-fleet-"))
            # the critic's checkpoint is written as in any run (its cost is part of the fleet's), but here
            env["SRL_CRITIC__CHECKPOINT"] = str(scratch / "critic-{robot}-{agent}-N{horizon}.json")
            login: dict[str, dict[str, str]] = {}
            if secure:
                logins = Logins.create(settings.transport, lockstep=False, robots=robots)
                login = logins.environment
                common = logins.argv(common)
                # this process's probes and status lines log in as the read-only monitor
                settings = settings.model_copy(update={"transport": logins.monitor})
            supervisor.spawn("router", ["router", *common], login.get("router"))
            supervisor.wait_for("router", lambda: router_reachable(settings), timeout=30)
            if record is not None:  # subscribed before the first state is published
                recorder = supervisor.spawn("recorder", ["record", str(record), "--clock", "wall", *common])
                supervisor.wait_for("recorder", said(recorder, "srl record: recording"), timeout=30)
            starts = circle_starts(len(robots), circle)
            if bridged:  # emulated or real TurtleBot3s behind bridges
                from tools.launch.fleet_robot import spawn_robot_plants

                ros = spawn_robot_plants(
                    supervisor,
                    settings,
                    common,
                    robots,
                    starts,
                    robot_endpoints or {},
                    bridge_args or [],
                    layout,
                    login.get("plant"),
                    None if logins is None else logins.directory / "robot",  # removed with the fleet's logins
                )
            else:
                spawn_sim_plants(supervisor, common, robots, layout, circle, login.get("plant"))
            supervisor.spawn("critic", ["critic", *common, f"--robots={ids}"], login.get("critic"))
            wait_fleet_alive(supervisor, settings, robots, "plant")
            if bridged:
                from tools.launch.fleet_robot import wait_fleet_odometry

                wait_fleet_odometry(supervisor, settings, ros)
            wait_fleet_alive(supervisor, settings, robots, "critic")
            actors = spawn_actors(supervisor, common, robots, layout, actor_hosts, duration, login.get("actor"))
            wait_fleet_alive(supervisor, settings, robots, "actor")
            measures = measure_fleet(supervisor, settings, actors, duration, len(robots), on_status, count_messages)
            for actor in actors:
                if actor.process.returncode != 0:
                    supervisor.check()
        finally:
            signals.cleaning = True
            if bridged:
                from tools.launch.fleet_robot import stop_bridges

                stop_bridges(supervisor, robots, layout)
            supervisor.stop_all()
            if scratch is not None:
                shutil.rmtree(scratch, ignore_errors=True)
            if logins is not None:
                logins.remove()
        signals.raise_if_received()
    for name, child in supervisor.children.items():  # every service ended cleanly (as srl up checks)
        if exit_code(child.process.returncode) != 0:
            raise ServiceDiedError(name, child.process.returncode, child.stderr_tail[-10:])
    critic = TypeAdapter(CriticSummary).validate_python(supervisor.children["critic"].summary())
    per_robot, process_counters = actor_summaries(supervisor, robots, layout, actor_hosts)
    view = fleet_view(per_robot)
    ticks = sum(summary.steps for summary in per_robot.values())
    hurried = sum(summary.counters.get("hurried_solves", 0.0) for summary in per_robot.values())
    summary = {
        "plant": plant,
        "layout": layout,
        "robots": robots,
        "seconds": duration,
        "run_seconds": measures.ran,  # the span over which CPU was measured
        "circle_radius_m": circle,
        "actor_hosts": actor_hosts if layout == "host" else len(robots),
        "secure": secure,
        "router": router if logins is None or logins.tls_router is None else logins.tls_router,
        "agent": settings.actor.agent,
        "horizon": settings.actor.horizon,
        "fleet": view.to_json_dict(),
        # how the actor processes ticked: how many had their tick thread real-time
        # (actor.realtime_priority), and the share of ticks solved in a hurry (late or over budget)
        "actor_ticks": {
            "processes": len(process_counters),
            "realtime": sum(counters.get("realtime_priority", 0.0) > 0 for counters in process_counters),
            "hurried_percent": 100.0 * hurried / ticks if ticks else 0.0,
        },
        "critic": {
            "transitions_received": critic.transitions_received,
            "weights_published": critic.weights_published,
            "fit_ms": critic.fit_ms.to_json_dict(),
            "checkpoint_ms": critic.checkpoint_ms.to_json_dict(),
            "batch_transitions": None if critic.batch_transitions is None else critic.batch_transitions.to_json_dict(),
            "waiting_transitions": None
            if critic.waiting_transitions is None
            else critic.waiting_transitions.to_json_dict(),
            "fits_coalesced": critic.fits_coalesced,
            "fits_at_rest": critic.fits_at_rest,
            "pooled": critic.pooled,
        },
        **measures.fields(len(supervisor.children)),
        "wall_seconds": time.monotonic() - started,
        "services": {name: child.process.pid for name, child in supervisor.children.items()},
        "exit_codes": {name: exit_code(child.process.returncode) for name, child in supervisor.children.items()},
    }
    if record is not None:
        summary["recording"] = str(record)
        summary["recorder"] = next(
            (line for line in supervisor.children["recorder"].stdout_lines if line.startswith("srl record:")), None
        )
    if count_messages:  # over the same span as the CPU: [count, bytes] of each kind
        summary["messages"] = measures.messages
    if bridged:
        from tools.launch.fleet_robot import robot_fleet_summary

        summary["robot_plant"] = robot_fleet_summary(supervisor, settings, robots, layout)
    if summary_dir is not None:
        write_child_summaries(summary_dir, supervisor.children)
        summary["summary_dir"] = str(summary_dir)
        summary["per_robot_final"] = {r: s.final_state for r, s in per_robot.items()}
    return summary


def format_fleet_summary(summary: dict[str, Any]) -> str:
    view = FleetView.model_validate(summary["fleet"])
    lines = [
        f"srl up --robots {len(summary['robots'])} ({summary['layout']} layout): {summary['seconds']:.0f} s, "
        f"{summary['agent']} N = {summary['horizon']}, starts on a {summary['circle_radius_m']} m circle"
        + (", MuJoCo TurtleBot3s (final m: their true pose)" if summary.get("plant") == "physics" else ""),
        f"  {'robot':<12} {'steps':>5} {'missed':>6} {'jitter p99':>10} {'latency p99':>11} {'staleness p99/max':>17} "
        f"{'final m':>8} parked",
    ]
    if summary.get("secure"):
        lines.insert(
            1,
            "  security       user/password login per role + access rules at the router for every robot"
            + (", mutual TLS" if str(summary.get("router", "")).startswith("tls/") else ""),
        )
        if summary.get("robot_plant"):
            from tools.launch.fleet_robot import robot_router_line

            lines.insert(2, robot_router_line(summary["robot_plant"]))
    for row in view.rows:
        lines.append(
            f"  {row.robot:<12} {row.steps:>5} {row.missed_deadlines:>6} {row.jitter_p99_ms:>8.2f}ms "
            f"{row.latency_p99_ms:>9.2f}ms {row.staleness_p99_steps:>8.0f}/{row.staleness_max_steps:<8.0f} "
            f"{row.final_distance_m:>8.3f} {'yes' if row.parked else 'no'}"
        )
    lines.append(
        f"  fleet: {view.robots} robots, parked {view.parked}, missed deadlines {view.missed_deadlines}, "
        f"jitter p99 {view.jitter_p99_ms:.2f} ms, latency p99 {view.latency_p99_ms:.2f} ms (worst robot), "
        f"staleness p99/max {view.staleness_p99_steps:.0f}/{view.staleness_max_steps:.0f} steps, "
        f"CPU {summary['cpu_percent']:.0f} %, RSS {summary['rss_mb']:.0f} MB in {summary['processes']} processes"
    )
    phases = summary.get("cpu_phases")
    if phases:
        drive, rest = phases["driving"], phases["at_rest"]
        lines.append(
            f"  CPU while the robots drove {drive['cpu_percent']:.0f} % ({drive['seconds']:.1f} s), "
            f"once every robot had arrived {rest['cpu_percent']:.0f} % ({rest['seconds']:.1f} s: no solve, no fit"
            + (
                f"; at times only {rest['fewest_arrived']} of {len(summary['robots'])} arrived)"
                if rest["fewest_arrived"] < len(summary["robots"])
                else ")"
            )
        )
    if summary.get("actor_ticks"):
        ticks = summary["actor_ticks"]
        lines.append(
            f"  actor ticks: real-time (SCHED_FIFO) in {ticks['realtime']} of {ticks['processes']} actor processes, "
            f"{ticks['hurried_percent']:.1f} % solved in a hurry (served late or over the host's CPU budget)"
        )
    if summary.get("robot_plant"):
        from tools.launch.fleet_robot import format_robot_lines

        lines += format_robot_lines(summary["robot_plant"])
    return "\n".join(lines)
