"""What every benchmark's JSON says about its own run: when, on which code, on which machine.

The generated pages under docs/benchmarks/ (tools/docs/benchmarks.py) print these beside the
numbers: a figure without its machine, load, date and commit cannot be compared with another.
"""

from __future__ import annotations

import datetime
import os
import platform
import shlex
import subprocess
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]


def _git(*args: str) -> subprocess.CompletedProcess[str] | None:
    try:
        # --no-optional-locks: reading the commit never rewrites the index of a shared worktree
        return subprocess.run(
            ["git", "--no-optional-locks", *args], cwd=ROOT, capture_output=True, text=True, timeout=20, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return None


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo), else what :mod:`platform` knows."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as handle:
            for line in handle:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def command_line() -> str | None:
    """The ``srl ...`` command this process runs, when it is the srl command (not a test calling it)."""
    if Path(sys.argv[0]).name not in ("srl", "cli.py"):
        return None
    return " ".join(["srl", *(shlex.quote(arg) for arg in sys.argv[1:])])


def run_info() -> dict[str, Any]:
    """Command, date (UTC), commit (and whether the worktree differs from it), CPU, cores and load."""
    head = _git("rev-parse", "HEAD")
    commit = head.stdout.strip() if head is not None and head.returncode == 0 else None
    diff = _git("diff", "--quiet", "HEAD", "--") if commit else None
    return {
        "command": command_line(),
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "commit": commit,
        "worktree_modified": None if diff is None else diff.returncode != 0,
        "cpu_model": cpu_model(),
        "cpu_count": os.cpu_count(),
        "cpus_usable": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "platform": platform.platform(),
        "python": platform.python_version(),
    }
