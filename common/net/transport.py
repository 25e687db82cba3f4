"""Zenoh transport helpers: session config from settings and typed publish/subscribe/query.

The only module of ``common`` that imports zenoh; the math never does. Every subscriber
decodes with the schema of its :class:`~common.contracts.keys.Topic`; a payload that does not decode
is counted under ``rejected.<topic>`` and logged (rate-limited), and never reaches the handler. A
topic with a batch form (:class:`~common.contracts.keys.Batch`) reaches a subscriber both ways: on
the robot's key, and as the items of batches, each handed over as if it had come alone; or, to a
consumer that takes them in bulk (:class:`Inbox`: a recorder), as columns, decoded on its thread.
"""

from __future__ import annotations

import functools
import itertools
import json
import logging
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from datetime import timedelta
from typing import Any, Generic, Literal, TypeVar

import zenoh
import zenoh.ext

from common.config.settings import TransportSettings
from common.contracts.columns import (
    Columns,
    batch_rows,
    check_columns,
    columns_of,
    decode_columns,
    encode_columns,
)
from common.contracts.keys import (
    Service,
    Topic,
    advanced_pattern,
    batch_of,
    identity_key,
    identity_of,
    identity_pattern,
    liveliness_key,
    on_demand,
    robot_of,
)
from common.contracts.messages import Message, MessageError, decode
from common.math.fleet import split_evenly
from common.net.provenance import QUIET_REFUSALS, PlantConflictError, SourceGate, yields_to
from common.net.security import check_network_exposure, tls_entries, zenoh_entries

log = logging.getLogger(__name__)
M = TypeVar("M", bound=Message)
R = TypeVar("R", bound=Message)
RECOVERY_HEARTBEAT_S = 0.5  # advanced publishers announce their last sequence number this often
# What a subscription recovers from advanced publishers' caches (Bus.subscribe): nothing (False);
# their history, then every sample it misses (True); or only the samples it misses after the
# first it gets from a publisher, asked for every MISSED_QUERY_PERIOD (MISSED: an actor's
# weights, where the history of a critic's earlier runs is nobody's)
MISSED: Literal["missed"] = "missed"
Recover = bool | Literal["missed"]
RECOVERY_RANK: dict[Recover, int] = {False: 0, MISSED: 1, True: 2}
MISSED_QUERY_PERIOD = timedelta(seconds=1)
# After declaring its identity, a plant waits this long for the identity of a plant that started
# at the same moment (both passed the check before declaring): a liveliness token reaches the
# router's other subscribers in about 1.5 ms on loopback, and a few hundred ms on a loaded
# host or a slow link; 0.3 s delays a plant's start only once.
PLANT_SETTLE_S = 0.3
STATUS_WAKES = 10  # a status loop wakes at most this often a period (start_status_thread)
# The robots a bus remembers the batch deliveries of, per batch key (Bus._route_batches): a fleet's
# robots, many times over; past it the memory is emptied and matched anew.
BATCH_ROBOTS_KEPT = 4096


def zenoh_config(
    transport: TransportSettings, *, router: bool = False, listen: list[str] | None = None
) -> zenoh.Config:
    """Explicit endpoints, multicast scouting off unless the settings say otherwise.

    A router listens on ``transport.router``; a client connects to it (and to ``connect``).
    ``transport.secure``: the router authenticates users and enforces the role rules, a client
    logs in as ``transport.user`` (raises :class:`common.net.security.SecurityError` if it cannot).
    ``tls/`` endpoints: TLS with ``transport.tls_*`` (mutual unless ``tls_mtls`` is off). A router
    listening off loopback raises SecurityError unless secure and TLS (or ``allow_insecure_network``).
    """
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps("router" if router else transport.mode))
    config.insert_json5("scouting/multicast/enabled", json.dumps(transport.multicast_scouting))
    # Advanced publishers (the transition cache) stamp their samples: timestamps must be on.
    config.insert_json5("timestamping/enabled", "true")
    # Zenoh's own bound on a (defragmented) message: a bigger one is dropped on arrival, before
    # it is reassembled in memory and handed to us (an unbounded put grows every receiving
    # service by its size, retained). srl's messages are a few kB.
    config.insert_json5("transport/link/rx/max_message_size", json.dumps(transport.max_message_bytes))
    # The bound holds only for what crosses the link: with shared memory on (Zenoh's default,
    # DEFAULT_CONFIG.json5 transport/shared_memory/transport_optimization), a put of 3 kB or more
    # between sessions of one host travels as a reference into the sender's pool and is never
    # reassembled: an oversized put is delivered whole (docs/security.md#limits).
    # Off on every session and router srl builds: an intruder's session cannot turn it back on,
    # shared memory needs both ends.
    config.insert_json5("transport/shared_memory/enabled", json.dumps(transport.shared_memory))
    if router:
        listening, connecting = listen or [transport.router], transport.connect
        check_network_exposure(transport, listening)  # off loopback only with login + TLS (or opted out)
    else:
        listening, connecting = listen or transport.listen, [transport.router, *transport.connect]
    config.insert_json5("listen/endpoints", json.dumps(listening))
    config.insert_json5("connect/endpoints", json.dumps(connecting))
    if any(endpoint.startswith("tls/") for endpoint in [*listening, *connecting]):
        for path, value in tls_entries(transport, router=router).items():
            config.insert_json5(path, json.dumps(value))
    if transport.secure:  # Zenoh's own user/password authentication and access rules (common/net/security.py)
        for path, value in zenoh_entries(transport, router=router).items():
            config.insert_json5(path, json.dumps(value))
    return config


def plain_config(transport: TransportSettings, endpoint: str, *, router: bool = False) -> zenoh.Config:
    """A session on another Zenoh network than srl's own, e.g. the robot's (rmw_zenohd on the
    robot): no srl login or access rules; a client connects to ``endpoint`` only, a router
    listens on it only. Scouting and the message bound are srl's settings, as in :func:`zenoh_config`."""
    plain = transport.model_copy(
        update={"router": endpoint, "connect": [], "listen": [], "secure": False, "mode": "client"}
    )
    return zenoh_config(plain, router=router)


def session_errors() -> tuple[type[Exception], ...]:
    """What opening (or using) a Zenoh session raises when the network refuses it, for modules
    that must catch it without importing zenoh themselves (common.process.runtime's connect retry)."""
    return (zenoh.ZError,)


def decode_sample(topic: Topic[M], key: str, payload: bytes) -> M:
    """A sample received on ``key`` as ``topic.schema``: :func:`~common.contracts.messages.decode`,
    and a message about a robot (its ``robot`` field) must come on that robot's key
    (``srl/<robot>/...``): on another robot's key it is refused (MessageError), whoever may
    publish there, so no service files one robot's sample under another's."""
    message = decode(topic.schema, payload)
    robot = getattr(message, "robot", None)
    if robot is not None and robot != robot_of(key):
        raise MessageError(f"{topic.schema.__name__}: robot {robot!r} on the key {key}, which names another robot")
    return message


def counter_name(topic: Topic[Any]) -> str:
    """The part of ``topic``'s key its counters are named by (``received.<name>``, ``rejected.<name>``)."""
    return topic.pattern.split("/", 2)[-1].replace("{service}", "*")


def source_of(sample: zenoh.Sample) -> str | None:
    """The id of the session that published ``sample`` (its Zenoh timestamp's id; None if unstamped)."""
    stamp = sample.timestamp
    return None if stamp is None else str(stamp.get_id())


@dataclass(frozen=True)
class _Route:
    """A subscription that batch items may go to: its key, its counters' name, its handler (called
    with the item's source too when ``with_source``)."""

    key: zenoh.KeyExpr
    name: str
    handler: Callable[..., None]
    with_source: bool


class Bus:
    """One Zenoh session of one service, with counters shared by all its handlers."""

    def __init__(
        self, session: zenoh.Session, service: str, express: bool = True, callback_threads: bool = False
    ) -> None:
        self.session = session
        self.service = service
        self.express = express  # transport.express: every put sent at once, or batched by Zenoh
        self.callback_threads = callback_threads  # transport.callback_threads (see _callback)
        self.counters: Counter[str] = Counter()
        self._lock = threading.Lock()
        self._last_warning: dict[str, float] = {}
        self._keep: list[Any] = []  # declared entities live as long as the bus
        self._queriers: dict[tuple[str, float], Any] = {}
        # batch key -> the subscriptions its items go to (_Route): one
        # Zenoh subscription per batch key, however many robots subscribe (_route_batches)
        self._batch_routes: dict[str, tuple[_Route, ...]] = {}
        # batch pattern -> robot id -> the routes of its items (emptied when the routes change)
        self._batch_targets: dict[str, dict[str, tuple[_Route, ...]]] = {}
        self._batch_recovers: dict[str, Recover] = {}  # batch key -> its first subscription's recovery
        # Our own threads (status): ended and joined by close(), before the session goes, so
        # none is inside Zenoh or pydantic when the interpreter finalizes.
        self.closing = threading.Event()
        self._threads: list[threading.Thread] = []

    @classmethod
    def open(cls, transport: TransportSettings, service: str) -> Bus:
        return cls(zenoh.open(zenoh_config(transport)), service, transport.express, transport.callback_threads)

    def _callback(self, handler: Callable[[Any], None], threaded: bool | None = None) -> Any:
        """A subscription's handler as Zenoh runs it (``threaded``, by default
        transport.callback_threads): in a Python thread of its own, fed by a channel (Zenoh's
        default), or directly in Zenoh's network thread. Direct saves a thread per subscription
        (an actor host of 50 robots has ~250) and the hand-over of every sample to it: ~7 % of a
        core for such a host (docs/fleets.md). Handlers here only decode, check and store (none
        waits on the network), so they may run on the network thread. A few subscriptions that
        take many samples each (a recorder's wildcards) are cheaper threaded: a Python thread that
        lives as long as the subscription calls the handler, where on the network thread every
        sample attaches that thread to the interpreter anew."""
        return zenoh.handlers.Callback(handler, indirect=self.callback_threads if threaded is None else threaded)

    def close(self) -> None:
        self.closing.set()
        for thread in self._threads:
            thread.join(timeout=5.0)
        for entity in reversed(self._keep):
            try:
                entity.undeclare()
            except zenoh.ZError as error:  # already gone with the session
                log.debug("undeclare: %s", error)
        self._keep.clear()
        self.session.close()  # type: ignore[no-untyped-call]  # zenoh stub: close(self) has no annotations

    def adopt(self, thread: threading.Thread) -> None:
        """A thread of this service that uses the session: :meth:`close` ends and joins it first."""
        self._threads.append(thread)

    def count(self, name: str, amount: int = 1) -> None:
        with self._lock:
            self.counters[name] += amount

    def reject(self, what: str, reason: str) -> None:
        """Count a refused input and log it, at most once a second per kind (at INFO for the
        refusals of normal operation, :data:`common.net.provenance.QUIET_REFUSALS`)."""
        self.count(f"rejected.{what}")
        now = time.monotonic()
        if now - self._last_warning.get(what, 0.0) >= 1.0:
            self._last_warning[what] = now
            log.log(
                logging.INFO if what in QUIET_REFUSALS else logging.WARNING,
                "%s: rejected %s: %s (total %d)",
                self.service,
                what,
                reason,
                self.counters[f"rejected.{what}"],
            )

    # -- pub/sub ------------------------------------------------------------------------
    def publisher(self, topic: Topic[M], robot: str, *, cache: int = 0, **chunks: str) -> Callable[[M], None]:
        """Typed put on ``topic``. ``cache > 0``: a Zenoh advanced publisher that keeps the last
        ``cache`` samples and sends heartbeats, so a subscriber declared with ``recover=True``
        gets what it missed (late start, restart, partition) instead of losing it. A topic that
        srl's services read only in batches (common.contracts.keys.Batch.on_demand) is a
        ValueError: on the robot's own key its messages would reach nobody of srl
        (:meth:`round_publisher` sends them)."""
        if on_demand(topic):
            raise ValueError(f"srl reads {topic.pattern} only in batches: send it with round_publisher")
        publisher = self._declare_publisher(topic.key(robot, **chunks), cache)

        def publish(message: M) -> None:
            if not isinstance(message, topic.schema):
                raise TypeError(f"{topic.pattern} carries {topic.schema.__name__}, not {type(message)}")
            publisher.put(message.encode())

        return publish

    def _declare_publisher(self, key: str, cache: int) -> Any:
        """A publisher on ``key`` that lives as long as the bus: advanced, caching the last
        ``cache`` samples, if ``cache > 0`` (:meth:`publisher`)."""
        publisher: Any
        if cache > 0:
            publisher = zenoh.ext.declare_advanced_publisher(
                self.session,
                key,
                cache=zenoh.ext.CacheConfig(cache),
                express=self.express,
                sample_miss_detection=zenoh.ext.MissDetectionConfig(
                    heartbeat=RECOVERY_HEARTBEAT_S, sporadic_heartbeat=None
                ),
                publisher_detection=True,
            )
        else:
            # express (transport.express): sent at once, never held back to fill a batch
            publisher = self.session.declare_publisher(key, express=self.express)
        self._keep.append(publisher)
        return publisher

    def round_publisher(
        self, topic: Topic[M], batches: bool = True, cache: int = 0, robots: Sequence[str] = ()
    ) -> Callable[[Sequence[M] | Columns[M]], None]:
        """Puts rounds of many robots' messages on ``topic``: with ``batches`` (a service that
        serves many robots) and a topic that has a batch form, every round as batches
        (common.contracts.keys.Batch: one sample per 64 KiB of them,
        common.contracts.messages.MAX_PAYLOAD_BYTES), a round of one robot too; else each message
        on its robot's key. One sender's messages of a robot so take one path: a receiver's
        subscriptions may each run in a thread of their own, and two paths would lose their order.
        Every receiver gets each message as if it had come alone (:meth:`subscribe`). ``cache > 0``:
        the publisher (of the batches, or of each robot's key) is an advanced one that keeps its
        last ``cache`` samples (:meth:`publisher`): a batch sample counts as one. A round is its
        messages, or their columns (common.contracts.columns.Columns: a host's arrays, checked
        as a receiver checks them before anything is sent).

        A topic that srl reads only in batches (common.contracts.keys.Batch.on_demand) goes in
        batches whatever ``batches`` says, and each robot's messages also on its own key while an
        outside subscriber matches it (:class:`OnDemand`; ``robots``: those known now)."""
        own_keys = OnDemand(self, topic, robots) if on_demand(topic) else None
        batch = batch_of(topic) if batches or own_keys is not None else None
        batched = None if batch is None else self._declare_publisher(batch.pattern, cache)
        numbers = itertools.count(1)  # the batches' sequence numbers (a receiver counts gaps: BatchSequence)
        singles: dict[str, Callable[[M], None]] = {}

        def publish(round_: Sequence[M] | Columns[M]) -> None:
            if isinstance(round_, Columns):
                if round_.schema is not topic.schema:
                    raise TypeError(f"{topic.pattern} carries {topic.schema.__name__}, not {round_.schema.__name__}")
                check_columns(round_)  # built from a host's arrays: checked as a message would be
            else:
                for message in round_:
                    if not isinstance(message, topic.schema):
                        raise TypeError(f"{topic.pattern} carries {topic.schema.__name__}, not {type(message)}")
            if batched is not None:
                columns = round_ if isinstance(round_, Columns) else columns_of(topic.schema, round_)
                for payload in encode_columns(columns, numbers):
                    batched.put(payload)
                    self.count("batches_published")
                if own_keys is not None:
                    own_keys.send(columns)
                return
            messages = list(round_.items()) if isinstance(round_, Columns) else round_
            for message in messages:
                robot = getattr(message, "robot")  # noqa: B009  # every topic's schema names its robot
                single = singles.get(robot)
                if single is None:
                    single = singles[robot] = self.publisher(topic, robot, cache=cache)
                single(message)

        return publish

    def matching_publisher(self, key: str, on_change: Callable[[bool], None]) -> Callable[[bytes], None]:
        """A plain put of payloads on ``key``, for as long as the bus lives; ``on_change(matching)``
        on Zenoh's thread whenever whether some subscriber matches ``key`` changes (Zenoh's
        matching status)."""
        publisher = self._declare_publisher(key, 0)
        self._keep.append(publisher.declare_matching_listener(lambda status: on_change(status.matching)))
        return publisher.put  # type: ignore[no-any-return]

    @property
    def zid(self) -> str:
        """This session's Zenoh id: the id Zenoh stamps on every sample it publishes."""
        return str(self.session.info.zid())

    def subscribe(
        self,
        topic: Topic[M],
        key: str,
        handler: Callable[..., None],
        what: str | None = None,
        recover: Recover = False,
        with_source: bool = False,
        threaded: bool | None = None,
    ) -> None:
        """Decode every sample on ``key`` (may be a wildcard) as ``topic.schema``; ``threaded``:
        where the handler runs (:meth:`_callback`).

        ``recover``: a Zenoh advanced subscriber that fetches the history cached by advanced
        publishers (also of publishers that appear later) and recovers samples it missed, as
        detected by their sequence numbers and heartbeats. The handler may then see a sample
        more than once (history overlapping what it got live): it must be idempotent. ``MISSED``:
        no history; from a publisher's first sample on, what it misses is asked for every
        :data:`MISSED_QUERY_PERIOD` (a lost last sample too).

        ``with_source``: the handler is called as ``handler(message, source)``, ``source`` the id
        of the session that published the sample (its Zenoh timestamp's id; None if unstamped),
        to be checked against the live identities (:meth:`watch_identities`)."""
        name = what or counter_name(topic)
        route = _Route(zenoh.KeyExpr(key), name, handler, with_source)

        def deliver(message: M, source: str | None) -> None:
            self.count(f"received.{name}")
            self._handle(name, handler, *((message, source) if with_source else (message,)))

        on_sample = self._message_reader(topic, name, deliver)
        batch = batch_of(topic)
        if batch is not None:
            first = self._batch_recovers.get(batch.pattern, recover)
            if RECOVERY_RANK[first] < RECOVERY_RANK[recover]:
                had = "without recovery" if not first else f"with recovery {first!r}"
                raise ValueError(f"{batch.pattern} is subscribed {had} in this process: ask for {recover!r} first")
        if not on_demand(topic):  # an on-demand topic's own keys carry nothing for srl
            self._keep.append(self._declare_subscriber(key, self._callback(on_sample, threaded), recover))
        if batch is not None:
            self._route_batches(topic, route, threaded, recover)

    def raw_subscriber(
        self, key: str, handler: Callable[[zenoh.Sample], None], recover: Recover = False, threaded: bool | None = None
    ) -> None:
        """``handler`` gets the samples on ``key`` as Zenoh delivers them, undecoded, for as long as
        the bus lives (an :class:`Inbox` decodes them later, on its consumer's thread); ``recover``
        and ``threaded`` as in :meth:`subscribe`."""
        self._keep.append(self._declare_subscriber(key, self._callback(handler, threaded), recover))

    def subscribe_columns(
        self,
        topic: Topic[M],
        keys: Sequence[str],
        handler: Callable[[Columns[M], str | None], None],
        what: str | None = None,
        threaded: bool | None = None,
        alone: Callable[[M, str | None], None] | None = None,
    ) -> None:
        """``topic``'s samples on ``keys`` as columns, one call of ``handler(columns, source)`` per
        sample: a batch's rows of the robots the keys include (from one subscription of the batch
        key, decoded and checked once: :class:`BatchReader`), a message alone on its robot's key as
        a batch of one row. A consumer that takes a batch as arrays (a plant host's actions) has
        one path for both. ``alone``: a message alone goes to ``alone(message, source)`` as it came
        instead (a consumer that judges such a message at less cost than a batch of one: an actor
        host's states from a robot bridge). Refusals and counts as :meth:`subscribe`'s
        (``received.<name>`` per row); ``threaded`` as there."""
        name = what or counter_name(topic)
        batch = batch_of(topic)
        if batch is None:
            raise TypeError(f"{topic.pattern} has no batch form")

        included = Included(topic, keys)

        def call(columns: Columns[M], source: str | None) -> None:
            if len(columns):
                self.count(f"received.{name}", len(columns))
                self._handle(name, handler, columns, source)

        def single(message: M, source: str | None) -> None:
            if alone is None:
                call(columns_of(topic.schema, [message]), source)
            else:
                self.count(f"received.{name}")
                self._handle(name, alone, message, source)

        on_sample = self._message_reader(topic, name, single)
        on_batch = self._batch_reader(topic, name, lambda columns, source: call(included(columns), source))
        for key in [] if on_demand(topic) else keys:
            self._keep.append(self._declare_subscriber(key, self._callback(on_sample, threaded), False))
        self._keep.append(self._declare_subscriber(batch.pattern, self._callback(on_batch, threaded), False))

    def inbox(self, limit: int) -> Inbox:
        """Samples that wait for a consumer that takes them in bulk, at most ``limit`` rows (:class:`Inbox`)."""
        return Inbox(self, limit)

    def _declare_subscriber(self, key: str, callback: Any, recover: Recover) -> Any:
        """A subscriber on ``key``; ``recover``: an advanced one, with history and recovery, or
        (``MISSED``) recovery alone (:meth:`subscribe`)."""
        if not recover:
            return self.session.declare_subscriber(key, callback)
        if recover == MISSED:
            # the binding takes a timedelta (a float is a TypeError), its stub says float
            period: Any = MISSED_QUERY_PERIOD
            recovery = zenoh.ext.RecoveryConfig(heartbeat=None, periodic_queries=period)
            return zenoh.ext.declare_advanced_subscriber(self.session, key, callback, recovery=recovery)
        return zenoh.ext.declare_advanced_subscriber(
            self.session,
            key,
            callback,
            history=zenoh.ext.HistoryConfig(detect_late_publishers=True),
            recovery=zenoh.ext.RecoveryConfig(heartbeat=True, periodic_queries=None),
        )

    def _route_batches(self, topic: Topic[M], route: _Route, threaded: bool | None, recover: Recover) -> None:
        """The items of ``topic``'s batches whose robot ``route``'s key includes go to its handler,
        with the batch's source: one Zenoh subscription per batch key and bus (the first
        subscriber's ``threaded`` says where its handler runs, its ``recover`` whether the batches'
        history and missed samples are fetched: a later subscription may not ask for a recovery
        the first did not), each batch decoded once and its items handed to every subscription of
        their robot (an item of a robot nobody here subscribed to is not ours, and is passed over).
        A batch's items are counted (``received.<name>``) before any handler runs, once per batch,
        and each handler call is guarded as :meth:`_handle` guards one: a failing item is counted
        and logged, and the batch's other items are still delivered."""
        batch = batch_of(topic)
        assert batch is not None
        pattern = batch.pattern
        with self._lock:
            first = pattern not in self._batch_routes
            self._batch_recovers.setdefault(pattern, recover)
            self._batch_routes[pattern] = (*self._batch_routes.get(pattern, ()), route)
            self._batch_targets = {}  # the routes changed: every robot's deliveries again

        def deliveries_of(robot: str, targets: dict[str, tuple[_Route, ...]]) -> tuple[_Route, ...]:
            if len(targets) >= BATCH_ROBOTS_KEPT:  # bounded whatever robot ids senders invent
                targets.clear()
            concrete = zenoh.KeyExpr(topic.key(robot))
            found = targets[robot] = tuple(r for r in self._batch_routes[pattern] if r.key.intersects(concrete))
            return found

        def on_columns(columns: Columns[M], source: str | None) -> None:
            targets = self._batch_targets.get(pattern)
            if targets is None:
                targets = self._batch_targets[pattern] = {}
            chosen = []  # (row, its routes): a robot's routes are matched once, not per item
            for row, robot in enumerate(columns.robots):
                routes = targets.get(robot)
                if routes is None:
                    routes = deliveries_of(robot, targets)
                if routes:
                    chosen.append((row, routes))
            if not chosen:
                return
            received = Counter(r.name for _, routes in chosen for r in routes)
            with self._lock:
                for name, amount in received.items():
                    self.counters[f"received.{name}"] += amount
            for row, routes in chosen:
                item = columns.item(row)  # a message is built for the robots served here only
                for r in routes:
                    try:
                        if r.with_source:
                            r.handler(item, source)
                        else:
                            r.handler(item)
                    except Exception:
                        self.count(f"handler_errors.{r.name}")
                        log.exception("%s: handler for %s failed", self.service, r.name)

        if first:
            on_batch = self._batch_reader(topic, route.name, on_columns)
            self._keep.append(self._declare_subscriber(pattern, self._callback(on_batch, threaded), recover))

    def _handle(self, name: str, handler: Callable[..., None], *args: Any) -> None:
        """``handler(*args)`` on a subscription's behalf: a handler bug is counted and logged, and
        never kills Zenoh's callback thread silently."""
        try:
            handler(*args)
        except Exception:
            self.count(f"handler_errors.{name}")
            log.exception("%s: handler for %s failed", self.service, name)

    def _message_reader(
        self, topic: Topic[M], name: str, deliver: Callable[[M, str | None], None]
    ) -> Callable[[zenoh.Sample], None]:
        """A subscription's callback for ``topic``'s messages alone: each decoded (one that does not
        decode is refused, counted under ``rejected.<name>``) and delivered with its source."""

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                message = decode_sample(topic, str(sample.key_expr), sample.payload.to_bytes())
            except MessageError as error:
                self.reject(name, str(error))
                return
            deliver(message, source_of(sample))

        return on_sample

    def _batch_reader(
        self, topic: Topic[M], name: str, deliver: Callable[[Columns[M], str | None], None]
    ) -> Callable[[zenoh.Sample], None]:
        """A subscription's callback for ``topic``'s batch key: each batch read once
        (:class:`BatchReader`: decoded, checked, its sender's gaps counted; a bad one refused and
        counted) and delivered as columns with its source."""
        read = BatchReader(self, topic, name)

        def on_batch(sample: zenoh.Sample) -> None:
            source = source_of(sample)
            try:
                columns = read(sample.payload.to_bytes(), source)
            except MessageError as error:
                self.reject(name, str(error))
                return
            deliver(columns, source)

        return on_batch

    def history(
        self,
        topic: Topic[M],
        keys: str | Sequence[str],
        handler: Callable[[M], None],
        done: Callable[[], None] | None = None,
        timeout: float = 10.0,
    ) -> None:
        """Ask every advanced publisher on ``keys`` (one key or several) for all it caches, without
        waiting: each cached sample is decoded (a malformed one counted as rejected) and handed to
        ``handler`` on Zenoh's thread, in the cache's order. A topic with a batch form
        (common.contracts.keys.Batch) asks the batch publishers' caches too, once for all of
        ``keys``: the items of their robots are handed over one by one. ``done`` is called once,
        when every publisher has answered or ``timeout`` has passed.

        A :meth:`subscribe` with ``recover=True`` gets a publisher's history only if the answer
        to its own history query comes before that publisher's next live sample: a sample it
        delivers live ends the recovery of everything older. A service that sees a stream
        start later than it should asks again with this (the critic does)."""
        name = topic.pattern.split("/", 2)[-1]
        wanted = [keys] if isinstance(keys, str) else list(keys)
        batch = batch_of(topic)
        selectors = [] if on_demand(topic) else [advanced_pattern(key) for key in wanted]
        if batch is not None:
            selectors.append(advanced_pattern(batch.pattern))
        expressions = [zenoh.KeyExpr(key) for key in wanted]
        open_queries = [len(selectors)]  # queries not yet ended (done when none is left)
        lock = threading.Lock()

        def hand(message: M) -> None:
            self.count(f"recovered.{name}")
            handler(message)

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is None:
                return
            key = str(reply.ok.key_expr)
            try:
                if batch is None or key != batch.pattern:
                    hand(decode_sample(topic, key, reply.ok.payload.to_bytes()))
                    return
                columns = decode_columns(topic.schema, reply.ok.payload.to_bytes())
            except MessageError as error:
                self.reject(name, str(error))
                return
            for row, robot in enumerate(columns.robots):
                robot_key = zenoh.KeyExpr(topic.key(robot))
                if any(expression.intersects(robot_key) for expression in expressions):
                    hand(columns.item(row))

        def on_end() -> None:
            with lock:
                open_queries[0] -= 1
                last = open_queries[0] == 0
            if last and done is not None:
                done()

        for index, selector in enumerate(selectors):
            try:
                self.session.get(
                    selector,
                    zenoh.handlers.Callback(on_reply, on_end, indirect=self.callback_threads),
                    target=zenoh.QueryTarget.ALL,
                    consolidation=zenoh.ConsolidationMode.NONE,
                    accept_replies=zenoh.ReplyKeyExpr.ANY,  # the cache answers on the key itself
                    timeout=timeout,
                )
            except BaseException:  # a query that cannot be sent (a closed session) has ended, so have the rest
                with lock:
                    open_queries[0] -= len(selectors) - index - 1
                on_end()
                raise

    # -- queries ------------------------------------------------------------------------
    def serve(self, service: Service[M, R], robot: str, handler: Callable[[M], R]) -> None:
        """A queryable: each valid request gets the handler's reply; bad ones an error reply."""
        name = service.pattern.split("/", 2)[-1]

        def on_query(query: zenoh.Query) -> None:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            try:
                request = decode(service.request, payload)
                reply = handler(request)
            except (MessageError, ValueError) as error:
                self.reject(name, str(error))
                query.reply_err(str(error).encode())
                return
            self.count(f"served.{name}")
            query.reply(query.key_expr, reply.encode())

        self._keep.append(self.session.declare_queryable(service.key(robot), on_query))

    def query(self, service: Service[M, R], robot: str, request: M, timeout: float) -> R:
        """One request, one validated reply; raises ``TimeoutError`` or ``MessageError``.

        Through a Zenoh querier declared once per key and timeout: on loopback it costs a
        quarter less CPU and a fifth less round-trip time than a fresh ``session.get``."""
        key = service.key(robot)
        querier = self._queriers.get((key, timeout))
        if querier is None:
            querier = self._queriers[(key, timeout)] = self.session.declare_querier(key, timeout=timeout)
            self._keep.append(querier)
        replies = querier.get(payload=request.encode())
        for reply in replies:
            if reply.ok is None:
                why = reply.err.payload.to_bytes().decode(errors="replace") if reply.err is not None else "no reply"
                raise MessageError(f"{service.pattern}: {why}")
            return decode(service.reply, reply.ok.payload.to_bytes())
        raise TimeoutError(f"no reply from {service.key(robot)} within {timeout} s")

    # -- liveliness ---------------------------------------------------------------------
    def declare_alive(self, robot: str) -> None:
        """This service's liveliness token ``srl/<robot>/alive/<service>`` (readiness, health
        checks) and its session's identity token ``.../<service>/<zid>`` (provenance)."""
        liveliness = self.session.liveliness()
        self._keep.append(liveliness.declare_token(liveliness_key(robot, self.service)))
        self._keep.append(liveliness.declare_token(identity_key(robot, self.service, self.zid)))

    def refuse_other_plant(self, robot: str) -> None:
        """One plant per robot, checked before declaring: a plant (simulator or robot bridge)
        never starts beside a live plant of the same robot (:class:`PlantConflictError`)."""
        others = self.live_identities(robot, self.service)
        if others:
            raise _plant_conflict(robot, others)

    def declare_sole_plant(self, robot: str, settle: float = PLANT_SETTLE_S) -> None:
        """:meth:`declare_sole_plants` for one robot."""
        self.declare_sole_plants([robot], settle)

    def declare_sole_plants(self, robots: list[str], settle: float = PLANT_SETTLE_S) -> None:
        """Declare this plant alive for every robot (:meth:`declare_alive`), then break a tie
        with a plant that started at the same moment: after ``settle`` seconds, the session that
        sorts after another live plant identity (:func:`common.net.provenance.yields_to`)
        withdraws all the tokens it declared here and raises :class:`PlantConflictError`; the
        other one computes the same answer and stays. One settle for all the robots of a plant
        host: a fleet of 100 starts in 0.3 s, not 30 s."""
        kept = len(self._keep)
        for robot in robots:
            self.declare_alive(robot)
        time.sleep(settle)
        for robot in robots:
            ahead = yields_to(self.zid, self.live_identities(robot, self.service))
            if ahead:
                for token in self._keep[kept:]:
                    token.undeclare()
                del self._keep[kept:]
                raise _plant_conflict(robot, ahead)

    def live_identities(self, robot: str, service: str, timeout: float = 1.0) -> list[str]:
        """The session ids of every live identity token of ``service`` of ``robot`` (not ours)."""
        replies = self.session.liveliness().get(identity_pattern(robot, service), timeout=timeout)
        found = {identity_of(str(reply.ok.key_expr)) for reply in replies if reply.ok is not None}
        return sorted(found - {self.zid})

    def watch_identities(
        self, robot: str, service: str, gate: SourceGate, on_change: Callable[[str, bool], None] | None = None
    ) -> None:
        """Keep ``gate`` up to date with the live identities of ``service`` of ``robot``.

        The identities alive now are read synchronously before this returns (a liveliness
        query), so a sample that arrives right after is judged against them; later changes come
        from a liveliness subscriber (a vanished session: ~ms after a kill or a lost router)."""

        def on_token(sample: zenoh.Sample) -> None:
            zid, alive = identity_of(str(sample.key_expr)), sample.kind == zenoh.SampleKind.PUT
            gate.update(zid, alive)
            if on_change is not None:
                on_change(zid, alive)

        self._keep.append(
            self.session.liveliness().declare_subscriber(
                identity_pattern(robot, service), self._callback(on_token), history=True
            )
        )
        for zid in self.live_identities(robot, service, timeout=1.0):
            if zid not in gate.sources():
                gate.update(zid, True)
                if on_change is not None:
                    on_change(zid, True)

    def watch_alive(self, robot: str, service: str, handler: Callable[[bool], None]) -> None:
        """``handler(True)`` when the service's token appears (or already exists), ``False``
        when it vanishes (its holder died or lost the network: ~ms after a kill)."""

        def on_token(sample: zenoh.Sample) -> None:
            handler(sample.kind == zenoh.SampleKind.PUT)

        self._keep.append(
            self.session.liveliness().declare_subscriber(
                liveliness_key(robot, service), self._callback(on_token), history=True
            )
        )

    def is_alive(self, robot: str, service: str, timeout: float = 1.0) -> bool:
        replies = self.session.liveliness().get(liveliness_key(robot, service), timeout=timeout)
        return any(reply.ok is not None for reply in replies)

    def wait_alive(self, robot: str, service: str, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.is_alive(robot, service, timeout=min(0.5, timeout)):
                return
            time.sleep(0.05)
        raise TimeoutError(f"service {service!r} of robot {robot!r} not alive after {timeout} s")


def _plant_conflict(robot: str, others: list[str]) -> PlantConflictError:
    return PlantConflictError(
        f"another plant (session {', '.join(others)}) is alive for robot {robot}: one plant per robot; stop it first"
    )


StatusRow = tuple[str, Callable[[], dict[str, float]]]  # a robot and its status counters


def bus_status(bus: Bus, extra: Callable[[], dict[str, float]]) -> Callable[[], dict[str, float]]:
    """A one-robot service's status counters: its bus's counters and ``extra()``."""

    def counters() -> dict[str, float]:
        merged = {k: float(v) for k, v in dict(bus.counters).items()}
        merged.update(extra())
        return merged

    return counters


class BatchSequence:
    """The batches of one batch key as they arrive, per sending session (the header's sequence
    number, common.contracts.columns): ``seen`` says how many of a session's batches were skipped
    before this one (lost on the way, or sent before this subscriber came: a session's first
    batch counts none) and whether it is one already passed (a recovered or repeated one). Kept
    for at most :data:`SOURCES_KEPT` sessions (forgotten all at once past it)."""

    SOURCES_KEPT = 64

    def __init__(self) -> None:
        self.last: dict[str | None, int] = {}

    def seen(self, source: str | None, seq: int) -> tuple[int, bool]:
        last = self.last.get(source)
        if last is None:
            if len(self.last) >= self.SOURCES_KEPT:
                self.last.clear()
            self.last[source] = seq
            return 0, False
        if seq <= last:
            return 0, True
        self.last[source] = seq
        return seq - last - 1, False


class BatchReader:
    """The batches of one batch key as one receiver reads them: decoded and checked
    (:func:`~common.contracts.columns.decode_columns`, MessageError if refused), each sending
    session's skipped and repeated batches counted on the bus (``batches_missed.<name>``,
    ``batches_repeated.<name>``, :class:`BatchSequence`)."""

    def __init__(self, bus: Bus, topic: Topic[M], name: str) -> None:
        self.bus, self.schema, self.name = bus, topic.schema, name
        self.order = BatchSequence()

    def __call__(self, payload: bytes, source: str | None) -> Columns[Any]:
        columns = decode_columns(self.schema, payload)
        missed, repeated = self.order.seen(source, columns.seq)
        if missed:
            self.bus.count(f"batches_missed.{self.name}", missed)
        if repeated:
            self.bus.count(f"batches_repeated.{self.name}")
        return columns


class Included(Generic[M]):
    """A batch's rows of the robots whose key one of ``keys`` (wildcards allowed) includes, in
    order (the batch itself when every row is); each robot's answer is remembered (at most
    BATCH_ROBOTS_KEPT, whatever robot ids senders invent)."""

    def __init__(self, topic: Topic[M], keys: Sequence[str]) -> None:
        self.topic = topic
        self.wanted = [zenoh.KeyExpr(key) for key in keys]
        self.chosen: dict[str, bool] = {}

    def __call__(self, columns: Columns[M]) -> Columns[M]:
        chosen, mine = self.chosen, []
        for row, robot in enumerate(columns.robots):
            included = chosen.get(robot)
            if included is None:
                if len(chosen) >= BATCH_ROBOTS_KEPT:
                    chosen.clear()
                concrete = zenoh.KeyExpr(self.topic.key(robot))
                included = chosen[robot] = any(key.intersects(concrete) for key in self.wanted)
            if included:
                mine.append(row)
        return columns if len(mine) == len(columns) else columns.take(mine)


class OnDemand(Generic[M]):
    """The robots' own keys of a topic that srl's services read only in batches
    (common.contracts.keys.Batch.on_demand), for outside clients: each robot a host sends the topic
    for gets a publisher on its key, and its messages are put there only while a subscriber
    matches that key (Zenoh's matching status). No service of srl subscribes those keys, so a
    match is an outside client (a viewer, a logger, someone's own tool); a round that nobody
    outside asks for costs a set comparison. Counted: ``on_demand.<topic>`` per message put."""

    def __init__(self, bus: Bus, topic: Topic[M], robots: Sequence[str]) -> None:
        self.bus, self.topic = bus, topic
        self.name = f"on_demand.{counter_name(topic)}"
        self.puts: dict[str, Callable[[bytes], None]] = {}  # robot -> the put on its key
        self.matched: set[str] = set()  # the robots whose key some subscriber matches (Zenoh's thread)
        # the robots known now get their keys at once: a subscriber already there gets their first
        # messages (a key declared with a robot's first round hears of its match only after it)
        self.declare(robots)

    def declare(self, robots: Sequence[str]) -> None:
        """A publisher on each of ``robots``' keys that has none yet, whose matches are followed."""
        for robot in robots:
            if robot not in self.puts:
                self.puts[robot] = self.bus.matching_publisher(
                    self.topic.key(robot), functools.partial(self._matching, robot)
                )

    def send(self, columns: Columns[M]) -> None:
        """Put each row of ``columns`` (a round, as sent in batches) on its robot's key if matched."""
        if not self.puts.keys() >= set(columns.robots):
            self.declare(columns.robots)
        matched = self.matched
        if not matched:
            return
        for row, robot in enumerate(columns.robots):
            if robot in matched:
                self.puts[robot](columns.item(row).encode())
                self.bus.count(self.name)

    def _matching(self, robot: str, matching: bool) -> None:
        if matching:
            self.matched.add(robot)
        else:
            self.matched.discard(robot)


class Inbox:
    """Samples of some topics waiting, in arrival order, for one consumer that takes them in bulk
    (:meth:`take`): a recorder's writer, which wakes a few times a second. Zenoh's threads only
    append a sample's bytes (no Python thread per subscription, nothing decoded on them); the
    consumer decodes what waits in one go, on its own thread. A topic with a batch form comes as
    columns (common.contracts.columns): a batch's rows of the robots the key includes, and a
    message that came alone on its robot's key as a batch of one row; any other topic as messages.

    What a decoded sample would do on :meth:`Bus.subscribe` it does here: a malformed one is
    counted under ``rejected.<name>`` and logged, never handed over; a message on another robot's
    key is refused; a batch's skipped and repeated sequence numbers are counted
    (``batches_missed.<name>``, ``batches_repeated.<name>``); the rows handed over are counted
    under ``received.<name>``. At most ``limit`` rows wait: the rest are counted in
    :attr:`dropped` (the consumer is behind), never silently lost.

    A consumer that answers what comes (the critic) sleeps in :meth:`wait`, which returns once a
    sample was put (or :meth:`wake` was called) since the last :meth:`take` began."""

    def __init__(self, bus: Bus, limit: int) -> None:
        self.bus = bus
        self.limit = limit
        self.waiting = 0  # rows put and not yet taken
        self.dropped = 0  # rows refused because ``limit`` waited
        self.last_put = time.monotonic()  # when the newest sample came (or the inbox was made)
        self._ready = threading.Event()  # something was put since the last take began
        self._batches: set[str] = set()  # the batch keys subscribed (once each)
        self._lock = threading.Lock()  # put runs on several of Zenoh's threads
        # (reader, name, rows, payload, key, source, arrival [ns]), oldest first
        self._samples: deque[tuple[Callable[[bytes, str, str | None], Any], str, int, bytes, str, str | None, int]]
        self._samples = deque()

    def subscribe(
        self, topic: Topic[M], keys: str | Sequence[str], what: str | None = None, recover: bool = False
    ) -> None:
        """Take ``topic``'s samples on ``keys`` (one key or several; a wildcard takes every
        robot's) and, with a batch form, its batches' rows of the robots the keys include, from
        ONE subscription of the batch key (a topic's batches are subscribed once per inbox: a
        second call for the topic is a ValueError); ``recover`` as in :meth:`Bus.subscribe`."""
        bus = self.bus
        name = what or counter_name(topic)
        batch = batch_of(topic)
        keys = [keys] if isinstance(keys, str) else list(keys)
        if batch is not None:
            if batch.pattern in self._batches:
                raise ValueError(f"{batch.pattern} is subscribed by this inbox already: give every key at once")
            self._batches.add(batch.pattern)

        def alone(payload: bytes, sample_key: str, source: str | None) -> Any:
            message = decode_sample(topic, sample_key, payload)
            return message if batch is None else columns_of(topic.schema, [message])

        for key in [] if on_demand(topic) else keys:
            self._declare(name, key, alone, lambda payload: 1, recover)
        if batch is None:
            return
        read, included = BatchReader(bus, topic, name), Included(topic, keys)

        def rows(payload: bytes, sample_key: str, source: str | None) -> Columns[M]:
            return included(read(payload, source))

        self._declare(name, batch.pattern, rows, lambda payload: batch_rows(payload) or 1, recover)

    def _declare(
        self,
        name: str,
        key: str,
        reader: Callable[[bytes, str, str | None], Any],
        rows_of: Callable[[bytes], int],
        recover: bool,
    ) -> None:
        samples, lock = self._samples, self._lock

        def put(sample: zenoh.Sample) -> None:
            payload = sample.payload.to_bytes()
            rows = rows_of(payload)
            with lock:
                if self.waiting + rows > self.limit:
                    self.dropped += rows
                    return
                self.waiting += rows
                samples.append((reader, name, rows, payload, str(sample.key_expr), source_of(sample), time.time_ns()))
                self.last_put = time.monotonic()
            self._ready.set()

        # on Zenoh's thread: a put is an append, and a Python thread per subscription would only
        # contend with the consumer for the interpreter
        self.bus.raw_subscriber(key, put, recover, threaded=False)

    def settle(self, quiet: float, longest: float) -> bool:
        """Before the subscriptions close: sleep until no sample has come for ``quiet`` seconds, at
        most ``longest`` seconds, so that what the publishers sent just before they stopped (still
        on its way through the router) is taken too. True: it went quiet."""
        deadline = time.monotonic() + longest
        while True:
            now = time.monotonic()
            left = quiet - (now - self.last_put)
            if left <= 0:
                return True
            if now >= deadline:
                return False
            time.sleep(min(left, deadline - now))

    def wait(self, timeout: float) -> bool:
        """Sleep until a sample was put since the last :meth:`take` began (at once if one was),
        at most ``timeout`` seconds; False: none was."""
        return self._ready.wait(timeout)

    def wake(self) -> None:
        """End a :meth:`wait` (the consumer has something of its own to take)."""
        self._ready.set()

    def take(self) -> Iterator[tuple[Any, int]]:
        """What waits, oldest first, as ``(columns or message, arrival [ns])``; a sample that does
        not decode is counted and logged (:meth:`Bus.reject`) and passed over."""
        samples, lock, bus = self._samples, self._lock, self.bus
        self._ready.clear()  # a sample put from here on is taken now, or wakes the next wait
        while samples:
            reader, name, rows, payload, key, source, arrived_ns = samples.popleft()
            with lock:
                self.waiting -= rows
            try:
                taken = reader(payload, key, source)
            except MessageError as error:
                bus.reject(name, str(error))
                continue
            bus.count(f"received.{name}", len(taken) if isinstance(taken, Columns) else 1)
            yield taken, arrived_ns


def start_status_thread(
    bus: Bus,
    rows: Sequence[StatusRow],
    period: float,
    stop: threading.Event,
    on_status: Callable[[dict[str, float]], None] | None = None,
) -> threading.Thread:
    """Each robot's status (``srl/<robot>/status/<bus.service>``, a row ``(robot, counters)``) once a
    ``period``, until stop or until the bus closes (which joins the thread, so it is never left
    inside Zenoh). One service of one robot and a host of K robots run the same loop.

    * Spread over the period in at most :data:`STATUS_WAKES` bursts: K <= 10 robots one at a time
      every ``period / K``; more, ``ceil(K / 10)`` at a time every ``period / 10``. A host's K in
      one burst would hold the GIL from its tick thread for all of them (100 robots: ~4 ms); a
      wake per robot costs each process a thread switch per robot (at 100 robots at rest, 1 Hz
      statuses one at a time cost ~0.04 ms of CPU per robot tick, docs/notes/status-on-demand.md),
      and puts due together leave in one Zenoh batch (``transport.express`` false).
    * Sent whether or not anyone subscribes: gating them on Zenoh's matching status saved no
      measurable CPU and was in doubt across linked routers (docs/notes/status-on-demand.md).
      Counted: ``statuses_published``.
    * Counters that are NaN or infinite are left out (the schema refuses them).
    * ``on_status`` gets every row's counters (the actor logs its status line: compose shows it)."""
    from common.contracts.keys import STATUS
    from common.contracts.messages import ServiceStatus

    service = bus.service
    publishers = [(robot, counters, bus.publisher(STATUS, robot, service=service)) for robot, counters in rows]
    bursts = split_evenly(publishers, max(1, min(len(publishers), STATUS_WAKES)))
    gap = period / len(bursts)

    def send(robot: str, counters: Callable[[], dict[str, float]], publish: Callable[[ServiceStatus], None]) -> bool:
        """One robot's status out; False once the session closed under us (shutdown: nothing to report to)."""
        values = counters()
        if on_status is not None:
            on_status(values)
        finite = {k: v for k, v in values.items() if v == v and abs(v) != float("inf")}
        try:
            publish(ServiceStatus(robot=robot, service=service, stamp_ns=time.monotonic_ns(), counters=finite))
        except zenoh.ZError as error:
            log.debug("%s status: %s", service, error)
            return False
        return True

    def loop() -> None:
        while True:
            for burst in bursts:
                if bus.closing.wait(gap) or stop.is_set() or not all(send(*row) for row in burst):
                    return
                bus.count("statuses_published", len(burst))

    thread = threading.Thread(target=loop, name=f"{service}-status", daemon=True)
    thread.start()
    bus.adopt(thread)  # joined by bus.close()
    return thread
