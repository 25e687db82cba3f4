"""``srl experiment paper``'s options and outcome, shared by its command line, runner and output."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from common.math.agents import PAPER_AGENTS

DEFAULT_HORIZONS = (12, 6)
EXIT_INTERRUPTED = 130


class ExperimentError(RuntimeError):
    """A run or a service failed: the experiment stops (partial results are still written)."""


# -- options -----------------------------------------------------------------------------
# -- options ----------------------------------------------------------------------------
@dataclass
class ExperimentOptions:
    grid: int = 5
    extent: float = 2.0
    starts: str = "paper"
    seed: int = 0
    agents: tuple[str, ...] = PAPER_AGENTS
    horizons: tuple[int, ...] = DEFAULT_HORIZONS
    transport: str = "inproc"
    localization: str = "none"  # inproc: the simulated robot's pose corrected by amcl or mocap
    workers: int = 0  # 0 = every core this process may use
    out: Path = field(default_factory=lambda: Path("out"))
    plots: bool = True
    progress: bool = True
    command: str = ""
    record: Path | None = None  # one MCAP file of every run (tools/recording/record.py)

    def worker_count(self, runs: int) -> int:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        return max(1, min(self.workers or cores, runs))


@dataclass
class Outcome:
    rows: list[dict[str, Any]]
    arrays: dict[str, dict[str, np.ndarray]]
    planned: int
    interrupted: bool
    error: str | None
    wall_seconds: float
    setup_seconds: float
    workers: int
    services: dict[str, Any]
    worker_pids: list[int]
