"""The experiment's analysis and files: the marks ``J_agent / J_mpc`` per run, group and claim,
and ``runs.csv``, ``trajectories.npz``, ``config.toml``, ``summary.md`` (pure: no processes)."""

from __future__ import annotations

import csv
import json
import math
import subprocess
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from common.math.agents import REFERENCE_AGENT, learns
from common.math.parking import MAX_SIGN_CHANGES, SPAN_M, WINDOW_S
from common.math.systems import System, system_row
from tools.experiment.marks import PARK_TOLERANCE_M, TIE_PERCENT


# -- analysis ---------------------------------------------------------------------------
def ratio_table(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """``J_agent / J_mpc * 100 %`` for every non-MPC run whose start has an MPC run at its N."""
    mpc = {(r["horizon"], r["start_index"]): r["accumulated_cost"] for r in rows if r["agent"] == REFERENCE_AGENT}
    table = []
    for r in rows:
        if r["agent"] == REFERENCE_AGENT or (r["horizon"], r["start_index"]) not in mpc:
            continue
        reference = mpc[(r["horizon"], r["start_index"])]
        ratio = 100.0 * r["accumulated_cost"] / reference if reference > 0 else float("nan")
        table.append(
            {
                "agent": r["agent"],
                "horizon": r["horizon"],
                "start_index": r["start_index"],
                "start_x": r["start_x"],
                "start_y": r["start_y"],
                "run_id": r["run_id"],
                "j_agent": r["accumulated_cost"],
                "j_mpc": reference,
                "ratio_percent": ratio,
            }
        )
    return table


def group_summary(
    rows: Sequence[dict[str, Any]],
    agents: Sequence[str],
    horizons: Sequence[int],
    ratios: Sequence[dict[str, Any]],
    tolerance: float = PARK_TOLERANCE_M,
) -> list[dict[str, Any]]:
    """Each (agent, N): its runs' J, marks, and how many ended within ``tolerance`` of the goal
    ("parked": the robot's 0.25 m; another system's ``stabilized`` distance)."""
    groups = []
    for horizon in horizons:
        for agent in agents:
            runs = [r for r in rows if r["agent"] == agent and r["horizon"] == horizon]
            if not runs:
                continue
            costs = np.array([r["accumulated_cost"] for r in runs])
            marks = np.array([t["ratio_percent"] for t in ratios if t["agent"] == agent and t["horizon"] == horizon])
            marks = marks[np.isfinite(marks)]
            parked = sum(r["final_distance"] <= tolerance for r in runs)
            at_rest = sum(int(r.get("at_rest", 0)) for r in runs)
            entry: dict[str, Any] = {
                "agent": agent,
                "horizon": horizon,
                "runs": len(runs),
                "median_cost": float(np.median(costs)),
                "mean_cost": float(np.mean(costs)),
                "parked": int(parked),
                "at_rest": int(at_rest),
                "median_final_distance": float(np.median([r["final_distance"] for r in runs])),
                "solver_failures": int(sum(r["solver_failures"] for r in runs)),
                "solve_ms_median": float(np.median([r["solve_ms_median"] for r in runs])),
                "solve_ms_max": float(max(r["solve_ms_max"] for r in runs)),
                "critic_timeouts": int(sum(r.get("critic_timeouts", 0) for r in runs)),
            }
            if learns(agent) and marks.size:
                entry.update(
                    {
                        "ratios": int(marks.size),
                        "median_ratio_percent": float(np.median(marks)),
                        "beat_mpc": int(np.sum(marks < 100.0 - TIE_PERCENT)),
                        "beat_mpc_share": float(np.mean(marks < 100.0 - TIE_PERCENT)),
                        "ties": int(np.sum(np.abs(marks - 100.0) <= TIE_PERCENT)),
                        "min_ratio_percent": float(np.min(marks)),
                        "max_ratio_percent": float(np.max(marks)),
                    }
                )
            groups.append(entry)
    return groups


def head_to_head(rows: Sequence[dict[str, Any]], first: str, second: str, horizon: int) -> dict[str, Any] | None:
    """Starts where ``first`` has a lower J than ``second`` at ``horizon``."""
    a = {r["start_index"]: r["accumulated_cost"] for r in rows if r["agent"] == first and r["horizon"] == horizon}
    b = {r["start_index"]: r["accumulated_cost"] for r in rows if r["agent"] == second and r["horizon"] == horizon}
    common_starts = sorted(i for i in set(a) & set(b) if b[i] > 0)  # J = 0: a start at the goal, no ratio
    if not common_starts:
        return None
    wins = sum(100.0 * a[i] / b[i] < 100.0 - TIE_PERCENT for i in common_starts)
    return {
        "first": first,
        "second": second,
        "horizon": horizon,
        "starts": len(common_starts),
        "wins": wins,
        "median_ratio_percent": float(np.median([100.0 * a[i] / b[i] for i in common_starts])),
    }


def check_claims(
    groups: Sequence[dict[str, Any]], rows: Sequence[dict[str, Any]], horizons: Sequence[int]
) -> list[dict[str, Any]]:
    """The paper's three claims (section IV), each judged on this run's numbers."""
    by = {(g["agent"], g["horizon"]): g for g in groups if "beat_mpc_share" in g}
    claims = []
    rl = [a for a in ("rlq", "rlqv") if any(k[0] == a for k in by)]
    if rl:
        parts, holds = [], True
        for agent in rl:
            for horizon in horizons:
                g = by.get((agent, horizon))
                if g is None:
                    continue
                ok = g["beat_mpc_share"] > 0.5
                holds &= ok
                parts.append(
                    f"{agent} N={horizon}: better than MPC from {g['beat_mpc']}/{g['ratios']} starts "
                    f"(median {g['median_ratio_percent']:.1f} %)"
                )
        claims.append(
            {"claim": "both RL agents mostly below 100 % (better than MPC)", "holds": holds, "detail": "; ".join(parts)}
        )
    if all(any(k[0] == a for k in by) for a in ("rlq", "rlqv")):
        parts, holds = [], True
        for horizon in horizons:
            q, qv = by.get(("rlq", horizon)), by.get(("rlqv", horizon))
            duel = head_to_head(rows, "rlqv", "rlq", horizon)
            if q is None or qv is None or duel is None:
                continue
            ok = qv["median_ratio_percent"] < q["median_ratio_percent"] and duel["wins"] > duel["starts"] / 2
            holds &= ok
            parts.append(
                f"N={horizon}: median {qv['median_ratio_percent']:.1f} % (QV) vs "
                f"{q['median_ratio_percent']:.1f} % (Q), QV better than Q from {duel['wins']}/"
                f"{duel['starts']} starts"
            )
        claims.append({"claim": "QV better than Q", "holds": holds, "detail": "; ".join(parts)})
    if len(horizons) >= 2 and rl:
        long_h, short_h = max(horizons), min(horizons)
        parts, holds = [], True
        for agent in rl:
            g_long, g_short = by.get((agent, long_h)), by.get((agent, short_h))
            if g_long is None or g_short is None:
                continue
            ok = g_long["beat_mpc_share"] > g_short["beat_mpc_share"]
            holds &= ok
            parts.append(
                f"{agent}: better than MPC from {g_long['beat_mpc']}/{g_long['ratios']} starts at "
                f"N={long_h} vs {g_short['beat_mpc']}/{g_short['ratios']} at N={short_h}"
            )
        claims.append(
            {
                "claim": f"RL better than MPC more consistently at the longer horizon (N={long_h})",
                "holds": holds,
                "detail": "; ".join(parts),
            }
        )
    return claims


# -- outputs ----------------------------------------------------------------------------
CSV_COLUMNS = (
    "run_id",
    "agent",
    "horizon",
    "start_index",
    "start_x",
    "start_y",
    "start_alpha",
    "accumulated_cost",
    "ratio_to_mpc_percent",
    "final_x",
    "final_y",
    "final_alpha",
    "final_distance",
    "parked",
    "at_rest",
    "last_span_m",
    "sign_changes",
    "steps",
    "solver_failures",
    "solve_ms_median",
    "solve_ms_p99",
    "solve_ms_max",
    "wall_seconds",
    "worker",
    "critic_timeouts",
    "max_staleness_steps",
    "true_accumulated_cost",  # on the true states, where the plant knows them ('' where not)
    "true_final_distance",
)


def sorted_rows(rows: Iterable[dict[str, Any]], agents: Sequence[str], horizons: Sequence[int]) -> list[dict]:
    order = {a: i for i, a in enumerate(agents)}
    horizon_order = {h: i for i, h in enumerate(horizons)}
    return sorted(
        rows, key=lambda r: (horizon_order.get(r["horizon"], 99), order.get(r["agent"], 99), r["start_index"])
    )


def write_runs_csv(
    path: Path, rows: Sequence[dict[str, Any]], ratios: Sequence[dict[str, Any]], tolerance: float = PARK_TOLERANCE_M
) -> None:
    """One row per run (``parked``: within ``tolerance``, as :func:`group_summary`); another system
    than the robot has its first three state entries in the robot's columns (``start_x``,
    ``start_y``, ``start_alpha``, ``final_*``; nan where it has fewer), its whole states in
    trajectories.npz."""
    by_run = {t["run_id"]: t["ratio_percent"] for t in ratios}
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        for r in rows:
            ratio = by_run.get(r["run_id"], 100.0 if r["agent"] == REFERENCE_AGENT else None)
            writer.writerow(
                {
                    **{k: r.get(k) for k in CSV_COLUMNS},
                    **{k: "" if r.get(k) is None else repr(float(r[k])) for k in CSV_COLUMNS[-2:]},
                    "ratio_to_mpc_percent": "" if ratio is None else repr(float(ratio)),
                    "parked": int(r["final_distance"] <= tolerance),
                    **{
                        k: repr(float(r[k]))
                        for k in (
                            "start_x",
                            "start_y",
                            "start_alpha",
                            "accumulated_cost",
                            "final_x",
                            "final_y",
                            "final_alpha",
                            "final_distance",
                            "last_span_m",
                        )
                    },
                }
            )


def read_runs_csv(path: Path | str) -> list[dict[str, Any]]:
    """``runs.csv`` back as typed rows (numbers as numbers)."""
    path = Path(path)
    ints = {
        "horizon",
        "start_index",
        "steps",
        "solver_failures",
        "worker",
        "parked",
        "at_rest",
        "sign_changes",
        "critic_timeouts",
        "max_staleness_steps",
    }
    rows = []
    with path.open(newline="") as handle:
        for raw in csv.DictReader(handle):
            row: dict[str, Any] = {}
            for key, value in raw.items():
                if key in ("run_id", "agent"):
                    row[key] = value
                elif value == "":
                    row[key] = None
                elif key in ints:
                    row[key] = int(value)
                else:
                    row[key] = float(value)
            rows.append(row)
    return rows


def write_trajectories(path: Path, rows: Sequence[dict[str, Any]], arrays: dict[str, dict[str, np.ndarray]]) -> None:
    """One compressed ``.npz``: ``run_id[R]``, ``states[R, S+1, 3]``, ``actions[R, S, 2]``,
    ``costs[R, S]`` in the row order of ``runs.csv`` (every run has the same ``S`` steps)."""
    ids = [r["run_id"] for r in rows if r["run_id"] in arrays]
    if not ids:
        np.savez_compressed(path, run_id=np.array([], dtype=str))
        return
    np.savez_compressed(
        path,
        run_id=np.array(ids),
        states=np.stack([arrays[i]["states"] for i in ids]),
        actions=np.stack([arrays[i]["actions"] for i in ids]),
        costs=np.stack([arrays[i]["costs"] for i in ids]),
    )


def toml_dumps(data: dict[str, Any]) -> str:
    """A small TOML writer for the settings' shape: tables of scalars and scalar lists."""

    def value(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, int):
            return str(v)
        if isinstance(v, float):
            if not math.isfinite(v):
                raise ValueError(f"TOML settings must be finite, got {v}")
            return repr(v)
        if isinstance(v, str):
            return json.dumps(v)  # JSON string escapes are valid TOML basic-string escapes
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(value(x) for x in v) + "]"
        raise TypeError(f"cannot write {type(v).__name__} to TOML")

    lines: list[str] = []

    def table(name: str, body: dict[str, Any]) -> None:
        scalars = {k: v for k, v in body.items() if not isinstance(v, dict) and v is not None}
        if name:
            lines.append(f"[{name}]")
        lines.extend(f"{k} = {value(v)}" for k, v in scalars.items())
        lines.append("")
        for k, v in body.items():
            if isinstance(v, dict):
                table(f"{name}.{k}" if name else k, v)

    table("", data)
    return "\n".join(lines).lstrip("\n")


def _git(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["git", *args], capture_output=True, text=True, timeout=5, cwd=Path(__file__).resolve().parent, check=False
    )


def git_commit() -> str | None:
    try:
        done = _git("rev-parse", "--short", "HEAD")
        dirty = _git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return None
    if done.returncode != 0:
        return None
    return done.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")


def _fmt_init(value: str | list[float]) -> str:
    return value if isinstance(value, str) else "[" + ", ".join(f"{w:.4g}" for w in value) + "]"


def starts_box(system: System) -> str:
    """``theta in [-0.4, 0.4], omega in [-0.5, 0.5]``: the start box's first two entries, by name."""
    box = system.box_of_starts
    return " and ".join(
        f"{label} in [-{width:g}, {width:g}]"
        for (label, _), width in zip(system.state_labels()[:2], box[:2], strict=False)
        if width > 0  # the entries the lattice spans (tools/experiment/grid.py system_starts)
    )


def _fmt_ratio(v: float | None) -> str:
    return "—" if v is None or not math.isfinite(v) else f"{v:.1f} %"


def summary_markdown(summary: dict[str, Any]) -> str:
    e, s = summary["experiment"], summary["settings"]
    name = e.get("system", "unicycle")
    system = system_row(name)
    lines = [
        f"# srl experiment paper — {e['starts']} starts, transport {e['transport']}, plant {s['plant']['model']}"
        + (f", pose {e['localization']}" if e.get("localization", "none") != "none" else "")
        + ("" if system.wheeled else f", system {name}"),
        "",
    ]
    status = (
        "INTERRUPTED: partial results"
        if summary["interrupted"]
        else (f"FAILED: {summary['error'].splitlines()[0]}" if summary.get("error") else "complete")
    )
    lines += [
        f"* command: `{e['command']}`" if e.get("command") else "* command: (library call)",
        f"* status: {status}, {summary['runs_completed']}/{summary['runs_planned']} runs",
        f"* starts: {e['grid']} x {e['grid']} "
        + ("lattice" if e["starts"] == "paper" else f"stratified-jittered (seed {e['seed']})")
        + (
            f" over [-{e['extent']:g}, {e['extent']:g}]^2, heading turned away from the target (pi at the centre)"
            if system.wheeled
            else f" over {starts_box(system)}, the other entries 0 (runs.csv: the first three entries)"
        ),
        f"* agents {', '.join(e['agents'])}; horizons N = {', '.join(str(h) for h in e['horizons'])}; "
        f"episode {e['duration']:g} s = {e['steps']} steps of delta = {s['plant']['sampling_time']} s; "
        "every RL run learns online from the initial weights (no pretraining)",
        f"* wall time **{summary['wall_seconds']:.1f} s** on {summary['workers']} worker processes "
        f"({summary['cpu_count']} cores; setup {summary['setup_seconds']:.1f} s), git {summary.get('git') or '?'}",
        f"* settings: R = diag{tuple(s['cost']['r_diag'])}, gamma = {s['critic']['discount_rate']} /s "
        f"(beta = {s['derived']['discount_beta']:.4f}), M = {s['critic']['replay_size']}, "
        f"ridge lambda = {s['critic']['ridge']}, weight bounds = {s['critic']['weight_bounds'] or 'none'}, "
        f"initial weights q = {_fmt_init(s['critic']['q_init'])}, v = {_fmt_init(s['critic']['v_init'])}, "
        f"solver {s['actor']['solver']}, predictor {s['actor']['predictor']} (all in config.toml)",
        (
            f"* parked = final distance to the target <= {summary['park_tolerance_m']} m; "
            if system.wheeled
            else f"* stabilized = final distance to the goal <= {summary['park_tolerance_m']:g}; "
        )
        + f"better than MPC = J/J_mpc < {100 - summary['tie_percent']:g} % (within {summary['tie_percent']:g} % "
        "of 100 % is a tie: the solver tolerance alone moves J that much); "
        + (
            f"at rest = over the last {WINDOW_S:g} s the position spans <= {SPAN_M:g} m and v (|v| >= 0.01 m/s) "
            f"changes sign at most {MAX_SIGN_CHANGES} times (no chatter)"
            if system.wheeled
            else f"at rest = over the last {WINDOW_S:g} s every state within {summary['park_tolerance_m']:g} "
            "of the goal"
        ),
        "",
        *results_lines(summary),
    ]
    if e["transport"] == "zenoh":
        timeouts = sum(g["critic_timeouts"] for g in summary["groups"])
        lines += ["", f"Zenoh lockstep with the synchronous critic: {timeouts} critic timeouts."]
    lines += [
        "",
        "Files: runs.csv (one row per run), trajectories.npz, config.toml (use with --config), "
        "settings.json, summary.json, " + ", ".join(summary.get("plots", [])) + ".",
    ]
    return "\n".join(lines) + "\n"


def results_lines(summary: dict[str, Any]) -> list[str]:
    """The results of a summary as markdown lines: the table of J/J_mpc per agent and horizon,
    RL-QV against RL-Q start by start, and the paper's claims (summary.md; the systems' pages)."""
    wheeled = system_row(summary["experiment"].get("system", "unicycle")).wheeled
    lines = [
        "| agent | N | runs | median J | median J/J_mpc | better than MPC | ties | min J/J_mpc | max J/J_mpc "
        f"| {'parked' if wheeled else 'stabilized'} | at rest | solver failures |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for g in summary["groups"]:
        beat = f"{g['beat_mpc']}/{g['ratios']} ({100 * g['beat_mpc_share']:.0f} %)" if "beat_mpc" in g else "—"
        lines.append(
            f"| {g['agent']} | {g['horizon']} | {g['runs']} | {g['median_cost']:.2f} | "
            f"{_fmt_ratio(g.get('median_ratio_percent'))} | {beat} | {g.get('ties', '—')} | "
            f"{_fmt_ratio(g.get('min_ratio_percent'))} | {_fmt_ratio(g.get('max_ratio_percent'))} | "
            f"{g['parked']}/{g['runs']} | {g.get('at_rest', 0)}/{g['runs']} | {g['solver_failures']} |"
        )
    if summary.get("head_to_head"):
        lines += ["", "RL-QV vs RL-Q, start by start:", ""]
        for d in summary["head_to_head"]:
            lines.append(
                f"* N = {d['horizon']}: RL-QV better than RL-Q from {d['wins']}/{d['starts']} starts, "
                f"median J_rlqv/J_rlq = {d['median_ratio_percent']:.1f} %"
            )
    if summary.get("claims"):
        lines += ["", "The paper's claims on these numbers:", ""]
        for c in summary["claims"]:
            lines.append(f"* **{'holds' if c['holds'] else 'does not hold'}** — {c['claim']}: {c['detail']}")
    return lines
