"""The simulated plant models, one row each: ``plant.model`` in the settings, the command lines'
choices, the summaries' fields and the docs read them from here (docs/turtlebot-models.md).

A row is what the model simulates and how its robot is built (:class:`PlantModelRow`);
:func:`simulated_robot` builds the row's robot for plant_sim, the in-process plant (``srl run``,
the experiment) and the TurtleBot3 emulator alike. A model whose row builds no robot (``ideal``)
is the exact unicycle: plant_sim integrates it in closed form, the emulator puts the firmware's
conversion in front of it.

A new model is one row: a class that satisfies
:class:`~common.math.turtlebot.SimulatedRobot`, and :func:`register_plant_model` (or a row
here, for a built-in one). ``tests/test_plant_models.py`` registers one defined in the test file
and runs it through every consumer.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from common.math.dynamics import FloatArray
from common.math.rows import add_row
from common.math.turtlebot import SimulatedRobot, TurtleBot, TurtleBotParams

if TYPE_CHECKING:
    from common.math.physics import PhysicsParams

# what a row builds: the robot at rest at ``pose`` from the settings' [actuator] and [physics]
# constants (a model reads those it needs)
RobotFactory = Callable[[TurtleBotParams, "PhysicsParams", FloatArray], SimulatedRobot]


@dataclass(frozen=True)
class PlantModelRow:
    """One simulated plant model: ``what`` it simulates (help texts, the docs' table) and
    ``build``, its robot (None: no robot model, the exact unicycle)."""

    what: str
    build: RobotFactory | None

    @property
    def exact(self) -> bool:
        """No robot model: the exact unicycle, which a host of many robots steps as one array."""
        return self.build is None


def _actuator(params: TurtleBotParams, physics: PhysicsParams, pose: FloatArray) -> SimulatedRobot:
    return TurtleBot(params, pose)


def _physics(params: TurtleBotParams, physics: PhysicsParams, pose: FloatArray) -> SimulatedRobot:
    from common.math.physics import PhysicsBot  # MuJoCo is an extra, imported when a PhysicsBot is made

    return PhysicsBot(params, physics, pose)


PLANT_MODELS: dict[str, PlantModelRow] = {
    "ideal": PlantModelRow("the exact unicycle", None),
    "actuator": PlantModelRow("a TurtleBot3's wheels and odometry ([actuator])", _actuator),
    "physics": PlantModelRow("a rigid-body TurtleBot3 in MuJoCo ([physics], the extra srl[physics])", _physics),
}
BUILT_IN_PLANT_MODELS = tuple(PLANT_MODELS)  # the rows srl ships


def plant_model_row(name: str) -> PlantModelRow:
    """The row of ``name``; an unknown name raises ValueError naming the known ones (one line)."""
    row = PLANT_MODELS.get(name)
    if row is None:
        raise ValueError(f"unknown plant model {name!r} ({', '.join(PLANT_MODELS)})")
    return row


def register_plant_model(name: str, what: str, build: RobotFactory) -> None:
    """Add a plant model: ``plant.model = name`` then builds ``build(params, physics, pose)`` in
    every consumer of this process. A name that is taken, or not 1-32 of a-z 0-9 _ starting with
    a letter, raises ValueError. Command lines list the models registered when their parser is
    built."""
    add_row(PLANT_MODELS, "plant model", name, PlantModelRow(what, build))


def simulated_robot(
    model: str, params: TurtleBotParams, physics: PhysicsParams, pose: FloatArray
) -> SimulatedRobot | None:
    """The robot of ``plant.model`` at rest at ``pose`` (None: the exact unicycle, ``ideal``)."""
    build = plant_model_row(model).build
    return None if build is None else build(params, physics, pose)


def plant_models_text() -> str:
    """``ideal: the exact unicycle; actuator: ...``: the rows as one line (help texts, descriptions)."""
    return "; ".join(f"{name}: {row.what}" for name, row in PLANT_MODELS.items())
