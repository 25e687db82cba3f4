"""The simulated plant models, one row each: ``plant.model`` in the settings, the command lines'
choices, the summaries' fields and the docs read them from here (docs/turtlebot-models.md).

A row is the model's name and what it is; :func:`common.math.physics.simulated_robot` builds it
(``ideal``: no robot model, the plant integrates the exact unicycle)."""

from __future__ import annotations

from typing import Literal, get_args

PlantModel = Literal["ideal", "actuator", "physics"]
PLANT_MODELS: dict[PlantModel, str] = {
    "ideal": "the exact unicycle",
    "actuator": "a TurtleBot3's wheels and odometry ([actuator])",
    "physics": "a rigid-body TurtleBot3 in MuJoCo ([physics], the extra srl[physics])",
}
assert tuple(PLANT_MODELS) == get_args(PlantModel), "one row per name of PlantModel"


def plant_models_text() -> str:
    """``ideal: the exact unicycle; actuator: ...``: the rows as one line (help texts, descriptions)."""
    return "; ".join(f"{name}: {what}" for name, what in PLANT_MODELS.items())
