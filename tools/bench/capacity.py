"""``srl bench capacity``: what one robot costs each component, and what a large fleet needs.

Runs the simulated fleet (``srl up --robots K``, host layout: router, plant host, critic, actor
hosts) at a few sizes, real time, with a counter subscribed to ``srl/**`` (tools/launch/measure.py's
:class:`~tools.launch.measure.MessageCounter`). From each run: every process's CPU over the run (from
/proc) and every message kind's count and bytes. A straight line through the sizes (least
squares) splits each component's CPU into a fixed part and a part per robot; messages per robot
and second are the counts over robots and seconds (their spread over the sizes is printed too).

The model then answers "how many hosts and routers for 1,000 and 10,000 robots": a component's
cores are ``fixed + per_robot * robots`` at a utilisation of at most ``--utilisation`` (real-time
work needs headroom: a loaded machine misses deadlines well before 100 %); one actor host
process serves as many robots as fit one core at that utilisation (its solves run in one thread);
routers as many as the routed messages need cores (the router's CPU per robot, measured with the
counter attached: one extra delivery per message, so the figure is an upper bound), at least one per
host (rmw_zenoh's multi-host layout). Real robots carry their own plant (the bridge per robot
replaces the plant host's share), so the model is given for simulated robots and says so.
"""

from __future__ import annotations

import argparse
import json
import math
from typing import Any

import numpy as np

from common.config.arguments import UsageError
from common.config.settings import Settings
from common.math.fleet import parse_robots
from tools.bench.fleet import actor_hosts, measured_run, robot_counts, run_header
from tools.bench.meta import run_info
from tools.launch.up import UpOptions

COMPONENTS = ("router", "plant", "critic", "actor")
FLEETS = (1_000, 10_000)


def component(service: str) -> str:
    """A child's name -> its component (``actor-2`` -> ``actor``)."""
    for name in COMPONENTS:
        if service == name or service.startswith(f"{name}-"):
            return name
    return service


def fit_line(sizes: list[int], values: list[float]) -> tuple[float, float]:
    """Least-squares ``fixed + per_robot * size`` (a single size: all of it per robot)."""
    if len(set(sizes)) < 2:
        return 0.0, values[0] / sizes[0]
    per_robot, fixed = np.polyfit(np.asarray(sizes, dtype=float), np.asarray(values, dtype=float), 1)
    return float(fixed), float(per_robot)


def model(rows: list[dict[str, Any]], utilisation: float, host_cores: int) -> dict[str, Any]:
    """The per-component costs (fitted) and what 1,000 and 10,000 robots need."""
    ok = [row for row in rows if "error" not in row]
    sizes = [row["robots"] for row in ok]
    cpu: dict[str, dict[str, float]] = {}
    for name in COMPONENTS:
        values = [
            sum(p for s, p in row["cpu_percent_by_service"].items() if component(s) == name) / 100.0 for row in ok
        ]
        fixed, per_robot = fit_line(sizes, values)
        cpu[name] = {"fixed_cores": fixed, "per_robot_cores": per_robot}
    kinds = sorted({kind for row in ok for kind in row["messages"]})
    messages: dict[str, dict[str, float]] = {}
    for kind in kinds:
        rates = [row["messages"].get(kind, [0, 0])[0] / row["robots"] / row["run_seconds"] for row in ok]
        sizes_bytes = [row["messages"].get(kind, [0, 0])[1] / row["robots"] / row["run_seconds"] for row in ok]
        messages[kind] = {
            "per_robot_per_s": float(np.median(rates)),
            "min": float(min(rates)),
            "max": float(max(rates)),
            "bytes_per_robot_per_s": float(np.median(sizes_bytes)),
        }
    per_message_router = cpu["router"]["per_robot_cores"] / max(
        sum(m["per_robot_per_s"] for m in messages.values()), 1e-9
    )
    needs = {}
    for fleet in FLEETS:
        cores = {name: c["fixed_cores"] + c["per_robot_cores"] * fleet for name, c in cpu.items()}
        robots_per_actor_host = max(1, math.floor(utilisation / cpu["actor"]["per_robot_cores"]))
        actor_hosts = math.ceil(fleet / robots_per_actor_host)
        total_cores = sum(cores.values()) / utilisation
        hosts = math.ceil(total_cores / host_cores)
        routers = max(hosts, math.ceil(cores["router"] / utilisation))
        needs[str(fleet)] = {
            "cores": {name: value for name, value in cores.items()},
            "actor_host_processes": actor_hosts,
            "robots_per_actor_host": robots_per_actor_host,
            "hosts": hosts,
            "routers": routers,
            "messages_per_s": fleet * sum(m["per_robot_per_s"] for m in messages.values()),
            "megabytes_per_s": fleet * sum(m["bytes_per_robot_per_s"] for m in messages.values()) / 1e6,
        }
    return {
        "cpu": cpu,
        "messages": messages,
        "router_core_seconds_per_message": per_message_router,
        "utilisation": utilisation,
        "host_cores": host_cores,
        "fleets": needs,
    }


def run_capacity_benchmark(args: argparse.Namespace, settings: Settings, settings_argv: list[str]) -> int:
    sizes = robot_counts(args.robots, "--robots")
    if not sizes:
        raise UsageError("--robots: at least one fleet size, e.g. 10,25,50")
    if not (math.isfinite(args.seconds) and 5 <= args.seconds <= 600):
        raise UsageError(f"--seconds {args.seconds}: a run is 5 to 600 s")
    if not (math.isfinite(args.utilisation) and 0 < args.utilisation <= 1):
        raise UsageError(f"--utilisation {args.utilisation}: a share of a core, 0 < u <= 1")
    if args.host_cores < 1:
        raise UsageError(f"--host-cores {args.host_cores}: at least 1")
    rows: list[dict[str, Any]] = []
    for size in sizes:
        options = UpOptions(
            settings_argv,
            duration=args.seconds,
            robots=parse_robots(str(size)),
            quiet=True,
            actor_hosts=actor_hosts("auto", size),
            count_messages=True,
        )
        row = measured_run(settings, options)
        rows.append(row)
        print(format_row(row), flush=True)
    if not any("error" not in row for row in rows):
        raise UsageError("srl bench capacity: no run finished (see the rows above)")
    result = {
        **run_header(settings, args.seconds),
        "rows": rows,
        "model": model(rows, args.utilisation, args.host_cores),
    }
    print(format_model(result))
    if args.json:
        print(json.dumps({**result, "run": run_info()}))
    return 0


def format_row(row: dict[str, Any]) -> str:
    load = f"load {row['load_before'][0]:.2f} -> {row['load_after'][0]:.2f}"
    if "error" in row:
        return f"{row['robots']:>5} robots: failed: {row['error']} ({load})"
    by = {name: 0.0 for name in COMPONENTS}
    for service, percent in row["cpu_percent_by_service"].items():
        by[component(service)] = by.get(component(service), 0.0) + percent
    cpu = ", ".join(f"{name} {percent:.0f} %" for name, percent in by.items())
    sent = sum(count for count, _ in row["messages"].values()) / row["run_seconds"]
    f = row["fleet"]
    return (
        f"{row['robots']:>5} robots: CPU {cpu}; {sent:.0f} messages/s; missed deadlines {f['missed_deadlines']}; "
        f"{f['parked']}/{row['robots']} parked ({load})"
    )


def format_model(result: dict[str, Any]) -> str:
    m = result["model"]
    lines = [
        f"srl bench capacity: {result['seconds']:.0f} s real time per size, {result['agent']} N = "
        f"{result['horizon']}, {result['cpus']} CPUs; CPU per component = fixed + per robot (least squares "
        "over the sizes; 1 core = 100 %)",
        f"  {'component':<10} {'fixed % core':>12} {'per robot % core':>16}",
    ]
    for name, c in m["cpu"].items():
        lines.append(f"  {name:<10} {100 * c['fixed_cores']:>12.2f} {100 * c['per_robot_cores']:>16.3f}")
    lines.append(f"  {'message kind':<22} {'per robot /s':>12} {'(min-max)':>13} {'bytes/robot/s':>13}")
    for kind, r in m["messages"].items():
        spread = f"({r['min']:.1f}-{r['max']:.1f})"
        lines.append(f"  {kind:<22} {r['per_robot_per_s']:>12.2f} {spread:>13} {r['bytes_per_robot_per_s']:>13.0f}")
    lines.append(
        f"  router: {1e6 * m['router_core_seconds_per_message']:.1f} us of a core per message routed (with the "
        "counter attached: an upper bound)"
    )
    lines.append(
        f"  what a fleet needs at <= {100 * m['utilisation']:.0f} % of each core, {m['host_cores']}-core hosts "
        "(simulated robots: the plant host's share is on the robots for real ones):"
    )
    for fleet, need in m["fleets"].items():
        cores = ", ".join(f"{name} {value:.1f}" for name, value in need["cores"].items())
        lines.append(
            f"  {int(fleet):>6} robots: cores {cores}; {need['actor_host_processes']} actor host processes "
            f"({need['robots_per_actor_host']} robots each), {need['hosts']} hosts, {need['routers']} routers, "
            f"{need['messages_per_s']:.0f} messages/s ({need['megabytes_per_s']:.1f} MB/s)"
        )
    return "\n".join(lines)
