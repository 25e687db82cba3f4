"""The benchmark pages and the README's headline table, read off the JSON ``srl bench`` printed.

``srl bench KIND ... --json`` prints one JSON object as its last stdout line; kept as
docs/benchmarks/data/KIND.json it becomes docs/benchmarks/KIND.md. Every page states what the
JSON says about its run (tools/bench/meta.py): the command, date, commit, CPU, cores and the load,
because a figure measured on a shared, loaded machine means little without them.

A page shows what was measured, the command, a summary and links to the full data: where a run has
many rows (``parking``'s runs, ``actor``'s agent x N x weights x solver) the page summarises them and
the rows go beside the JSON as a CSV, docs/benchmarks/data/KIND.csv. Each page stays under
``MAX_WORDS`` words (tests/test_docs.py).
"""

from __future__ import annotations

import csv
import importlib
import io
import json
import math
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from common.math.agents import REFERENCE_AGENT
from tools.docs.reference import GENERATED, cell, code, docstring, first_paragraph

# The most words (``len(text.split())``) a benchmark page may have: a summary, not the data.
MAX_WORDS = 1500
HEADLINE_BEGIN = "<!-- headline:begin -->"
HEADLINE_END = "<!-- headline:end -->"
# The order of the pages in the index, and their titles.
KINDS = {
    "actor": "Actor solve time",
    "loop": "Real-time loop",
    "bridge": "Robot bridge",
    "parking": "Parking",
    "parking-localized": "Parking from every start, localized",
    "fleet": "Fleet on one machine",
    "capacity": "Fleet capacity",
    "critic": "Critic fits across robots",
    "messages": "A message's CPU",
}


def ms(value: Any, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:.{digits}f}"


def load_data(directory: Path) -> dict[str, dict[str, Any]]:
    """``kind -> JSON`` of every docs/benchmarks/data/*.json, by name."""
    return {path.stem: json.loads(path.read_text()) for path in sorted(directory.glob("*.json"))}


def run_lines(data: dict[str, Any]) -> list[str]:
    """What the JSON says about its run: command, date, commit, machine, load."""
    run = data.get("run") or {}
    if not run:
        return ["*This JSON carries no record of its run (date, commit, machine): rerun the command.*", ""]
    commit = run.get("commit") or "unknown"
    modified = " (with uncommitted changes)" if run.get("worktree_modified") else ""
    load = run.get("load_average")
    load_text = " / ".join(f"{x:.2f}" for x in load) if load else "unknown"
    lines = [
        "| | |",
        "|---|---|",
        f"| Command | {code(run.get('command') or 'not recorded')} |",
        f"| Date (UTC) | {cell(run.get('date', 'unknown'))} |",
        f"| Commit | `{commit[:12]}`{modified} |",
        f"| CPU | {cell(run.get('cpu_model', 'unknown'))}, {run.get('cpu_count', '?')} cores "
        f"({run.get('cpus_usable', '?')} usable) |",
        f"| Load average (1 / 5 / 15 min) at the end | {load_text} |",
    ]
    if run.get("wall_seconds") is not None:
        lines.append(f"| Wall time | {run['wall_seconds']:.0f} s |")
    lines.append("")
    if run.get("note"):
        lines += [f"**Note.** {run['note']}", ""]
    return lines


def targets_lines(targets: dict[str, Any]) -> list[str]:
    """The bench's own targets: ``name -> "PASS"/"FAIL"`` or ``name -> {description, pass, worst, worst_row}``."""
    if not targets:
        return []
    lines = ["## Targets", "", "| Target | Verdict | Worst |", "|---|---|---|"]
    for name, target in targets.items():
        if isinstance(target, dict):
            verdict = {None: "N/A", True: "PASS", False: "FAIL"}[target.get("pass")]
            worst = "" if target.get("worst") is None else f"{target['worst']:.4g} ({target.get('worst_row', '')})"
            lines.append(f"| {cell(target.get('description', name))} | {verdict} | {cell(worst)} |")
        else:
            lines.append(f"| {cell(name)} | {cell(target)} | |")
    return [*lines, ""]


def _stats_row(name: str, stats: dict[str, Any] | None, unit: str = "ms") -> str:
    stats = stats or {}
    return f"| {cell(name)} | {ms(stats.get('median'))} | {ms(stats.get('p99'))} | {ms(stats.get('max'))} | {unit} |"


def percent(share: float) -> str:
    """A share as a percentage: whole percents, a tenth where it is under 1 % but not 0."""
    return f"{share:.1%}" if 0 < share < 0.01 else f"{share:.0%}"


def _span(values: Iterable[str]) -> str:
    """``low-high`` of formatted values (already sorted by their number), or the one value."""
    texts = list(values)
    return texts[0] if texts[0] == texts[-1] else f"{texts[0]}-{texts[-1]}"


def _columns(rows: list[dict[str, Any]], solver: str | None) -> list[tuple[int, str]]:
    """The (N, solver) pairs the actor rows cover: every N of the default solver, then the others."""
    pairs = list(dict.fromkeys((r["horizon"], r["solver"]) for r in rows))
    return sorted(pairs, key=lambda p: (p[1] != solver, p[1], p[0]))


def _column_name(pair: tuple[int, str], solver: str | None) -> str:
    return f"N = {pair[0]}" if pair[1] == solver else f"N = {pair[0]}, {pair[1]}"


def _time_cell(row: dict[str, Any] | None) -> str:
    """``median / p99 (speedup)`` of one actor row."""
    if row is None:
        return "-"
    speedup = row["speedup"]
    return f"{ms(row['median_ms'])} / {ms(row['p99_ms'])} ({speedup:.{0 if speedup >= 10 else 1}f}x)"


def actor_body(data: dict[str, Any]) -> list[str]:
    """One row per agent and weights, one column per N (and solver): time, speedup, argmin quality."""
    rows = data.get("rows", [])
    machine = data.get("machine") or {}
    solver = machine.get("solver")
    columns = _columns(rows, solver)
    by_key: dict[tuple[str, str], dict[tuple[int, str], dict[str, Any]]] = {}
    for r in rows:
        by_key.setdefault((r["agent"], r["weights"]), {})[(r["horizon"], r["solver"])] = r
    head = " | ".join(_column_name(c, solver) for c in columns)
    rule = "|---|---|" + "---|" * len(columns)
    lines = [
        "Whole actor step [ms] per agent, critic weights and N, median / p99, and in parentheses the",
        "speedup over the slow baseline's median (SLSQP with finite differences, no warm start); "
        f"solver {solver or '?'} unless the column names another.",
        "",
        f"| agent | weights | {head} |",
        rule,
    ]
    for (agent, weights), cells in by_key.items():
        times = [_time_cell(cells.get(c)) for c in columns]
        lines.append(f"| {agent} | {cell(weights)} | {' | '.join(times)} |")
    lines += [
        "",
        "The argmin's quality: *not worse*, the share of the states where the objective the actor reached is",
        "as low as a cold SLSQP solve's at the same state or lower, and (trained weights, where judged)",
        "after the slash *best known*, the share of the loop's states where it is within 1e-6 of the best",
        "known minimum (`BestKnown`), +/- its standard error.",
        "",
        f"| agent | weights | {head} |",
        rule,
    ]
    for (agent, weights), cells in by_key.items():
        shares = []
        for c in columns:
            r = cells.get(c)
            share = None if r is None else (r.get("objective") or {}).get("share_le")
            best = (r or {}).get("best_known") or {}
            text = "-" if share is None else f"{share:.0%}"
            if best.get("share_le") is not None:
                error = best.get("standard_error")
                text += f" / {best['share_le']:.0%}" + ("" if error is None else f" +/- {error:.0%}")
            shares.append(text)
        lines.append(f"| {agent} | {cell(weights)} | {' | '.join(shares)} |")
    references = sorted(
        b["reference_share"] for r in rows if (b := r.get("best_known") or {}).get("reference_share") is not None
    )
    failures = sum(r.get("failures", 0) for r in rows)
    lines += [
        "",
        f"Solver failures: {failures} in {len(rows)} rows."
        + (
            ""
            if not references
            else f" The best known minimum agreed with a second run of the judge (other random draws) at "
            f"{_span(f'{x:.0%}' for x in references)} of the states: the judge's own reliability."
        ),
    ]
    phased = [r for r in rows if r.get("phases")]
    if phased:
        names = list(dict.fromkeys(n for r in phased for n in r["phases"]))
        horizons = sorted({r["horizon"] for r in phased})
        lines += [
            "",
            "Where a step's time goes: each phase of the argmin (replayed on the inputs it had in the tick), the",
            "solver, the rest of the compiled tick (tick_glue) and the Python around it (python): the share of the",
            "steps that ran it / its mean cost per run [ms], lowest-highest over the agents and weights.",
            "",
            "| phase | " + " | ".join(f"N = {h}" for h in horizons) + " |",
            "|---|" + "---|" * len(horizons),
        ]
        for name in names:
            spans = []
            for h in horizons:
                found = [r["phases"][name] for r in phased if r["horizon"] == h and name in r["phases"]]
                if not found:
                    spans.append("-")
                    continue
                share = _span(percent(x) for x in sorted(p["share"] for p in found))
                cost = _span(f"{x:.3f}" for x in sorted(p["mean_ms"] for p in found))
                spans.append(f"{share} / {cost}")
            lines.append(f"| {cell(name)} | {' | '.join(spans)} |")
    load = _load_pair(machine.get("load_average"), machine.get("load_average_end"))
    lines += [
        "",
        f"Solver {machine.get('solver', '?')}, predictor {machine.get('predictor', '?')}, JIT "
        f"{machine.get('jit', '?')}; casadi {machine.get('casadi', '?')}, scipy {machine.get('scipy', '?')}, "
        f"numpy {machine.get('numpy', '?')}; load {load}. Per row, the gap to the cold solve, the baseline's "
        "times and each phase are in the data below.",
        "",
    ]
    return lines


def _load_pair(before: Iterable[float] | None, after: Iterable[float] | None) -> str:
    def one(load: Iterable[float] | None) -> str:
        return "?" if not load else f"{next(iter(load)):.2f}"

    return f"{one(before)} -> {one(after)} (1-min average, start -> end)"


def loop_body(data: dict[str, Any]) -> list[str]:
    machine = data.get("machine") or {}
    lines = [
        f"{data.get('agent')}, N = {data.get('horizon')}, {data.get('seconds')} s in real time "
        f"({data.get('steps')} steps), critic load: {'M = 1000 every step' if data.get('critic_load') else 'no'}; "
        f"load {_load_pair(machine.get('load_before'), machine.get('load_after'))}.",
        "",
        "| | median | p99 | max | unit |",
        "|---|---|---|---|---|",
        _stats_row("tick period", data.get("period_ms")),
        _stats_row("tick jitter", data.get("jitter_ms")),
        _stats_row("actor solve", data.get("solve_ms")),
        _stats_row("state -> action latency", data.get("latency_ms")),
        _stats_row("weight staleness", data.get("staleness_steps"), "steps"),
        _stats_row("critic fit", data.get("critic_fit_ms")),
        "",
        f"Missed deadlines: {data.get('missed_deadlines')}; transitions the critic received: "
        f"{data.get('transitions_received')}.",
        "",
    ]
    return lines


def bridge_body(data: dict[str, Any]) -> list[str]:
    internal = data.get("bridge_internal") or {}
    lines = [
        f"Profile {data.get('profile')} ({data.get('ros_distro')}, {data.get('cmd_type')}), "
        f"{data.get('steps')} commands per phase.",
        "",
        "| | median | p99 | max | unit |",
        "|---|---|---|---|---|",
        _stats_row("zenoh hop via the router (baseline)", data.get("zenoh_hop_ms")),
        _stats_row("another process and back (baseline)", data.get("process_echo_ms")),
        _stats_row("bridge: action -> cmd_vel", data.get("action_to_cmd_ms")),
        _stats_row("bridge: odom -> state", data.get("odom_to_state_ms")),
        _stats_row("command -> odometry (bridge + robot)", data.get("command_to_odom_ms")),
        _stats_row("cmd_vel -> odometry (robot alone, baseline)", data.get("direct_cmd_to_odom_ms")),
        _stats_row("inside the bridge: action -> cmd_vel", internal.get("action_to_cmd_ms")),
        _stats_row("inside the bridge: odom -> state", internal.get("odom_to_state_ms")),
        "",
    ]
    if data.get("bridge_cpu_seconds") is not None:
        lines += [
            f"Bridge process: {data['bridge_cpu_seconds']:.2f} CPU s over {data['bridge_wall_seconds']:.0f} s, "
            f"peak RSS {data['bridge_peak_rss_mb']:.1f} MB.",
            "",
        ]
    return lines


def arrived_in_time(rows: list[dict[str, Any]]) -> str:
    """``K of N`` runs that arrived within their bound; ``--`` where the run did not judge arrival."""
    judged = [r["arrival_ok"] for r in rows if "arrival_ok" in r]
    return f"{sum(judged)} of {len(judged)}" if judged else "--"


def nearest_rank(values: Iterable[float], q: float) -> float:
    """The ``q`` quantile of ``values`` by nearest rank (a value of the list; ``inf`` sorts last)."""
    ordered = sorted(values)
    return ordered[max(0, math.ceil(q * len(ordered)) - 1)]


def _seconds(value: float) -> str:
    return "never" if math.isinf(value) else f"{value:.1f}"


def parking_body(data: dict[str, Any]) -> list[str]:
    """One row per method, plant, pose, agent and N: how many runs passed each criterion, and how far
    and how soon they parked; every run is in the JSON and the CSV."""
    targets = data.get("targets") or {}
    lines = [
        f"{data.get('seconds')} s per run; the last {data.get('window_seconds')} s judged. Passed "
        f"**{data.get('passed')} of {data.get('total')}**. Targets: "
        + ", ".join(f"{k} {v:g}" for k, v in sorted(targets.items()))
        + ".",
        "",
        "Per method, plant, pose the actor sees, agent and N, the runs that passed (*within 0.05 m*: true",
        "final distance within the target; *at rest*: span and sign changes of `v` over the judged window within",
        "theirs; *in time*: arrived by the bound; *passed*: all three), the true final distance (median /",
        "p90 by nearest rank, and lowest-highest), when the robot arrived (median / p90; *never*: not",
        "within the run), the most sign changes of `v`, saturated and deadband commands in one run, and the",
        "*worst start* (x [m], y [m], heading [rad]): that of the run that ended farthest from the target.",
        "",
        "| method | plant | pose | agent | N | passed | within 0.05 m | at rest | in time | true final d [m] "
        "| arrived [s] | v sign changes | saturated / deadband | worst start |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    groups: dict[tuple[str, str, str, str, int], list[dict[str, Any]]] = {}
    for r in data.get("rows", []):
        key = (r["method"], r["plant"], r.get("localization", "odometry only"), r["agent"], r["horizon"])
        groups.setdefault(key, []).append(r)
    for (method, plant, pose, agent, horizon), rows in groups.items():
        n = len(rows)
        finals = [r["true_final_distance"] for r in rows]
        arrivals = [math.inf if r.get("arrival_seconds") is None else r["arrival_seconds"] for r in rows]
        at_rest = sum(bool(r.get("span_ok")) and bool(r.get("sign_changes_ok")) for r in rows)
        within = sum(bool(r.get("final_ok")) for r in rows)
        worst = max(rows, key=lambda r: r["true_final_distance"])
        start = ", ".join(f"{c:.2f}" for c in worst["start"])
        deadband = max(r.get("deadband_commands", 0) for r in rows)
        lines.append(
            f"| {method} | {plant} | {pose} | {agent} | {horizon} | {sum(r['passed'] for r in rows)}/{n} | "
            f"{within}/{n} | {at_rest}/{n} | {arrived_in_time(rows).replace(' of ', '/')} | "
            f"{nearest_rank(finals, 0.5):.3f} / {nearest_rank(finals, 0.9):.3f}; {min(finals):.3f}-{max(finals):.3f} | "
            f"{_seconds(nearest_rank(arrivals, 0.5))} / {_seconds(nearest_rank(arrivals, 0.9))} | "
            f"{max(r['sign_changes'] for r in rows)} | {max(r['saturated_commands'] for r in rows)} / {deadband} | "
            f"({start}) |"
        )
    return [*lines, ""]


def phase_cell(row: dict[str, Any], phase: str) -> str:
    """A fleet row's CPU per robot tick [ms] in one phase of its run ("-": not measured, a row from
    before the phases were, or not every robot arrived)."""
    from tools.bench.fleet import phase_ms

    measured = phase_ms(row, phase)
    return "-" if math.isnan(measured) else f"{measured:.3f}"


def fleet_body(data: dict[str, Any]) -> list[str]:
    from tools.bench.fleet import layout_label

    lines = [
        f"{data.get('agent')}, N = {data.get('horizon')}, {data.get('seconds')} s in real time per row"
        + (", `srl record` attached to every row" if data.get("recorded") else "")
        + ". Jitter, latency, staleness: the worst robot; parked: within 0.25 m at the end; at target: by the "
        "robot's own final state within 0.05 m and at rest (its last command zero), as one robot alone is "
        "judged; worst: the farthest robot by its own state; CPU: all srl processes (100 % = one core), of it "
        "their Zenoh runtime threads' (the network, and the handlers Zenoh calls on its thread), and that CPU "
        "per robot per sampling interval, over the run, while the robots drive (until every robot has reported "
        "itself arrived) and at rest (from then on: no solve, no fit; what the fleet's messages and bookkeeping "
        "cost alone); hurried: ticks solved in a hurry (served late or over the host's CPU budget).",
        "",
        "| robots | layout | missed | jitter p99 [ms] | latency p99 [ms] | staleness p99 / max [steps] | parked "
        "| at target | worst [m] | CPU % | of it Zenoh % | CPU per robot tick [ms] | driving | at rest | RSS MB "
        "| hurried | recorded | load before -> after | targets |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in data.get("rows", []):
        load = f"{row['load_before'][0]:.2f} -> {row['load_after'][0]:.2f}"
        if "error" in row:
            lines.append(f"| {row['robots']} | {row['layout']} | failed: {cell(row['error'])} |{' |' * 14} {load} | |")
            continue
        f = row["fleet"]
        layout = layout_label(row)
        targets = ", ".join(f"{k}: {v}" for k, v in row.get("targets", {}).items()) or "-"
        worst = f.get("worst_own_final_distance_m")
        per_tick = row.get("cpu_ms_per_robot_tick")
        ticks = row.get("actor_ticks") or {}
        hurried = ticks.get("hurried_percent")
        recorder = row.get("recorder") or ""
        recorded = recorder.removeprefix("srl record: recorded ").split(" on ", 1)[0] if recorder else "-"
        zenoh = row.get("zenoh_cpu_percent")
        lines.append(
            f"| {row['robots']} | {layout} | {f['missed_deadlines']} | {f['jitter_p99_ms']:.2f} | "
            f"{f['latency_p99_ms']:.2f} | {f['staleness_p99_steps']:.0f} / {f['staleness_max_steps']:.0f} | "
            f"{f['parked']}/{row['robots']} | {f.get('at_target', '-')}/{row['robots']} | "
            f"{'-' if worst is None else f'{worst:.3f}'} | {row['cpu_percent']:.0f} | "
            f"{'-' if zenoh is None else f'{zenoh:.0f}'} | {'-' if per_tick is None else f'{per_tick:.3f}'} | "
            f"{phase_cell(row, 'driving')} | {phase_cell(row, 'at_rest')} | {row['rss_mb']:.0f} | "
            f"{'-' if hurried is None else f'{hurried:.1f} %'} | {cell(recorded)} | {load} | {cell(targets)} |"
        )
    by_process = [row for row in data.get("rows", []) if "zenoh_cpu_percent_by_service" in row]
    if by_process:
        lines += [
            "",
            "CPU of each process [% of a core], and in parentheses of its Zenoh runtime threads:",
            "",
            "| robots | layout | processes |",
            "|---|---|---|",
        ]
        for row in by_process:
            zenoh = row["zenoh_cpu_percent_by_service"]
            each = ", ".join(
                f"{name} {cpu:.1f} ({zenoh.get(name, math.nan):.1f})"
                for name, cpu in row["cpu_percent_by_service"].items()
            )
            layout = layout_label(row)
            lines.append(f"| {row['robots']} | {layout} | {each} |")
    phased = [row for row in data.get("rows", []) if row.get("cpu_phases")]
    if phased:
        lines += [
            "",
            "CPU of each process [% of a core] while the robots drive and once every robot has arrived (at rest: "
            "no solve, no fit; where measured, how often its threads woke a second), and how long each phase lasted:",
            "",
            "| robots | layout | driving | at rest |",
            "|---|---|---|---|",
        ]
        for row in phased:
            layout = layout_label(row)
            cells = []
            for phase in ("driving", "at_rest"):
                spent = row["cpu_phases"][phase]
                wakes = spent.get("wakes_per_second_by_service") or {}
                each = ", ".join(
                    f"{name} {cpu:.1f}" + (f" ({wakes[name]:.0f}/s)" if name in wakes else "")
                    for name, cpu in spent["cpu_percent_by_service"].items()
                )
                cells.append(f"{spent['seconds']:.1f} s: {each}")
            lines.append(f"| {row['robots']} | {layout} | {cells[0]} | {cells[1]} |")
    return [*lines, ""]


def capacity_body(data: dict[str, Any]) -> list[str]:
    model = data.get("model") or {}
    lines = [
        f"{data.get('agent')}, N = {data.get('horizon')}, {data.get('seconds')} s in real time per fleet size "
        f"({', '.join(str(r['robots']) for r in data.get('rows', []))} robots). CPU per component = fixed + per "
        "robot, a least-squares line over the sizes (1 core = 100 %).",
        "",
        "| component | fixed [% of a core] | per robot [% of a core] |",
        "|---|---|---|",
    ]
    for name, c in (model.get("cpu") or {}).items():
        lines.append(f"| {name} | {100 * c['fixed_cores']:.2f} | {100 * c['per_robot_cores']:.3f} |")
    lines += ["", "| message kind | per robot per s | bytes per robot per s |", "|---|---|---|"]
    for kind, r in (model.get("messages") or {}).items():
        lines.append(f"| {cell(kind)} | {r['per_robot_per_s']:.2f} | {r['bytes_per_robot_per_s']:.0f} |")
    lines += [
        "",
        f"What a fleet needs at <= {100 * model.get('utilisation', 0):.0f} % of each core, "
        f"{model.get('host_cores')}-core hosts:",
        "",
        "| robots | cores | actor host processes | hosts | routers | messages/s | MB/s |",
        "|---|---|---|---|---|---|---|",
    ]
    for fleet, need in (model.get("fleets") or {}).items():
        cores = ", ".join(f"{name} {value:.1f}" for name, value in need["cores"].items())
        lines.append(
            f"| {fleet} | {cores} | {need['actor_host_processes']} | {need['hosts']} | {need['routers']} | "
            f"{need['messages_per_s']:.0f} | {need['megabytes_per_s']:.1f} |"
        )
    return [*lines, ""]


def critic_body(data: dict[str, Any]) -> list[str]:
    lines = [
        f"CPU per robot's fit [us], the median of {data.get('rounds')} rounds run in turn (per robot, rebuilt, "
        "batched, per round): **per robot** one robot per call, designs built from the samples; **rebuilt** "
        "every robot due in one stacked solve, designs built from the samples; **batched** the stacked solve on "
        "the designs the replays keep. The weights of the three ways must agree (largest difference shown).",
        "",
        "| robots | per robot | rebuilt | batched | speedup | add a sample | largest weight difference |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in data.get("rows", []):
        lines.append(
            f"| {r['robots']} | {r['per_robot_fit_us']:.1f} | {r['rebuilt_fit_us']:.1f} | {r['batched_fit_us']:.1f} "
            f"| {r['speedup']:.1f}x | {r['add_us']:.1f} | {r['max_weight_difference']:.1e} |"
        )
    return [*lines, ""]


def messages_body(data: dict[str, Any]) -> list[str]:
    lines = [
        "CPU per message [us] in one process: **encode** `Message.encode`; **parse** the JSON alone "
        "(pydantic-core's parser, the one `decode` uses); **decode** parse and validate (bounds, NaN, sizes, "
        "versions); **validate** their difference.",
        "",
        "| kind | bytes | encode | parse | decode | validate |",
        "|---|---|---|---|---|---|",
    ]
    for c in data.get("codec", []):
        lines.append(
            f"| {c['kind']} | {c['bytes']} | {c['encode_us']:.1f} | {c['parse_us']:.1f} | {c['decode_us']:.1f} "
            f"| {c['validate_us']:.1f} |"
        )
    lines += [
        "",
        f"Through a Zenoh router on loopback: {data.get('robots')} robots' `{data.get('kind')}` messages at "
        f"{ms(data.get('rate_hz'), 0)} Hz, {ms(data.get('seconds'), 0)} s a run, {data.get('rounds')} rounds of "
        "the ways in turn; CPU of each process (user + system, every thread) per robot message, the median "
        "of the rounds. **each**: srl's wire, one message per robot on its own key, the subscriber's handler on "
        "Zenoh's network thread (srl's default); **threaded**: the same, the handler on a thread of its own "
        "(what `srl record`'s wildcards do); **batched**: one message per tick holding every robot's (not srl's "
        "wire: what a host could send), each validated on arrival.",
        "",
        "| way | publisher | router | subscriber | total | validated / sent |",
        "|---|---|---|---|---|---|",
    ]
    for r in data.get("rows", []):
        lines.append(
            f"| {r['way']} | {r['publisher_us']:.1f} | {r['router_us']:.1f} | {r['subscriber_us']:.1f} "
            f"| {r['total_us']:.1f} | {r['validated']} / {r['sent']} |"
        )
    before, after = data.get("load_before") or [math.nan], data.get("load_after") or [math.nan]
    return [*lines, "", f"Load (1 min) {ms(before[0], 2)} before, {ms(after[0], 2)} after.", ""]


def generic_body(data: dict[str, Any]) -> list[str]:
    scalars = {k: v for k, v in sorted(data.items()) if isinstance(v, str | int | float | bool) and k != "run"}
    return ["| | |", "|---|---|", *(f"| {cell(k)} | {cell(v)} |" for k, v in scalars.items()), ""]


BODIES: dict[str, Callable[[dict[str, Any]], list[str]]] = {
    "actor": actor_body,
    "loop": loop_body,
    "bridge": bridge_body,
    "parking": parking_body,
    "parking-localized": parking_body,
    "fleet": fleet_body,
    "capacity": capacity_body,
    "critic": critic_body,
    "messages": messages_body,
}


def bench_of(kind: str) -> str:
    """The benchmark a page's data comes from: ``parking-localized`` is a run of ``srl bench parking``."""
    return kind.partition("-")[0]


def what_it_measures(kind: str) -> str:
    try:
        module = importlib.import_module(f"tools.bench.{bench_of(kind)}")
    except ImportError:
        return ""
    return first_paragraph(module.__doc__)


# The benchmarks whose rows the page summarises: their rows are also a CSV beside the JSON.
CSV_BENCHES = ("actor", "parking")


def flatten(row: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """One JSON row as ``column -> value``: nested keys joined by ``.``, list items numbered (``start.0``)."""
    out: dict[str, Any] = {}
    for key, value in row.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten(value, f"{name}."))
        elif isinstance(value, list):
            out.update(flatten({str(i): v for i, v in enumerate(value)}, f"{name}."))
        else:
            out[name] = value
    return out


def _csv_value(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def csv_text(rows: list[dict[str, Any]]) -> str:
    """The rows as CSV: one line each, the columns of every row in the order first met, floats to 6 digits."""
    flat = [flatten(r) for r in rows]
    names = list(dict.fromkeys(name for r in flat for name in r))
    # a field null in some rows and an object in others: its object's columns alone
    columns = [name for name in names if not any(other.startswith(f"{name}.") for other in names)]
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(columns)
    writer.writerows([_csv_value(r.get(name)) for name in columns] for r in flat)
    return out.getvalue()


def has_csv(kind: str, data: dict[str, Any]) -> bool:
    return bench_of(kind) in CSV_BENCHES and bool(data.get("rows"))


def run_command(kind: str, data: dict[str, Any]) -> str:
    """The command that made the JSON, as run from a checkout (``./srl``)."""
    command = (data.get("run") or {}).get("command") or f"srl bench {bench_of(kind)} --json"
    return f"./{command}" if command.startswith("srl ") else command


def benchmark_page(kind: str, data: dict[str, Any]) -> str:
    title = KINDS.get(kind, kind)
    lines = [GENERATED, "", f"# {title}: `srl bench {bench_of(kind)}`", ""]
    about = what_it_measures(kind)
    if about:
        lines += [docstring(about), ""]
    lines += run_lines(data)
    lines += [
        "## How to run",
        "",
        "The command of this run, its JSON kept, and the page regenerated:",
        "",
        "<!-- not run: a benchmark takes minutes and loads the machine -->",
        "```bash",
        f"{run_command(kind, data)} | tail -n 1 > docs/benchmarks/data/{kind}.json",
        "./srl docs",
        "```",
        "",
    ]
    lines += ["## Results", ""]
    lines += BODIES.get(kind, generic_body)(data)
    lines += targets_lines(data.get("targets") or {})
    lines += ["## Full data", "", f"* [{kind}.json](data/{kind}.json): everything the run printed."]
    if has_csv(kind, data):
        lines.append(
            f"* [{kind}.csv](data/{kind}.csv): one line per row of the JSON, its nested fields as columns "
            "(`a.b`, a list's items `a.0`, `a.1`, ...), numbers to 6 significant digits."
        )
    lines.append("")
    return "\n".join(lines)


def index_page(data: dict[str, dict[str, Any]]) -> str:
    lines = [
        GENERATED,
        "",
        "# Benchmarks",
        "",
        "Each page below is generated by `srl docs` from the JSON one `srl bench KIND ... --json` printed as",
        "its last line, kept in `docs/benchmarks/data/KIND.json`. Each says the command, date, commit, CPU and",
        "load of its run: the machine these ran on is shared with other work, so the times are an upper bound",
        "of what the code does on a quiet machine, and targets marked FAIL there may pass on one.",
        "",
        "To refresh a page, run its benchmark and regenerate:",
        "",
        "<!-- not run: a benchmark takes minutes and loads the machine -->",
        "```bash",
        "./srl bench actor --horizons 12 --json | tail -n 1 > docs/benchmarks/data/actor.json",
        "./srl docs",
        "```",
        "",
        "| Benchmark | Command | Date (UTC) | Commit | CPU | Load (1 min) at the end |",
        "|---|---|---|---|---|---|",
    ]
    for kind in sorted(data, key=lambda k: (list(KINDS).index(k) if k in KINDS else len(KINDS), k)):
        run = data[kind].get("run") or {}
        load = run.get("load_average")
        lines.append(
            f"| [{KINDS.get(kind, kind)}]({kind}.md) | {code(run.get('command') or 'not recorded')} | "
            f"{cell(run.get('date', '?'))} | `{(run.get('commit') or '?')[:12]}` | "
            f"{cell(run.get('cpu_model', '?'))}, {run.get('cpu_count', '?')} cores | "
            f"{'?' if not load else f'{load[0]:.2f}'} |"
        )
    lines.append("")
    return "\n".join(lines)


# -- the README's headline table --------------------------------------------------------------
def _fleet_cpu_text(row: dict[str, Any]) -> str:
    """A fleet row's CPU for the headline: over the run, and at rest when every robot arrived."""
    if row.get("cpu_ms_per_robot_tick") is None:
        return ""
    rest = ((row.get("cpu_phases") or {}).get("at_rest") or {}).get("cpu_ms_per_robot_tick")
    at_rest = "" if rest is None or not math.isfinite(rest) else f" (at rest {rest:.2f})"
    return f", {row['cpu_ms_per_robot_tick']:.2f} ms CPU per robot tick{at_rest}"


def headline_table(data: dict[str, dict[str, Any]], paper_summary: dict[str, Any] | None) -> str:
    """Today's headline figures: the actor's step at N = 12, the paper experiment's ratios, a fleet."""
    lines = ["| Figure | Value | Source |", "|---|---|---|"]
    machines: list[str] = []
    actor = data.get("actor")
    if actor:
        solver = (actor.get("machine") or {}).get("solver")
        rows = [
            r
            for r in actor.get("rows", [])
            if r["horizon"] == 12
            and (r["agent"] == REFERENCE_AGENT or r["weights"] == "initial")
            and (solver is None or r["solver"] == solver)
        ]
        if rows:
            times = ", ".join(f"{r['agent']} {ms(r['median_ms'], 2)} / {ms(r['p99_ms'], 1)}" for r in rows)
            lines.append(
                f"| Actor step at N = 12, median / p99 [ms] (initial critic weights) | {times} | "
                "[actor benchmark](docs/benchmarks/actor.md) |"
            )
            machines.append(_machine_text("actor", actor))
    if paper_summary:
        by_horizon: dict[int, list[str]] = {}
        for group in paper_summary.get("groups", []):
            if "median_ratio_percent" in group:
                by_horizon.setdefault(group["horizon"], []).append(
                    f"{group['agent']} {group['median_ratio_percent']:.1f} % ({group['beat_mpc']}/{group['ratios']})"
                )
        for horizon, ratios in sorted(by_horizon.items(), reverse=True):
            lines.append(
                f"| Paper experiment at N = {horizon}: median J / J_mpc (starts better than MPC) | "
                f"{', '.join(ratios)} | [experiment](docs/experiment.md) |"
            )
    fleet = data.get("fleet")
    if fleet:
        values = [
            f"{row['robots']} robot{'s' if row['robots'] != 1 else ''}: {row['fleet']['missed_deadlines']} missed, "
            f"jitter p99 {row['fleet']['jitter_p99_ms']:.2f} ms, "
            f"{row['fleet'].get('at_target', row['fleet'].get('parked'))} "
            + ("at target" if "at_target" in row["fleet"] else "parked")
            + _fleet_cpu_text(row)
            for row in fleet.get("rows", [])
            if "error" not in row and row.get("layout", "host") == "host"  # the baseline rows are on the page
        ]
        if values:
            lines.append(
                f"| Fleet on one machine, {fleet.get('seconds', '?')} s"
                + (", `srl record` attached" if fleet.get("recorded") else "")
                + f" | {'; '.join(values)} | "
                "[fleet benchmark](docs/benchmarks/fleet.md) |"
            )
            machines.append(_machine_text("fleet", fleet))
    lines.append("")
    if machines:
        lines.append("Measured on " + "; ".join(machines) + ": [all benchmarks](docs/benchmarks/index.md).")
    if paper_summary:
        lines.append(
            f"The paper experiment: `srl experiment paper`, {paper_summary.get('finished_at', '?')[:10]} "
            "(docs/paper/paper-grid/summary.json)."
        )
    return "\n".join(lines)


def _machine_text(kind: str, data: dict[str, Any]) -> str:
    """The machine and date of a headline row (the README names no commit: its page does)."""
    run = data.get("run") or {}
    load = run.get("load_average")
    return (
        f"{kind}: {run.get('date', '?')[:10]}, "
        f"{run.get('cpu_model', '?')} ({run.get('cpu_count', '?')} cores, shared), "
        f"load {'?' if not load else f'{load[0]:.1f}'}"
    )


def replace_headline(readme: str, table: str) -> str:
    """``readme`` with ``table`` between the headline markers (unchanged if the markers are absent)."""
    begin, end = readme.find(HEADLINE_BEGIN), readme.find(HEADLINE_END)
    if begin < 0 or end < begin:
        return readme
    return readme[: begin + len(HEADLINE_BEGIN)] + "\n" + table.rstrip() + "\n" + readme[end:]


def pages(data_dir: Path) -> dict[str, str]:
    """``file name under docs/benchmarks/ -> text``: a page for every JSON, the index, and the CSV of
    the rows a page summarises (``data/KIND.csv``)."""
    data = load_data(data_dir)
    out = {f"{kind}.md": benchmark_page(kind, values) for kind, values in data.items()}
    out.update({f"data/{kind}.csv": csv_text(values["rows"]) for kind, values in data.items() if has_csv(kind, values)})
    out["index.md"] = index_page(data)
    return out


def read_json(path: Path) -> dict[str, Any] | None:
    return json.loads(path.read_text()) if path.is_file() else None
