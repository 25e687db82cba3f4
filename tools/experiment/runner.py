"""``srl experiment paper``: the paper's section IV experiment, end to end.

A grid of starts over the ``2 extent x 2 extent`` polygon (default 5 x 5 over ``[-2, 2]^2``),
each turned away from the target (``alpha_0 = atan2(y_0, x_0)``, ``pi`` at the centre); every
agent at every horizon parks from every start with Algorithm 1 in lockstep, each RL run
learning online from the initial weights (no pretraining). The marks are the paper's
``J_agent / J_mpc * 100 %`` per start and horizon (eqs. rql, rql-v), drawn as contour plots
(figures 3-4) and summarized in a table.

Runs are spread over worker processes (spawned, so no Zenoh or CasADi state is forked). A
worker builds each ``(agent, N)`` actor once and reuses it for every run of that pair (the
solver is stateless between episodes except for the warm start, which ``reset`` clears; the
same run is bit-identical on a fresh and on a reused actor). The scheduler hands a worker
runs of the pair it already built while any are left, so the ~1 s JIT builds happen about
once per pair and worker.

Transports:

* ``inproc``: each worker runs :func:`common.config.assembly.run_episode` with the exact plant and the
  local critic, as ``srl run`` does.
* ``zenoh``: a router and, per worker, one ``srl plant-sim --mode lockstep`` and one
  ``srl critic`` process (robot id ``exp<worker>``), all on a free loopback port with
  multicast scouting off, started once and kept up across runs: the plant is reset and the
  critic starts a fresh learner per episode id. Each worker is that robot's actor: it runs
  the actor service's lockstep code (``ZenohPlant``, ``ZenohCriticPort`` with the synchronous
  critic, ``WeightsInbox``) through :func:`run_episode`, so the distributed system executes
  Algorithm 1 exactly and reproduces the inproc numbers.

Outputs (``--out``): ``runs.csv``, ``trajectories.npz``, ``config.toml`` (loadable with
``--config``) and ``settings.json``, ``summary.md`` and ``summary.json``, ``ratio_N<N>.png``
per horizon and ``trajectories.png``. Ctrl-C stops the workers and services, writes what has
finished (marked interrupted) and exits with 130.
"""

from __future__ import annotations

import contextlib
import json
import logging
import queue
import signal
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from common.config.settings import Settings
from tools.experiment.grid import RunSpec, make_starts, plan_runs
from tools.experiment.options import EXIT_INTERRUPTED, ExperimentError, ExperimentOptions, Outcome
from tools.experiment.output import experiment_settings, prepare_output, record_experiment, write_outputs
from tools.experiment.report import (
    sorted_rows,
)
from tools.experiment.services import ExperimentServices
from tools.experiment.workers import Scheduler, WorkerConfig, worker_main

log = logging.getLogger(__name__)


def run_grid(options: ExperimentOptions, base: Settings, specs: list[RunSpec], config_path: Path) -> Outcome:
    """Run every spec over the workers; on Ctrl-C or a failure return what finished."""
    import multiprocessing

    workers = options.worker_count(len(specs))
    context = multiprocessing.get_context("spawn")  # never fork a process that holds Zenoh threads
    results = context.Queue()
    task_queues = [context.Queue() for _ in range(workers)]
    processes: list[Any] = []
    services: ExperimentServices | None = None
    services_info: dict[str, Any] = {}
    done: list[dict[str, Any]] = []
    arrays: dict[str, dict[str, np.ndarray]] = {}
    interrupted = False
    error: str | None = None
    started = time.perf_counter()
    setup_seconds = 0.0
    progress = _progress(options.progress)
    previous_sigterm = _set_signal(signal.SIGTERM, _sigterm_as_interrupt)
    try:
        with progress:
            task = progress.add_task("starting workers", total=len(specs))
            base_data = base.model_dump(mode="json")
            if options.transport == "zenoh":
                progress.update(task, description="starting router, plant_sim and critic services")
                services = ExperimentServices(config_path, base, workers)
                services.start()
                services_info["endpoint"] = services.endpoint
            setup_seconds = time.perf_counter() - started
            for slot in range(workers):
                data = json.loads(json.dumps(base_data))
                robot = ""
                if services is not None:
                    robot = services.robots[slot]
                    data["transport"].update(services.transport_for(robot))
                process = context.Process(
                    target=worker_main,
                    args=(
                        WorkerConfig(slot, data, options.transport, robot, options.localization),
                        task_queues[slot],
                        results,
                    ),
                    name=f"srl-experiment-worker-{slot}",
                    daemon=True,
                )
                # Started with SIGINT ignored, a spawned interpreter never installs its own
                # KeyboardInterrupt handler: a Ctrl-C while it still imports cannot kill it.
                handler = _set_signal(signal.SIGINT, signal.SIG_IGN)
                try:
                    process.start()
                finally:
                    _set_signal(signal.SIGINT, handler)
                processes.append(process)
            scheduler = Scheduler(specs)
            released: set[int] = set()  # workers told to finish (None sent): they may exit
            progress.update(task, description="building actors")
            while len(done) < len(specs):
                try:
                    kind, slot, payload = results.get(timeout=0.5)
                except queue.Empty:
                    for index, process in enumerate(processes):
                        if process.exitcode is not None and index not in released:
                            raise ExperimentError(
                                f"worker {index} (pid {process.pid}) exited with code {process.exitcode}"
                            ) from None
                    if services is not None:
                        services.check()
                    continue
                if kind == "error":
                    raise ExperimentError(str(payload))
                if kind == "done":
                    row = payload["row"]
                    # the trajectory before the row: a Ctrl-C (KeyboardInterrupt) between the two
                    # leaves at most an unlisted trajectory, never a listed run without one
                    arrays[row["run_id"]] = payload["arrays"]
                    done.append(row)
                    progress.update(task, advance=1, description=f"{row['run_id']}  J = {row['accumulated_cost']:.2f}")
                    log.info(
                        "run %s done (%d/%d): J = %.4f", row["run_id"], len(done), len(specs), row["accumulated_cost"]
                    )
                spec = scheduler.next_for(slot)
                task_queues[slot].put(spec)
                if spec is None:
                    released.add(slot)
    except KeyboardInterrupt:
        interrupted = True
    except ExperimentError as failure:
        error = str(failure)
    finally:
        # A second Ctrl-C must not cut the cleanup short (it is bounded: a few seconds).
        previous_sigint = _set_signal(signal.SIGINT, signal.SIG_IGN)
        try:
            _stop_workers(processes, task_queues)
            if services is not None:
                services_info["pids"] = services.pids()
                services_info["exit_codes"] = services.stop()
                services_info["resources"] = services.resources()
        finally:
            _set_signal(signal.SIGINT, previous_sigint)
            _set_signal(signal.SIGTERM, previous_sigterm)
    return Outcome(
        done,
        arrays,
        len(specs),
        interrupted,
        error,
        time.perf_counter() - started,
        setup_seconds,
        workers,
        services_info,
        [p.pid for p in processes],
    )


def _sigterm_as_interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def _set_signal(signum: int, handler: Any) -> Any:
    """``signal.signal`` where Python allows it (the main thread); elsewhere a no-op."""
    if handler is None or threading.current_thread() is not threading.main_thread():
        return None
    return signal.signal(signum, handler)


def _stop_workers(processes: list[Any], task_queues: list[Any]) -> None:
    """Ask idle workers to finish, end busy ones by pid (SIGTERM, then SIGKILL)."""
    for task_queue in task_queues:
        with contextlib.suppress(Exception):
            task_queue.put(None)
    deadline = time.monotonic() + 0.5
    for process in processes:
        process.join(timeout=max(0.0, deadline - time.monotonic()))
    for process in processes:
        if process.is_alive():
            process.terminate()
    deadline = time.monotonic() + 5.0
    for process in processes:
        process.join(timeout=max(0.1, deadline - time.monotonic()))
        if process.is_alive():
            log.warning("worker pid %d did not stop: killing it", process.pid)
            process.kill()
            process.join(timeout=5.0)
    for task_queue in task_queues:
        task_queue.cancel_join_thread()


def _progress(enabled: bool) -> Any:
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    return Progress(
        TextColumn("[bold]srl experiment[/bold]"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("runs"),
        TimeElapsedColumn(),
        TextColumn("ETA"),
        TimeRemainingColumn(),
        TextColumn("{task.description}"),
        console=Console(stderr=True),
        disable=not enabled,
        transient=False,
    )


def run_experiment(options: ExperimentOptions, base: Settings) -> tuple[int, dict[str, Any]]:
    """Everything ``srl experiment paper`` does after parsing: (exit code, summary)."""
    base = experiment_settings(base)
    starts = make_starts(options.starts, options.grid, options.extent, options.seed, base.system)
    specs = plan_runs(starts, options.agents, options.horizons)
    recorder = None
    if options.record is not None:  # created now: a bad path fails before the first run
        from tools.recording.record import episode_recorder

        recorder = episode_recorder(
            options.record,
            base.plant.sampling_time,
            {"source": "srl experiment", "command": options.command, "horizons": list(options.horizons)},
        )
    config_path = prepare_output(options.out, base)
    try:
        outcome = run_grid(options, base, specs, config_path)
    except BaseException:
        if recorder is not None:
            recorder.close()  # a valid, empty recording: never a torn file
        raise
    summary = write_outputs(options.out, options, base, outcome)
    if recorder is not None:
        record_experiment(recorder, sorted_rows(outcome.rows, options.agents, options.horizons), outcome.arrays)
        summary["recording"] = str(options.record)
    if outcome.interrupted:
        return EXIT_INTERRUPTED, summary
    return (1 if outcome.error else 0), summary
