"""srl's robots as Gymnasium environments and srl's agents as policies (docs/gym.md).

Importing this package registers the robot's three environments (``gymnasium.register``):

* ``srl/Unicycle-v0`` -- the paper's ideal unicycle (``plant.model = "ideal"``);
* ``srl/TurtleBot3-v0`` -- the TurtleBot3 Burger's actuator model (``"actuator"``);
* ``srl/TurtleBot3Physics-v0`` -- the MuJoCo Burger (``"physics"``, the physics extra);

and one per other system of common/math/systems.py (``srl/DynamicUnicycle-v0``,
``srl/Pendulum-v0``, ``srl/Cartpole-v0``, ``srl/TwoTank-v0``). The robot's also have a vector
entry point (:class:`tools.gym.vector.SrlVectorEnv`), so
``gymnasium.make_vec(ID, num_envs=K)`` steps K robots in one call.

How ``gymnasium.make`` finds them: Gymnasium 1.x loads no plugins from the ``gymnasium.envs``
entry point group (Gymnasium 0.x's plugin loading is gone: 1.x's ``gymnasium/envs/registration.py``
reads no package metadata). It imports the module named before a colon in the id instead:
``gymnasium.make("tools.gym:srl/Unicycle-v0")`` imports this package, which registers the ids;
after ``import tools.gym`` the plain ``gymnasium.make("srl/Unicycle-v0")`` works too. So srl
declares no entry point (Gymnasium would never read it) and requires ``gymnasium>=1.0`` (the
extra ``srl[gym]``).
"""

from __future__ import annotations

try:
    import gymnasium
except ImportError as error:  # pragma: no cover - the extra is missing
    raise ImportError("srl's Gymnasium environments need the gym extra: pip install 'srl[gym]'") from error

from tools.gym.envs import ENV_MODELS, SrlEnv, StartDistribution, normalized_actions, system_envs

NAMESPACE = "srl"


def register() -> None:
    """Register the environments of :data:`ENV_MODELS` and one per system of common/math/systems.py
    other than the robot (:func:`tools.gym.envs.system_envs`: ``srl/Pendulum-v0``, ...; a system a
    plugin registers later: call this again), once: an id already there is kept."""
    for env_id, model in ENV_MODELS.items():
        if env_id not in gymnasium.registry:
            gymnasium.register(
                id=env_id,
                entry_point="tools.gym.envs:SrlEnv",
                vector_entry_point="tools.gym.vector:SrlVectorEnv",
                kwargs={"model": model},
            )
    for env_id, system in system_envs().items():
        if env_id not in gymnasium.registry:  # stepped one by one (make_vec: Gymnasium's sync vector)
            gymnasium.register(
                id=env_id, entry_point="tools.gym.envs:SrlEnv", kwargs={"system": system, "starts": "box"}
            )


register()

__all__ = ["ENV_MODELS", "NAMESPACE", "SrlEnv", "StartDistribution", "normalized_actions", "register"]
