"""Typed run summaries: what each service prints as its last stdout line (one JSON object) and
what ``srl run --json`` prints, shared by their producers (the services, :mod:`common.config.assembly`)
and their consumers (``srl up``, the experiment, the tests).

Every model forbids unknown fields, so a producer that adds or renames a key without saying it
here fails its own tests instead of surprising a consumer. Statistics are :class:`Quantiles`
(NaN where nothing was measured, kept as NaN in the JSON as Python's ``json`` writes it).

A service is a host of K robots (docs/fleets.md): with K > 1 it prints every robot's own summary
and, for the actor, the fleet's worst cases (:class:`FleetView`, one row per robot: ``srl up
--robots`` and ``srl bench fleet`` build the same view from one actor process per robot, so both
layouts are judged by one definition); with K = 1 it prints its robot's own summary
(:func:`robot_summary`), as a service of one robot always did.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Annotated, Any, Literal, Protocol

import numpy as np
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, TypeAdapter

from common.math.agents import agent_row
from common.math.systems import system_row


def _known_agent(name: str) -> str:
    agent_row(name)  # a row of common/math/agents.py (built in or registered): else one line naming them
    return name


AgentName = Annotated[str, AfterValidator(_known_agent)]


class _Summary(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    def to_json_dict(self) -> dict[str, Any]:
        """The JSON-ready dict (floats stay floats, NaN included; None fields are kept)."""
        return self.model_dump()


class Quantiles(_Summary):
    """``common.math.stats.summarize`` / ``Window.summary``: median and p99 (of the window), max."""

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

    agent: AgentName
    horizon: int
    steps: int
    episode_seconds: float
    accumulated_cost: float
    start_state: list[float]
    final_state: list[float]
    final_distance: float
    solve_ms: Quantiles
    solver_failures: int
    plant_model: str = Field(
        description="the simulated plant's model (settings plant.model); robot: a robot behind the bridge"
    )
    system: str = Field(default="unicycle", description="the sampled system (settings plant.system)")
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
    agent: AgentName
    horizon: int
    episode_id: int
    steps: int
    accumulated_cost: float
    system: str = Field(default="unicycle", description="the sampled system (settings plant.system)")
    start_state: list[float] | None = Field(description="the first state the robot reported (its own start)")
    final_state: list[float] | None = Field(description="the last state the robot reported (its odometry)")
    final_distance: float | None = Field(
        default=None, description="the final state's distance to the goal, in the system's terms (None: no state)"
    )
    truth: TrueView | None = Field(description="None: the plant sent no truth (a real robot): only odometry is known")
    saturated_commands: int | None = Field(description="from the plant, if it knows (a simulator)")
    weights_version: int
    loop: LoopStats
    solve_ms: Quantiles
    solver_failures: int
    latency_ms: Quantiles = Field(
        description="state arrival -> action handed to the transport, minus the solve (an actor host's "
        "outbox may hold the action up to ~2 ms more, services/actor/host.py ACTION_WAIT_S)"
    )
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
    batch_transitions: Quantiles | None = Field(
        default=None, description="transitions taken per batch (one checkpoint each; a fleet's come together)"
    )
    waiting_transitions: Quantiles | None = Field(
        default=None,
        description="transitions waiting when a batch began: the critic's backlog (one that keeps up has "
        "at most about a round of its robots' transitions waiting)",
    )
    fits_coalesced: int = Field(default=0, description="due fits left to a newer transition of the robot in the batch")
    fits_at_rest: int = Field(
        default=0, description="due fits not made: the robot held at rest by the arrival rule (no action uses them)"
    )
    pooled: bool = Field(default=False, description="one learner for every robot (critic.pooled)")
    counters: dict[str, float]
    resources: dict[str, Any] | None = None


POSE_KEYS = ("x", "y", "alpha")  # a robot's pose in an actor's status


def status_distance(c: Mapping[str, float]) -> tuple[float, str] | None:
    """How far an actor's status says its robot is from the goal, and the unit: the robot's pose
    (x, y, alpha) gives hypot(x, y) in "m"; another system's status carries its ``distance`` in the
    system's terms (unit ""). None: the status has neither (no state yet)."""
    if all(k in c for k in POSE_KEYS):
        return math.hypot(c["x"], c["y"]), "m"
    return (c["distance"], "") if "distance" in c else None


def format_status_line(c: dict[str, float], elapsed: float, first_version: list[float]) -> str:
    """One line of the actor's 1 Hz status (``srl/<robot>/status/actor``).

    Weight versions are microsecond clock values (they never go back across critic restarts);
    shown is how many versions the actor moved on since this line first saw one, and how many
    steps old the weights it used were (staleness)."""
    pose, far = "", status_distance(c)
    if far is not None and all(k in c for k in POSE_KEYS):
        pose = f"  x {c['x']:+.2f} y {c['y']:+.2f} alpha {c['alpha']:+.2f}  distance {far[0]:.2f} {far[1]}"
    elif far is not None:
        pose = f"  distance to the goal {far[0]:.4f}"
    version = c.get("weights_version", -1.0)
    if not first_version and version > 0:
        first_version.append(version)
    weights = f"weights +{int(version - first_version[0])}" if first_version else "weights initial"
    return (
        f"{elapsed:5.1f} s: step {int(c.get('steps', 0))}{pose}  J {c.get('accumulated_cost', 0.0):.3f}"
        f"  {weights} (staleness {int(c.get('staleness_steps', 0))})"
        f"  missed deadlines {int(c.get('missed_deadlines', 0))}"
        f"  solver failures {int(c.get('solver_failures', 0))}"
        f"{format_alarms(c)}"
    )


def format_alarms(c: dict[str, float]) -> str:
    """What the status line says only when it happens: two plants alive, the live
    plant's states refused with none accepted for a second (a lockout's pattern), and the
    bridge's refused actions (``plant.*``, from the plant's status) and resyncs."""
    alarms = []
    if c.get("plant_conflict", 0.0):
        alarms.append(f"PLANT CONFLICT ({int(c.get('plant_sources', 0))} plants alive)")
    if c.get("lockout_suspect", 0.0):
        alarms.append("LOCKOUT SUSPECT (the live plant's states refused)")
    refused = int(sum(v for k, v in c.items() if k.startswith("plant.rejected.action")))
    if refused:
        alarms.append(f"bridge refused {refused} actions ({int(c.get('plant.action_resyncs', 0))} resyncs)")
    return "".join(f"  {alarm}" for alarm in alarms)


class PlantSummary(_Summary):
    """A simulated robot (services/plant_sim): what ``srl plant-sim`` of one robot prints, and each
    robot's row of a plant host's summary (:class:`FleetPlantSummary`; one robot's is its row with
    the process's counters, :func:`robot_summary`)."""

    service: Literal["plant"] = "plant"
    mode: Literal["realtime", "lockstep"]
    plant_model: str = Field(description="plant.model (common/math/plant_models.py)")
    start_state: list[float] | None = Field(
        default=None, description="[x m, y m, alpha rad] where it started; None: lockstep (each reset places it)"
    )
    final_state: list[float] = Field(description="[x m, y m, alpha rad] when it ended, as the robot reported it")
    true_final_state: list[float] = Field(description="[x m, y m, alpha rad]: where it truly was")
    saturated_commands: int = Field(description="commands with a wheel beyond its speed limit (actuator model)")
    counters: dict[str, int] = Field(
        description="the robot's actions applied, refused; watchdog, actor-lost stops (one robot: its process's too)"
    )
    resources: dict[str, Any] | None = None


class CmdVelTarget(_Summary):
    """One cmd_vel subscription of the robot the bridge sent to."""

    type: str = Field(description="the ROS 2 message type, e.g. geometry_msgs/msg/Twist")
    key: str = Field(description="its Zenoh key expression")


class BridgeTiming(_Summary):
    odom_to_state_ms: Quantiles
    action_to_cmd_ms: Quantiles
    state_to_cmd_ms: Quantiles


class BridgeSummary(_Summary):
    """The ROS 2 robot bridge (services/robot_bridge/host.py)."""

    service: Literal["robot_bridge"] = "robot_bridge"
    # the wire names as plain strings: common.contracts.ros_wire's Literals would pull rosbags into every
    # importer of the summaries (srl run); the settings already refused any other value
    profile: str = Field(description="rmw_zenoh or ros2dds")
    ros_distro: str = Field(description="humble or jazzy")
    namespace: str
    goal: list[float] = Field(description="the target pose in the odom frame (localized: map) [m, m, rad]")
    cmd_vel: list[CmdVelTarget]
    fallback: bool = Field(description="cmd_vel guessed from the distro, never announced by the robot")
    discovered: list[str]
    attachment_format: str | None = Field(description="rmw_zenoh: compact or legacy, None until seen")
    final_state: list[float] | None
    localization: str = Field(
        default="odometry only",
        description="the state's pose: 'odometry only' or '<pose_source> on <topic> (frame <frame>)'",
    )
    max_abs_command: list[float] = Field(description="[|v| m/s, |omega| rad/s], the largest sent")
    timing: BridgeTiming
    counters: dict[str, int]
    resources: dict[str, Any] | None = None


class EmulatorSummary(_Summary):
    """The emulated TurtleBot3 (services/tb3_emulator)."""

    service: Literal["tb3_emulator"] = "tb3_emulator"
    profile: str = Field(description="rmw_zenoh or ros2dds")
    ros_distro: str = Field(description="humble or jazzy")
    cmd_type: str
    attachment: str | None = Field(description="rmw_zenoh: compact or legacy; None with ros2dds")
    cmd_key: str
    odom_key: str
    localization: str | None = Field(
        default=None, description="the localization it publishes (a bridge.pose_source), None: odometry only"
    )
    model: str = Field(description="the emulated robot's plant.model (common/math/plant_models.py)")
    final_pose: list[float] = Field(description="[x m, y m, theta rad] in the odom frame: the truth")
    final_odometry: list[float] = Field(description="[x m, y m, theta rad]: what its odometry reported")
    saturated_commands: int = Field(description="commands with a wheel beyond its speed limit (actuator model)")
    applied: list[float] = Field(description="[v m/s, omega rad/s] applied when it ended")
    max_abs_applied: list[float]
    cmd_timeouts: int
    counters: dict[str, int]
    missed_ticks: int
    initial_pose: list[float]
    resources: dict[str, Any] | None = None


class RouterSummary(_Summary):
    """The Zenoh router (``srl router``, tools/cli.py)."""

    service: Literal["router"] = "router"
    endpoint: str
    resources: dict[str, Any] | None = None
    close_timed_out: bool = Field(False, description="its session's close outlasted the bound and was left")


# -- hosts of many robots (docs/fleets.md) ---------------------------------------------
PARKED_WITHIN_M = 0.25  # [m] a robot that ends this close to the target parked (the fleet bench's bound)
# As one robot alone parks (docs/turtlebot-parking.md): by its own final state, within this of the
# target, and at rest: the last command its actor sent was exactly zero (the arrival rule's stop).
AT_TARGET_M = 0.05


class RobotRow(_Summary):
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


class FleetView(_Summary):
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
    parked: int = Field(
        description=f"robots ending within {PARKED_WITHIN_M} m of the target (another system's: stabilized)"
    )
    at_target: int = Field(
        default=0, description=f"robots whose own final state is within {AT_TARGET_M} m of the target, at rest"
    )
    worst_own_final_distance_m: float = Field(default=math.nan, description="by the robots' own final states")
    rows: list[RobotRow]


class FleetActorSummary(_Summary):
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
    system = system_row(summary.system)
    own = math.nan if summary.final_state is None else system.distance(np.asarray(summary.final_state, dtype=float))
    distance = own if summary.truth is None else summary.truth.final_distance
    last = summary.transitions_tail[-1] if summary.transitions_tail else None  # k, state, action, r
    n, m = system.state_dim, system.action_dim
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
        # a wheeled robot within PARKED_WITHIN_M of its target; another system stabilized (its row's)
        parked=math.isfinite(distance) and distance <= (PARKED_WITHIN_M if system.wheeled else system.stabilized),
        own_final_distance_m=own,
        at_rest=last is not None and not any(last[1 + n : 1 + n + m]),
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


class FleetPlantSummary(_Summary):
    """What a plant host of many robots prints (``srl plant-sim --robots``): each robot's own summary."""

    service: str = "plant"
    layout: str = "host"
    robots: list[str]
    plant_model: str
    circle_radius_m: float
    per_robot: dict[str, PlantSummary]
    missed_ticks: int
    counters: dict[str, float]
    resources: dict[str, Any] | None = None


class FleetBridgeSummary(_Summary):
    """What ``srl robot-bridge --robots`` prints: every robot's own bridge summary, its namespace
    (= its id) and the endpoint of its robot ('' = srl's router)."""

    service: str = "robot_bridge"
    layout: str = "host"
    robots: list[str]
    endpoints: dict[str, str]
    per_robot: dict[str, BridgeSummary]
    counters: dict[str, float]
    resources: dict[str, Any] | None = None


class HostSummary(Protocol):
    """A host's summary (:class:`FleetActorSummary`, :class:`FleetPlantSummary`,
    :class:`FleetBridgeSummary`): its robots, each one's own summary, the process's counters."""

    @property
    def robots(self) -> list[str]: ...

    @property
    def per_robot(self) -> Mapping[str, _Summary]: ...

    @property
    def counters(self) -> dict[str, float]: ...

    def to_json_dict(self) -> dict[str, Any]: ...


def printed_summary(host: HostSummary, fleet: bool) -> dict[str, Any]:
    """What a host's command prints: started with ``--robots`` (``fleet``), the host's whole summary
    (every robot's row and the process's counters); else its one robot's own summary
    (:func:`robot_summary`), as a service of one robot always printed."""
    return host.to_json_dict() if fleet else robot_summary(host)


def robot_summary(host: HostSummary) -> dict[str, Any]:
    """What a host of ONE robot prints as its service of one robot always did: the robot's own
    summary (its entry of ``host.per_robot``, re-validated as its own type), its counters the
    process's and the robot's. The actor's, the plant's and the bridge's (services/*/host.py)."""
    [robot] = host.robots
    own = host.per_robot[robot]
    values = own.to_json_dict()
    values["counters"] = host.counters | values["counters"]
    return dict(type(own).model_validate(values).to_json_dict())
