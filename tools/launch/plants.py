"""What ``srl up --plant`` starts as the robots' plant: one row per choice, read by ``srl up`` (one
robot and a fleet, tools/launch/up.py), its command line and the Variants page (``srl docs``).

A row says whether the plant is a robot behind the robot bridge (a ROS 2 TurtleBot3: the
emulator unless ``bridge.robot_endpoint`` names a real one; real time only, a robot cannot be
stepped by a lockstep query) or a simulator (plant_sim, or a plant host of many robots), and which
``plant.model`` it simulates: its own, or the settings' (:data:`LaunchPlant.model` None).
"""

from __future__ import annotations

from dataclasses import dataclass

from common.config.settings import Settings


@dataclass(frozen=True)
class LaunchPlant:
    """One ``--plant`` choice: ``what`` it starts, whether the robot is ``behind_bridge``, and the
    ``model`` (``plant.model``) it sets for every child (None: the settings' own)."""

    what: str
    behind_bridge: bool
    model: str | None = None


# how a fleet's robots are laid out in processes (``srl up --layout``): ``host``, one host of every
# robot per service (actor hosts: --actor-hosts); ``process``, one plant and one actor per robot
LAYOUTS = ("host", "process")

LAUNCH_PLANTS: dict[str, LaunchPlant] = {
    "sim": LaunchPlant("plant_sim of plant.model", behind_bridge=False),
    "physics": LaunchPlant("plant_sim with the MuJoCo TurtleBot3 (plant.model = physics)", False, "physics"),
    "robot": LaunchPlant(
        "robot_bridge + tb3-emulator of plant.model (or the robot at --robot-endpoint); real time only",
        behind_bridge=True,
    ),
}


def launch_plant(name: str) -> LaunchPlant:
    """The row of ``name``; ValueError (one line naming the rows) for another."""
    row = LAUNCH_PLANTS.get(name)
    if row is None:
        raise ValueError(f"unknown plant {name!r} ({', '.join(LAUNCH_PLANTS)})")
    return row


def launch_plant_help() -> str:
    """``sim: ...; physics: ...; robot: ...``: the rows as one help text."""
    return "; ".join(f"{name}: {row.what}" for name, row in LAUNCH_PLANTS.items())


def with_launch_plant(settings: Settings, env: dict[str, str], name: str) -> Settings:
    """The settings of a run on plant ``name``: its model, if it sets one, said to every child
    through ``env`` and to this process by the settings returned."""
    model = launch_plant(name).model
    if model is None:
        return settings
    env["SRL_PLANT__MODEL"] = model
    return settings.model_copy(update={"plant": settings.plant.model_copy(update={"model": model})})
