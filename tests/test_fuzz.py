"""Bad input: property tests of every schema and decoder, and a live fuzz of the running services.

Invariants: a decoder returns a valid message or raises :class:`MessageError`, nothing else;
a valid message survives encode/decode unchanged. Live: for 10 s a rogue client floods every
key the services subscribe to; no service crashes, every refusal is counted, the actor's loop
holds, and every command the plant applies is finite and within the robot's bounds.
"""

from __future__ import annotations

import json
import math
import random
import time
from datetime import timedelta
from typing import Any

import pytest
import zenoh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from common.config.settings import Settings
from common.contracts.columns import columns_of, encode_columns
from common.contracts.keys import TRANSITION_BATCH
from common.contracts.messages import (
    MAX_PAYLOAD_BYTES,
    Action,
    CriticWeights,
    Message,
    MessageError,
    PlantState,
    ResetRequest,
    ServiceStatus,
    StepRequest,
    Transition,
    decode,
)
from common.contracts.ros_wire import TB3_BURGER_OMEGA_MAX, TB3_BURGER_V_MAX
from common.net.provenance import RESYNC_AFTER, SequenceGuard, SourceGate
from services.actor.ports import WeightsInbox
from services.actor.realtime import MAX_SEQ_JUMP
from services.robot_bridge.bridge import RobotBridge
from tests.harness import FakeCounts, cluster, wait_until
from tests.test_realtime_actor import PLANT, Loop

SCHEMAS: list[type[Message]] = [PlantState, Action, Transition, CriticWeights, StepRequest, ResetRequest, ServiceStatus]

# -- property tests ---------------------------------------------------------------------

WILD_NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(min_value=-(2**80), max_value=2**80),
    st.sampled_from([1e308, -1e308, 1e-320, 0.0, -0.0, 2**63, -(2**63) - 1]),
)
JSON_VALUES = st.recursive(
    st.one_of(st.none(), st.booleans(), WILD_NUMBERS, st.text(max_size=20)),
    lambda children: st.one_of(
        st.lists(children, max_size=20), st.dictionaries(st.text(max_size=10), children, max_size=5)
    ),
    max_leaves=40,
)


def _dumps(value: Any) -> bytes:
    return json.dumps(value, allow_nan=True).encode()


def _check(schema: type[Message], payload: bytes) -> None:
    try:
        message = decode(schema, payload)
    except MessageError:
        return
    # accepted: it must be a fully valid, finite message that round-trips
    assert isinstance(message, schema)
    assert decode(schema, message.encode()) == message
    for value in message.model_dump().values():
        for number in value if isinstance(value, tuple) else (value,):
            if isinstance(number, float):
                assert math.isfinite(number)


@pytest.mark.parametrize("schema", SCHEMAS, ids=lambda s: s.__name__)
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(payload=st.binary(max_size=300))
def test_random_bytes_decode_or_message_error(schema: type[Message], payload: bytes) -> None:
    _check(schema, payload)


def _field_values(schema: type[Message]) -> st.SearchStrategy[dict[str, Any]]:
    """Objects with the schema's own field names and wild values (the likeliest near-misses)."""
    names = list(schema.model_fields)
    return st.dictionaries(
        st.sampled_from([*names, "extra"]),
        st.one_of(JSON_VALUES, st.lists(WILD_NUMBERS, max_size=16)),
        max_size=len(names) + 1,
    )


@pytest.mark.parametrize("schema", SCHEMAS, ids=lambda s: s.__name__)
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_near_miss_objects_decode_or_message_error(schema: type[Message], data: st.DataObject) -> None:
    _check(schema, _dumps(data.draw(_field_values(schema))))


@settings(max_examples=200, deadline=None)
@given(
    state=st.tuples(*[st.floats(-1e4, 1e4)] * 2, st.floats(-1e6, 1e6)),
    action=st.tuples(*[st.floats(-100, 100)] * 2),
    cost=st.floats(0, 1e12),
    step=st.integers(0, 2**62),
    episode=st.integers(0, 2**62),
)
def test_valid_messages_round_trip_exactly(
    state: tuple[float, float, float], action: tuple[float, float], cost: float, step: int, episode: int
) -> None:
    for message in (
        PlantState(robot="r", episode=episode, seq=step, stamp_ns=step, state=state, source="sim"),
        Action(robot="r", episode=episode, step=step, stamp_ns=0, action=action, state_seq=-1),
        Transition(robot="r", episode=episode, step=step, state=state, action=action, cost=cost),
    ):
        assert decode(type(message), message.encode()) == message


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), 1e300, -1e5])
def test_huge_and_non_finite_states_and_actions_are_refused(bad: float) -> None:
    state = _dumps({"robot": "r", "episode": 0, "seq": 0, "stamp_ns": 0, "state": [bad, 0, 0], "source": "sim"})
    action = _dumps({"robot": "r", "episode": 0, "step": 0, "stamp_ns": 0, "action": [bad, 0], "state_seq": -1})
    for schema, payload in ((PlantState, state), (Action, action)):
        with pytest.raises(MessageError):
            decode(schema, payload)


def test_versions_and_oversize_are_refused() -> None:
    ok = {"robot": "r", "episode": 0, "step": 0, "stamp_ns": 0, "action": [0.1, 0.0], "state_seq": -1}
    assert decode(Action, _dumps(ok)).action == (0.1, 0.0)
    for version in (0, 2, "1", None):
        with pytest.raises(MessageError):
            decode(Action, _dumps({**ok, "schema_version": version}))
    with pytest.raises(MessageError, match="exceeds"):
        decode(Action, b" " * (MAX_PAYLOAD_BYTES + 1))
    with pytest.raises(MessageError):
        decode(Action, b"[" * 5000 + b"]" * 5000)  # deep nesting: refused, not a RecursionError


# -- live fuzz ----------------------------------------------------------------------------

FUZZ_SECONDS = 10.0
FUZZ_RATE_HZ = 400  # samples per second over all keys


def _rogue_payload(rng: random.Random, key: str, now_us: int, episode: int) -> bytes:
    """One bad sample for ``key``: bytes, wrong schema, NaN/inf/huge, old/future versions, oversize."""
    kind = rng.randrange(7)
    if kind == 0:
        return rng.randbytes(rng.randrange(0, 200))
    if kind == 1:
        return b"x" * (MAX_PAYLOAD_BYTES + rng.randrange(1, 5000))
    if kind == 2:
        return _dumps({"schema_version": rng.choice([0, 2, 99]), "robot": "fz"})
    bad = rng.choice([float("nan"), float("inf"), -float("inf"), 1e300, -1e308])
    if key == "state":
        return _dumps(
            {
                "robot": "fz",
                "episode": 0,
                "seq": rng.randrange(10**6),
                "stamp_ns": 0,
                "state": [bad, 0.0, 0.0],
                "source": "sim",
            }
        )
    if key == "action":
        return _dumps({"robot": "fz", "episode": 0, "step": 0, "stamp_ns": 0, "action": [bad, bad], "state_seq": 0})
    if key == "transition":  # the critic reads transitions in batches alone (Batch.on_demand): a batch's columns
        columns = columns_of(
            Transition, [Transition(robot="fz", episode=0, step=0, state=(0, 0, 0), action=(0, 0), cost=0)]
        )
        columns.floats[:, -1] = bad if kind != 3 else -1.0  # the cost
        (payload,) = encode_columns(columns)  # written as it is: the receiver checks
        return payload
    weights = {
        "robot": "fz",
        "episode": episode,
        "version": 1,
        "trained_step": 0,
        "q_weights": [1.0] * 15,
        "v_weights": [1.0] * 6,
        "q_residual": 0.0,
        "v_residual": 0.0,
        "pairs": 0,
    }
    if kind == 3:  # valid schema, a version from the far future (would lock out the real critic)
        return _dumps({**weights, "version": now_us + 10**12})
    if kind == 4:  # valid schema, an old version (or an old episode)
        return _dumps({**weights, "version": 1} if rng.random() < 0.5 else {**weights, "episode": max(0, episode - 1)})
    return _dumps({**weights, "q_weights": [bad] * 15})


# -- valid but malicious: well-formed messages with extreme values, then the real stream -----
# Each property feeds a receiver's gate an attack of well-formed messages with extreme but valid
# numbers, as a forger that copies the live session's id would, then lets the real stream go on
# from its own numbers: it must be followed again within a bounded number of messages (no
# lockout), and nothing out of bounds may ever come out.

BIG = 2**62
EXTREME = st.one_of(
    st.sampled_from([0, 1, BIG - 1, BIG, BIG + 1, 2**63 - 1]),
    st.integers(0, 2**63 - 1),
    st.integers(0, 20_000),
)
MALICIOUS = settings(max_examples=60, deadline=timedelta(seconds=2), suppress_health_check=[HealthCheck.too_slow])


def _near(real: int) -> st.SearchStrategy[int]:
    """Values around the real stream's own numbers: just behind, equal, just ahead, the jump bound."""
    return st.integers(-3, 10_003).map(lambda d: max(0, real + d))


@MALICIOUS
@given(data=st.data(), real=st.integers(0, 10**9))
def test_a_sequence_guard_is_never_locked_out(data: st.DataObject, real: int) -> None:
    guard = SequenceGuard(MAX_SEQ_JUMP)
    assert guard.check("plant", real) is None
    attack = data.draw(st.lists(st.one_of(EXTREME, _near(real), st.integers(-(2**63), -1)), max_size=60))
    now = 0.0
    for value in attack:
        now += 0.001
        guard.check("plant", value, now)
    accepted = []
    for k in range(1, 3 * guard.restart_after):
        now += 0.02  # 50 Hz states
        accepted.append(guard.check("plant", real + k, now) is None)
    first = accepted.index(True)
    assert first < guard.restart_after and all(accepted[first:])


@MALICIOUS
@given(
    data=st.data(),
    episode=st.integers(0, BIG),
    step=st.integers(0, 10**6),
)
def test_the_bridge_action_gate_is_never_locked_out_and_never_exceeds_the_limits(
    data: st.DataObject, episode: int, step: int
) -> None:
    settings_ = Settings.load(transport={"robot": "fz"})
    commands: list[tuple[float, float]] = []
    counts = FakeCounts()
    gate = SourceGate("actor")
    bridge = RobotBridge(settings_, lambda s: None, lambda v, w: commands.append((v, w)), counts, gate)
    gate.update("a1", True)
    bridge.on_actor_identity("a1", True)
    now = 0.0

    def act(e: int, k: int, v: float, w: float, source: str = "a1") -> None:
        bridge.on_action(Action(robot="fz", episode=e, step=k, stamp_ns=0, action=(v, w), state_seq=-1), now, source)

    act(episode, step, 0.1, 0.0)
    speeds = st.floats(-100, 100, allow_nan=False)
    attack = data.draw(
        st.lists(
            st.tuples(st.one_of(EXTREME, _near(episode)), st.one_of(EXTREME, _near(step)), speeds, speeds),
            max_size=40,
        )
    )
    for e, k, v, w in attack:
        now += 0.001
        act(e, k, v, w, data.draw(st.sampled_from(["a1", "a1", "rogue"])))
    applied = []
    for n in range(1, 3 * RESYNC_AFTER):
        now += 0.1  # the real actor at 10 Hz, from its own numbers
        act(episode, step + n, 0.05, 0.5)
        applied.append(commands[-1] == (0.05, 0.5))
    first = applied.index(True)
    assert first < RESYNC_AFTER and all(applied[first:])
    v_max = min(settings_.plant.v_max, TB3_BURGER_V_MAX)
    omega_max = min(settings_.plant.omega_max, TB3_BURGER_OMEGA_MAX)
    assert all(abs(v) <= v_max and abs(w) <= omega_max for v, w in commands)


@MALICIOUS
@given(data=st.data())
def test_the_weights_inbox_is_never_locked_out_and_holds_only_boxed_weights(data: st.DataObject) -> None:
    settings_ = Settings.load()
    low, high = settings_.critic.bounds or (-1e6, 1e6)
    gate = SourceGate("critic")
    gate.update("c1", True)
    counts = FakeCounts()
    inbox = WeightsInbox(settings_, counts, gate)  # type: ignore[arg-type]
    inbox.reset(5)
    inbox.published(100)
    now_us = time.time_ns() // 1000
    start = now_us - 3_600_000_000  # a critic that started an hour ago: versions far behind the clock

    def offer(version: int, value: float, trained: int = 50, source: str = "c1") -> None:
        inbox.offer(
            CriticWeights(
                robot="fz",
                episode=5,
                version=version,
                trained_step=trained,
                q_weights=(value,) * 15,
                v_weights=(value,) * 6,
                q_residual=0.0,
                v_residual=0.0,
                pairs=0,
            ),
            source,
        )

    offer(start, 1.0)
    edges = st.sampled_from([low, high, high + 1e-9, low - 1e-9, high * 1.0000001, -high, 1e300, -1e300])
    versions = st.one_of(
        EXTREME.map(lambda v: max(1, v)),
        st.integers(-10_000_000, 10_000_000).map(lambda d: max(1, now_us + d)),
        st.integers(-3, 50).map(lambda d: max(1, start + d)),
    )
    attack = data.draw(
        st.lists(st.tuples(versions, st.one_of(edges, st.floats(low, high)), st.integers(-1, 200)), max_size=40)
    )
    for version, value, trained in attack:
        offer(version, value, trained, data.draw(st.sampled_from(["c1", "c1", "rogue"])))
        held = inbox.current()
        assert low <= float(min(held.q.min(), held.v.min())) and float(max(held.q.max(), held.v.max())) <= high
        assert held.trained_step <= 100
    accepted = []
    for n in range(1, 3 * RESYNC_AFTER):
        offer(start + 100 + n, 2.0)  # the real critic goes on counting from its own numbers
        accepted.append(inbox.current().version == start + 100 + n)
    first = accepted.index(True)
    assert first < RESYNC_AFTER and all(accepted[first:])


@MALICIOUS
@given(data=st.data(), real_seq=st.integers(0, 10**9))
def test_the_actor_state_acceptance_is_never_locked_out(data: st.DataObject, real_seq: int) -> None:
    t = Loop()
    t.run(2)
    t.seq = real_seq
    t.publish_state()
    attack = data.draw(
        st.lists(st.tuples(st.one_of(EXTREME, st.integers(0, 3)), st.one_of(EXTREME, _near(real_seq))), max_size=40)
    )
    for episode, seq in attack:
        state = (data.draw(st.floats(-1e4, 1e4)), data.draw(st.floats(-1e4, 1e4)), 0.0)
        t.loop.on_state(
            PlantState(robot="fk", episode=episode, seq=seq, stamp_ns=BIG, state=state, source="sim"), PLANT
        )
    taken = []
    for _ in range(1, 3 * t.loop.order.restart_after):
        t.publish_state(x=0.25)  # the real plant: episode 0, seq on from its own
        held = t.loop.latest
        taken.append(held is not None and held[0].seq == t.seq and held[0].state[0] == 0.25)
    first = taken.index(True)
    assert first < t.loop.order.restart_after + RESYNC_AFTER and all(taken[first:])


@pytest.mark.timing
@pytest.mark.integration
@pytest.mark.slow
def test_live_fuzz_every_key_for_ten_seconds() -> None:
    rng = random.Random(20261122)
    keys = ["state", "action", "transition", "critic/weights"]
    sent = {k: 0 for k in keys}
    actions: list[tuple[float, float]] = []
    episodes: list[int] = []  # the actor's episode id: the rogue forges weights for it
    with cluster(robot="fz") as c:
        c.start_plant_and_critic()
        actor = c.start("actor", "actor", "--mode", "realtime", "--run-seconds", str(FUZZ_SECONDS + 4))
        c.wait_alive("actor")
        assert c.session is not None
        c.session.declare_subscriber("srl/fz/action", lambda s: _record_action(s, actions, episodes))
        wait_until(lambda: bool(episodes), 30, "the actor's first action")
        publishers = {  # each on the key its service reads (transitions: the batch key alone)
            k: c.session.declare_publisher(
                TRANSITION_BATCH.pattern if k == "transition" else f"srl/fz/{k}",
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
            for k in keys
        }
        started = time.monotonic()
        next_at = started
        while time.monotonic() < started + FUZZ_SECONDS:
            key = rng.choice(keys)
            publishers[key].put(_rogue_payload(rng, key, time.time_ns() // 1000, episodes[0]))
            sent[key] += 1
            next_at += 1.0 / FUZZ_RATE_HZ
            time.sleep(max(0.0, next_at - time.monotonic()))
        for name in ("plant", "critic", "actor"):
            assert c.alive(name), f"{name} died under the fuzz"
        assert actor.process.wait(timeout=60) == 0, actor.stderr[-10:]
        summaries = {"actor": actor.summary()}
        for name in ("critic", "plant"):
            assert c.procs[name].stop() == 0, c.procs[name].stderr[-10:]
            summaries[name] = c.procs[name].summary()
    counters = {name: s["counters"] for name, s in summaries.items()}
    # every refusal counted: each bad sample is refused by each service that subscribes to it
    assert counters["actor"].get("rejected.state", 0) >= sent["state"]
    assert counters["actor"].get("rejected.critic/weights", 0) >= sent["critic/weights"]
    assert counters["plant"].get("rejected.action", 0) >= sent["action"]
    assert counters["critic"].get("rejected.transition", 0) >= sent["transition"]
    assert summaries["critic"]["stale_episode"] == 0  # no forged transition entered a replay
    assert counters["actor"].get("tick_errors", 0) == 0
    # the loop held and the real critic's weights were still taken (no future version locked it out)
    loop = summaries["actor"]["loop"]
    assert loop["missed_deadlines"] == 0
    assert summaries["actor"]["steps"] >= 0.8 * (FUZZ_SECONDS + 4) / 0.1
    assert summaries["actor"]["staleness_steps"]["median"] <= 1
    # every command on the action key that the plant accepted is finite and within bounds: the
    # actor's own (the rogue's are refused above); the plant clamps again before applying
    plant = Settings.load().plant
    assert actions, "no valid action was seen"
    for v, w in actions:
        assert math.isfinite(v) and math.isfinite(w)
        assert abs(v) <= plant.v_max and abs(w) <= plant.omega_max
    total = sum(sent.values())
    print(f"fuzz: {total} bad samples in {FUZZ_SECONDS:.0f} s ({sent}); counters {counters}")


def _record_action(sample: zenoh.Sample, sink: list[tuple[float, float]], episodes: list[int]) -> None:
    try:
        message = decode(Action, sample.payload.to_bytes())
    except MessageError:
        return  # the rogue's own garbage on the same key: refused by the plant as well
    sink.append(message.action)
    if not episodes:
        episodes.append(message.episode)


def test_the_true_state_is_optional_on_the_wire_and_absent_when_unknown() -> None:
    """Schema 1 plus an optional true state (docs/reference/messages.md): a robot's message carries no such key,
    byte for byte what it was; a simulator's round-trips."""
    robot = PlantState(robot="r", episode=1, seq=2, stamp_ns=3, state=(0.1, 0.2, 0.3), source="robot")
    assert json.loads(robot.encode()) == {
        "schema_version": 1,
        "robot": "r",
        "episode": 1,
        "seq": 2,
        "stamp_ns": 3,
        "state": [0.1, 0.2, 0.3],
        "source": "robot",
    }
    sim = PlantState(
        robot="r", episode=1, seq=2, stamp_ns=3, state=(0.1, 0.2, 0.3), source="sim", true_state=(0.0, 0.2, 0.3)
    )
    assert decode(PlantState, sim.encode()) == sim
    for bad in (float("nan"), 1e300):
        with pytest.raises(MessageError):
            decode(PlantState, sim.encode().replace(b"[0.0,", f"[{bad},".encode()))
