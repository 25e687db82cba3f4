"""The distributed simulator as an environment: steps through a running lockstep plant_sim.

:class:`ZenohEnv` is :class:`tools.gym.envs.SrlEnv` whose plant is the one the actor's lockstep
mode drives (``srl up --mode lockstep``, ``srl run --transport zenoh``): the queryables
``srl/<robot>/plant/reset`` and ``srl/<robot>/plant/step`` of ``srl plant-sim --mode
lockstep``, queried through the actor's own client, :class:`services.actor.ports.ZenohPlant`
(a timed-out query is retried; the plant answers a retried step without applying it twice). The
plant_sim integrates the same plant and clamps to the same box as the in-process environment,
and actions and states cross the wire as JSON numbers written to round-trip (pydantic's
shortest repr of a binary64), so an episode is the in-process one bit for bit
(tests/test_gym.py). Observation, action, reward and episode are :class:`SrlEnv`'s.

The plant_sim's own settings choose its plant (``plant.model``, ``plant.system``); give this
environment the same settings (``model``, ``system`` and ``settings`` as the plant_sim's) so that
its limits and cost are that plant's: another system's lockstep plant (``srl plant-sim --mode
lockstep --system pendulum``) is ``ZenohEnv(system="pendulum")``. ``robot`` and ``router``
default to ``transport.robot`` and ``transport.router``; the environment waits up to ``timeout``
seconds for the router and for the robot's plant to be alive (one ``TimeoutError`` line saying
what to start otherwise). Each reset starts a new episode id;
:meth:`ZenohEnv.close` closes the Zenoh session.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from typing import Any

from common.config.settings import Settings
from common.net.transport import Bus
from common.process.runtime import connect_with_retry
from services.actor.ports import ZenohPlant, new_episode_id
from tools.gym.envs import FloatArray, SrlEnv, env_settings


class ZenohEnv(SrlEnv):
    """One robot behind a lockstep plant_sim (module docstring)."""

    def __init__(
        self,
        robot: str | None = None,
        router: str | None = None,
        model: str = "ideal",
        starts: str | Sequence[Sequence[float]] = "paper",
        grid: int = 5,
        extent: float = 2.0,
        held_out_seed: int = 0,
        settings: Settings | None = None,
        timeout: float = 10.0,
        system: str = "unicycle",
    ) -> None:
        base = env_settings(settings, model, system)
        data = base.model_dump()
        data["transport"].update({k: v for k, v in (("robot", robot), ("router", router)) if v is not None})
        settings = Settings.model_validate(data)
        transport = settings.transport
        self.bus: Bus = connect_with_retry(
            lambda: Bus.open(transport, "gym"), settings, "gym", timeout, threading.Event()
        )
        deadline = time.monotonic() + timeout
        while not self.bus.live_identities(transport.robot, "plant", timeout=0.5):
            if time.monotonic() > deadline:
                self.bus.close()
                raise TimeoutError(
                    f"no plant of robot {transport.robot} at {transport.router} within {timeout:g} s: "
                    f"start `srl plant-sim --mode lockstep --robot {transport.robot}`"
                )
            time.sleep(0.1)
        self.episode_id = new_episode_id()
        self.zenoh_plant = ZenohPlant(settings, self.bus, self.episode_id)
        super().__init__(model, starts, grid, extent, held_out_seed, settings, plant=self.zenoh_plant, system=system)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[FloatArray, dict[str, Any]]:
        # a new episode id per reset, increasing: the plant_sim refuses steps of another episode
        self.episode_id = max(new_episode_id(), self.episode_id + 1)
        self.zenoh_plant.episode = self.episode_id
        return super().reset(seed=seed, options=options)

    def close(self) -> None:
        self.bus.close()
        super().close()
