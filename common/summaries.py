"""Typed run summaries: what each service prints as its last stdout line (one JSON object) and
what ``srl run --json`` prints, shared by their producers (the services, :mod:`common.assembly`)
and their consumers (``srl up``, the experiment, the tests).

Every model forbids unknown fields, so a producer that adds or renames a key without saying it
here fails its own tests instead of surprising a consumer. Statistics are :class:`Quantiles`
(NaN where nothing was measured, kept as NaN in the JSON as Python's ``json`` writes it).
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter

from common.agents import Agent


class _Summary(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    def to_json_dict(self) -> dict[str, Any]:
        """The JSON-ready dict (floats stay floats, NaN included; None fields are kept)."""
        return self.model_dump()


class Quantiles(_Summary):
    """``common.stats.summarize`` / ``Window.summary``: median and p99 (of the window), max."""

    median: float
    p99: float
    max: float


class EpisodeSummary(_Summary):
    """One episode of Algorithm 1 (``srl run --json``; the base of the lockstep actor's)."""

    agent: Agent
    horizon: int
    steps: int
    episode_seconds: float
    accumulated_cost: float
    start_state: list[float]
    final_state: list[float]
    final_distance: float
    solve_ms: Quantiles
    solver_failures: int
    settings: dict[str, Any]


class LoopStats(_Summary):
    period_ms: Quantiles
    jitter_ms: Quantiles
    missed_deadlines: int
    late_ticks: int


class RealtimeActorSummary(_Summary):
    """The real-time actor (services/actor/realtime.py)."""

    service: Literal["actor"] = "actor"
    mode: Literal["realtime"] = "realtime"
    agent: Agent
    horizon: int
    episode_id: int
    steps: int
    accumulated_cost: float
    start_state: list[float] | None
    final_state: list[float] | None
    weights_version: int
    loop: LoopStats
    solve_ms: Quantiles
    solver_failures: int
    latency_ms: Quantiles
    staleness_steps: Quantiles
    staleness_ms: Quantiles
    stale_state_stops: int
    plant_conflict_stops: int
    plant_sources: list[str]
    transitions_tail: list[list[float]] = Field(description="the newest transitions (k, x, y, alpha, v, omega, r)")
    transition_steps: list[list[int]] = Field(description="the steps published, as [first, last] runs")
    counters: dict[str, float]
    resources: dict[str, Any] | None = None


class LockstepActorSummary(EpisodeSummary):
    """The lockstep actor (services/actor/service.py): the episode plus what crossed the bus."""

    service: Literal["actor"] = "actor"
    mode: Literal["lockstep"] = "lockstep"
    episode_id: int
    weights_version: int
    staleness_steps: Quantiles
    critic_timeouts: int
    trajectory: list[list[float]]
    counters: dict[str, float]
    resources: dict[str, Any] | None = None


ActorSummary = Annotated[RealtimeActorSummary | LockstepActorSummary, Field(discriminator="mode")]
ACTOR_SUMMARY: TypeAdapter[RealtimeActorSummary | LockstepActorSummary] = TypeAdapter(ActorSummary)


class CriticSummary(_Summary):
    """The critic learner (services/critic/service.py)."""

    service: Literal["critic"] = "critic"
    transitions_received: int
    duplicates: int
    too_old: int
    stale_episode: int
    restored: bool
    resume: bool
    checkpoint: str | None
    checkpoint_ms: Quantiles
    seen_steps: dict[str, list[list[int]]]
    replay: dict[str, list[list[float]]]
    weights_published: int
    last_version: int
    fit_ms: Quantiles
    counters: dict[str, float]
    resources: dict[str, Any] | None = None


def format_status_line(c: dict[str, float], elapsed: float, first_version: list[float]) -> str:
    """One line of the actor's 1 Hz status (``srl/<robot>/status/actor``).

    Weight versions are microsecond clock values (they never go back across critic restarts);
    shown is how many versions the actor moved on since this line first saw one, and how many
    steps old the weights it used were (staleness)."""
    pose = ""
    if all(k in c for k in ("x", "y", "alpha")):
        pose = f"  x {c['x']:+.2f} y {c['y']:+.2f} alpha {c['alpha']:+.2f}  distance {math.hypot(c['x'], c['y']):.2f} m"
    version = c.get("weights_version", -1.0)
    if not first_version and version > 0:
        first_version.append(version)
    weights = f"weights +{int(version - first_version[0])}" if first_version else "weights initial"
    return (
        f"{elapsed:5.1f} s: step {int(c.get('steps', 0))}{pose}  J {c.get('accumulated_cost', 0.0):.3f}"
        f"  {weights} (staleness {int(c.get('staleness_steps', 0))})"
        f"  missed deadlines {int(c.get('missed_deadlines', 0))}"
        f"  solver failures {int(c.get('solver_failures', 0))}"
    )
