"""``srl bench fleet``: how many robots one 2-core machine serves at ``delta`` (docs/fleets.md).

For each fleet size, one real-time run of ``--seconds`` with the host layout (one actor host,
one plant host, the critic: ``srl up --robots K``), and for the baseline sizes one run with
the process layout (one plant_sim and one actor process per robot), in the same invocation and
interleaved by size, so both see the same machine. Each row: missed deadlines (all robots), tick
jitter and state -> action latency p99 (worst robot), weight staleness p99 / max (worst robot),
robots parked (within 0.25 m of the target at the end; starts on a 1.5 m circle), robots at their
target as one robot alone parks (by their own final state within 0.05 m, and at rest: the last
command zero) and the farthest, CPU % of all srl processes over the run (100 % = one core) and
that CPU per robot per sampling interval, their total resident memory, and the machine's load
average before and after. Targets (PASS/FAIL) at 50, 100 and 300 robots, the soak's (RSS
growth <= 2 % at 50 robots over 600 s and more), and with ``--record`` a complete recording (its
writer dropped nothing). Every run is bounded (start-up timeouts, then
``--seconds``) and every process is stopped after it (tools/launch/up.py). ``--record``: every
row with ``srl record`` attached for the whole run (a subscriber to every robot's keys, as a user
records a fleet), its file in a temporary directory removed after the row.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import tempfile
import time
from pathlib import Path
from typing import Any

from common.config.arguments import UsageError
from common.config.settings import Settings
from common.math.fleet import FleetError, parse_robots
from tools.bench.meta import run_info
from tools.launch.supervisor import ServiceDiedError
from tools.launch.up import UpOptions, actor_hosts, run_up

TARGETS: dict[int, dict[str, float]] = {
    50: {"missed_deadlines": 0, "latency_p99_ms": 20.0, "staleness_p99_steps": 1.0},
    100: {
        "missed_deadlines": 0,
        "latency_p99_ms": 50.0,
        "staleness_p99_steps": 1.0,
        "rss_mb": 1536.0,
        "machine_cpu_percent": 70.0,
        "cpu_ms_per_robot_tick": 0.5,
    },
    300: {
        "missed_deadlines": 0,
        "latency_p99_ms": 50.0,
        "staleness_p99_steps": 1.0,
        "rss_mb": 2048.0,
        "cpu_ms_per_robot_tick": 0.5,
    },
}


def cpu_ms_per_robot_tick(cpu_percent: float, robots: int, delta: float) -> float:
    """CPU of every srl process per robot per sampling interval [ms]: ``cpu_percent`` is over the
    run, 100 % = one core, so each second costs ``cpu_percent / 100`` s, shared by ``robots / delta``
    robot ticks."""
    return cpu_percent / 100.0 * delta * 1e3 / robots


def robot_counts(text: str, option: str) -> list[int]:
    try:
        sizes = [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        raise UsageError(f"{option} {text!r}: comma-separated robot counts, e.g. 1,8,16") from None
    for size in sizes:
        try:
            parse_robots(str(size))
        except FleetError as error:
            raise UsageError(f"{option}: {error}") from None
    return sizes


# the soak: ``--robots 50 --baseline '' --seconds 600`` (RSS from the end of warm-up to the end)
SOAK_ROBOTS, SOAK_SECONDS, SOAK_GROWTH_PERCENT = 50, 600.0, 2.0


def checks(row: dict[str, Any]) -> dict[str, bool]:
    """The targets of a row's fleet size (none for other sizes)."""
    target = TARGETS.get(row["robots"])
    if target is None or "error" in row:
        return {} if "error" not in row else {"ran": False}
    fleet = row["fleet"]
    result = {
        "missed deadlines == 0": fleet["missed_deadlines"] == target["missed_deadlines"],
        f"latency p99 <= {target['latency_p99_ms']:.0f} ms": fleet["latency_p99_ms"] <= target["latency_p99_ms"],
        "staleness p99 <= 1 step": fleet["staleness_p99_steps"] <= target["staleness_p99_steps"],
    }
    if row["robots"] == 50:
        result["every robot parked"] = fleet["parked"] == row["robots"]
    if row["robots"] >= 100:  # as one robot alone: by its own state within 0.05 m, at rest
        result["every robot at its target"] = fleet.get("at_target", 0) == row["robots"]
    if "machine_cpu_percent" in target:
        machine = row["cpu_percent"] / (row.get("cpus") or os.cpu_count() or 1)
        result[f"CPU <= {target['machine_cpu_percent']:.0f} % of the machine"] = (
            machine <= target["machine_cpu_percent"]
        )
    if "cpu_ms_per_robot_tick" in target:
        limit = target["cpu_ms_per_robot_tick"]
        result[f"CPU per robot tick <= {limit} ms"] = row["cpu_ms_per_robot_tick"] <= limit
    if "rss_mb" in target:
        result[f"RSS <= {target['rss_mb'] / 1024:.1f} GB"] = row["rss_mb"] <= target["rss_mb"]
    if "recorder_dropped" in row:  # srl record attached: it recorded the whole run, nothing dropped
        result["recording complete"] = row["recorder_dropped"] == 0
    if row["robots"] == SOAK_ROBOTS and row["seconds"] >= SOAK_SECONDS:  # the soak: memory stays put
        result[f"soak: RSS growth <= {SOAK_GROWTH_PERCENT:.0f} %"] = row["rss_growth_percent"] <= SOAK_GROWTH_PERCENT
    return result


def measured_run(settings: Settings, options: UpOptions) -> dict[str, Any]:
    """One bench row: the fleet run of ``options`` (:func:`run_up`; ``options.robots`` its robots),
    the machine's load before and after; a run that fails is a row with its error."""
    assert options.robots is not None, "a bench row is a fleet's run"
    size = len(options.robots)
    load_before = os.getloadavg()
    started = time.monotonic()
    try:
        summary = run_up(settings, options)
    except (ServiceDiedError, TimeoutError, ValueError) as error:
        summary = {"error": str(error), "wall_seconds": time.monotonic() - started}
    row = {"layout": options.layout, **summary, "robots": size, "cpus": os.cpu_count()}
    recording = options.record
    if recording is not None:
        from tools.recording.record import dropped_by_writer

        row["recording_mb"] = recording.stat().st_size / 1e6 if recording.exists() else 0.0
        row["recorder_dropped"] = dropped_by_writer(row.get("recorder"))
    row["load_before"], row["load_after"] = list(load_before), list(os.getloadavg())
    if "cpu_percent" in row:
        row["cpu_ms_per_robot_tick"] = cpu_ms_per_robot_tick(row["cpu_percent"], size, settings.plant.sampling_time)
    for phase in (row.get("cpu_phases") or {}).values():  # driving, and at rest (no solve, no fit)
        phase["cpu_ms_per_robot_tick"] = cpu_ms_per_robot_tick(phase["cpu_percent"], size, settings.plant.sampling_time)
    return row


def layout_label(row: dict[str, Any]) -> str:
    """A row's layout as tables show it: ``process``, or ``host xH`` (H actor hosts)."""
    return str(row["layout"]) if row["layout"] == "process" else f"host x{row.get('actor_hosts', 1)}"


def phase_ms(row: dict[str, Any], phase: str, figure: str = "cpu_ms_per_robot_tick") -> float:
    """A figure of one phase of a row's run: its CPU per robot tick [ms], or another of the phase's
    (``wakes_per_second`` at rest: tools.launch.measure.Wakes); NaN: not every robot arrived, or
    not read."""
    return float(((row.get("cpu_phases") or {}).get(phase) or {}).get(figure, math.nan))


def run_header(settings: Settings, seconds: float) -> dict[str, Any]:
    """What every row of a fleet benchmark shares: run length, CPUs, agent and horizon."""
    return {
        "seconds": seconds,
        "cpus": os.cpu_count(),
        "agent": settings.actor.agent,
        "horizon": settings.actor.horizon,
    }


def run_fleet_benchmark(args: argparse.Namespace, settings: Settings, settings_argv: list[str]) -> int:
    hosts = robot_counts(args.robots, "--robots")
    baseline = robot_counts(args.baseline, "--baseline") if args.baseline else []
    if not (math.isfinite(args.seconds) and 5 <= args.seconds <= 600):
        raise UsageError(f"--seconds {args.seconds}: a run is 5 to 600 s")
    for size in hosts:
        actor_hosts(args.actor_hosts, size)  # a bad value is refused before the first run
    plan = sorted([(n, "host") for n in hosts] + [(n, "process") for n in baseline])
    rows: list[dict[str, Any]] = []
    record = bool(getattr(args, "record", False))
    outside = bool(getattr(args, "outside", False))
    for size, layout in plan:
        split = actor_hosts(args.actor_hosts, size) if layout == "host" else 1
        with tempfile.TemporaryDirectory(prefix="srl-bench-fleet-") as scratch:
            recording = Path(scratch) / f"fleet-{size}.mcap" if record else None
            row = measured_run(
                settings,
                UpOptions(
                    settings_argv,
                    duration=args.seconds,
                    robots=parse_robots(str(size)),
                    quiet=True,
                    layout=layout,
                    actor_hosts=split,
                    record=recording,
                    outside=outside,
                ),
            )
        row["targets"] = {name: "PASS" if ok else "FAIL" for name, ok in checks(row).items()}
        rows.append(row)
        print(format_row(row), flush=True)
    result = {**run_header(settings, args.seconds), "recorded": record, "outside": outside, "rows": rows}
    print(format_table(result))
    if args.json:
        print(json.dumps({**result, "run": run_info()}))
    return 0


HEADER = (
    f"{'robots':>6} {'layout':<10} {'missed':>6} {'jitter p99':>10} {'latency p99':>11} {'stale p99/max':>13} "
    f"{'parked':>7} {'at target':>9} {'worst m':>7} {'CPU %':>6} {'Zenoh %':>7} {'ms/tick':>7} {'drive':>6} "
    f"{'rest':>6} {'wakes/s':>7} {'RSS MB':>7} "
    f"{'growth':>7} "
    f"{'procs':>5} {'RT':>5} {'hurried':>7}  "
    "load before -> after  targets"
)


def format_row(row: dict[str, Any]) -> str:
    load = f"{row['load_before'][0]:.2f} -> {row['load_after'][0]:.2f}"
    if "error" in row:
        return f"{row['robots']:>6} {row['layout']:<10} failed: {row['error']}  (load {load})"
    f = row["fleet"]
    layout = layout_label(row)
    targets = ", ".join(f"{name}: {verdict}" for name, verdict in row["targets"].items()) or "-"
    ticks = row.get("actor_ticks")  # RT: actor processes whose tick thread was real-time, of all
    realtime = f"{ticks['realtime']}/{ticks['processes']}" if ticks else "-"
    hurried = f"{ticks['hurried_percent']:.1f}%" if ticks else "-"
    if "recording_mb" in row:  # srl record's summary line: "srl record: recorded N messages on ..."
        said = (row.get("recorder") or "").split(" on ", 1)[0].removeprefix("srl record: ")
        dropped = f", {row['recorder_dropped']} dropped" if row.get("recorder_dropped") else ""
        targets += f"; {said or 'srl record said nothing'}{dropped} ({row['recording_mb']:.1f} MB)"
    if row.get("outside_received") is not None:  # --outside: what the outside subscriber got
        targets += f"; outside subscriber: {row['outside_received']:,} transitions"
    return (
        f"{row['robots']:>6} {layout:<10} {f['missed_deadlines']:>6} {f['jitter_p99_ms']:>8.2f}ms "
        f"{f['latency_p99_ms']:>9.2f}ms {f['staleness_p99_steps']:>6.0f}/{f['staleness_max_steps']:<6.0f} "
        f"{f['parked']:>3}/{row['robots']:<3} {f.get('at_target', 0):>4}/{row['robots']:<4} "
        f"{f.get('worst_own_final_distance_m', math.nan):>7.3f} {row['cpu_percent']:>6.0f} "
        f"{row.get('zenoh_cpu_percent', math.nan):>7.0f} {row['cpu_ms_per_robot_tick']:>7.3f} "
        f"{phase_ms(row, 'driving'):>6.3f} {phase_ms(row, 'at_rest'):>6.3f} "
        f"{phase_ms(row, 'at_rest', 'wakes_per_second'):>7.0f} {row['rss_mb']:>7.0f} "
        f"{row['rss_growth_percent']:>6.1f}% {row['processes']:>5} {realtime:>5} {hurried:>7}  {load:<20} {targets}"
    )


def format_table(result: dict[str, Any]) -> str:
    lines = [
        f"srl bench fleet: {result['seconds']:.0f} s real time per row, {result['agent']} N = {result['horizon']}, "
        f"starts on a 1.5 m circle, {result['cpus']} CPUs"
        + (", srl record attached to every row" if result.get("recorded") else "")
        + (", an outside subscriber of every robot's transition key on every row" if result.get("outside") else "")
        + "; jitter, latency, staleness: worst robot; "
        "at target: robots whose own final state is within 0.05 m of the target, at rest (last command zero); "
        "worst m: the farthest robot by its own state; "
        "CPU: all srl processes (100 % = one core), Zenoh: of it their Zenoh runtime threads' (the network, and "
        "the handlers called on it), ms/tick: their CPU per robot per sampling interval, over the run, while the "
        "robots drive (drive: until every robot has reported itself arrived) and at rest (rest: from then on, no "
        "solve and no fit; nan: not every robot arrived); "
        "wakes/s: at rest, how often their threads woke from a wait, a second (each wake costs a context "
        "switch and a cold cache); "
        "growth: their RSS from the end of warm-up (the first "
        "tenth) to the end; RT: actor processes whose tick thread ran under SCHED_FIFO (actor.realtime_priority); "
        "hurried: ticks solved in a hurry (served late or over actor.host_cpu_budget); load: 1-min average",
        HEADER,
        *(format_row(row) for row in result["rows"]),
    ]
    return "\n".join(lines)
