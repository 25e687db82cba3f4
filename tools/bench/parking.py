"""``srl bench parking``: does the robot park, truly, and rest there? (docs/turtlebot-parking.md)

In process and as fast as the CPU allows (Algorithm 1 with the in-process plant and critic,
the lockstep semantics): starts (five of the paper's 5 x 5 grid by default, ``--starts grid`` all
25, ``--starts random:25:SEED`` random positions within 3 m and random headings) x the agents at
one horizon x the plants (``plant.model``: ideal, actuator, physics; ``slipping``: the actuator
model whose wheels slip 25 %) x the pose the actor sees (``--localization``: ``none`` = odometry
only, ``amcl`` or ``mocap``: odometry corrected by a simulated localization with the robot
bridge's own fusion, common/math/localization.py), 35 s each. One row per run: the TRUE final
distance, the one the robot reported (what srl saw), the span of the true position and the sign
changes of ``v`` over the last 10 s (common/math/parking.py), when it arrived (within 0.05 m of the
target, true, and staying) against its bound, J on the true and on the reported states, the
commands a wheel could not follow and those below the wheels' breakaway. Targets: true final
distance <= 0.05 m, span <= 0.05 m, <= 5 sign changes, arrival by the bound
(:func:`arrival_bound`); PASS/FAIL per row and a count.
With ``--json`` the last stdout line is one JSON object (:class:`ParkingResult`).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike
from pydantic import BaseModel, ConfigDict

from common.config.arguments import UsageError
from common.config.assembly import build_actor, local_critic, localized_plant, run_episode
from common.config.settings import METHODS, Settings, with_method
from common.contracts.summaries import AgentName
from common.math.actor import StackedActor
from common.math.agents import learns, parse_agents, parse_horizons
from common.math.arrival import WheelDeadband
from common.math.frames import wrap_angle
from common.math.localization import SIM_SOURCES
from common.math.parking import FINAL_DISTANCE_M, MAX_SIGN_CHANGES, SPAN_M, WINDOW_S, distance_to_target, parking
from common.math.physics import breakaway_speed
from common.math.plant_models import PLANT_MODELS
from tools.bench.meta import run_info
from tools.experiment.grid import grid_starts

# Five nodes of the paper's 5 x 5 grid over [-2, 2]^2 (docs/experiment.md), one per quadrant
# and one on an axis; each start turned away from the target, as the paper's.
STARTS: tuple[tuple[float, ...], ...] = ((2.0, 2.0), (-2.0, 2.0), (-1.0, -2.0), (2.0, -1.0), (-2.0, 0.0))
AGENTS = "mpc,rlq,rlqv"
HORIZON = 12
PLANTS = "ideal,actuator,physics"
PLANT_NAMES = (*PLANT_MODELS, "slipping")
SLIPPING = 0.25  # the slipping robot: the actuator model with [actuator] slip 0.25 (odometry 25 % long)
METHOD_NAMES = ",".join(METHODS)  # paper (the robot settings off) and robot (srl.toml's)
SECONDS = 35.0
ParkingPlant = str  # a plant model (common/math/plant_models.py), or slipping: the actuator model on a slippery floor
Method = Literal["paper", "robot"]
Localization = Literal["none", "amcl", "mocap"]
LOCALIZATIONS = ("none", *SIM_SOURCES)
ODOMETRY_ONLY = "odometry only"  # what a row without a localization says its pose was
TRUTH = "truth"  # ... on the ideal plant, whose reported pose is the true one
# The arrival bound: the time to turn to the target, drive there and turn to its heading at the
# Burger's top speeds (0.22 m/s, 2.84 rad/s: ROBOTIS e-Manual), x 1.5, + 3 s.
TOP_SPEED, TOP_TURN, BOUND_FACTOR, BOUND_SLACK = 0.22, 2.84, 1.5, 3.0
RANDOM_RADIUS = 3.0  # [m] random starts: uniform over the disc of this radius, heading uniform


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ParkingRow(_Model):
    method: Method  # paper: the paper's actor; robot: with the arrival rule, wheel box, convex critics
    plant: ParkingPlant
    localization: str = ODOMETRY_ONLY  # the pose the actor saw: "odometry only", "amcl", "mocap"
    agent: AgentName
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
    deadband_commands: int = 0  # commands moving no wheel: not zero, every wheel below breakaway
    arrival_seconds: float | None = None  # [s] true distance <= 0.05 m from then on (None: not)
    arrival_bound: float = math.inf  # [s] arrival_bound(start)
    final_ok: bool
    span_ok: bool
    sign_changes_ok: bool
    arrival_ok: bool = True
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


Start = tuple[float, ...]  # (x, y): turned away from the target, as the paper's; (x, y, alpha)


def random_starts(count: int, seed: int, radius: float = RANDOM_RADIUS) -> list[Start]:
    """``count`` starts uniform over the disc of ``radius`` around the target, each with a heading
    uniform in [-pi, pi) (``numpy.random.default_rng(seed)``)."""
    rng = np.random.default_rng(seed)
    starts: list[Start] = []
    for _ in range(count):
        r, phi, alpha = (
            radius * math.sqrt(rng.uniform()),
            rng.uniform(-math.pi, math.pi),
            rng.uniform(-math.pi, math.pi),
        )
        starts.append((r * math.cos(phi), r * math.sin(phi), alpha))
    return starts


def parse_starts(text: str) -> list[Start]:
    """``grid`` (the paper's 25, tools/experiment/grid.py), ``random:COUNT:SEED``, or X,Y[,ALPHA]
    starts separated by ';': ``"2,2;-2,2,0.5"`` -> [(2, 2), (-2, 2, 0.5)]."""
    if "+" in text:  # several sets, one after the other
        return [start for part in text.split("+") for start in parse_starts(part)]
    if text == "grid":
        return [(s.x, s.y, s.alpha) for s in grid_starts(5, 2.0)]
    if text.startswith("random:"):
        parts = text.split(":")
        if len(parts) != 3 or not (parts[1].isdigit() and parts[2].isdigit()) or int(parts[1]) < 1:
            raise ValueError(f"random starts are random:COUNT:SEED (COUNT >= 1), got {text!r}")
        return random_starts(int(parts[1]), int(parts[2]))
    starts: list[Start] = []
    for part in text.split(";"):
        values = [float(c) for c in part.split(",")]
        if len(values) not in (2, 3) or not all(math.isfinite(c) for c in values):
            raise ValueError(f"a start is X,Y or X,Y,ALPHA, got {part!r}")
        starts.append(tuple(values))
    return starts


def parse_names(text: str, allowed: Sequence[str], what: str) -> list[Any]:
    """Comma-separated ``text`` as a list of ``allowed`` names; one line naming them otherwise."""
    names = text.split(",")
    for name in names:
        if name not in allowed:
            raise ValueError(f"a {what} is {', '.join(allowed)}, got {name!r}")
    return names


def arrival_bound(start: Sequence[float]) -> float:
    """The latest arrival item 3 allows from ``start`` ``(x, y, alpha)`` (goal frame): 1.5 x (d0 /
    0.22 m/s + |heading change| / 2.84 rad/s) + 3 s, the heading change of turning to face the
    target, driving there and turning to its heading (0): ``|wrap(bearing - alpha)| +
    |wrap(bearing)|``; at the target, ``|wrap(alpha)|``."""
    x, y, alpha = (float(c) for c in start)
    d0 = math.hypot(x, y)
    if d0 > 0.0:
        bearing = math.atan2(-y, -x)
        turn = abs(wrap_angle(bearing - alpha)) + abs(wrap_angle(bearing))
    else:
        turn = abs(wrap_angle(alpha))
    return BOUND_FACTOR * (d0 / TOP_SPEED + turn / TOP_TURN) + BOUND_SLACK


def arrival_time(true_states: ArrayLike, sampling_time: float, radius: float = FINAL_DISTANCE_M) -> float | None:
    """The first time [s] from which every true state is within ``radius`` of the target (None:
    the last one is not)."""
    distances = np.hypot(*np.asarray(true_states, dtype=float)[:, :2].T)
    outside = np.flatnonzero(distances > radius)
    if len(outside) == 0:
        return 0.0
    last = int(outside[-1])
    return None if last == len(distances) - 1 else (last + 1) * sampling_time


def deadband_commands(
    actions: ArrayLike, breakaway: float, radius: float, separation: float, resolution: float = 0.0
) -> int:
    """Commands that move no wheel: not exactly zero, and every wheel below ``breakaway`` [rad/s]
    as the robot applies the command (each component truncated to a multiple of ``resolution``:
    the OpenCR path's 0.01, common/math/arrival.py WheelDeadband.applied)."""
    wheels = WheelDeadband(breakaway, radius, separation, resolution)
    count = 0
    for action in np.asarray(actions, dtype=float).reshape(-1, 2):
        count += int(np.any(action != 0.0) and wheels.peak(action) < breakaway)
    return count


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
    start: Start,
    seconds: float,
    method: Method = "robot",
) -> Settings:
    data = with_method(base, method).model_dump(mode="json")
    data["plant"]["model"] = "actuator" if plant == "slipping" else plant
    if plant == "slipping":
        data["actuator"]["slip"] = SLIPPING
    data["actor"].update(agent=agent, horizon=horizon)
    data["episode"].update(start=list(start), duration=seconds)
    return Settings.model_validate(data)


def command_resolution(settings: Settings) -> float:
    """The simulated robot's command resolution: 0.01 (m/s, rad/s) on the OpenCR path
    (``actuator.quantize``, common/math/turtlebot.py firmware_velocity), else none; the ideal plant
    takes commands as sent."""
    return 0.01 if settings.plant.model != "ideal" and settings.actuator.quantize else 0.0


def parking_row(
    settings: Settings,
    actor: StackedActor,
    method: Method = "robot",
    plant_name: ParkingPlant | None = None,
    localization: Localization = "none",
    noise: tuple[float, float] | None = None,
) -> ParkingRow:
    """One run in process and its parking metrics."""
    started = time.perf_counter()
    critic = local_critic(settings, learn=learns(settings.actor.agent))
    plant = localized_plant(settings, localization, noise)
    episode = run_episode(settings, actor=actor, plant=plant, critic=critic)
    delta, r_diag = settings.plant.sampling_time, tuple(settings.r_diag)
    true_states = episode.true_states if episode.truth_known else episode.states
    metrics = parking(true_states, episode.actions, delta)
    true_cost = episode.true_accumulated_cost(delta, r_diag)
    final_ok = metrics.final_distance <= FINAL_DISTANCE_M
    span_ok, flips_ok = metrics.span <= SPAN_M, metrics.sign_changes <= MAX_SIGN_CHANGES
    start = tuple(float(c) for c in settings.start_state())
    arrived, bound = arrival_time(true_states, delta), arrival_bound(start)
    arrival_ok = arrived is not None and arrived <= bound
    a, name = settings.actor, plant_name or settings.plant.model
    breakaway = breakaway_speed(settings.physics_params(), delta)
    return ParkingRow(
        method=method,
        plant=name,
        localization=localization if localization != "none" else TRUTH if name == "ideal" else ODOMETRY_ONLY,
        agent=settings.actor.agent,
        horizon=settings.actor.horizon,
        start=start,  # type: ignore[arg-type]
        steps=episode.steps,
        true_final_distance=metrics.final_distance,
        reported_final_distance=distance_to_target(episode.final_state),
        span_m=metrics.span,
        sign_changes=metrics.sign_changes,
        median_speed=metrics.median_speed,
        true_cost=episode.accumulated_cost if true_cost is None else true_cost,
        reported_cost=episode.accumulated_cost,
        saturated_commands=episode.saturated_commands or 0,
        deadband_commands=deadband_commands(
            episode.actions, breakaway, a.wheel_radius, a.wheel_separation, resolution=command_resolution(settings)
        ),
        arrival_seconds=arrived,
        arrival_bound=bound,
        final_ok=final_ok,
        span_ok=span_ok,
        sign_changes_ok=flips_ok,
        arrival_ok=arrival_ok,
        passed=final_ok and span_ok and flips_ok and arrival_ok,
        wall_seconds=time.perf_counter() - started,
    )


def run_parking(
    base: Settings,
    plants: list[ParkingPlant],
    agents: Sequence[str],
    horizon: int,
    starts: list[Start],
    seconds: float = SECONDS,
    methods: Sequence[Method] = ("robot",),
    localizations: Sequence[Localization] = ("none",),
    noise: tuple[float, float] | None = None,
) -> ParkingResult:
    actors: dict[tuple[Method, str], StackedActor] = {}  # one problem per method and agent, reset per run
    rows = []
    for method in methods:
        for plant in plants:
            for localization in localizations:
                for agent in agents:
                    for start in starts:
                        settings = run_settings(base, plant, agent, horizon, start, seconds, method)
                        if (method, agent) not in actors:
                            actors[method, agent] = build_actor(settings)
                        rows.append(parking_row(settings, actors[method, agent], method, plant, localization, noise))
    return ParkingResult(
        seconds=seconds,
        window_seconds=WINDOW_S,
        targets={
            "true_final_distance_m": FINAL_DISTANCE_M,
            "span_m": SPAN_M,
            "sign_changes": MAX_SIGN_CHANGES,
            "arrival_bound_factor": BOUND_FACTOR,
            "arrival_bound_slack_s": BOUND_SLACK,
        },
        rows=rows,
        passed=sum(r.passed for r in rows),
        total=len(rows),
    )


def _pose(row: ParkingRow) -> str:
    return "odom" if row.localization == ODOMETRY_ONLY else row.localization


def format_table(result: ParkingResult) -> str:
    lines = [
        f"srl bench parking: {result.seconds:.0f} s per run, in process; last {result.window_seconds:.0f} s window; "
        f"targets: true final <= {FINAL_DISTANCE_M} m, span <= {SPAN_M} m, v sign changes <= {MAX_SIGN_CHANGES}, "
        f"arrival (true d <= {FINAL_DISTANCE_M} m, staying) by {BOUND_FACTOR:g} x (d0 / {TOP_SPEED} m/s + "
        f"|turn| / {TOP_TURN} rad/s) + {BOUND_SLACK:g} s",
        f"  {'method':<6} {'plant':<8} {'agent':<5} {'N':>3} {'pose':<5} {'start':>20} {'true d':>7} {'saw d':>7} "
        f"{'span':>6} {'flips':>5} {'arrive':>6} {'bound':>6} {'|v|med':>6} {'J true':>8} {'J rep':>8} {'sat':>4} "
        f"{'dead':>4}  final rest arrival  result",
    ]
    for r in result.rows:
        checks = (("d", r.final_ok), ("span", r.span_ok), ("flips", r.sign_changes_ok), ("arrival", r.arrival_ok))
        fails = [name for name, ok in checks if not ok]
        arrived = "never" if r.arrival_seconds is None else f"{r.arrival_seconds:.1f}"
        start = f"({r.start[0]:+.2f},{r.start[1]:+.2f},{r.start[2]:+.2f})"
        verdicts = " ".join(
            f"{'PASS' if ok else 'FAIL':<{width}}"
            for ok, width in ((r.final_ok, 5), (r.span_ok and r.sign_changes_ok, 4), (r.arrival_ok, 7))
        )
        lines.append(
            f"  {r.method:<6} {r.plant:<8} {r.agent:<5} {r.horizon:>3} {_pose(r):<5} {start:>20} "
            f"{r.true_final_distance:>7.3f} {r.reported_final_distance:>7.3f} {r.span_m:>6.3f} {r.sign_changes:>5d} "
            f"{arrived:>6} {r.arrival_bound:>6.1f} {r.median_speed:>6.3f} {r.true_cost:>8.3f} {r.reported_cost:>8.3f} "
            f"{r.saturated_commands:>4d} {r.deadband_commands:>4d}  {verdicts}  "
            + ("PASS" if r.passed else "FAIL (" + ", ".join(fails) + ")")
        )
    lines.append(f"  passed {result.passed} of {result.total}")
    unlocalized = sorted({r.plant for r in result.rows if r.localization == ODOMETRY_ONLY and r.plant != "ideal"})
    if unlocalized:
        lines.append(
            f"  pose: odometry only on {', '.join(unlocalized)} (pose odom): the true distance includes the "
            "odometry's drift; --localization amcl|mocap corrects it"
        )
    return "\n".join(lines)


def parse_noise(text: str) -> tuple[float, float]:
    values = [float(c) for c in text.split(",")]
    if len(values) != 2 or not all(math.isfinite(v) and v >= 0 for v in values):
        raise ValueError(f"--localization-noise is SIGMA_XY,SIGMA_THETA (>= 0), got {text!r}")
    return values[0], values[1]


def run_parking_benchmark(args: argparse.Namespace, settings: Settings) -> int:
    try:
        horizons = parse_horizons(args.horizons) if args.horizons else (HORIZON,)
        if len(horizons) != 1:
            raise ValueError(f"parking runs one horizon at a time (--horizons N), got {list(horizons)}")
        plants: list[ParkingPlant] = parse_names(args.plants or PLANTS, PLANT_NAMES, "plant")
        methods = parse_methods(args.methods or METHOD_NAMES)
        agents = list(parse_agents(args.agents or AGENTS))
        starts = parse_starts(args.starts) if args.starts else list(STARTS)
        localizations: list[Localization] = parse_names(
            getattr(args, "localization", None) or "none", LOCALIZATIONS, "localization"
        )
        noise_text = getattr(args, "localization_noise", None)
        noise = parse_noise(noise_text) if noise_text else None
        if not (args.parking_seconds > 0 and math.isfinite(args.parking_seconds)):
            raise ValueError(f"--parking-seconds must be > 0, got {args.parking_seconds}")
    except ValueError as error:
        raise UsageError(f"srl bench parking: {error}") from None
    result = run_parking(
        settings, plants, agents, horizons[0], starts, args.parking_seconds, methods, localizations, noise
    )
    print(format_table(result))
    if args.json:
        print(json.dumps({**result.model_dump(), "run": run_info()}))
    return 0
