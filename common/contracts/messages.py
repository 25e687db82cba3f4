"""Wire messages (pydantic, JSON on the wire). Each carries its schema version.

Every model is frozen, forbids unknown fields and refuses NaN/inf, so a decoded message is
always safe to use. Decoding never raises anything but :class:`MessageError`.
Units are in the field descriptions; states are in the goal frame (heading unwrapped).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated, Any, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError

SCHEMA_VERSION: Literal[1] = 1
MAX_PAYLOAD_BYTES = 64 * 1024  # nothing we send comes close; bigger is refused unparsed

Finite = Annotated[float, Field(allow_inf_nan=False)]
# Physical sanity bounds, far beyond any robot but finite in every product the math forms
# (a cost r(s, u) of a state at 1e300 m would overflow to inf): "huge" is refused on the wire.
MAX_POSITION = 1e4  # [m] x, y in the goal frame
MAX_HEADING = 1e6  # [rad] alpha, unwrapped (continuous), so it may grow by 2 pi per turn
MAX_SPEED = 100.0  # [m/s], [rad/s]: commands are clamped to the robot's limits after this
MAX_COST = 1e12  # a stage cost of bounded states and actions stays far below (no poisoned replay)
Position = Annotated[float, Field(allow_inf_nan=False, ge=-MAX_POSITION, le=MAX_POSITION)]
Heading = Annotated[float, Field(allow_inf_nan=False, ge=-MAX_HEADING, le=MAX_HEADING)]
Speed = Annotated[float, Field(allow_inf_nan=False, ge=-MAX_SPEED, le=MAX_SPEED)]
Vec3 = tuple[Position, Position, Heading]  # a state (x, y, alpha)
Vec2 = tuple[Speed, Speed]  # an action (v, omega)
RobotId = Annotated[str, Field(pattern=r"^[A-Za-z0-9_\-]{1,64}$")]


class MessageError(ValueError):
    """A payload that is not a valid message of the expected schema and version."""


class Message(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    schema_version: Literal[1] = Field(default=SCHEMA_VERSION, description="wire schema version")

    def encode(self) -> bytes:
        return self.model_dump_json().encode()


M = TypeVar("M", bound=Message)
T = TypeVar("T")


def _validated(what: str, item: str, validate: Callable[[bytes], T], payload: bytes) -> T:
    """``validate(payload)`` within :data:`MAX_PAYLOAD_BYTES`; any problem -> one MessageError line
    naming ``what`` and where (``item`` before a field's location: "item " in a batch)."""
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise MessageError(f"{what}: payload of {len(payload)} bytes exceeds {MAX_PAYLOAD_BYTES}")
    try:
        return validate(payload)
    except ValidationError as error:
        first: Any = error.errors()[0]
        location = ".".join(str(p) for p in first["loc"])
        raise MessageError(f"{what}: {item + location if location else 'payload'}: {first['msg']}") from None


def decode(schema: type[M], payload: bytes) -> M:
    """Parse and validate; any problem (size, JSON, schema, version, NaN) -> MessageError."""
    return _validated(schema.__name__, "", schema.model_validate_json, payload)


class PlantState(Message):
    """The robot's state, published by plant_sim or robot_bridge.

    ``state`` is what the robot reports (a robot's odometry, or its localized pose). ``true_state``
    and ``saturated_commands`` are optional: set only by a plant that knows the truth (plant_sim),
    never by the robot bridge; ``map_to_odom`` only by a localized robot bridge. Each is omitted
    from the payload when absent (:meth:`encode` drops None fields)."""

    robot: RobotId
    episode: int = Field(ge=0)
    seq: int = Field(ge=0, description="publisher's sequence number, strictly increasing")
    stamp_ns: int = Field(ge=0, description="sender's monotonic-epoch time [ns]")
    state: Vec3 = Field(description="(x [m], y [m], alpha [rad]) in the goal frame, as the robot reports it")
    source: Literal["sim", "robot"]
    true_state: Vec3 | None = Field(default=None, description="where the robot really is (a simulator only)")
    saturated_commands: int | None = Field(
        default=None, ge=0, description="commands of this episode a wheel could not follow (a simulator only)"
    )
    map_to_odom: Vec3 | None = Field(
        default=None,
        description="(x [m], y [m], theta [rad]) of the map -> odom correction applied to this state "
        "(a localized robot bridge only, docs/turtlebot-localization.md)",
    )

    def encode(self) -> bytes:
        return self.model_dump_json(exclude_none=True).encode()


class Action(Message):
    """The held action for the next sampling interval, published by the actor."""

    robot: RobotId
    episode: int = Field(ge=0)
    step: int = Field(ge=0, description="k, the sampling interval this action is held over")
    stamp_ns: int = Field(ge=0)
    action: Vec2 = Field(description="(v [m/s], omega [rad/s])")
    state_seq: int = Field(ge=-1, description="seq of the PlantState the action answers (-1: none)")


class Transition(Message):
    """One replay sample ``(s_k, u_k, c_k)``, published by the actor after each step."""

    robot: RobotId
    episode: int = Field(ge=0)
    step: int = Field(ge=0)
    state: Vec3 = Field(description="s_k, goal frame")
    action: Vec2 = Field(description="u_k held over [k delta, (k+1) delta)")
    cost: Finite = Field(ge=0, le=MAX_COST, description="c_k = delta r(s_k, u_k)")


class CriticWeights(Message):
    """Versioned critic weights, published by the critic learner."""

    robot: RobotId
    episode: int = Field(ge=0)
    version: int = Field(ge=1, description="strictly increasing per critic instance and episode")
    trained_step: int = Field(ge=-1, description="last transition step the fit used (-1: initial)")
    q_weights: tuple[Finite, ...] = Field(min_length=15, max_length=15)
    v_weights: tuple[Finite, ...] = Field(min_length=6, max_length=6)
    q_residual: Finite = Field(ge=0)
    v_residual: Finite = Field(ge=0)
    pairs: int = Field(ge=0, description="TD pairs in the fit")


class StepRequest(Message):
    """Lockstep: hold ``action`` for ``duration`` seconds, then return the state."""

    robot: RobotId
    episode: int = Field(ge=0)
    step: int = Field(ge=0)
    action: Vec2
    duration: Finite = Field(gt=0, le=10.0, description="[s]")


class ResetRequest(Message):
    """Lockstep: start episode ``episode`` at ``state``."""

    robot: RobotId
    episode: int = Field(ge=0)
    state: Vec3


class ServiceStatus(Message):
    """Periodic health and counters of one service (1 Hz)."""

    robot: RobotId
    service: str = Field(pattern=r"^[a-z_\-]{1,32}$")
    stamp_ns: int = Field(ge=0)
    counters: dict[str, Finite] = Field(default_factory=dict)
