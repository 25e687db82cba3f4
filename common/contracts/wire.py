"""The wire of a sampled system: its messages and topics, sized by its row (common/math/systems.py).

The robot's (``unicycle``) are the messages of common.contracts.messages and the topics of
common.contracts.keys, byte for byte. Another system's are made from them: the same keys and
fields, but

* every message names its system (``system``, required: a message of another system, or of
  none, is refused in one line as any bad input is);
* ``state`` and ``true_state`` are ``n`` numbers, ``action`` ``m`` (the row's dimensions), each
  finite and within ``MAX_VALUE`` (1e6); the critic's weights are of the row's feature counts;
* the robot's own fields (a localized robot's ``map_to_odom``) are not there.

Their batches are columns as the robot's are (common.contracts.columns derives every layout from
the schema, ``system`` a choice of one name), so a batch of another system's size or name is
refused whole (a batch of another system names it first in its manifest). :func:`wire` makes a
system's once. The services (plant, actor, critic) carry any system's messages (``srl up --system
NAME``, real time and lockstep, a fleet too); the robot bridge, a recording and a live view the
robot's."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, create_model

from common.contracts.columns import SCHEMA_CODES, choice_code
from common.contracts.keys import ACTION, PLANT_RESET, PLANT_STEP, STATE, TRANSITION, WEIGHTS, Service, Topic
from common.contracts.messages import (
    Action,
    CriticWeights,
    Finite,
    Message,
    PlantState,
    ResetRequest,
    StepRequest,
    Transition,
)
from common.math.systems import System, system_row

# Any entry of another system's state or action: finite, and far beyond any plant's range yet
# finite in every product the math forms (a stage cost of entries at 1e6 stays near 1e12).
MAX_VALUE = 1e6
Value = Annotated[float, Field(allow_inf_nan=False, ge=-MAX_VALUE, le=MAX_VALUE)]
ROBOT_ONLY = ("map_to_odom",)  # fields of the wheeled robot's messages only


@dataclass(frozen=True)
class Wire:
    """One system's messages and the topics that carry them (the keys are every system's)."""

    system: str
    # the schemas (typed loosely: another system's are made at run time, their fields its sizes)
    state: type[Any]
    action: type[Any]
    transition: type[Any]
    weights: type[Any]
    step_request: type[Any]
    reset_request: type[Any]
    STATE: Topic[Any]
    ACTION: Topic[Any]
    TRANSITION: Topic[Any]
    WEIGHTS: Topic[Any]
    PLANT_STEP: Service[Any, Any]
    PLANT_RESET: Service[Any, Any]

    @property
    def named(self) -> dict[str, str]:
        """The fields every message of this wire takes beside its own: ``{"system": NAME}``, or
        none for the robot's (``wire.transition(**wire.named, robot=..., ...)``)."""
        return {} if self.system == "unicycle" else {"system": self.system}

    def named_columns(self, schema: type[Message]) -> dict[str, Any]:
        """:attr:`named` as a batch of ``schema`` carries it (``system``: the choice's code), and the
        robot's own fields absent (NaN): what ``Columns.of`` takes beside a round's own fields."""
        columns: dict[str, Any] = {field: np.nan for field in ROBOT_ONLY if field in schema.model_fields}
        return columns | {field: choice_code(schema, field, name) for field, name in self.named.items()}


ROBOT_WIRE = Wire(
    "unicycle",
    PlantState,
    Action,
    Transition,
    CriticWeights,
    StepRequest,
    ResetRequest,
    STATE,
    ACTION,
    TRANSITION,
    WEIGHTS,
    PLANT_STEP,
    PLANT_RESET,
)


def _sized(schema: type[Message], name: str, system: System) -> type[Message]:
    """``schema`` for ``system``: its fields but the robot's own, vectors of the system's sizes,
    and ``system`` naming it (required)."""
    n, m = system.state_dim, system.action_dim
    vectors: dict[str, Any] = {
        "state": tuple[(Value,) * n],  # type: ignore[misc]
        "true_state": tuple[(Value,) * n] | None,  # type: ignore[misc]
        "action": tuple[(Value,) * m],  # type: ignore[misc]
        "q_weights": Annotated[tuple[Finite, ...], Field(min_length=system.q_features, max_length=system.q_features)],
        "v_weights": Annotated[tuple[Finite, ...], Field(min_length=system.v_features, max_length=system.v_features)],
    }
    fields: dict[str, Any] = {"system": (Literal[name], Field(description="the sampled system (plant.system)"))}
    for field, info in schema.model_fields.items():
        if field in ROBOT_ONLY or field == "schema_version":
            continue
        if field in vectors:  # required as the robot's is, or with its default (None)
            fields[field] = (vectors[field], Field(default=info.default, description=info.description))
        else:
            fields[field] = (info.annotation, info)
    made: type[Message] = create_model(f"{schema.__name__}[{name}]", __base__=Message, __doc__=schema.__doc__, **fields)
    if schema in SCHEMA_CODES:  # its batches: the schema's code, the system's layout
        SCHEMA_CODES[made] = SCHEMA_CODES[schema]
    made.encode = schema.encode  # type: ignore[method-assign]  # as the robot's (a state leaves absent fields out)
    return made


@functools.cache
def wire(system: str = "unicycle") -> Wire:
    """The messages and topics of ``system`` (a row of common/math/systems.py SYSTEMS; an unknown
    one: ValueError naming the known ones): the robot's are srl's own, another's made once."""
    row = system_row(system)
    if system == "unicycle":
        return ROBOT_WIRE
    made = [_sized(schema, system, row) for schema in (PlantState, Action, Transition, CriticWeights)]
    requests = [_sized(schema, system, row) for schema in (StepRequest, ResetRequest)]
    state, action, transition, weights = made
    step, reset = requests
    return Wire(
        system,
        state,
        action,
        transition,
        weights,
        step,
        reset,
        Topic(STATE.pattern, state),
        Topic(ACTION.pattern, action),
        Topic(TRANSITION.pattern, transition),
        Topic(WEIGHTS.pattern, weights),
        Service(PLANT_STEP.pattern, step, state),
        Service(PLANT_RESET.pattern, reset, state),
    )
