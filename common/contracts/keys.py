"""Every Zenoh key expression of srl, and the only place one is written.

Keys are namespaced by robot id: ``srl/<robot>/...``. A :class:`Topic` pairs a key pattern
with the message schema that travels on it, so publishers and subscribers cannot disagree.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

from common.contracts.messages import (
    Action,
    CriticWeights,
    Message,
    PlantState,
    ResetRequest,
    ServiceStatus,
    StepRequest,
    Transition,
)

M = TypeVar("M", bound=Message)
R = TypeVar("R", bound=Message)
_CHUNK = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")


def check_chunk(value: str, what: str) -> str:
    """A robot or service id must be one plain key chunk (no ``/``, ``*``, ``$``, ``?``, ``#``)."""
    if not _CHUNK.match(value):
        raise ValueError(f"{what} {value!r} must be 1-64 characters of A-Z a-z 0-9 _ -")
    return value


@dataclass(frozen=True)
class Topic(Generic[M]):
    """A key pattern and the schema of what it carries: ``STATE = Topic("srl/{robot}/state",
    PlantState)``. Publishers and subscribers take a Topic (common.net.transport.Bus), so a key and
    its message type cannot be mismatched; the keys' reference page is generated from the Topics.

    Args:
        pattern: the key expression with ``{robot}`` (and other chunks, e.g. ``{service}``) to fill.
        schema: the message class every sample on the key decodes to (common.contracts.messages).
    """

    pattern: str
    schema: type[M]

    def key(self, robot: str, **chunks: str) -> str:
        """The key of one robot (and the other chunks of the pattern). Raises ValueError for an id
        that is not one plain key chunk (:func:`check_chunk`)."""
        check_chunk(robot, "robot id")
        for name, value in chunks.items():
            check_chunk(value, name)
        return self.pattern.format(robot=robot, **chunks)


@dataclass(frozen=True)
class Service(Generic[M, R]):
    """A queryable: requests of ``request`` schema, replies of ``reply`` schema."""

    pattern: str
    request: type[M]
    reply: type[R]

    def key(self, robot: str) -> str:
        return self.pattern.format(robot=check_chunk(robot, "robot id"))


@dataclass(frozen=True)
class Batch(Generic[M]):
    """Many robots' messages of ``topic`` in one sample: the topic's messages as columns (each row
    validated as a message is, common.contracts.columns), on the topic's key with the robot
    chunk :data:`BATCH_CHUNK`. A service that serves many robots sends what it has for them in one
    round as one sample (common.net.transport.Bus.round_publisher): a sample's cost in Zenoh and in
    the receiving process is mostly per sample, not per byte (docs/fleets.md). A receiver gets
    each item as if it had come on its robot's key (common.net.transport.Bus.subscribe).

    ``on_demand``: only srl's hosts send the topic (no robot bridge, no outside client may), so
    they send it only in batches, a host of one robot too, and srl's services read only the batch
    key; a robot's own key carries its messages only while someone outside srl subscribes to it
    (Zenoh's matching status: common.net.transport.OnDemand). Without it, a robot's own key is
    also an input (a robot bridge publishes its states there), which srl's services subscribe."""

    topic: Topic[M]
    on_demand: bool = False

    @property
    def pattern(self) -> str:
        return self.topic.pattern.format(robot=BATCH_CHUNK)

    @property
    def schema(self) -> type[M]:
        return self.topic.schema


# A verbatim chunk (``@``): no wildcard matches it (``srl/*/...`` nor ``srl/**``), so a per-robot
# subscriber never receives a batch it would refuse, and access rules name batch keys explicitly.
# No robot id can take it (an id is A-Z a-z 0-9 _ -).
BATCH_CHUNK = "@batch"

STATE = Topic("srl/{robot}/state", PlantState)
ACTION = Topic("srl/{robot}/action", Action)
# sent by srl only while a subscriber outside srl matches it; srl's critic reads the batches (TRANSITION_BATCH)
TRANSITION = Topic("srl/{robot}/transition", Transition)
WEIGHTS = Topic("srl/{robot}/critic/weights", CriticWeights)
STATUS = Topic("srl/{robot}/status/{service}", ServiceStatus)
# an actor host's actions of one tick group (a host of many robots)
ACTION_BATCH = Batch(ACTION)
# the states a plant host publishes at one state tick (a host of many robots)
STATE_BATCH = Batch(STATE)
# the weights of one fit round of a critic of a robot list (a fleet's), of every robot it fitted,
# sent through an advanced publisher whose cache keeps its last rounds (an actor recovers what it missed)
WEIGHTS_BATCH = Batch(WEIGHTS)
# an actor host's transitions of one tick group (every actor host's, one robot's too), sent through
# an advanced publisher whose cache keeps transport.transition_cache periods of them (a late critic
# recovers); a robot's own transition key only for outside subscribers (Batch.on_demand)
TRANSITION_BATCH = Batch(TRANSITION, on_demand=True)
PLANT_STEP = Service("srl/{robot}/plant/step", StepRequest, PlantState)
PLANT_RESET = Service("srl/{robot}/plant/reset", ResetRequest, PlantState)

ALIVE = "srl/{robot}/alive/{service}"  # liveliness tokens (see liveliness_key)
# Identity tokens: one per live session of a service, naming the session's Zenoh id, so a
# receiver knows WHICH session is the live plant / actor / critic (see identity_key).
IDENTITY = "srl/{robot}/alive/{service}/{zid}"
ALL_KEYS = "srl/**"  # every key of srl (but the verbatim @adv chunks: see advanced_pattern)

SERVICES = ("actor", "critic", "plant", "router")


def batch_of(topic: Topic[M]) -> Batch[M] | None:
    """The batch form of ``topic``, if its messages may also come in batches (:class:`Batch`):
    on the same key, carrying the topic's own schema (another system's, common.contracts.wire)."""
    found = BATCHES.get(topic.pattern)
    return found if found is None or found.topic == topic else Batch(topic, found.on_demand)


BATCHES: dict[str, Batch[Any]] = {
    ACTION.pattern: ACTION_BATCH,
    STATE.pattern: STATE_BATCH,
    WEIGHTS.pattern: WEIGHTS_BATCH,
    TRANSITION.pattern: TRANSITION_BATCH,
}


def on_demand(topic: Topic[M]) -> bool:
    """Whether srl reads ``topic`` only in batches and sends a robot's own key of it only on
    demand (:class:`Batch` ``on_demand``)."""
    batch = batch_of(topic)
    return batch is not None and batch.on_demand


@dataclass(frozen=True)
class Unasked:
    """The keys srl's services put samples on whether or not anyone outside subscribes
    (:func:`unasked_patterns`): ``robot_keys``, every topic's of every robot (``srl/*/...``) but
    the on-demand ones, each sample a robot's message; ``batches``, the batch keys, each sample
    many robots' rows."""

    robot_keys: tuple[str, ...]
    batches: str


def unasked_patterns() -> Unasked:
    """What an observer of srl's traffic subscribes to: ``srl/**`` would match every robot's keys
    of the topics sent on demand (:class:`Batch` ``on_demand``) and so make srl send them."""
    topics: tuple[Topic[Any], ...] = (STATE, ACTION, TRANSITION, WEIGHTS, STATUS)
    every = tuple(topic.pattern.format(robot="*", service="*") for topic in topics if not on_demand(topic))
    return Unasked(every, f"srl/{BATCH_CHUNK}/**")


def every_robot(topic: Topic[M], **chunks: str) -> str:
    """``topic`` of every robot (the robot chunk a wildcard): what a recorder or viewer subscribes to."""
    for name, value in chunks.items():
        check_chunk(value, name)
    return topic.pattern.format(robot="*", **chunks)


def robot_of(key: str) -> str:
    """The robot chunk of one of srl's keys (``srl/<robot>/...``): the robot the key's messages
    are about, which their ``robot`` field must name too (common.net.transport checks it)."""
    parts = key.split("/", 2)
    return parts[1] if len(parts) > 2 and parts[0] == "srl" else ""


def liveliness_key(robot: str, service: str) -> str:
    """Liveliness token of one service of one robot: ``srl/<robot>/alive/<service>``."""
    return ALIVE.format(robot=check_chunk(robot, "robot id"), service=check_chunk(service, "service"))


def identity_key(robot: str, service: str, zid: str) -> str:
    """Identity token of one session of a service: ``srl/<robot>/alive/<service>/<zid>``.

    Declared beside :func:`liveliness_key` by every service (common.net.transport.Bus.declare_alive);
    a receiver accepts a plant's states, an actor's actions or a critic's weights only from a
    session whose identity token is live (common.net.provenance.SourceGate)."""
    return IDENTITY.format(
        robot=check_chunk(robot, "robot id"), service=check_chunk(service, "service"), zid=check_chunk(zid, "zid")
    )


def identity_pattern(robot: str, service: str) -> str:
    """Every identity token of ``service`` of ``robot``: ``srl/<robot>/alive/<service>/*``."""
    return f"{liveliness_key(robot, service)}/*"


def identity_of(key: str) -> str:
    """The zid chunk of an identity token key (the last chunk)."""
    return key.rsplit("/", 1)[-1]


def liveliness_pattern(robot: str) -> str:
    return f"srl/{check_chunk(robot, 'robot id')}/alive/*"


def status_pattern(robot: str) -> str:
    return f"srl/{check_chunk(robot, 'robot id')}/status/*"


def advanced_pattern(key: str) -> str:
    """The keys zenoh-ext's advanced publisher/subscriber on ``key`` use for themselves: the
    publisher's cache queryable, heartbeats and liveliness token live at ``<key>/@adv/pub/<zid>/...``
    (and a subscriber's token at ``<key>/@adv/sub/...``). ``@adv`` is a verbatim chunk: no ``*``
    or ``**`` matches it, so access rules name it explicitly."""
    return f"{key}/@adv/**"
