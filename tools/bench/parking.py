"""``srl bench parking``: does the robot park, truly, and rest there? (docs/turtlebot.md)

In process and as fast as the CPU allows (Algorithm 1 with the in-process plant and critic,
the lockstep semantics), five starts of the paper's 5 x 5 grid x the agents at one horizon x
the plants (``plant.model``: ideal, actuator, physics), 35 s each. One row per run: the TRUE final
distance, the one the robot reported (what srl saw), the span of the true position and the
sign changes of ``v`` over the last 10 s (common/math/parking.py), J on the true and on the
reported states, and the commands a wheel could not follow. Targets: true final
distance <= 0.05 m, span <= 0.05 m, <= 5 sign changes; PASS/FAIL per row and a count.
With ``--json`` the last stdout line is one JSON object (:class:`ParkingResult`).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Sequence
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict

from common.config.arguments import UsageError
from common.config.assembly import build_actor, build_plant, local_critic, run_episode
from common.config.settings import METHODS, PAPER_METHOD, Settings
from common.math.actor import StackedActor
from common.math.agents import Agent, learns, parse_agents, parse_horizons
from common.math.parking import FINAL_DISTANCE_M, MAX_SIGN_CHANGES, SPAN_M, WINDOW_S, distance_to_target, parking
from tools.bench.meta import run_info

# Five nodes of the paper's 5 x 5 grid over [-2, 2]^2 (docs/experiment.md), one per quadrant
# and one on an axis; each start turned away from the target, as the paper's.
STARTS: tuple[tuple[float, float], ...] = ((2.0, 2.0), (-2.0, 2.0), (-1.0, -2.0), (2.0, -1.0), (-2.0, 0.0))
AGENTS = "mpc,rlq,rlqv"
HORIZON = 12
PLANTS = "ideal,actuator,physics"
METHOD_NAMES = ",".join(METHODS)  # paper (the robot settings off) and robot (srl.toml's)
SECONDS = 35.0
PlantModel = Literal["ideal", "actuator", "physics"]
Method = Literal["paper", "robot"]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ParkingRow(_Model):
    method: Method  # paper: the paper's actor; robot: with the arrival rule, wheel box, convex critics
    plant: PlantModel
    agent: Agent
    horizon: int
    start: tuple[float, float, float]
    steps: int
    true_final_distance: float  # [m]
    reported_final_distance: float  # [m] what srl saw (the robot's odometry)
    span_m: float  # of the true position over the last window
    sign_changes: int  # of v (|v| >= 0.01 m/s) over the last window
    median_speed: float  # median |v| over the last window [m/s]
    true_cost: float  # J on the true states
    reported_cost: float  # J on the reported states (the run's score as srl computes it)
    saturated_commands: int  # commands with a wheel beyond its limit
    final_ok: bool
    span_ok: bool
    sign_changes_ok: bool
    passed: bool
    wall_seconds: float


class ParkingResult(_Model):
    seconds: float
    window_seconds: float
    targets: dict[str, float]
    rows: list[ParkingRow]
    passed: int
    total: int
    run: dict[str, Any] | None = None  # date, commit, machine (tools/bench/meta.py), set when printed


def parse_starts(text: str) -> list[tuple[float, float]]:
    """``"2,2;-2,2"`` -> [(2, 2), (-2, 2)]."""
    starts = []
    for part in text.split(";"):
        values = [float(c) for c in part.split(",")]
        if len(values) != 2:
            raise ValueError(f"a start is X,Y, got {part!r}")
        starts.append((values[0], values[1]))
    return starts


def parse_plants(text: str) -> list[PlantModel]:
    plants: list[PlantModel] = []
    for name in text.split(","):
        if name not in ("ideal", "actuator", "physics"):
            raise ValueError(f"a plant is ideal, actuator or physics, got {name!r}")
        plants.append(name)  # type: ignore[arg-type]
    return plants


def parse_methods(text: str) -> list[Method]:
    methods: list[Method] = []
    for name in text.split(","):
        if name not in METHODS:
            raise ValueError(f"a method is {' or '.join(METHODS)}, got {name!r}")
        methods.append(name)  # type: ignore[arg-type]
    return methods


def run_settings(
    base: Settings,
    plant: str,
    agent: str,
    horizon: int,
    start: tuple[float, float],
    seconds: float,
    method: Method = "robot",
) -> Settings:
    data = base.model_dump(mode="json")
    if method == "paper":
        data["actor"].update(PAPER_METHOD["actor"])
    data["plant"]["model"] = plant
    data["actor"].update(agent=agent, horizon=horizon)
    data["episode"].update(start=list(start), duration=seconds)
    return Settings.model_validate(data)


def parking_row(settings: Settings, actor: StackedActor, method: Method = "robot") -> ParkingRow:
    """One run in process and its parking metrics."""
    started = time.perf_counter()
    critic = local_critic(settings, learn=learns(settings.actor.agent))
    episode = run_episode(settings, actor=actor, plant=build_plant(settings), critic=critic)
    delta, r_diag = settings.plant.sampling_time, tuple(settings.cost.r_diag)
    true_states = episode.true_states if episode.truth_known else episode.states
    metrics = parking(true_states, episode.actions, delta)
    true_cost = episode.true_accumulated_cost(delta, r_diag)
    final_ok = metrics.final_distance <= FINAL_DISTANCE_M
    span_ok, flips_ok = metrics.span <= SPAN_M, metrics.sign_changes <= MAX_SIGN_CHANGES
    return ParkingRow(
        method=method,
        plant=settings.plant.model,
        agent=settings.actor.agent,
        horizon=settings.actor.horizon,
        start=tuple(float(c) for c in settings.start_state()),  # type: ignore[arg-type]
        steps=episode.steps,
        true_final_distance=metrics.final_distance,
        reported_final_distance=distance_to_target(episode.final_state),
        span_m=metrics.span,
        sign_changes=metrics.sign_changes,
        median_speed=metrics.median_speed,
        true_cost=episode.accumulated_cost if true_cost is None else true_cost,
        reported_cost=episode.accumulated_cost,
        saturated_commands=episode.saturated_commands or 0,
        final_ok=final_ok,
        span_ok=span_ok,
        sign_changes_ok=flips_ok,
        passed=final_ok and span_ok and flips_ok,
        wall_seconds=time.perf_counter() - started,
    )


def run_parking(
    base: Settings,
    plants: list[PlantModel],
    agents: Sequence[str],
    horizon: int,
    starts: list[tuple[float, float]],
    seconds: float = SECONDS,
    methods: Sequence[Method] = ("robot",),
) -> ParkingResult:
    actors: dict[tuple[Method, str], StackedActor] = {}  # one problem per method and agent, reset per run
    rows = []
    for method in methods:
        for plant in plants:
            for agent in agents:
                for start in starts:
                    settings = run_settings(base, plant, agent, horizon, start, seconds, method)
                    if (method, agent) not in actors:
                        actors[method, agent] = build_actor(settings)
                    rows.append(parking_row(settings, actors[method, agent], method))
    return ParkingResult(
        seconds=seconds,
        window_seconds=WINDOW_S,
        targets={"true_final_distance_m": FINAL_DISTANCE_M, "span_m": SPAN_M, "sign_changes": MAX_SIGN_CHANGES},
        rows=rows,
        passed=sum(r.passed for r in rows),
        total=len(rows),
    )


def format_table(result: ParkingResult) -> str:
    lines = [
        f"srl bench parking: {result.seconds:.0f} s per run, in process; last {result.window_seconds:.0f} s window; "
        f"targets: true final <= {FINAL_DISTANCE_M} m, span <= {SPAN_M} m, v sign changes <= {MAX_SIGN_CHANGES}",
        f"  {'method':<6} {'plant':<8} {'agent':<5} {'N':>3} {'start':>13} {'true d':>7} {'saw d':>7} {'span':>6} "
        f"{'flips':>5} {'|v|med':>6} {'J true':>8} {'J rep':>8} {'sat':>4}  result",
    ]
    for r in result.rows:
        fails = [name for name, ok in (("d", r.final_ok), ("span", r.span_ok), ("flips", r.sign_changes_ok)) if not ok]
        lines.append(
            f"  {r.method:<6} {r.plant:<8} {r.agent:<5} {r.horizon:>3} {f'({r.start[0]:+.1f},{r.start[1]:+.1f})':>13} "
            f"{r.true_final_distance:>7.3f} {r.reported_final_distance:>7.3f} {r.span_m:>6.3f} {r.sign_changes:>5d} "
            f"{r.median_speed:>6.3f} {r.true_cost:>8.3f} {r.reported_cost:>8.3f} {r.saturated_commands:>4d}  "
            + ("PASS" if r.passed else "FAIL (" + ", ".join(fails) + ")")
        )
    lines.append(f"  passed {result.passed} of {result.total}")
    return "\n".join(lines)


def run_parking_benchmark(args: argparse.Namespace, settings: Settings) -> int:
    try:
        horizons = parse_horizons(args.horizons) if args.horizons else (HORIZON,)
        if len(horizons) != 1:
            raise ValueError(f"parking runs one horizon at a time (--horizons N), got {list(horizons)}")
        plants = parse_plants(args.plants or PLANTS)
        methods = parse_methods(args.methods or METHOD_NAMES)
        agents = list(parse_agents(args.agents or AGENTS))
        starts = parse_starts(args.starts) if args.starts else list(STARTS)
        if not (args.parking_seconds > 0 and math.isfinite(args.parking_seconds)):
            raise ValueError(f"--parking-seconds must be > 0, got {args.parking_seconds}")
    except ValueError as error:
        raise UsageError(f"srl bench parking: {error}") from None
    result = run_parking(settings, plants, agents, horizons[0], starts, args.parking_seconds, methods)
    print(format_table(result))
    if args.json:
        print(json.dumps({**result.model_dump(), "run": run_info()}))
    return 0
