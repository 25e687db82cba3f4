"""Another system's messages and batches (common/contracts/wire.py): sized by its row, naming it,
and refused in one line when of another system or size; the robot's are srl's own, unchanged."""

from __future__ import annotations

import json
import math
from typing import Any

import pytest

from common.contracts import keys
from common.contracts.columns import batch_payloads, decode_batch, layout
from common.contracts.messages import (
    Action,
    CriticWeights,
    MessageError,
    PlantState,
    StepRequest,
    Transition,
    decode,
)
from common.contracts.wire import MAX_VALUE, ROBOT_WIRE, wire
from common.math.systems import BUILT_IN_SYSTEMS, SYSTEMS, register_system

OTHERS = [name for name in BUILT_IN_SYSTEMS if not SYSTEMS[name].wheeled]


def one_line(error: pytest.ExceptionInfo[MessageError]) -> str:
    text = str(error.value)
    assert "\n" not in text, text
    return text


def messages_of(name: str, robots: int = 3) -> dict[str, list[Any]]:
    """A few valid messages of each kind of ``name``'s wire."""
    made, row = wire(name), SYSTEMS[name]
    s, u = tuple(0.1 * (i + 1) for i in range(row.state_dim)), tuple(0.01 for _ in range(row.action_dim))
    q, v = (0.5,) * row.q_features, (0.25,) * row.v_features
    return {
        "state": [
            made.state(system=name, robot=f"r{i}", episode=0, seq=i, stamp_ns=1, state=s, source="sim")
            for i in range(robots)
        ],
        "action": [
            made.action(system=name, robot=f"r{i}", episode=0, step=i, stamp_ns=1, action=u, state_seq=i)
            for i in range(robots)
        ],
        "transition": [
            made.transition(system=name, robot=f"r{i}", episode=0, step=i, state=s, action=u, cost=0.1)
            for i in range(robots)
        ],
        "weights": [
            made.weights(
                system=name,
                robot=f"r{i}",
                episode=0,
                version=1,
                trained_step=-1,
                q_weights=q,
                v_weights=v,
                q_residual=0.0,
                v_residual=0.0,
                pairs=0,
            )
            for i in range(robots)
        ],
    }


def test_the_robots_wire_is_srls_own_messages_and_topics() -> None:
    assert wire() is wire("unicycle") is ROBOT_WIRE
    assert (ROBOT_WIRE.state, ROBOT_WIRE.action, ROBOT_WIRE.transition) == (PlantState, Action, Transition)
    assert (ROBOT_WIRE.weights, ROBOT_WIRE.step_request) == (CriticWeights, StepRequest)
    assert (ROBOT_WIRE.STATE, ROBOT_WIRE.TRANSITION, ROBOT_WIRE.PLANT_STEP) == (
        keys.STATE,
        keys.TRANSITION,
        keys.PLANT_STEP,
    )
    assert wire("pendulum") is wire("pendulum")  # made once
    with pytest.raises(ValueError, match="unknown system"):
        wire("no_such_system")


@pytest.mark.parametrize("name", OTHERS)
def test_another_systems_messages_are_of_its_sizes_name_it_and_round_trip(name: str) -> None:
    made, row = wire(name), SYSTEMS[name]
    for kind, messages in messages_of(name).items():
        for message in messages:
            again = decode(type(message), message.encode())
            assert again == message and again.system == name, kind  # type: ignore[attr-defined]
    state = messages_of(name)["state"][0]
    assert len(state.state) == row.state_dim and "map_to_odom" not in made.state.model_fields
    assert b"true_state" not in state.encode()  # absent optional fields left out, as the robot's
    weights = messages_of(name)["weights"][0]
    assert (len(weights.q_weights), len(weights.v_weights)) == (row.q_features, row.v_features)
    # the same keys as the robot's, carrying this system's schema
    assert made.TRANSITION.pattern == keys.TRANSITION.pattern and made.TRANSITION.schema is made.transition
    assert made.PLANT_STEP.request is made.step_request and made.PLANT_STEP.reply is made.state


@pytest.mark.parametrize("name", OTHERS)
def test_a_message_of_another_size_system_or_none_is_refused_in_one_line(name: str) -> None:
    made, row = wire(name), SYSTEMS[name]
    transition = messages_of(name)["transition"][0]
    good = transition.model_dump()
    other = next(o for o in OTHERS if o != name)
    for change, said in (
        ({"state": [*good["state"], 0.0]}, "state"),
        ({"action": [*good["action"], 0.0]}, "action"),
        ({"system": other}, "system"),
        ({"system": "unicycle"}, "system"),
        ({"state": [MAX_VALUE * 10, *good["state"][1:]]}, "state.0"),
        ({"cost": -1.0}, "cost"),
    ):
        bad = {**good, **change}
        with pytest.raises(MessageError) as refused:
            decode(made.transition, json.dumps(bad).encode())
        assert said in one_line(refused), (change, str(refused.value))
    without = {k: v for k, v in good.items() if k != "system"}
    with pytest.raises(MessageError) as refused:
        decode(made.transition, json.dumps(without).encode())
    assert "system: Field required" in one_line(refused)
    nan = transition.encode().replace(str(good["cost"]).encode(), b"NaN")
    with pytest.raises(MessageError):
        decode(made.transition, nan)
    # the robot's schema and this one refuse each other's messages
    robot = Transition(robot="r0", episode=0, step=0, state=(1.0, 2.0, 0.3), action=(0.1, 0.0), cost=0.5)
    with pytest.raises(MessageError) as refused:
        decode(made.transition, robot.encode())
    one_line(refused)
    with pytest.raises(MessageError) as refused:
        decode(Transition, transition.encode())
    one_line(refused)
    assert len(good["state"]) == row.state_dim


@pytest.mark.parametrize("name", OTHERS)
def test_another_systems_batches_round_trip_and_name_their_system(name: str) -> None:
    made = wire(name)
    for kind, messages in messages_of(name, robots=5).items():
        schema = type(messages[0])
        assert layout(schema)[0].name == "system" and layout(schema)[0].choices == (name,)  # a choice of one
        (payload,) = batch_payloads(messages)
        assert decode_batch(schema, payload) == messages, kind
        assert f"@{name}\n".encode() in payload  # the manifest names the system first
    (payload,) = batch_payloads(messages_of(name)["transition"])
    for other in [*OTHERS, "unicycle"]:
        if other == name:
            continue
        with pytest.raises(MessageError) as refused:
            decode_batch(wire(other).transition, payload)
        assert f"a batch of system {name}, not {other}" in one_line(refused)
    robot = Transition(robot="r0", episode=0, step=0, state=(1.0, 2.0, 0.3), action=(0.1, 0.0), cost=0.5)
    (robots,) = batch_payloads([robot])
    with pytest.raises(MessageError) as refused:
        decode_batch(made.transition, robots)
    assert f"a batch of system unicycle, not {name}" in one_line(refused)
    assert decode_batch(Transition, robots) == [robot]  # the robot's batches as before


def test_a_users_system_has_a_wire_too() -> None:
    from tests.test_systems import DOUBLE_INTEGRATOR  # a system defined in a test file

    name = "wire_test_double_integrator"
    register_system(name, DOUBLE_INTEGRATOR)
    try:
        (payload,) = batch_payloads(messages_of(name)["weights"])
        (first, *_) = decode_batch(wire(name).weights, payload)
        assert first.system == name and len(first.q_weights) == 6  # type: ignore[attr-defined]
        assert math.isfinite(first.q_residual)
    finally:
        SYSTEMS.pop(name, None)
