"""The experiment's output directory: the resolved config first, then runs.csv, trajectories.npz,
summary.md and summary.json, the figures and the optional MCAP recording."""

from __future__ import annotations

import json
import os
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from common.config.settings import Settings
from tools.experiment.marks import PARK_TOLERANCE_M, TIE_PERCENT
from tools.experiment.options import ExperimentError, ExperimentOptions, Outcome
from tools.experiment.report import (
    check_claims,
    git_commit,
    group_summary,
    head_to_head,
    ratio_table,
    sorted_rows,
    summary_markdown,
    toml_dumps,
    write_runs_csv,
    write_trajectories,
)

OUTPUT_FILES = (
    "runs.csv",
    "trajectories.npz",
    "config.toml",
    "settings.json",
    "summary.md",
    "summary.json",
    "trajectories.png",
)


def write_outputs(out: Path, options: ExperimentOptions, base: Settings, outcome: Outcome) -> dict[str, Any]:
    rows = sorted_rows(outcome.rows, options.agents, options.horizons)
    ratios = ratio_table(rows)
    system = base.system
    tolerance = PARK_TOLERANCE_M if system.wheeled else system.stabilized  # parked, or stabilized
    groups = group_summary(rows, options.agents, options.horizons, ratios, tolerance)
    duels = [d for h in options.horizons if (d := head_to_head(rows, "rlqv", "rlq", h)) is not None]
    write_runs_csv(out / "runs.csv", rows, ratios, tolerance)
    write_trajectories(out / "trajectories.npz", rows, outcome.arrays)
    summary: dict[str, Any] = {
        "experiment": {
            "starts": options.starts,
            "grid": options.grid,
            "extent": options.extent,
            "seed": options.seed,
            "agents": list(options.agents),
            "horizons": list(options.horizons),
            "transport": options.transport,
            "localization": options.localization,
            "duration": base.episode.duration,
            "steps": base.steps,
            "command": options.command,
            "system": base.plant.system,
        },
        "status": "interrupted" if outcome.interrupted else ("failed" if outcome.error else "complete"),
        "interrupted": outcome.interrupted,
        "error": outcome.error,
        "runs_planned": outcome.planned,
        "runs_completed": len(rows),
        "wall_seconds": outcome.wall_seconds,
        "setup_seconds": outcome.setup_seconds,
        "workers": outcome.workers,
        "cpu_count": os.cpu_count(),
        "git": git_commit(),
        "finished_at": datetime.now(UTC).isoformat(timespec="seconds"),
        "park_tolerance_m": tolerance,
        "tie_percent": TIE_PERCENT,
        "groups": groups,
        "head_to_head": duels,
        "claims": check_claims(groups, rows, options.horizons) if not outcome.interrupted else [],
        "ratios": [
            {k: t[k] for k in ("run_id", "agent", "horizon", "start_index", "start_x", "start_y", "ratio_percent")}
            for t in ratios
        ],
        "services": outcome.services,
        "worker_pids": outcome.worker_pids,
        "settings": base.as_dict(),
        "plots": [],
    }
    if options.plots and rows:
        from tools.experiment.plots import plot_ratio_contours, plot_trajectory_overview

        for horizon in options.horizons:
            path = out / f"ratio_N{horizon}.png"
            if plot_ratio_contours(
                [t for t in ratios if t["horizon"] == horizon], horizon, options.extent, path, system
            ):
                summary["plots"].append(path.name)
        plot_trajectory_overview(
            rows,
            outcome.arrays,
            options.agents,
            options.horizons,
            options.extent,
            out / "trajectories.png",
            tolerance,
            system,
        )
        summary["plots"].append("trajectories.png")
    (out / "summary.json").write_text(json.dumps(summary, indent=2, allow_nan=True) + "\n")
    (out / "summary.md").write_text(summary_markdown(summary))
    return summary


def record_experiment(recorder: Any, rows: list[dict[str, Any]], arrays: dict[str, dict[str, np.ndarray]]) -> None:
    """Every run that finished into one recording: run ``<run_id>`` is the robot ``/<run_id>/...``
    (ROS-named: ``rlqv_N12_s000``), and every run starts at the same moment, so a player shows the
    whole grid parking at once. States, actions and costs as trajectories.npz holds them (the
    experiment keeps no per-step weights or solve times: those topics are absent)."""
    from common.math.loop import Episode
    from tools.recording.record import record_episode

    origin_ns = time.time_ns()
    try:
        for row in rows:
            run = arrays[row["run_id"]]
            episode = Episode(
                agent=row["agent"],
                horizon=row["horizon"],
                states=list(run["states"]),
                actions=list(run["actions"]),
                costs=[float(c) for c in run["costs"]],
            )
            record_episode(recorder, episode, row["run_id"], origin_ns)
    finally:
        recorder.close()


def prepare_output(out: Path, base: Settings) -> Path:
    """Create ``out``, remove our own stale files, write the resolved config; return its path."""
    out.mkdir(parents=True, exist_ok=True)
    for name in OUTPUT_FILES:
        (out / name).unlink(missing_ok=True)
    for stale in out.glob("ratio_N*.png"):
        stale.unlink()
    config_path = out / "config.toml"
    config_path.write_text(
        "# Every setting of this experiment, resolved (packaged srl.toml < --config < SRL_ env < flags).\n"
        "# Runs override only actor.agent, actor.horizon and episode.start. Reuse: --config config.toml\n"
        + toml_dumps(base.model_dump(mode="json"))
    )
    # The file must reproduce these settings exactly (as the experiment uses them: an SRL_
    # environment variable naming a checkpoint still applies on load, and is switched off again).
    reloaded, expected = experiment_settings(Settings.load(config_path)), experiment_settings(base)
    if reloaded != expected:
        differ = [k for k, v in expected.model_dump().items() if reloaded.model_dump()[k] != v]
        raise ExperimentError(f"{config_path} does not reproduce the resolved settings (sections {differ})")
    (out / "settings.json").write_text(json.dumps(base.as_dict(), indent=2) + "\n")
    return config_path


def experiment_settings(base: Settings) -> Settings:
    """The base settings as the experiment uses them: no critic checkpoint file.

    Every episode starts from the initial weights by design, and a checkpoint per robot id
    (``exp<worker>``) would be shared by concurrent experiments and cost a synced write per step.
    """
    data = base.model_dump(mode="json")
    if data["critic"].get("checkpoint"):
        data["critic"]["checkpoint"] = ""
        return Settings.model_validate(data)
    return base
