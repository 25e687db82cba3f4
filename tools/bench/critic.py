"""``srl bench critic``: the CPU of one critic fit, per robot, when a fleet's critic fits K robots.

Three ways to make the same fits (docs/concepts.md, "The critic update"), on the same data:

* ``per-robot``: one robot per call, its design rebuilt from its replay's samples
  (``update_many([critic], [replay], rebuild=True)``), as a critic fitting each robot alone;
* ``rebuilt``: every robot due in one stacked solve, the designs rebuilt from the samples
  (``update_many(critics, replays, rebuild=True)``);
* ``batched``: every robot due in one stacked solve, the designs read from the replays' kept
  arrays (``update_many(critics, replays)``), as the critic service fits a batch of transitions.

The data is a real closed-loop run (the README's first command: rlqv, N = 12, from (2, 2), the
ideal plant, 300 steps); robot ``k`` replays its own segment of it, so the robots' fits and
active sets differ. Per size and round: fresh critics (srl.toml's ``[critic]``), a warm-up of M
steps that fills the replays (not timed), then ``--steps`` steps (more for a small K: at least
1000 fits per round, as far as the run goes), each adding every robot's sample and fitting every
robot, timed in process CPU (``time.process_time``: every thread).
The ways alternate (per-robot, rebuilt, batched, per-robot, ...) so all see the same machine;
each row gives the median over the rounds, the CPU of adding a sample (its kept row computed),
the machine's load average before and after, and the largest difference between the ways'
weights (0: the same bits).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the CLI imports this module to register it: numpy and the critic load when it runs
    from common.math.critic import Sample

WAYS = ("per-robot", "rebuilt", "batched")


def add_parser(kinds: Any) -> None:
    """``srl bench critic`` among ``srl bench``'s kinds (an argparse subparsers action)."""
    helptext = "the critic's CPU per fit, K robots fitted one by one vs in one batch, per K"
    parser = kinds.add_parser("critic", help=helptext, description=helptext[0].upper() + helptext[1:] + ".")
    parser.add_argument("--robots", default="1,10,100,300", help="comma-separated K values (default: 1,10,100,300)")
    parser.add_argument("--rounds", type=int, default=5, help="rounds of each way per K, alternated (default: 5)")
    parser.add_argument(
        "--steps",
        type=int,
        default=20,
        help="timed fits per robot per round, more for a small K: at least 1000 fits per round while the "
        "recorded run lasts (default: 20)",
    )
    parser.add_argument("--json", action="store_true", help="last stdout line: one JSON object")
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from common.config.arguments import UsageError

    try:
        sizes = [int(part) for part in args.robots.split(",") if part.strip()]
    except ValueError:
        raise UsageError(f"--robots {args.robots!r}: comma-separated robot counts, e.g. 1,10,100") from None
    if not sizes or min(sizes) < 1:
        raise UsageError(f"--robots {args.robots!r}: at least one count, each >= 1")
    if args.rounds < 1 or args.steps < 1:
        raise UsageError("--rounds and --steps must be >= 1")
    result = run_critic_benchmark(sizes, args.rounds, args.steps)
    print(format_table(result))
    if args.json:
        print(json.dumps(result))
    return 0


def recorded_run() -> list[Sample]:
    """The README's first run (rlqv, N = 12, from (2, 2), 30 s): its 300 transitions."""
    from common.config.assembly import run_episode
    from common.config.settings import Settings
    from common.math.critic import Sample

    settings = Settings.load(actor={"agent": "rlqv", "horizon": 12}, episode={"start": [2.0, 2.0], "duration": 30.0})
    episode = run_episode(settings)
    return [Sample(k, episode.states[k], episode.actions[k], episode.costs[k]) for k in range(episode.steps)]


def one_way(way: str, robots: int, samples: list[Sample], steps: int) -> dict[str, Any]:
    """One round of one way: CPU per fit and per sample added, and the final weights."""
    import numpy as np

    from common.config.settings import Settings
    from common.math.critic import DoubleCritic, Replay, Sample, update_many

    settings = Settings.load()
    c = settings.critic
    critics = [
        DoubleCritic(settings.initial_q_weights(), settings.initial_v_weights(), settings.discount, c.ridge, c.bounds)
        for _ in range(robots)
    ]
    replays = [Replay(c.replay_size) for _ in range(robots)]
    warm = c.replay_size
    span = warm + steps
    offsets = [(7 * k) % max(1, len(samples) - span) for k in range(robots)]  # robot k's segment

    def add(step: int) -> None:
        for replay, offset in zip(replays, offsets, strict=True):
            sample = samples[offset + step]
            replay.add(Sample(step, sample.state, sample.action, sample.cost))

    def fit() -> None:
        if way != "per-robot":
            update_many(critics, replays, rebuild=way == "rebuilt")
        else:
            for critic, replay in zip(critics, replays, strict=True):
                update_many([critic], [replay], rebuild=True)

    for step in range(warm):
        add(step)
        fit()
    adding = fitting = 0.0
    for step in range(warm, span):
        started = time.process_time()
        add(step)
        added = time.process_time()
        fit()
        adding += added - started
        fitting += time.process_time() - added
    weights = np.array([np.concatenate([x.q_weights, x.v_weights]) for x in critics])
    return {"fit_us": fitting / (steps * robots) * 1e6, "add_us": adding / (steps * robots) * 1e6, "weights": weights}


def run_critic_benchmark(sizes: list[int], rounds: int, steps: int) -> dict[str, Any]:
    import numpy as np

    from common.config.settings import Settings
    from tools.bench.meta import run_info

    samples = recorded_run()
    warm = Settings.load().critic.replay_size
    if len(samples) < warm + 2:
        raise ValueError(f"a replay of M = {warm} needs a run of more than {len(samples)} steps to time")
    rows = []
    for robots in sizes:
        load_before = os.getloadavg()
        runs: dict[str, list[dict[str, Any]]] = {way: [] for way in WAYS}
        # a small K: enough fits to time; every robot's segment (M warm-up steps, then these) within the run
        timed = min(max(steps, -(-1000 // robots)), len(samples) - warm - 1)
        for _ in range(rounds):
            for way in WAYS:  # alternated: per-robot, rebuilt, batched, per-robot, ...
                runs[way].append(one_way(way, robots, samples, timed))
        difference = max(
            float(np.max(np.abs(one["weights"] - other["weights"])))
            for way in WAYS[1:]
            for one, other in zip(runs["per-robot"], runs[way], strict=True)
        )
        fit_us = {way: statistics.median(r["fit_us"] for r in runs[way]) for way in WAYS}
        rows.append(
            {
                "robots": robots,
                "steps": timed,
                "per_robot_fit_us": fit_us["per-robot"],
                "rebuilt_fit_us": fit_us["rebuilt"],
                "batched_fit_us": fit_us["batched"],
                "speedup": fit_us["per-robot"] / fit_us["batched"],
                **{f"{way.replace('-', '_')}_fit_us_rounds": [r["fit_us"] for r in runs[way]] for way in WAYS},
                "add_us": statistics.median(r["add_us"] for r in runs["batched"]),
                "max_weight_difference": difference,
                "load_before": list(load_before),
                "load_after": list(os.getloadavg()),
            }
        )
    summary = {  # one line per K for a page that lists the scalars (docs/benchmarks/)
        f"fit_us_K{row['robots']}": f"per-robot {row['per_robot_fit_us']:.1f}, rebuilt {row['rebuilt_fit_us']:.1f}, "
        f"batched {row['batched_fit_us']:.1f} ({row['speedup']:.1f}x)"
        for row in rows
    }
    return {"rounds": rounds, "steps": steps, **summary, "rows": rows, "run": run_info()}


def format_table(result: dict[str, Any]) -> str:
    lines = [
        f"critic fits: CPU per fit [us], median of {result['rounds']} alternated rounds of 'steps' fits per "
        "robot (replays full, M as configured); speedup = per-robot / batched",
        f"{'K':>5} {'steps':>5} {'per-robot':>10} {'rebuilt':>10} {'batched':>10} {'speedup':>8} "
        f"{'add/sample':>11} {'max |dw|':>9} {'load before/after':>18}",
    ]
    for row in result["rows"]:
        lines.append(
            f"{row['robots']:>5} {row['steps']:>5} {row['per_robot_fit_us']:>10.1f} {row['rebuilt_fit_us']:>10.1f} "
            f"{row['batched_fit_us']:>10.1f} "
            f"{row['speedup']:>7.1f}x {row['add_us']:>11.1f} {row['max_weight_difference']:>9.1e} "
            f"{row['load_before'][0]:>8.2f} / {row['load_after'][0]:<8.2f}"
        )
    return "\n".join(lines)
