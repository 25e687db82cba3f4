"""Programs the network-fault tests run inside the namespaces (``python -m tests.netns_tools ...``).

* ``relay``: a TCP relay that holds every chunk it forwards for a fixed delay, in both directions
  (asyncio). This kernel has no ``netem``: a client that connects to the relay instead of its
  real peer sees that delay added to every byte it sends and receives (connection set-up is not
  delayed). It terminates TCP on both sides, so the veth checksum offloads that trouble a
  packet-level relay do not matter here. Optionally an echo server for ``probe``.
* ``probe``: ping-like round trips of a small message to an echo server (directly, or through
  the relay), to measure the delay the relay adds.
* ``observe``: a Zenoh client that prints, as JSON lines stamped with ``time.monotonic()`` (one
  clock for every namespace of the machine), the services' liveliness, their status counters
  every critic weight message and every transition's step: the test watches the run through it.
  ``observe-fleet``: the same for every robot of a fleet, and who (which Zenoh session) sent each
  robot's actions.

Every program prints ``{"kind": "ready", ...}`` once it serves, and a ``{"kind": "summary", ...}``
line when stopped by SIGINT or SIGTERM.
"""

from __future__ import annotations

import argparse
import asyncio
import functools
import json
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

CHUNK = 65536
HELD_KEPT = 100_000  # hold times kept for the summary's percentiles


def _open_until(router: str, connect_timeout: float, stop: threading.Event, who: str) -> Any:
    """A client session to ``router``, retried until ``connect_timeout`` or ``stop`` (None: said
    why on stderr)."""
    import zenoh

    from tests.harness import client_config

    deadline = time.monotonic() + connect_timeout
    while True:
        try:
            return zenoh.open(client_config(router))
        except zenoh.ZError as error:
            if time.monotonic() > deadline or stop.is_set():
                print(f"{who}: cannot reach the router at {router}: {error}", file=sys.stderr)
                return None
            time.sleep(0.1)


def emit(kind: str, **fields: Any) -> None:
    print(json.dumps({"kind": kind, "t": time.monotonic(), **fields}), flush=True)


def _address(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    if not host or not port.isdigit():
        raise argparse.ArgumentTypeError(f"expected HOST:PORT, got {text!r}")
    return host, int(port)


def _forward(text: str) -> tuple[tuple[str, int], tuple[str, int]]:
    listen, sep, target = text.partition("=")
    if not sep:
        raise argparse.ArgumentTypeError(f"expected LISTEN_HOST:PORT=TARGET_HOST:PORT, got {text!r}")
    return _address(listen), _address(target)


def _percentiles(values: Sequence[float], scale: float = 1.0) -> dict[str, float]:
    data = sorted(v * scale for v in values)
    if not data:
        return {}
    return {
        "min": data[0],
        "median": data[len(data) // 2],
        "p99": data[min(len(data) - 1, int(0.99 * len(data)))],
        "max": data[-1],
    }


def _nodelay(writer: asyncio.StreamWriter) -> None:
    sock = writer.get_extra_info("socket")
    if sock is not None:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


# -- relay ------------------------------------------------------------------------------
class RelayStats:
    def __init__(self) -> None:
        self.connections = 0
        self.bytes = {"to_target": 0, "to_client": 0}
        self.chunks = 0
        self.held: list[float] = []  # seconds each chunk was held (receive -> write)

    def summary(self) -> dict[str, Any]:
        return {
            "connections": self.connections,
            "bytes": self.bytes,
            "chunks": self.chunks,
            "held_ms": _percentiles(self.held, 1e3),
        }


async def _pipe(
    reader: asyncio.StreamReader, writer: asyncio.StreamWriter, delay: float, stats: RelayStats, direction: str
) -> None:
    """Forward ``reader`` to ``writer``, each chunk written no earlier than ``delay`` after it was read.

    Reading goes on while earlier chunks wait: the delay is added to every byte, the throughput
    is not divided by it (like a long cable, not a slow one)."""
    loop = asyncio.get_running_loop()
    queue: asyncio.Queue[tuple[float, bytes]] = asyncio.Queue()

    async def receive() -> None:
        while True:
            try:
                data = await reader.read(CHUNK)
            except OSError:
                data = b""
            queue.put_nowait((loop.time(), data))
            if not data:
                return

    async def send() -> None:
        while True:
            received, data = await queue.get()
            while (wait := received + delay - loop.time()) > 0:
                await asyncio.sleep(wait)
            if not data:
                if writer.can_write_eof():
                    writer.write_eof()
                return
            writer.write(data)
            await writer.drain()
            stats.chunks += 1
            stats.bytes[direction] += len(data)
            if len(stats.held) < HELD_KEPT:
                stats.held.append(loop.time() - received)

    await asyncio.gather(receive(), send())


async def _relay_connection(
    client_reader: asyncio.StreamReader,
    client_writer: asyncio.StreamWriter,
    target: tuple[str, int],
    delay: float,
    stats: RelayStats,
) -> None:
    try:
        target_reader, target_writer = await asyncio.open_connection(*target)
    except OSError:
        client_writer.close()
        return
    stats.connections += 1
    _nodelay(client_writer)
    _nodelay(target_writer)
    try:
        await asyncio.gather(
            _pipe(client_reader, target_writer, delay, stats, "to_target"),
            _pipe(target_reader, client_writer, delay, stats, "to_client"),
        )
    except OSError:
        pass  # a reset on one side: close both
    finally:
        for writer in (client_writer, target_writer):
            writer.close()


async def _echo(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    _nodelay(writer)
    try:
        while data := await reader.read(CHUNK):
            writer.write(data)
            await writer.drain()
    except OSError:
        pass
    finally:
        writer.close()


async def _serve_relay(args: argparse.Namespace) -> None:
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(signum, stop.set)
    delay = args.delay_ms / 1e3
    servers = []
    stats: dict[str, RelayStats] = {}  # per forward, by its listening port
    for listen, target in args.forward:
        stats[str(listen[1])] = RelayStats()
        handler = functools.partial(_relay_connection, target=target, delay=delay, stats=stats[str(listen[1])])
        servers.append(await asyncio.start_server(handler, *listen))
    if args.echo is not None:
        servers.append(await asyncio.start_server(_echo, *args.echo))
    emit(
        "ready",
        delay_ms=args.delay_ms,
        forward=[f"{a[0]}:{a[1]}={b[0]}:{b[1]}" for a, b in args.forward],
        echo=None if args.echo is None else f"{args.echo[0]}:{args.echo[1]}",
    )
    await stop.wait()
    for server in servers:
        server.close()
    emit("summary", delay_ms=args.delay_ms, forwards={port: st.summary() for port, st in stats.items()})


# -- probe ------------------------------------------------------------------------------
def probe(target: tuple[str, int], count: int, size: int, interval: float, timeout: float) -> dict[str, Any]:
    payload = b"p" * size
    rtts: list[float] = []
    with socket.create_connection(target, timeout=timeout) as sock:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        for _ in range(count):
            started = time.perf_counter()
            sock.sendall(payload)
            got = 0
            while got < size:
                chunk = sock.recv(size - got)
                if not chunk:
                    raise ConnectionError("echo server closed the connection")
                got += len(chunk)
            rtts.append(time.perf_counter() - started)
            time.sleep(interval)
    return {"target": f"{target[0]}:{target[1]}", "count": len(rtts), "size": size, "rtt_ms": _percentiles(rtts, 1e3)}


# -- observe ----------------------------------------------------------------------------
def observe(router: str, robot: str, connect_timeout: float) -> int:
    import zenoh

    from common.contracts.keys import STATUS, TRANSITION, WEIGHTS, liveliness_pattern
    from common.contracts.messages import CriticWeights, MessageError, ServiceStatus, Transition, decode
    from common.process.runtime import SignalWatch

    stop = threading.Event()
    SignalWatch(lambda _signum: stop.set()).start()  # never stop.set() inside a handler
    lock = threading.Lock()
    counts = {"weights": 0, "status": 0, "alive": 0, "transition": 0, "undecodable": 0}

    def record(kind: str, **fields: Any) -> None:
        with lock:
            counts[kind] += 1
            emit(kind, **fields)

    def recorder(schema: Any, kind: str, fields: Callable[[Any], dict[str, Any]]) -> Callable[[zenoh.Sample], None]:
        def on_sample(sample: zenoh.Sample) -> None:
            try:
                message = decode(schema, sample.payload.to_bytes())
            except MessageError:
                record("undecodable", key=str(sample.key_expr))
                return
            record(kind, **fields(message))

        return on_sample

    on_weights = recorder(
        CriticWeights, "weights", lambda w: {"version": w.version, "trained_step": w.trained_step, "episode": w.episode}
    )
    on_status = recorder(ServiceStatus, "status", lambda s: {"service": s.service, "counters": s.counters})
    on_transition = recorder(
        Transition,
        "transition",
        lambda t: {"step": t.step, "episode": t.episode, "state": list(t.state), "action": list(t.action)},
    )

    def on_token(sample: zenoh.Sample) -> None:
        record("alive", service=str(sample.key_expr).rsplit("/", 1)[-1], alive=sample.kind == zenoh.SampleKind.PUT)

    session = _open_until(router, connect_timeout, stop, "observe")
    if session is None:
        return 1
    keep = [
        session.declare_subscriber(WEIGHTS.key(robot), on_weights),
        session.declare_subscriber(TRANSITION.key(robot), on_transition),
        session.declare_subscriber(STATUS.pattern.format(robot=robot, service="*"), on_status),
        session.liveliness().declare_subscriber(liveliness_pattern(robot), on_token, history=True),
    ]
    emit("ready", router=router, robot=robot)
    stop.wait()
    for entity in keep:
        entity.undeclare()
    session.close()
    with lock:
        emit("summary", counts=counts)
    return 0


def observe_fleet(router: str, connect_timeout: float) -> int:
    """Every robot at once: weights, transitions and liveliness (with the holder's Zenoh id) as
    JSON lines; each robot's actions counted by the id of the session that sent them (in the summary)."""
    import zenoh

    from common.contracts.columns import decode_batch
    from common.contracts.keys import (
        ACTION,
        ACTION_BATCH,
        STATUS,
        TRANSITION,
        TRANSITION_BATCH,
        WEIGHTS,
        WEIGHTS_BATCH,
        every_robot,
    )
    from common.contracts.messages import (
        Action,
        CriticWeights,
        MessageError,
        ServiceStatus,
        Transition,
        decode,
    )
    from common.process.runtime import SignalWatch

    stop = threading.Event()
    SignalWatch(lambda _signum: stop.set()).start()  # never stop.set() inside a handler
    lock = threading.Lock()
    counts = {"weights": 0, "status": 0, "alive": 0, "transition": 0, "action": 0, "undecodable": 0}
    action_sources: dict[str, dict[str, int]] = {}  # robot -> sender's zid -> actions

    def decoded(schema: Any, sample: zenoh.Sample) -> Any:
        try:
            return decode(schema, sample.payload.to_bytes())
        except MessageError:
            with lock:
                counts["undecodable"] += 1
            return None

    def record(kind: str, **fields: Any) -> None:
        with lock:
            counts[kind] += 1
            emit(kind, **fields)

    def on_weights(sample: zenoh.Sample) -> None:
        if (w := decoded(CriticWeights, sample)) is not None:
            record("weights", robot=w.robot, version=w.version, trained_step=w.trained_step)

    def items(schema: Any, sample: zenoh.Sample) -> list[Any]:
        """A batch's messages (common.contracts.keys.Batch); none if it does not decode (counted)."""
        try:
            return decode_batch(schema, sample.payload.to_bytes())
        except MessageError:
            with lock:
                counts["undecodable"] += 1
            return []

    def on_weights_batch(sample: zenoh.Sample) -> None:  # a fleet critic's round
        for w in items(CriticWeights, sample):
            record("weights", robot=w.robot, version=w.version, trained_step=w.trained_step)

    def on_transition(sample: zenoh.Sample) -> None:
        if (t := decoded(Transition, sample)) is not None:
            record("transition", robot=t.robot, step=t.step)

    def on_transition_batch(sample: zenoh.Sample) -> None:  # an actor host's tick group
        for t in items(Transition, sample):
            record("transition", robot=t.robot, step=t.step)

    def on_status(sample: zenoh.Sample) -> None:
        if (s := decoded(ServiceStatus, sample)) is not None:
            record("status", robot=s.robot, service=s.service, counters=s.counters)

    def count_action(robot: str, sample: zenoh.Sample) -> None:
        source = "unstamped" if sample.timestamp is None else str(sample.timestamp.get_id())
        with lock:
            counts["action"] += 1
            per_robot = action_sources.setdefault(robot, {})
            per_robot[source] = per_robot.get(source, 0) + 1

    def on_action(sample: zenoh.Sample) -> None:
        if decoded(Action, sample) is not None:
            count_action(str(sample.key_expr).split("/")[1], sample)

    def on_action_batch(sample: zenoh.Sample) -> None:  # an actor host's tick group
        for action in items(Action, sample):
            count_action(action.robot, sample)

    def on_token(sample: zenoh.Sample) -> None:
        chunks = str(sample.key_expr).split("/")  # srl/<robot>/alive/<service>[/<zid>]
        record(
            "alive",
            robot=chunks[1],
            service=chunks[3],
            zid=chunks[4] if len(chunks) > 4 else None,
            alive=sample.kind == zenoh.SampleKind.PUT,
        )

    session = _open_until(router, connect_timeout, stop, "observe-fleet")
    if session is None:
        return 1
    keep = [
        session.declare_subscriber(every_robot(WEIGHTS), on_weights),
        session.declare_subscriber(WEIGHTS_BATCH.pattern, on_weights_batch),
        session.declare_subscriber(every_robot(TRANSITION), on_transition),
        session.declare_subscriber(TRANSITION_BATCH.pattern, on_transition_batch),
        session.declare_subscriber(every_robot(ACTION), on_action),
        session.declare_subscriber(ACTION_BATCH.pattern, on_action_batch),
        session.declare_subscriber(STATUS.pattern.format(robot="*", service="*"), on_status),
        session.liveliness().declare_subscriber("srl/*/alive/**", on_token, history=True),
    ]
    emit("ready", router=router, zid=str(session.info.zid()))
    stop.wait()
    for entity in keep:
        entity.undeclare()
    session.close()
    with lock:
        emit("summary", counts=counts, action_sources=action_sources)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tests.netns_tools", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    relay = sub.add_parser("relay", help="delaying TCP relay (and an echo server)")
    relay.add_argument("--delay-ms", type=float, required=True, help="added to every chunk, each direction")
    relay.add_argument(
        "--forward", type=_forward, action="append", default=[], metavar="LISTEN_HOST:PORT=TARGET_HOST:PORT"
    )
    relay.add_argument("--echo", type=_address, metavar="HOST:PORT", help="also serve a TCP echo here")
    rtt = sub.add_parser("probe", help="round trips to a TCP echo server")
    rtt.add_argument("--target", type=_address, required=True)
    rtt.add_argument("--count", type=int, default=50)
    rtt.add_argument("--size", type=int, default=64)
    rtt.add_argument("--interval", type=float, default=0.01)
    rtt.add_argument("--timeout", type=float, default=5.0)
    obs = sub.add_parser("observe", help="print liveliness, status and critic weights as JSON lines")
    obs.add_argument("--router", required=True)
    obs.add_argument("--robot", required=True)
    obs.add_argument("--connect-timeout", type=float, default=30.0)
    fleet = sub.add_parser("observe-fleet", help="the same for every robot, and who sent each robot's actions")
    fleet.add_argument("--router", required=True)
    fleet.add_argument("--connect-timeout", type=float, default=30.0)
    args = parser.parse_args(argv)
    if args.command == "relay":
        asyncio.run(_serve_relay(args))
        return 0
    if args.command == "probe":
        emit("rtt", **probe(args.target, args.count, args.size, args.interval, args.timeout))
        return 0
    if args.command == "observe-fleet":
        return observe_fleet(args.router, args.connect_timeout)
    return observe(args.router, args.robot, args.connect_timeout)


if __name__ == "__main__":
    sys.exit(main())
