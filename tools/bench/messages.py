"""``srl bench messages``: where a message's CPU goes, and what one message per host tick would save.

Two parts, both on srl's own message classes and code (common/contracts/messages.py,
common/net/transport.py):

* **codec**, in this process: per kind of hot message (state, action, transition, weights), the CPU
  of ``Message.encode``, of parsing its JSON alone (pydantic-core's parser, ``from_json``, the one
  ``decode`` uses), and of ``decode`` (parsing and pydantic's validation: bounds, NaN, sizes,
  versions); validation is their difference.
* **wire**, over a Zenoh router on loopback (three processes: a publisher, the router, a subscriber):
  ``--robots`` robots' messages of one kind at ``1 / delta`` for ``--seconds``, sent three ways in
  turn, ``each, threaded, batched, each, ...`` (``--rounds`` rounds), so a change of the machine's
  load hits all:

  - ``each``: one message per robot on its own key (``srl/<robot>/state``), what a robot bridge and
    an outside client send and read, decoded and checked as :class:`~common.net.transport.Bus` does
    (``decode_sample``, a raw subscription of ``srl/*/state``), the subscriber's handler on Zenoh's
    network thread (``transport.callback_threads = false``);
  - ``threaded``: the same wire, the handler on a thread of its own (``Bus.subscribe(threaded=True)``,
    what ``srl record``'s wildcards do);
  - ``batched``: one message per tick holding every robot's, as srl's plant host sends its states and
    a fleet's critic its weights (common.contracts.keys.Batch): the same messages as columns
    (``batch_payloads``), each row validated as the schema validates a message on arrival
    (``decode_batch``), here on a key of the benchmark's own.

  The CPU of each process over the run (/proc: user + system, every thread), divided by the robot
  messages sent, is its cost per robot message; the subscriber's count of what it validated must
  equal what was sent (nothing lost).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from typing import Any

KINDS = ("state", "action", "transition", "weights")
WAYS = ("each", "threaded", "batched")  # the publisher of "threaded" is "each"'s
BATCH_KEY = "srl/bench/batch"  # the batched way's one key (outside every robot's srl/<robot>/...)
CODEC_REPEATS = 3000


def add_parser(kinds: Any) -> None:
    """``srl bench messages`` among ``srl bench``'s kinds (an argparse subparsers action)."""
    helptext = "a message's CPU: encode, parse, validate, and through Zenoh one per robot vs one per tick"
    parser = kinds.add_parser("messages", help=helptext, description=helptext[0].upper() + helptext[1:] + ".")
    parser.add_argument("--robots", type=int, default=100, help="robots whose messages are sent (default: 100)")
    parser.add_argument(
        "--kind", choices=KINDS, default="state", help="the message sent over the wire (default: state)"
    )
    parser.add_argument("--seconds", type=float, default=10.0, help="each run over the wire [s] (default: 10)")
    parser.add_argument("--rounds", type=int, default=2, help="rounds of runs (each, threaded, batched) (default: 2)")
    parser.add_argument("--json", action="store_true", help="last stdout line: one JSON object")
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from common.config.arguments import UsageError

    if args.robots < 1 or args.rounds < 1:
        raise UsageError("--robots and --rounds must be >= 1")
    if not 1.0 <= args.seconds <= 3600.0:
        raise UsageError(f"--seconds must be within 1 and 3600, got {args.seconds}")
    result = run_messages_benchmark(args.robots, args.kind, args.seconds, args.rounds)
    print(format_table(result))
    if args.json:
        print(json.dumps(result))
    return 0


def sample_message(kind: str, robot: int, step: int) -> Any:
    """A message of ``kind`` as the services send them (every field set, values of a running robot)."""
    from common.contracts import messages as m

    name = f"robot{robot + 1}"
    x, y, alpha = 1.2345678 - 0.001 * step, -0.8765432 + 0.001 * step, 0.785398 + 0.01 * robot
    if kind == "state":
        return m.PlantState(
            robot=name,
            episode=0,
            seq=step,
            stamp_ns=1_700_000_000_000_000_000 + step,
            state=(x, y, alpha),
            source="sim",
            true_state=(x, y, alpha),
            saturated_commands=0,
        )
    if kind == "action":
        return m.Action(
            robot=name, episode=0, step=step, stamp_ns=123_456_789_012 + step, action=(0.21, -1.3), state_seq=step
        )
    if kind == "transition":
        return m.Transition(robot=name, episode=0, step=step, state=(x, y, alpha), action=(0.21, -1.3), cost=0.0123456)
    return m.CriticWeights(
        robot=name,
        episode=0,
        version=step + 1,
        trained_step=step,
        q_weights=tuple(0.1234567 * (i + 1) for i in range(15)),
        v_weights=tuple(0.7654321 * (i + 1) for i in range(6)),
        q_residual=0.00123,
        v_residual=0.00456,
        pairs=99,
    )


def topic_of(kind: str) -> Any:
    from common.contracts import keys

    return {"state": keys.STATE, "action": keys.ACTION, "transition": keys.TRANSITION, "weights": keys.WEIGHTS}[kind]


def codec_row(kind: str, repeats: int = CODEC_REPEATS) -> dict[str, Any]:
    """CPU per message [us] of encode, JSON parse alone, decode (parse + validation) and validation."""
    from pydantic_core import from_json

    from common.contracts.messages import decode

    message = sample_message(kind, 0, 17)
    schema = type(message)
    payload = message.encode()

    def per_call(call: Any) -> float:
        started = time.process_time()
        for _ in range(repeats):
            call()
        return (time.process_time() - started) / repeats * 1e6

    encode_us = per_call(message.encode)
    parse_us = per_call(lambda: from_json(payload))
    decode_us = per_call(lambda: decode(schema, payload))
    return {
        "kind": kind,
        "bytes": len(payload),
        "encode_us": encode_us,
        "parse_us": parse_us,
        "decode_us": decode_us,
        "validate_us": max(0.0, decode_us - parse_us),
    }


# -- the wire: child processes ----------------------------------------------------------------


def _transport(router: str) -> Any:
    from common.config.settings import Settings

    return Settings.load(transport={"router": router}).transport


def _subscriber(router: str, kind: str, way: str, limit: float) -> None:
    """Count the robot messages validated on arrival, from "ready" until a line on stdin (or
    ``limit`` seconds); print the count."""
    import threading

    from common.contracts.columns import decode_batch
    from common.net.transport import Bus, decode_sample

    topic = topic_of(kind)
    bus = Bus.open(_transport(router), "bench")
    lock, count = threading.Lock(), [0]

    def one(_: object) -> None:
        with lock:
            count[0] += 1

    if way in ("each", "threaded"):
        # a raw subscription: srl's services read some kinds only in batches (Batch.on_demand)
        bus.raw_subscriber(
            topic.pattern.format(robot="*"),
            lambda sample: one(decode_sample(topic, str(sample.key_expr), sample.payload.to_bytes())),
            threaded=way == "threaded",
        )
    else:

        def many(sample: Any) -> None:
            messages = decode_batch(topic.schema, sample.payload.to_bytes())
            with lock:
                count[0] += len(messages)

        bus.session.declare_subscriber(BATCH_KEY, many)  # undeclared with the session
    told = threading.Event()

    def listen() -> None:
        sys.stdin.readline()
        told.set()

    threading.Thread(target=listen, daemon=True).start()
    print("ready", flush=True)
    told.wait(limit)
    time.sleep(0.5)  # what is still on its way arrives
    print(json.dumps({"validated": count[0]}), flush=True)
    bus.close()


def _publisher(router: str, kind: str, way: str, robots: int, seconds: float, period: float) -> None:
    """``robots`` robots' messages every ``period`` for ``seconds``: "sending" at the start, then the
    number of robot messages sent."""
    from common.contracts.columns import batch_payloads
    from common.net.transport import Bus

    topic = topic_of(kind)
    bus = Bus.open(_transport(router), "bench")
    if way != "batched":  # each robot's key, as a robot bridge or an outside client publishes it
        sends = [bus.session.declare_publisher(topic.key(f"robot{i + 1}"), express=bus.express) for i in range(robots)]
    else:
        batch = bus.session.declare_publisher(BATCH_KEY, express=bus.express)  # undeclared with the session
    time.sleep(1.0)  # the subscriber's interest reaches this session
    print("sending", flush=True)
    started, tick, sent = time.monotonic(), 0, 0
    while time.monotonic() - started < seconds:
        messages = [sample_message(kind, i, tick) for i in range(robots)]
        if way != "batched":
            for send, message in zip(sends, messages, strict=True):
                send.put(message.encode())
        else:
            for payload in batch_payloads(messages):
                batch.put(payload)
        sent += robots
        tick += 1
        time.sleep(max(0.0, started + tick * period - time.monotonic()))
    print(json.dumps({"sent": sent}), flush=True)
    time.sleep(0.5)  # the last messages leave before the session closes
    bus.close()


def child_main(argv: list[str]) -> int:
    """``python -m tools.bench.messages ROLE ...``: a child of the benchmark (it dies with its parent)."""
    from common.system.lifeline import set_parent_death_signal

    set_parent_death_signal()
    role, router, kind, way = argv[:4]
    if role == "subscribe":
        _subscriber(router, kind, way, float(argv[4]))
    else:
        _publisher(router, kind, way, int(argv[4]), float(argv[5]), float(argv[6]))
    return 0


class _Child:
    """A child of the benchmark: its own session (process group), reading lines with a time limit."""

    def __init__(self, argv: list[str]) -> None:
        self.process = subprocess.Popen(
            argv,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, "SRL_PARENT_PID": str(os.getpid())},
            start_new_session=True,
        )

    def line(self, timeout: float) -> str:
        """The child's next stdout line within ``timeout`` seconds; an error naming its last words if
        it ended or said nothing in time."""
        import select

        assert self.process.stdout is not None
        ready, _, _ = select.select([self.process.stdout], [], [], timeout)
        line = self.process.stdout.readline() if ready else ""
        if not line:
            self.stop()
            assert self.process.stderr is not None
            tail = self.process.stderr.read().strip().splitlines()[-1:] or ["no output"]
            raise RuntimeError(f"a benchmark process ended or hung: {tail[0]}")
        return line.strip()

    def tell(self) -> None:
        assert self.process.stdin is not None
        self.process.stdin.write("stop\n")
        self.process.stdin.flush()

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
        self.process.wait(timeout=10)


def one_run(router: tuple[str, int], kind: str, way: str, robots: int, seconds: float, period: float) -> dict[str, Any]:
    """One run over the wire: CPU per robot message of each process, and what arrived."""
    from tools.launch.measure import cpu_of

    endpoint, router_pid = router
    here = [sys.executable, "-m", "tools.bench.messages"]
    subscriber = _Child([*here, "subscribe", endpoint, kind, way, str(seconds + 60.0)])
    publisher = None
    try:
        if subscriber.line(30.0) != "ready":
            raise RuntimeError("the subscriber did not start")
        publisher = _Child([*here, "publish", endpoint, kind, way, str(robots), str(seconds), str(period)])
        if publisher.line(30.0) != "sending":
            raise RuntimeError("the publisher did not start")
        pids = {"publisher": publisher.process.pid, "router": router_pid, "subscriber": subscriber.process.pid}
        before = cpu_of(pids)
        sent = json.loads(publisher.line(seconds + 30.0))["sent"]
        after = cpu_of(pids)
        subscriber.tell()
        validated = json.loads(subscriber.line(30.0))["validated"]
    finally:
        for child in (publisher, subscriber):
            if child is not None:
                child.stop()
    per_message = {name: (after[name] - before[name]) / max(sent, 1) * 1e6 for name in pids}
    return {"way": way, "sent": sent, "validated": validated, **{f"{k}_us": v for k, v in per_message.items()}}


def run_messages_benchmark(robots: int, kind: str, seconds: float, rounds: int) -> dict[str, Any]:
    from common.config.settings import Settings
    from tools.bench.meta import run_info
    from tools.launch.supervisor import Supervisor, free_loopback_endpoint, router_reachable

    period = Settings.load().plant.sampling_time
    load_before = os.getloadavg()
    codec = [codec_row(k) for k in KINDS]
    endpoint = free_loopback_endpoint()
    supervisor = Supervisor([], dict(os.environ), quiet=True)
    runs: list[dict[str, Any]] = []
    try:
        router = supervisor.spawn("router", ["router", f"--router={endpoint}"])
        settings = Settings.load()
        supervisor.wait_for("router", lambda: router_reachable(settings, endpoint), 30.0)
        for round_ in range(rounds):
            for way in WAYS:
                print(
                    f"[bench] round {round_ + 1}/{rounds}: {way}, {robots} robots' {kind}", file=sys.stderr, flush=True
                )
                runs.append(one_run((endpoint, router.process.pid), kind, way, robots, seconds, period))
    finally:
        supervisor.stop_all()
    rows = []
    for way in WAYS:
        mine = [r for r in runs if r["way"] == way]
        row: dict[str, Any] = {"way": way, "runs": len(mine)}
        for name in ("publisher", "router", "subscriber"):
            row[f"{name}_us"] = statistics.median(r[f"{name}_us"] for r in mine)
        row["total_us"] = row["publisher_us"] + row["router_us"] + row["subscriber_us"]
        row["sent"] = sum(r["sent"] for r in mine)
        row["validated"] = sum(r["validated"] for r in mine)
        rows.append(row)
    return {
        "robots": robots,
        "kind": kind,
        "seconds": seconds,
        "rounds": rounds,
        "rate_hz": 1.0 / period,
        "codec": codec,
        "runs": runs,
        "rows": rows,
        "load_before": list(load_before),
        "load_after": list(os.getloadavg()),
        "run": run_info(),
    }


def format_table(result: dict[str, Any]) -> str:
    lines = [
        "srl bench messages: CPU per message [us], in this process (codec) and through a Zenoh router on "
        "loopback (wire)",
        "",
        "kind        bytes  encode   parse  decode  validate",
    ]
    for c in result["codec"]:
        lines.append(
            f"{c['kind']:<10} {c['bytes']:>6} {c['encode_us']:>7.1f} {c['parse_us']:>7.1f} {c['decode_us']:>7.1f} "
            f"{c['validate_us']:>9.1f}"
        )
    lines += [
        "",
        f"wire: {result['robots']} robots' {result['kind']} at {result['rate_hz']:.0f} Hz, {result['seconds']:.0f} s a "
        f"run, {result['rounds']} rounds (each, threaded, batched, in turn); CPU per robot message, median of "
        "the rounds",
        "way       publisher  router  subscriber   total  validated/sent",
    ]
    for r in result["rows"]:
        lines.append(
            f"{r['way']:<9} {r['publisher_us']:>9.1f} {r['router_us']:>7.1f} {r['subscriber_us']:>11.1f} "
            f"{r['total_us']:>7.1f}  {r['validated']}/{r['sent']}"
        )
    before, after = result["load_before"], result["load_after"]
    lines.append(f"load (1 min) {before[0]:.2f} -> {after[0]:.2f}, {os.cpu_count()} CPUs")
    lost = [r["way"] for r in result["rows"] if r["validated"] != r["sent"]]
    lines.append(f"target {'FAIL' if lost else 'PASS'} nothing lost: every robot message sent was validated")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(child_main(sys.argv[1:]))
