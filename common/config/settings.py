"""Settings: every constant in ONE TOML file (``common/config/srl.toml``), overridable.

Precedence, highest first: explicit overrides (CLI flags) > ``SRL_<SECTION>__<NAME>``
environment variables > a user TOML file (``--config`` or ``SRL_CONFIG``) > the packaged
``srl.toml``. The models declare no defaults of their own, so the packaged file is the single
source of truth. Settings are built in ``main()`` and passed down; nothing is created at import.
"""

from __future__ import annotations

import math
import os
import re
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, SecretStr, field_validator, model_validator
from pydantic_settings import (
    BaseSettings,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    TomlConfigSettingsSource,
)

from common.contracts.pose_sources import pose_source_names, pose_sources_text
from common.contracts.wire import Wire, wire
from common.math.agents import Agent, agent_names, agents_text
from common.math.dynamics import heading_away_from_target
from common.math.features import quadratic_weights_for_diag
from common.math.physics import PhysicsParams
from common.math.plant_models import PLANT_MODELS, plant_model_row, plant_models_text
from common.math.systems import SYSTEMS, System, system_row, systems_text
from common.math.turtlebot import TurtleBotParams

DEFAULT_CONFIG = Path(__file__).with_name("srl.toml")
# The settings whose values are the rows of a table, each its one definition (a row registered
# by a plugin, common/process/plugins.py, is a value too): what the validators accept, what the
# command lines offer (common/config/arguments.py) and what the docs list.
TABLE_SETTINGS: dict[tuple[str, str], tuple[str, Callable[[], tuple[str, ...]]]] = {
    ("actor", "agent"): ("agent", agent_names),  # common/math/agents.py AGENT_ROWS
    ("plant", "model"): ("plant model", lambda: tuple(PLANT_MODELS)),  # common/math/plant_models.py
    ("bridge", "pose_source"): ("pose source", pose_source_names),  # common/contracts/pose_sources.py
    ("plant", "system"): ("system", lambda: tuple(SYSTEMS)),  # common/math/systems.py
}


def table_value(section: str, name: str, value: str) -> str:
    """``value`` if it names a row of the table behind ``section.name``; else ValueError (one line
    naming the rows)."""
    what, names = TABLE_SETTINGS[(section, name)]
    known = names()
    if value not in known:
        raise ValueError(f"unknown {what} {value!r} ({', '.join(known)})")
    return value


# The actor's horizon bound. The JIT build (code generation + gcc -O3) grows with N: N = 100
# builds in ~35 s with a 0.6 GB peak (gcc included, 2 cores); N = 10000 runs gcc past 8.9 GB of
# memory (docs/benchmarks/). The paper uses N = 6 and 12.
MAX_HORIZON = 100
# Starts beyond this distance [m] from the target (per coordinate) are outside any room the
# robot could park in: warned. Beyond the state schema's bound (common/contracts/messages.py) refused.
WORKSPACE_HALF_WIDTH = 10.0
MAX_START = 1e4
# The methods, one row each: what a method sets on top of the settings (with_method applies it;
# the command lines' --method choices are the rows). paper: the paper's method exactly as the
# paper states it, the [actor] settings a running robot adds (the arrival rule, the wheel-speed
# box, the convexified critics) switched off (srl experiment's default); robot: the settings as
# configured (srl run, srl up).
PAPER_METHOD: dict[str, dict[str, Any]] = {"actor": {"arrival": False, "wheel_speed_max": 0.0, "convex_critics": False}}
METHODS: dict[str, dict[str, dict[str, Any]]] = {"paper": PAPER_METHOD, "robot": {}}
# Endpoints as Zenoh spells them: <protocol>/<address>, e.g. tcp/127.0.0.1:7447, tls/host:7447.
_ENDPOINT = re.compile(
    r"^(tcp|udp|tls|quic|ws)/(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.\-]+):[0-9]{1,5}([?#].*)?$"
    r"|^unixsock-stream/\S+$"
)


def check_endpoint(value: str, name: str, listen: bool = False) -> str:
    """A Zenoh endpoint, refused here with a readable message (Zenoh's own is a Rust ``Json5Err``).
    ``listen``: port 0 (any free port, as the experiment's peers listen) is allowed."""
    match = _ENDPOINT.match(value)
    lowest = 0 if listen else 1
    if not match or (match.group(1) and not lowest <= int(value.rsplit(":", 1)[1].split("?")[0].split("#")[0]) < 65536):
        raise ValueError(
            f"{name} must be a Zenoh endpoint <protocol>/<host>:<port>, e.g. tcp/127.0.0.1:7447 "
            f"(protocols tcp, udp, tls, quic, ws; or unixsock-stream/<path>), got {value!r}"
        )
    return value


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def _finite(value: float, name: str) -> float:
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value}")
    return value


class PlantSettings(_Section):
    sampling_time: float = Field(gt=0, description="delta [s]")
    v_max: float = Field(gt=0, description="[m/s]")
    omega_max: float = Field(gt=0, description="[rad/s]")
    model: str = Field(description=plant_models_text())
    system: str = Field(default="unicycle", description=systems_text())
    realtime_priority: int = Field(
        default=10, ge=0, le=99, description="the state loop under SCHED_FIFO at this priority, if allowed (0 = off)"
    )

    @field_validator("model")
    @classmethod
    def _is_a_plant_model(cls, name: str) -> str:
        return table_value("plant", "model", name)

    @field_validator("system")
    @classmethod
    def _is_a_system(cls, name: str) -> str:
        return table_value("plant", "system", name)

    @field_validator("sampling_time", "v_max", "omega_max")
    @classmethod
    def _is_finite(cls, v: float) -> float:
        return _finite(v, "plant constant")


class ActuatorSettings(_Section):
    """The TurtleBot3 Burger actuator and odometry model (common/math/turtlebot.py, docs/turtlebot-models.md)."""

    wheel_radius: float = Field(gt=0, description="r [m]")
    wheel_separation: float = Field(gt=0, description="b [m]")
    wheel_speed_max: float = Field(ge=0, description="[rad/s] per wheel (0: no saturation)")
    lag: float = Field(ge=0, le=10, description="[s] first-order time constant of each wheel")
    gain: float = Field(gt=0, le=10, description="steady-state wheel speed / command")
    deadband: float = Field(ge=0, description="[rad/s] a wheel at rest does not start below it")
    slip: float = Field(ge=0, le=0.95, description="mean slip of each wheel's ground speed")
    slip_std: float = Field(ge=0, le=1, description="its standard deviation, per command")
    quantize: bool = Field(description="the OpenCR command path int32(v * 100) * 0.01f")
    imu_heading: bool = Field(description="odometry heading from the IMU (ROBOTIS's use_imu)")
    substep: float = Field(gt=0, le=0.05, description="[s] internal integration step")
    seed: int = Field(ge=0)


class PhysicsSettings(_Section):
    """The MuJoCo TurtleBot3 Burger of plant.model = "physics" (common/math/physics.py, docs/turtlebot-models.md)."""

    timestep: float = Field(gt=0, le=0.01, description="[s] MuJoCo's integration step")
    tire_friction: float = Field(gt=0, le=10, description="sliding friction of the tyres on the floor")
    caster_friction: float = Field(gt=0, le=10, description="sliding friction of the caster's ball on the floor")
    torque_max: float = Field(gt=0, le=100, description="[N m] each wheel motor's torque at 100 % PWM (stall torque)")
    motor_friction: float = Field(ge=0, le=10, description="[N m] each wheel joint's breakaway (dry) friction")
    odometry_period: float = Field(gt=0, le=0.1, description="[s] how often the encoders are integrated")
    encoder_ticks: int = Field(ge=0, description="encoder ticks per wheel revolution (0: exact)")
    velocity_p_gain: int = Field(ge=0, le=16383, description="the XL430's Velocity P Gain(78), control table units")
    velocity_i_gain: int = Field(ge=0, le=16383, description="the XL430's Velocity I Gain(76), control table units")
    velocity_loop_period: float = Field(
        gt=0, le=0.01, description="[s] the XL430's control period, the time base of its I gain"
    )
    caster_socket_friction: float = Field(ge=0, le=1, description="[N m] the caster ball's dry friction in its socket")


class CostSettings(_Section):
    r_diag: tuple[float, ...] = Field(description="diag(R) over (s, u); [] = the system's own")

    @field_validator("r_diag")
    @classmethod
    def _psd(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if not all(math.isfinite(c) and c >= 0 for c in v):
            raise ValueError(f"r_diag must be finite and >= 0 (R positive semi-definite), got {v}")
        return v


class CriticSettings(_Section):
    discount_rate: float = Field(ge=0, description="gamma [1/s]")
    replay_size: int = Field(ge=2, description="M")
    ridge: float = Field(ge=0, description="lambda")
    weight_bounds: tuple[()] | tuple[float, float] = Field(description="[] or [low, high]")
    q_init: Literal["stage_cost", "discounted_stage_cost"] | list[float]
    v_init: Literal["stage_cost", "discounted_stage_cost"] | list[float]
    update_every: int = Field(ge=1)
    checkpoint: str = Field(description="checkpoint file ({robot}, {agent}, {horizon}); empty = none")
    resume: bool = Field(default=False, description="restore the checkpoint of an earlier run at start")
    checkpoint_period: float = Field(
        default=1.0, ge=0, le=3600, description="[s] at most one checkpoint write this often; 0 = after every batch"
    )
    coalesce_fits: bool = Field(
        default=False, description="fit each robot once per batch, on its newest transition (a fleet's critic)"
    )
    batch_window: float = Field(
        default=0.02,
        ge=0,
        le=1.0,
        allow_inf_nan=False,
        description="[s] a batch collects transitions this long after its first (until every robot is in)",
    )
    robots: str = Field(default="*", description="whose transitions to learn from: * = every robot, or one id")
    pooled: bool = Field(default=False, description="one learner trained on every robot's transitions (a fleet's)")
    session_niceness: int = Field(
        default=-5,
        ge=-20,
        le=19,
        description="its session's (autogroup's) niceness where it leads it; < 0 needs CAP_SYS_NICE; 0 = leave it",
    )

    @field_validator("robots")
    @classmethod
    def _robots(cls, v: str) -> str:
        if v != "*" and not re.fullmatch(r"[A-Za-z0-9_\-]{1,64}", v):
            raise ValueError(
                f"critic.robots must be '*' (every robot) or one robot id "
                f"(1-64 characters of A-Z a-z 0-9 _ -), got {v!r}"
            )
        return v

    @model_validator(mode="after")
    def _check(self) -> CriticSettings:
        if self.weight_bounds and not self.weight_bounds[0] < self.weight_bounds[1]:
            raise ValueError(f"weight_bounds must be [low, high] with low < high, got {self.weight_bounds}")
        for name, n in (("q_init", 15), ("v_init", 6)):
            value = getattr(self, name)
            if isinstance(value, list) and (len(value) != n or not all(math.isfinite(x) for x in value)):
                raise ValueError(f"{name} must be 'stage_cost' or {n} finite numbers, got {value}")
        return self

    @property
    def bounds(self) -> tuple[float, float] | None:
        return (self.weight_bounds[0], self.weight_bounds[1]) if self.weight_bounds else None


class ActorSettings(_Section):
    agent: Agent = Field(description=agents_text())

    @field_validator("agent")
    @classmethod
    def _is_an_agent(cls, name: str) -> str:
        return table_value("actor", "agent", name)

    horizon: int = Field(description="N, 2 .. MAX_HORIZON")
    predictor: Literal["euler", "rk4"]
    solver: Literal["fatrop", "ipopt"]
    jit: bool
    jit_cache: str = Field(
        default="auto", min_length=1, description="compiled problems kept: auto (~/.cache/srl/jit), off, or a directory"
    )
    realtime_priority: int = Field(
        default=10, ge=0, le=99, description="the tick thread under SCHED_FIFO at this priority, if allowed (0 = off)"
    )
    host_tick_group: int = Field(
        ge=1,
        le=1000,
        description="an actor host serves its robots' ticks in groups of this many, back to back (1 = each alone)",
    )
    host_cpu_budget: float = Field(
        default=0.3,
        gt=0,
        le=1,
        allow_inf_nan=False,
        description="share of each period an actor host's full solves may take; beyond, it hurries",
    )
    max_iter: int = Field(ge=1)
    tolerance: float = Field(gt=0)
    mu_init: float = Field(gt=0)
    bound_push: float = Field(gt=0, le=0.5)
    # what a running robot needs (the paper's method: arrival off, wheel_speed_max 0, PAPER_METHOD)
    arrival: bool = Field(description="the arrival rule: command zero inside the tolerances")
    arrival_position_tolerance: float = Field(gt=0, le=1.0, allow_inf_nan=False, description="[m]")
    arrival_heading_tolerance: float = Field(gt=0, le=math.pi, allow_inf_nan=False, description="[rad]")
    arrival_hysteresis: float = Field(ge=1.0, le=10.0, allow_inf_nan=False, description="outer = this x inner")
    wheel_breakaway_speed: float = Field(
        ge=0,
        le=10,
        allow_inf_nan=False,
        description="[rad/s] with arrival: a command whose wheels are all below this is zero inside the outer "
        "tolerances, else raised to it (common/math/arrival.py); 0 = off",
    )
    command_resolution: float = Field(
        ge=0,
        le=0.1,
        allow_inf_nan=False,
        description="[m/s, rad/s] with arrival: the robot truncates each cmd_vel component to a multiple of this; "
        "the deadband rule judges a command as applied (common/math/arrival.py); 0 = none",
    )
    turn_first_threshold: float = Field(
        ge=0,
        le=math.pi / 2,
        allow_inf_nan=False,
        description="[rad] with arrival: a goal whose line of travel (ahead or back) starts more than this off the "
        "target's bearing is turned to it in place first (common/math/arrival.py TurnFirst); 0 = off",
    )
    docking_radius: float = Field(
        ge=0,
        le=1.0,
        allow_inf_nan=False,
        description="[m] with arrival: within this of the target an approach that shuffles is finished by rotate, "
        "drive straight, rotate (common/math/arrival.py Docking); 0 = off",
    )
    docking_reversals: int = Field(
        ge=1, le=100, description="docking: this many reversals of the actor's v within the radius make a shuffle"
    )
    wheel_speed_max: float = Field(ge=0, allow_inf_nan=False, description="[rad/s] wheel box; 0 = off")
    wheel_radius: float = Field(gt=0, allow_inf_nan=False, description="[m]")
    wheel_separation: float = Field(gt=0, allow_inf_nan=False, description="[m]")
    convex_critics: bool = Field(description="the actor uses the nearest PSD quadratic to each learned critic")
    multistart: bool = Field(
        description="the actor's argmin: warm polish, a search over alternative plans and a vertex search each tick, "
        "the solver only where the Newton iterations fall short (false: the solver from the warm start)"
    )
    multistart_starts: int = Field(ge=1, le=32, description="alternative plans a robot keeps and descends every tick")
    multistart_iterations: int = Field(ge=1, le=1000, description="gradient iterations per alternative and tick")
    multistart_margin: float = Field(
        ge=0, allow_inf_nan=False, description="an alternative within this share of the warm answer is polished too"
    )
    multistart_flips: int = Field(
        ge=0, le=10, description="vertex-search sweeps after the polish: each decision entry to either bound (0 = off)"
    )
    newton_iterations: int = Field(
        ge=1,
        le=50,
        description="the polish: at most this many projected-Newton iterations, the solver only where they end "
        "short of stationary",
    )

    @field_validator("horizon")
    @classmethod
    def _bounded_horizon(cls, v: int) -> int:
        if not 2 <= v <= MAX_HORIZON:
            raise ValueError(
                f"the horizon N must be 2 .. {MAX_HORIZON} (N - 1 >= 1 actions; above {MAX_HORIZON} "
                f"the compiled problem outgrows the machine: gcc needs gigabytes), got {v}"
            )
        return v


class EpisodeSettings(_Section):
    duration: float = Field(gt=0, description="[s]")
    start: tuple[float, ...] = Field(description="the start state; [] = the system's own")

    @field_validator("start")
    @classmethod
    def _finite_start(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if not all(math.isfinite(c) for c in v):
            raise ValueError(f"start must be finite numbers, got {v}")
        return v


class TransportSettings(_Section):
    robot: str = Field(pattern=r"^[A-Za-z0-9_\-]{1,64}$")
    mode: Literal["client", "peer"]
    router: str = Field(description="endpoint of the Zenoh router, e.g. tcp/127.0.0.1:7447")

    @field_validator("router")
    @classmethod
    def _router_endpoint(cls, v: str) -> str:
        return check_endpoint(v, "transport.router")

    @field_validator("connect")
    @classmethod
    def _connect_endpoints(cls, v: list[str]) -> list[str]:
        return [check_endpoint(e, "every transport.connect entry") for e in v]

    @field_validator("listen")
    @classmethod
    def _listen_endpoints(cls, v: list[str]) -> list[str]:
        return [check_endpoint(e, "every transport.listen entry", listen=True) for e in v]

    connect: list[str]
    listen: list[str] = Field(description="endpoints a client/peer session listens on")
    multicast_scouting: bool
    query_timeout: float = Field(gt=0)
    critic_timeout: float = Field(gt=0)
    status_period: float = Field(gt=0)
    state_rate: float = Field(gt=0, le=1000)
    state_sync: bool = Field(
        description="a plant host publishes a driven robot's state only at the state ticks just before its actor's tick"
    )
    express: bool = Field(description="every put sent at once (true) or batched by Zenoh with others due")
    callback_threads: bool = Field(
        description="each subscription's handler in a Python thread of its own (true) or on Zenoh's network thread"
    )
    action_timeout_steps: int = Field(ge=2)
    transition_cache: int = Field(ge=0, description="transitions kept for recovery by a late critic")
    max_message_bytes: int = Field(ge=65_536, le=2**30, description="Zenoh drops bigger messages on arrival")
    shared_memory: bool = Field(
        description="Zenoh's shared memory between processes of one host: a large put skips max_message_bytes"
    )
    # Zenoh authentication and access control (common/net/security.py, docs/security.md)
    secure: bool = Field(description="router: require user/password, enforce role rules; others: log in")
    user: str = Field(description="this process's Zenoh user = its role (actor, critic, plant, monitor)")
    password: SecretStr = Field(description="usually from SRL_TRANSPORT__PASSWORD; never commit one")
    password_file: str = Field(description="file whose first line is the user's password")
    users_file: str = Field(description="router: the 'user:password' dictionary file")
    # TLS on tls/ endpoints (common/net/security.py tls_entries, common/net/certs.py, docs/security.md)
    tls_ca: str = Field(description="PEM file of the CA that signs the router's and the clients' certificates")
    tls_cert: str = Field(description="PEM certificate of this process (router: its server certificate)")
    tls_key: str = Field(description="PEM private key of tls_cert (mode 600)")
    tls_mtls: bool = Field(description="mutual TLS: the router accepts only clients with a certificate from tls_ca")
    allow_insecure_network: bool = Field(
        description="let a router listen off loopback without secure + TLS: only inside a private container network"
    )
    plant_queries: bool = Field(description="secure router: allow plant/step and plant/reset (lockstep runs only)")
    acl_robots: str = Field(
        pattern=r"^([A-Za-z0-9_\-]{1,64}(,[A-Za-z0-9_\-]{1,64})*)?$",
        description="secure router: the robots the role rules grant, comma-separated ('' = transport.robot)",
    )

    @property
    def rule_robots(self) -> list[str]:
        """The robots a secure router's role rules grant (:attr:`acl_robots`, else :attr:`robot`)."""
        return self.acl_robots.split(",") if self.acl_robots else [self.robot]

    @model_validator(mode="after")
    def _secure_needs_client_mode(self) -> TransportSettings:
        # the router enforces the rules; peers could also talk to each other directly, unchecked
        if self.secure and self.mode != "client":
            raise ValueError("transport.secure needs transport.mode = 'client' (the router enforces the rules)")
        return self


_ROS_NAME = r"[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*"


class BridgeSettings(_Section):
    """The robot bridge's view of the ROS 2 robot (see services/robot_bridge)."""

    profile: Literal["rmw_zenoh", "ros2dds"] = Field(description="wire profile of the robot's Zenoh side")
    ros_distro: Literal["humble", "jazzy"]
    domain_id: int = Field(ge=0, le=232, description="ROS_DOMAIN_ID of the robot (rmw_zenoh keys)")
    namespace: str = Field(pattern=rf"^(|{_ROS_NAME})$", description="ROS namespace, no leading slash")
    cmd_type: Literal["auto", "twist", "twist_stamped"]
    odom_topic: str = Field(pattern=rf"^{_ROS_NAME}$")
    cmd_vel_topic: str = Field(pattern=rf"^{_ROS_NAME}$")
    goal: tuple[float, float, float] = Field(
        description="goal pose (x [m], y [m], theta [rad]) in the odom frame (localized: in the map frame)"
    )
    watchdog_timeout_steps: int = Field(ge=1, description="zero velocity after this many delta without action")
    robot_endpoint: str = Field(description="'' = the robot is on srl's router; else its Zenoh endpoint")
    discovery_timeout: float = Field(gt=0, description="[s] auto cmd_type: wait this long for the robot's tokens")
    # The state's pose (services/robot_bridge/bridge.py, docs/turtlebot-localization.md)
    pose_source: str = Field(description="the state's pose: " + pose_sources_text())
    pose_topic: str = Field(
        pattern=rf"^(|{_ROS_NAME})$",
        description="the localization topic; '' = the source's usual one "
        "(tf, amcl_pose, odometry/filtered, mocap/pose)",
    )
    pose_timeout: float = Field(
        gt=0, description="[s] a streaming localization (tf, odometry, pose_stamped) older than this is stale"
    )
    pose_stale_distance: float = Field(
        gt=0, description="[m] any localization is stale once odometry has moved this far since its last fix"
    )
    pose_stale_angle: float = Field(
        gt=0, description="[rad] any localization is stale once odometry has turned this far since its last fix"
    )
    pose_blend_time: float = Field(ge=0, description="[s] a new localization correction is blended in over this")
    # The robot's own Zenoh router (rmw_zenohd): its login and TLS (services/robot_bridge/robot_router.py,
    # docs/security.md "The robot's own router")
    robot_user: str = Field(description="user the bridge logs in as at the robot's router ('' = no login)")
    robot_password_file: str = Field(description="file whose first line is robot_user's password (mode 600)")
    robot_tls_ca: str = Field(description="tls/ robot_endpoint: PEM CA certificate that signed the robot router's")
    robot_tls_cert: str = Field(description="tls/ robot_endpoint: the bridge's PEM certificate (mutual TLS)")
    robot_tls_key: str = Field(description="tls/ robot_endpoint: PEM private key of robot_tls_cert (mode 600)")
    robot_connect_timeout: float = Field(
        gt=0, description="[s] wait this long for the robot's router to accept the bridge (a robot boots slowly)"
    )

    @field_validator("pose_source")
    @classmethod
    def _is_a_pose_source(cls, name: str) -> str:
        return table_value("bridge", "pose_source", name)

    @field_validator("namespace", mode="before")
    @classmethod
    def _strip_slashes(cls, v: object) -> object:
        return v.strip("/") if isinstance(v, str) else v

    @field_validator(
        "goal",
        "discovery_timeout",
        "robot_connect_timeout",
        "pose_timeout",
        "pose_stale_distance",
        "pose_stale_angle",
        "pose_blend_time",
    )
    @classmethod
    def _finite_values(cls, v: object) -> object:
        values = v if isinstance(v, tuple) else (v,)
        if not all(math.isfinite(c) for c in values):
            raise ValueError(f"must be finite, got {v}")
        return v


def _as_dict(section: Any) -> dict[str, Any] | None:
    """A settings section as a dict: a dict as it is, a model dumped, anything else None."""
    if isinstance(section, BaseModel):
        return section.model_dump()
    return section if isinstance(section, dict) else None


class Settings(BaseSettings):
    """All constants of a run. Build with :meth:`load`."""

    model_config = SettingsConfigDict(env_prefix="SRL_", env_nested_delimiter="__", extra="forbid", frozen=True)

    plant: PlantSettings
    actuator: ActuatorSettings
    physics: PhysicsSettings
    cost: CostSettings
    critic: CriticSettings
    actor: ActorSettings
    episode: EpisodeSettings
    transport: TransportSettings
    bridge: BridgeSettings

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        # First wins, and pydantic-settings deep-merges the layers: flags > env > TOML files.
        toml = TomlConfigSettingsSource(settings_cls, deep_merge=True)
        return (init_settings, env_settings, toml)

    @classmethod
    def load(cls, config_file: str | Path | None = None, **overrides: Any) -> Settings:
        """Packaged ``srl.toml`` <- user file <- ``SRL_...`` environment <- ``overrides``.

        ``overrides`` are nested dicts by section, e.g. ``actor={"horizon": 6}``.
        """
        files = [DEFAULT_CONFIG]
        user_file = config_file or os.environ.get("SRL_CONFIG")
        if user_file:
            path = Path(user_file)
            if not path.is_file():
                raise FileNotFoundError(f"config file {path} does not exist")
            files.append(path)
        for path in files:  # a syntax error names its file (tomllib alone does not)
            try:
                tomllib.loads(path.read_text())
            except tomllib.TOMLDecodeError as error:
                raise ValueError(f"config file {path}: TOML syntax error: {error}") from error

        class _FromFiles(cls):  # type: ignore[valid-type,misc]
            model_config = SettingsConfigDict(toml_file=files)

        return cls.model_validate(_FromFiles(**overrides).model_dump())

    @model_validator(mode="before")
    @classmethod
    def _systems_horizon(cls, data: Any) -> Any:
        """``actor.horizon = 0``: the system's own N (its row's ``horizon``; the robot's 12), so every
        reader of the settings sees the N a run takes. A section may come as a dict (the files, the
        flags) or as its model (a caller's ``Settings(actor=ActorSettings(...))``); an unknown
        system is left to its field's check."""
        if not isinstance(data, dict):
            return data
        actor, plant = (_as_dict(data.get(name)) for name in ("actor", "plant"))
        if actor is None or str(actor.get("horizon")) != "0":
            return data
        row = SYSTEMS.get(str((plant or {}).get("system", "unicycle")))
        return data if row is None else {**data, "actor": {**actor, "horizon": row.horizon}}

    @model_validator(mode="after")
    def _fits_the_system(self) -> Settings:
        """The settings a system's row sizes -- the stage cost's weights, the start, the simulated
        model -- fit the system (common/math/systems.py)."""
        system, name = system_row(self.plant.system), self.plant.system
        n, m = system.state_dim, system.action_dim
        r_diag, start = self.cost.r_diag, self.episode.start
        if r_diag and len(r_diag) != n + m:
            raise ValueError(
                f"cost.r_diag: {n + m} numbers over {name}'s (s, u) = ({', '.join(system.states + system.actions)}), "
                f"or [] for its own; got {len(r_diag)}"
            )
        if start and system.wheeled:
            start_state(start)  # X,Y or X,Y,ALPHA
            if max(abs(start[0]), abs(start[1])) > MAX_START:
                raise ValueError(
                    f"episode.start ({start[0]:g}, {start[1]:g}) m is beyond the {MAX_START:g} m every state "
                    "message allows (common/contracts/messages.py): the paper's starts are within 2 m of the target"
                )
        elif start and len(start) != n:
            raise ValueError(
                f"episode.start: {n} numbers, {name}'s state ({', '.join(system.states)}); got {len(start)}"
            )
        if not system.wheeled and not plant_model_row(self.plant.model).exact:
            raise ValueError(
                f"plant.model {self.plant.model!r} simulates a TurtleBot3, a wheeled robot; system {name!r} "
                "is simulated by its own model: plant.model = ideal"
            )
        return self

    # -- derived quantities, in the paper's terms ------------------------------------
    @property
    def system(self) -> System:
        """The sampled system's row (``plant.system``, common/math/systems.py)."""
        return system_row(self.plant.system)

    @property
    def wire(self) -> Wire:
        """The messages and topics of the system (common/contracts/wire.py): the robot's are srl's own."""
        return wire(self.plant.system)

    def robot_only(self, what: str, *uses: tuple[str, bool]) -> Settings:
        """These settings, for ``what`` that serves the robot only (the services' wire, a recording,
        the experiment: the unicycle's pose and (v, omega)); ValueError (one line) for another system.
        ``uses``: (flag, used) pairs, of which only the used ones serve the robot only: refused,
        named after ``what``, when one is used (none given: ``what`` itself is)."""
        flags = [flag for flag, used in uses if used]
        if self.system.wheeled or (uses and not flags):
            return self
        name = self.plant.system
        raise ValueError(
            f"{' '.join([what, *flags])}: carries the robot's pose and (v, omega); system {name} runs in process "
            f"(srl run --system {name}) and as services (srl up --system {name})"
        )

    @property
    def r_diag(self) -> tuple[float, ...]:
        """diag(R) of the stage cost over (s, u): ``cost.r_diag``, or the system's own ([])."""
        return self.cost.r_diag or self.system.cost_diag

    @property
    def action_max(self) -> tuple[float, ...]:
        """The box of the held actions: a wheeled robot's ``(plant.v_max, plant.omega_max)``, another
        system's its row's."""
        system = self.system
        return (self.plant.v_max, self.plant.omega_max) if system.wheeled else system.action_max

    @property
    def discount(self) -> float:
        """beta = exp(-gamma delta)."""
        return math.exp(-self.critic.discount_rate * self.plant.sampling_time)

    @property
    def steps(self) -> int:
        return max(1, round(self.episode.duration / self.plant.sampling_time))

    def start_state(self) -> np.ndarray:
        """``episode.start`` (or the system's own, []) as the state: a wheeled robot's X,Y heads away
        from the target (:func:`start_state`)."""
        system = self.system
        start = self.episode.start or system.start
        return start_state(start) if system.wheeled else np.array(start, dtype=float)

    def _initial_scale(self, kind: str) -> float:
        """``stage_cost``: delta (one interval's cost); ``discounted_stage_cost``: delta / (1 - beta),
        the discounted cost of holding (s, u) for ever, the scale of the TD targets."""
        if kind == "discounted_stage_cost":
            if self.discount >= 1.0:
                raise ValueError("critic init 'discounted_stage_cost' needs discount_rate > 0 (beta < 1)")
            return self.plant.sampling_time / (1.0 - self.discount)
        return self.plant.sampling_time

    def initial_q_weights(self) -> np.ndarray:
        if isinstance(self.critic.q_init, str):
            return self._initial_scale(self.critic.q_init) * quadratic_weights_for_diag(self.r_diag)
        return np.array(self.critic.q_init, dtype=float)

    def initial_v_weights(self) -> np.ndarray:
        if isinstance(self.critic.v_init, str):
            return self._initial_scale(self.critic.v_init) * quadratic_weights_for_diag(
                self.r_diag[: self.system.state_dim]
            )
        return np.array(self.critic.v_init, dtype=float)

    def turtlebot_params(self) -> TurtleBotParams:
        """The TurtleBot3 model's constants: ``[actuator]``, the firmware limits of ``[plant]``."""
        a, p = self.actuator, self.plant
        return TurtleBotParams(
            v_max=p.v_max,
            omega_max=p.omega_max,
            wheel_radius=a.wheel_radius,
            wheel_separation=a.wheel_separation,
            wheel_speed_max=a.wheel_speed_max,
            lag=a.lag,
            gain=a.gain,
            deadband=a.deadband,
            slip=a.slip,
            slip_std=a.slip_std,
            quantize=a.quantize,
            imu_heading=a.imu_heading,
            substep=a.substep,
            seed=a.seed,
        )

    def physics_params(self) -> PhysicsParams:
        """The MuJoCo plant's own constants: ``[physics]``."""
        return PhysicsParams(**self.physics.model_dump())

    def as_dict(self) -> dict[str, Any]:
        """Every constant used, plus the derived discount, for printing with each result: the stage
        cost's weights as used (``cost.r_diag`` [] is the system's own)."""
        data = self.model_dump(mode="json")
        data["cost"]["r_diag"] = list(self.r_diag)
        data["derived"] = {"discount_beta": self.discount, "steps": self.steps}
        return data


def with_method(settings: Settings, method: str, **actor: Any) -> Settings:
    """``settings`` with ``method``'s row of :data:`METHODS` on its sections, then ``actor`` on its
    ``[actor]``. Copied, not validated again: a caller whose values come from a user validates
    (``Settings.model_validate(result.model_dump())``). Raises ValueError for an unknown method."""
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    update: dict[str, Any] = {
        name: getattr(settings, name).model_copy(update=values) for name, values in METHODS[method].items()
    }
    update["actor"] = update.get("actor", settings.actor).model_copy(update=actor)
    return settings.model_copy(update=update)


def start_state(start: tuple[float, ...] | list[float]) -> np.ndarray:
    """``(x, y)`` -> heading turned away from the target, as in the paper; ``(x, y, alpha)`` as is."""
    values = [float(c) for c in start]
    if len(values) not in (2, 3) or not all(math.isfinite(c) for c in values):
        raise ValueError(f"a start is X,Y or X,Y,ALPHA with finite numbers, got {start}")
    if len(values) == 2:
        values.append(heading_away_from_target(values[0], values[1]))
    return np.array(values)


def parse_start(text: str) -> tuple[float, ...]:
    """Parse the CLI form: finite numbers, comma-separated (a wheeled robot's ``X,Y`` or
    ``X,Y,ALPHA``, another system's whole state; the settings check the count against the system)."""
    try:
        values = tuple(float(part) for part in text.split(","))
    except ValueError as error:
        raise ValueError(f"a start is numbers, comma-separated (the robot's X,Y or X,Y,ALPHA), got {text!r}") from error
    if not all(math.isfinite(c) for c in values):
        raise ValueError(f"a start is finite numbers, got {text!r}")
    return values
