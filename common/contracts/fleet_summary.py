"""Typed summaries of a fleet (docs/fleets.md): one row per robot and the fleet's worst cases.

The actor host (services/actor/host.py) prints a :class:`FleetActorSummary`; ``srl up --robots``
and ``srl bench fleet`` read it, and build the same :class:`FleetView` from one actor process
per robot (the baseline layout), so both layouts are judged by one definition.
"""

from __future__ import annotations

import math
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from common.contracts.summaries import BridgeSummary, RealtimeActorSummary

PARKED_WITHIN_M = 0.25  # [m] a robot that ends this close to the target parked (the fleet bench's bound)
# As one robot alone parks (docs/turtlebot-parking.md): by its own final state, within this of the
# target, and at rest: the last command its actor sent was exactly zero (the arrival rule's stop).
AT_TARGET_M = 0.05


class FleetModel(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    def to_json_dict(self) -> dict[str, Any]:
        return self.model_dump()


class RobotRow(FleetModel):
    """One robot of a fleet run, from its actor's summary."""

    robot: str
    steps: int
    missed_deadlines: int
    jitter_p99_ms: float
    latency_p99_ms: float = Field(description="state -> action, without the solve (the loop's own)")
    solve_p99_ms: float
    staleness_p99_steps: float
    staleness_max_steps: float
    solver_failures: int
    stale_state_stops: int
    final_distance_m: float = Field(description="true final distance if the plant knows it, else reported; nan: none")
    parked: bool
    own_final_distance_m: float = Field(
        default=math.nan, description="final distance by the robot's own last state (its odometry); nan: none"
    )
    at_rest: bool = Field(default=False, description="the last command the actor sent was exactly zero")


class FleetView(FleetModel):
    """The fleet: the worst robot of each statistic (nan where no robot measured one)."""

    robots: int
    steps: int
    missed_deadlines: int = Field(description="over all robots")
    jitter_p99_ms: float = Field(description="worst robot")
    latency_p99_ms: float = Field(description="worst robot")
    solve_p99_ms: float = Field(description="worst robot")
    staleness_p99_steps: float = Field(description="worst robot")
    staleness_max_steps: float = Field(description="worst robot")
    solver_failures: int
    parked: int = Field(description=f"robots ending within {PARKED_WITHIN_M} m of the target")
    at_target: int = Field(
        default=0, description=f"robots whose own final state is within {AT_TARGET_M} m of the target, at rest"
    )
    worst_own_final_distance_m: float = Field(default=math.nan, description="by the robots' own final states")
    rows: list[RobotRow]


class FleetActorSummary(FleetModel):
    """What ``srl actor --robots`` prints: every robot's own summary and the fleet's view."""

    service: str = "actor"
    layout: str = "host"
    robots: list[str]
    per_robot: dict[str, RealtimeActorSummary]
    fleet: FleetView
    counters: dict[str, float]
    resources: dict[str, Any] | None = None


def _worst(values: list[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return max(finite) if finite else math.nan


def robot_row(robot: str, summary: RealtimeActorSummary) -> RobotRow:
    if summary.truth is not None:
        distance = summary.truth.final_distance
    elif summary.final_state is not None:
        distance = math.hypot(summary.final_state[0], summary.final_state[1])
    else:
        distance = math.nan
    own = math.hypot(summary.final_state[0], summary.final_state[1]) if summary.final_state is not None else math.nan
    last = summary.transitions_tail[-1] if summary.transitions_tail else None  # k, x, y, alpha, v, omega, r
    return RobotRow(
        robot=robot,
        steps=summary.steps,
        missed_deadlines=summary.loop.missed_deadlines,
        jitter_p99_ms=summary.loop.jitter_ms.p99,
        latency_p99_ms=summary.latency_ms.p99,
        solve_p99_ms=summary.solve_ms.p99,
        staleness_p99_steps=summary.staleness_steps.p99,
        staleness_max_steps=summary.staleness_steps.max,
        solver_failures=summary.solver_failures,
        stale_state_stops=summary.stale_state_stops,
        final_distance_m=distance,
        parked=math.isfinite(distance) and distance <= PARKED_WITHIN_M,
        own_final_distance_m=own,
        at_rest=last is not None and last[4] == 0.0 and last[5] == 0.0,
    )


def fleet_view(per_robot: dict[str, RealtimeActorSummary]) -> FleetView:
    rows = [robot_row(robot, summary) for robot, summary in per_robot.items()]
    return FleetView(
        robots=len(rows),
        steps=sum(r.steps for r in rows),
        missed_deadlines=sum(r.missed_deadlines for r in rows),
        jitter_p99_ms=_worst([r.jitter_p99_ms for r in rows]),
        latency_p99_ms=_worst([r.latency_p99_ms for r in rows]),
        solve_p99_ms=_worst([r.solve_p99_ms for r in rows]),
        staleness_p99_steps=_worst([r.staleness_p99_steps for r in rows]),
        staleness_max_steps=_worst([r.staleness_max_steps for r in rows]),
        solver_failures=sum(r.solver_failures for r in rows),
        parked=sum(r.parked for r in rows),
        at_target=sum(r.at_rest and r.own_final_distance_m <= AT_TARGET_M for r in rows),
        worst_own_final_distance_m=_worst([r.own_final_distance_m for r in rows]),
        rows=rows,
    )


class PlantRow(FleetModel):
    """One robot of a plant host."""

    start_state: list[float]
    final_state: list[float] = Field(description="[x m, y m, alpha rad] as the robot reported it")
    true_final_state: list[float]
    actions_applied: int
    actions_refused: int
    watchdog_stops: int
    actor_lost_stops: int


class FleetPlantSummary(FleetModel):
    """What ``srl plant-sim --robots`` prints."""

    service: str = "plant"
    layout: str = "host"
    robots: list[str]
    plant_model: str
    circle_radius_m: float
    per_robot: dict[str, PlantRow]
    missed_ticks: int
    counters: dict[str, float]
    resources: dict[str, Any] | None = None


class FleetBridgeSummary(FleetModel):
    """What ``srl robot-bridge --robots`` prints: every robot's own bridge summary, its namespace
    (= its id) and the endpoint of its robot ('' = srl's router)."""

    service: str = "robot_bridge"
    layout: str = "host"
    robots: list[str]
    endpoints: dict[str, str]
    per_robot: dict[str, BridgeSummary]
    counters: dict[str, float]
    resources: dict[str, Any] | None = None


def robot_summary(robots: list[str], per_robot: dict[str, Any], counters: dict[str, float]) -> dict[str, Any]:
    """What a host of ONE robot prints as its service of one robot always did: the robot's own
    summary (an entry of ``per_robot``, re-validated as its own type), its counters the process's
    ``counters`` and the robot's. The actor's and the bridge's (services/*/host.py)."""
    [robot] = robots
    own = per_robot[robot]
    values = own.to_json_dict()
    values["counters"] = counters | values["counters"]
    return dict(type(own).model_validate(values).to_json_dict())
