"""``srl bench loop``: the real-time system, every service a process, for N seconds.

Prints tick period (median/p99/max), missed deadlines, state-to-action latency excluding the
solve, weight staleness, and CPU / peak RSS per service; ``--critic-load`` makes the critic
fit a replay of M = 1000 at every step. With ``--json`` the last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
from typing import Any

from common.config.arguments import UsageError
from common.config.settings import Settings
from tools.bench.meta import run_info
from tools.launch.up import UpOptions, run_up

RECORD_JITTER_MARGIN_MS = 0.5  # a recorder may cost the loop's jitter p99 at most this much
TARGETS = {"missed_deadlines": 0, "jitter_p99_ms": 2.0, "latency_p99_ms": 1.0, "staleness_median_steps": 1.0}


def run_loop_benchmark(args: argparse.Namespace, settings: Settings, settings_argv: list[str]) -> int:
    if args.critic_load:
        # The children read settings from flags and environment: M goes by environment.
        os.environ["SRL_CRITIC__REPLAY_SIZE"] = "1000"
        settings = Settings.load(getattr(args, "config", None), **_overrides(settings))
    if args.rounds is not None and not args.record:
        raise UsageError("--rounds is for --record (pairs of runs without and with a recorder)")
    if args.record:
        return compare_recording(args, settings, settings_argv)
    load_before = os.getloadavg()
    summary = run_up(
        settings, UpOptions(settings_argv, mode="realtime", plant="sim", duration=args.seconds, quiet=True)
    )
    load_after = os.getloadavg()
    loop = summary["loop"]
    result: dict[str, Any] = {
        "seconds": args.seconds,
        "critic_load": bool(args.critic_load),
        "replay_size": settings.critic.replay_size,
        "agent": summary.get("agent"),
        "horizon": summary.get("horizon"),
        "steps": summary.get("steps"),
        "period_ms": loop["period_ms"],
        "jitter_ms": loop["jitter_ms"],
        "missed_deadlines": loop["missed_deadlines"],
        "solve_ms": summary.get("solve_ms"),
        "latency_ms": summary.get("latency_ms"),
        "staleness_steps": summary.get("staleness_steps"),
        "staleness_ms": summary.get("staleness_ms"),
        "critic_fit_ms": summary["critic"]["fit_ms"],
        "transitions_received": summary["critic"]["transitions_received"],
        "resources": summary.get("resources"),
        # other work on the machine disturbs real-time numbers: say how much there was
        "machine": {"cpus": os.cpu_count(), "load_before": list(load_before), "load_after": list(load_after)},
    }
    checks = {
        "missed_deadlines == 0": loop["missed_deadlines"] == TARGETS["missed_deadlines"],
        "jitter p99 <= 2 ms": loop["jitter_ms"]["p99"] <= TARGETS["jitter_p99_ms"],
        "latency p99 <= 1 ms": result["latency_ms"]["p99"] <= TARGETS["latency_p99_ms"],
    }
    if not args.critic_load:
        checks["staleness median <= 1 step"] = result["staleness_steps"]["median"] <= TARGETS["staleness_median_steps"]
    result["targets"] = {name: ("PASS" if ok else "FAIL") for name, ok in checks.items()}
    print(format_table(result))
    if args.json:
        print(json.dumps({**result, "run": run_info()}))
    return 0


def _overrides(settings: Settings) -> dict[str, Any]:
    return {
        "actor": settings.actor.model_dump(),
        "episode": settings.episode.model_dump(),
        "transport": settings.transport.model_dump(),
    }


def format_table(r: dict[str, Any]) -> str:
    def row(name: str, stats: dict[str, float] | None, unit: str = "ms") -> str:
        if not stats:
            return f"  {name:<34} n/a"
        return f"  {name:<34} {stats['median']:>10.3f} {stats['p99']:>10.3f} {stats['max']:>10.3f}  {unit}"

    lines = [
        f"srl bench loop: {r['seconds']:.0f} s real time, agent {r['agent']}, N = {r['horizon']}, "
        f"M = {r['replay_size']}{' (critic load)' if r['critic_load'] else ''}, {r['steps']} steps",
        f"  {'':<34} {'median':>10} {'p99':>10} {'max':>10}",
        row("tick period", r["period_ms"]),
        row("tick jitter |period - delta|", r["jitter_ms"]),
        row("actor solve", r["solve_ms"]),
        row("state -> action latency (no solve)", r["latency_ms"]),
        row("critic fit", r["critic_fit_ms"]),
        row("weight staleness", r["staleness_steps"], "steps"),
        row("weight age (data -> use)", r["staleness_ms"]),
        f"  missed deadlines {r['missed_deadlines']}, transitions received by the critic "
        f"{r['transitions_received']} of {r['steps']}",
        f"  {'service':<10} {'CPU s':>8} {'CPU %':>7} {'peak RSS MB':>12}",
    ]
    for name, res in (r["resources"] or {}).items():
        if res:
            lines.append(
                f"  {name:<10} {res['cpu_seconds']:>8.2f} {100 * res['cpu_seconds'] / r['seconds']:>7.1f} "
                f"{res['peak_rss_mb']:>12.1f}"
            )
    machine = r.get("machine")
    if machine:
        lines.append(
            f"  machine: {machine['cpus']} CPUs, load average "
            f"{'/'.join(f'{x:.2f}' for x in machine['load_before'])} -> "
            f"{'/'.join(f'{x:.2f}' for x in machine['load_after'])}"
        )
    lines.append("  targets: " + ", ".join(f"{k}: {v}" for k, v in r["targets"].items()))
    return "\n".join(lines)


def compare_recording(args: argparse.Namespace, settings: Settings, settings_argv: list[str]) -> int:
    """``--record``: runs without and with an ``srl record`` process, interleaved (without, with,
    without, with, ...: the machine's load drifts alike over both), ``--seconds`` each; the loop's
    tick jitter and period side by side, PASS if the mean jitter p99 with the recorder is within
    :data:`RECORD_JITTER_MARGIN_MS` of the mean without."""
    import tempfile
    from pathlib import Path

    rounds = 2 if args.rounds is None else args.rounds
    if rounds < 1:
        raise UsageError(f"--rounds must be >= 1, got {rounds}")
    runs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="srl-bench-record-") as directory:
        for index in range(rounds):
            for recording in (False, True):
                path = Path(directory) / f"round{index}.mcap" if recording else None
                load_before = os.getloadavg()[0]
                options = UpOptions(
                    settings_argv, mode="realtime", plant="sim", duration=args.seconds, quiet=True, record=path
                )
                summary = run_up(settings, options)
                loop = summary["loop"]
                runs.append(
                    {
                        "round": index,
                        "record": recording,
                        "steps": summary.get("steps"),
                        "jitter_ms": loop["jitter_ms"],
                        "period_ms": loop["period_ms"],
                        "missed_deadlines": loop["missed_deadlines"],
                        "solve_ms": summary.get("solve_ms"),
                        "load": [load_before, os.getloadavg()[0]],
                        "recorder": summary.get("recorder"),
                        "recording_bytes": path.stat().st_size if path is not None and path.exists() else None,
                    }
                )

    def mean_p99(recording: bool) -> float:
        values = [r["jitter_ms"]["p99"] for r in runs if r["record"] is recording]
        return sum(values) / len(values)

    without, with_recorder = mean_p99(False), mean_p99(True)
    result: dict[str, Any] = {
        "seconds": args.seconds,
        "rounds": rounds,
        "agent": settings.actor.agent,
        "horizon": settings.actor.horizon,
        "runs": runs,
        "jitter_p99_ms": {"without": without, "with": with_recorder, "difference": with_recorder - without},
        "machine": {"cpus": os.cpu_count()},
        "targets": {
            f"jitter p99 with recorder <= without + {RECORD_JITTER_MARGIN_MS} ms": (
                "PASS" if with_recorder - without <= RECORD_JITTER_MARGIN_MS else "FAIL"
            ),
            "missed_deadlines == 0": "PASS" if all(r["missed_deadlines"] == 0 for r in runs) else "FAIL",
        },
    }
    lines = [
        f"srl bench loop --record: {rounds} x (without, with srl record), {args.seconds:.0f} s each, "
        f"agent {result['agent']}, N = {result['horizon']}",
        f"  {'round':<6} {'recorder':<9} {'steps':>6} {'jitter median':>14} {'p99':>8} {'max':>8} "
        f"{'period p99':>11} {'missed':>7} {'load 1 min':>12}  recording",
    ]
    for r in runs:
        j, p = r["jitter_ms"], r["period_ms"]
        size = "" if r["recording_bytes"] is None else f"{r['recording_bytes'] / 1024:.0f} KiB"
        lines.append(
            f"  {r['round']:<6} {'with' if r['record'] else 'without':<9} {r['steps']:>6} {j['median']:>14.3f} "
            f"{j['p99']:>8.3f} {j['max']:>8.3f} {p['p99']:>11.3f} {r['missed_deadlines']:>7} "
            f"{r['load'][0]:>5.2f}->{r['load'][1]:<5.2f}  {size}"
        )
    lines.append(
        f"  jitter p99 [ms], mean over rounds: without {without:.3f}, with {with_recorder:.3f} "
        f"(difference {with_recorder - without:+.3f})"
    )
    lines.append("  targets: " + ", ".join(f"{k}: {v}" for k, v in result["targets"].items()))
    print("\n".join(lines))
    if args.json:
        print(json.dumps({**result, "run": run_info()}))
    return 0
