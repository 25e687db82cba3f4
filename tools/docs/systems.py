"""A page per built-in sampled system (docs/reference/systems/NAME.md): its standard box, read from
its row of common/math/systems.py ``SYSTEMS``, and its results, read from the summary.json of
``srl experiment paper --system NAME`` kept under docs/paper/systems/NAME/ (the robot's:
docs/paper/paper-grid/). ``srl docs --systems`` runs those experiments again and keeps what the
pages show (the summary and the figures); ``srl docs`` writes the pages."""

from __future__ import annotations

import contextlib
import io
import json
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from common.config.settings import Settings
from common.math.features import feature_count
from common.math.systems import BUILT_IN_SYSTEMS, SYSTEMS, System, gymnasium_id
from tools.docs.reference import GENERATED, cell, code, first_paragraph
from tools.experiment.report import results_lines

SYSTEM_DATA = Path("docs/paper/systems")  # NAME/: what each built-in system's page shows
ROBOT_DATA = Path("docs/paper/paper-grid")  # the robot's: the paper's experiment
KEPT = ("summary.json", "trajectories.png", "ratio_N12.png", "ratio_N6.png")  # of an experiment's output


def data_dir(name: str) -> Path:
    """Where ``name``'s experiment output is kept (relative to the repository)."""
    return ROBOT_DATA if name == "unicycle" else SYSTEM_DATA / name


def sampling_time() -> float:
    """[s] delta of srl.toml (``plant.sampling_time``): the pages' step error is over it."""
    return Settings.load().plant.sampling_time


def step_error(system: System, draws: int = 32) -> float:
    """The largest difference (max norm) over one held interval between the plant's step
    (``substeps`` RK4 steps) and 16 times as many, from ``draws`` seeded states in the start box
    and actions in the action box: the integrator's error the page states."""
    rng = np.random.default_rng(0)
    finer = replace(system, substeps=16 * system.substeps)
    worst, delta = 0.0, sampling_time()
    for _ in range(draws):
        state = system.draw_start(rng)
        action = rng.uniform(-1.0, 1.0, system.action_dim) * np.array(system.action_max)
        step, fine = system.step(state, action, delta), finer.step(state, action, delta)
        worst = max(worst, float(np.max(np.abs(step - fine))))
    return worst


def plant_step(system: System) -> str:
    if system.exact_step is not None:
        return "exact: the closed form of the held interval"
    return (
        f"{system.substeps} RK4 steps per held interval; over delta = {sampling_time():g} s they differ from "
        f"{16 * system.substeps} steps by at most {step_error(system):.1e} (32 seeded states of the start box, "
        "actions in the box)"
    )


def stage_cost(system: System) -> str:
    names = [label for label, _ in system.state_labels() + system.action_labels()]
    terms = " + ".join(f"{weight:g} {name}^2" for weight, name in zip(system.cost_diag, names, strict=True) if weight)
    return f"`r(s, u) = {terms}` (`cost.r_diag = []` takes these)"


def box_rows(name: str, system: System) -> list[list[str]]:
    """The standard box: what srl needs of the system, in the row's own terms."""
    labels = [label for label, _ in system.state_labels()]
    n, m = system.state_dim, system.action_dim
    bounds = ", ".join(
        f"`abs({label}) <= {bound:g}`"
        for (label, _), bound in zip(system.action_labels(), system.action_max, strict=True)
    )
    distance = "`hypot(x, y)` (whatever the heading)" if system.wheeled else "the norm of the state"
    model = first_paragraph(system.rhs.__doc__ or "") or "(no docstring)"
    starts = ", ".join(
        f"`abs({label}) <= {w:g}`" for label, w in zip(labels, system.box_of_starts, strict=True) if w > 0
    )
    if system.wheeled:  # the paper's grid: positions in the square, each turned away from the target
        starts = "positions `abs(x), abs(y) <= 2`, turned away from the target"
    return [
        ["state", f"n = {n}: " + ", ".join(code(s) for s in system.states)],
        ["action", f"m = {m}: " + ", ".join(code(a) for a in system.actions) + f", held within {bounds}"],
        ["model", f"`ds/dt = f(s, u)`, `{system.rhs.__name__}` in `common/math/systems.py`: {cell(model)}"],
        ["the plant's step", plant_step(system)],
        ["the actor's model", "`actor.predictor` over the same f: `euler` (default) or `rk4`, one step per delta"],
        ["horizon", f"N = {system.horizon} unless the settings name one (`actor.horizon = 0` takes it; `--horizon N`)"],
        ["stage cost", stage_cost(system)],
        [
            "critics",
            f"Q: {feature_count(n + m)} quadratic features of (s, u); V: {feature_count(n)} of s "
            "(`common/math/features.py`)",
        ],
        ["goal", "the origin: " + ", ".join(f"{label} = 0" for label in labels)],
        ["stabilized", f"{distance} < {system.stabilized:g}"],
        [
            "start",
            "(" + ", ".join(f"{value:.3g}" for value in system.start) + ") (`episode.start = []` takes it); "
            f"drawn or on the experiment's lattice: {starts or 'the start itself'}",
        ],
        [
            "run it",
            f"`srl run --system {name}`, `srl experiment paper --system {name}`, "
            f"`srl experiment baselines --system {name}`, Gymnasium `{gymnasium_id(name)}`, "
            + (
                "the services, `srl up` and the robots"
                if system.wheeled
                else f"`srl up --system {name}` (real time; `--mode lockstep`)"
            ),
        ],
    ]


def results(name: str, summary: dict[str, Any] | None, figures: list[str]) -> list[str]:
    """The page's results: the experiment's table and claims, and its figures."""
    if summary is None:
        return [f"No results kept yet: `srl docs --systems` runs `srl experiment paper --system {name}`."]
    e = summary["experiment"]
    lines = [
        f"`{e['command']}`: {summary['runs_completed']} runs, {e['grid']} x {e['grid']} starts "
        f"({'the goal left out' if name != 'unicycle' else 'the paper grid'}), {e['duration']:g} s each, "
        f"git {summary.get('git') or '?'}.",
        "",
        *results_lines(summary),
    ]
    for figure in figures:
        lines += [
            "",
            f"![{figure.removesuffix('.png')}](../../{data_dir(name).relative_to('docs').as_posix()}/{figure})",
        ]
    return lines


def system_page(name: str, system: System, summary: dict[str, Any] | None, figures: list[str]) -> str:
    return "\n".join(
        [
            GENERATED,
            "",
            f"# The system `{name}`",
            "",
            system.what[0].upper() + system.what[1:] + ".",
            "",
            "| | |",
            "|---|---|",
            *(f"| {key} | {value} |" for key, value in box_rows(name, system)),
            "",
            "## Results",
            "",
            *results(name, summary, figures),
        ]
    )


def pages(root: Path) -> dict[Path, str]:
    """docs/reference/systems/NAME.md for every built-in system, from its row and its kept results."""
    found = {}
    for name in BUILT_IN_SYSTEMS:
        directory = root / data_dir(name)
        summary_path = directory / "summary.json"
        summary = json.loads(summary_path.read_text()) if summary_path.is_file() else None
        figures = [f for f in ("trajectories.png", "ratio_N12.png") if (directory / f).is_file()]
        found[Path("docs/reference/systems") / f"{name}.md"] = system_page(name, SYSTEMS[name], summary, figures)
    return found


def run_experiments(root: Path, run: Callable[[list[str]], int], names: tuple[str, ...] | None = None) -> list[str]:
    """``srl experiment paper --system NAME`` for each system but the robot (``run``: the CLI's
    main), each into a temporary directory removed after; once all have run (so that each names
    the commit it ran, not a tree its forerunner changed, and a failure changes nothing), what the
    pages show is kept under :data:`SYSTEM_DATA`. The paths written. Each experiment's own output
    (its summary, the directory it names, soon removed) is kept back: one line each on stderr says
    it ran; a failure is a RuntimeError naming the experiment and its last line."""
    chosen = names if names is not None else tuple(n for n in BUILT_IN_SYSTEMS if not SYSTEMS[n].wheeled)
    written = []
    with tempfile.TemporaryDirectory(prefix="srl-docs-") as scratch:
        for name in chosen:
            argv = ["experiment", "paper", "--system", name, "--no-progress", "--out", f"{scratch}/{name}"]
            said, started = io.StringIO(), time.monotonic()
            with contextlib.redirect_stdout(said), contextlib.redirect_stderr(said):
                code = run(argv)
            if code != 0:
                last = (said.getvalue().strip().splitlines() or [""])[-1]
                raise RuntimeError(f"srl {' '.join(argv[:4])} exited {code}: {last}")
            print(f"srl docs: srl {' '.join(argv[:4])}: {time.monotonic() - started:.1f} s", file=sys.stderr)
        for name in chosen:
            target = root / SYSTEM_DATA / name
            target.mkdir(parents=True, exist_ok=True)
            for kept in KEPT:
                if (Path(scratch) / name / kept).is_file():
                    shutil.copyfile(Path(scratch) / name / kept, target / kept)
                    written.append(str((target / kept).relative_to(root)))
    return written
