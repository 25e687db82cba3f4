"""Typed run summaries: what each service prints as its last stdout line (one JSON object) and
what ``srl run --json`` prints, shared by their producers (the services, :mod:`common.assembly`)
and their consumers (``srl up``, the experiment, the tests).

Every model forbids unknown fields, so a producer that adds or renames a key without saying it
here fails its own tests instead of surprising a consumer. Statistics are :class:`Quantiles`
(NaN where nothing was measured, kept as NaN in the JSON as Python's ``json`` writes it).
"""

from __future__ import annotations

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


class TrueView(_Summary):
    """Where the robot really was, known only where the plant knows the truth (a simulator, the
    emulator): J on the true states with the actions applied, the true start and final state."""

    start_state: list[float]
    final_state: list[float]
    final_distance: float
    accumulated_cost: float


class EpisodeSummary(_Summary):
    """One episode of Algorithm 1 (``srl run --json``; the base of the lockstep actor's).

    ``start_state``, ``final_state``, ``final_distance``, ``accumulated_cost``: the robot's own
    view (what it reported: a robot's odometry); ``truth``: where it really was, or None when
    only the odometry is known (a real robot)."""

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
    plant_model: Literal["ideal", "actuator", "robot"] = Field(
        description="the simulated plant's model (settings plant.model); robot: a robot behind the bridge"
    )
    truth: TrueView | None = Field(description="None: the plant does not know the truth, only odometry is known")
    saturated_commands: int | None = Field(
        description="commands with a wheel beyond its speed limit (None: not known, a real robot)"
    )
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
    start_state: list[float] | None = Field(description="the first state the robot reported (its own start)")
    final_state: list[float] | None = Field(description="the last state the robot reported (its odometry)")
    truth: TrueView | None = Field(description="None: the plant sent no truth (a real robot): only odometry is known")
    saturated_commands: int | None = Field(description="from the plant, if it knows (a simulator)")
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
