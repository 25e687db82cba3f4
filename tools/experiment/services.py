"""The experiment's services (``--transport zenoh``): a router and, per worker, one lockstep
plant_sim and one critic, kept up across runs."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from common.config.settings import Settings
from tools.experiment.options import ExperimentError

PEER_MODE, PEER_LISTEN = "peer", ["tcp/127.0.0.1:0"]  # the zenoh transport's sessions (see transport_for)


class ExperimentServices:
    """Router + one plant_sim (lockstep) and one critic per worker, kept up across runs."""

    def __init__(self, config_path: Path, base: Settings, workers: int) -> None:
        from tools.launch.supervisor import Supervisor, free_loopback_endpoint

        self.endpoint = free_loopback_endpoint()
        self.robots = [f"exp{slot}" for slot in range(workers)]
        # No critic checkpoint (see experiment_settings), even if the environment names one:
        # SRL_ variables outrank the --config file the services read.
        env = {
            **os.environ,
            "PYTHONUNBUFFERED": "1",
            "SRL_CRITIC__CHECKPOINT": "",
            "SRL_TRANSPORT__MODE": PEER_MODE,
            "SRL_TRANSPORT__LISTEN": json.dumps(PEER_LISTEN),
        }
        self.supervisor = Supervisor([], env, quiet=True)
        self.common = ["--config", str(config_path), "--router", self.endpoint]
        self.base = base

    def transport_for(self, robot: str) -> dict[str, Any]:
        # Peers that listen on a free loopback port and learn each other from the router
        # (gossip, no multicast): the worker's queries, transitions and weights go straight to
        # its plant and critic instead of through the router, which then only introduces them
        # (less wall time and router CPU than client sessions routing every message).
        return {
            "router": self.endpoint,
            "robot": robot,
            "multicast_scouting": False,
            "connect": [],
            "mode": PEER_MODE,
            "listen": PEER_LISTEN,
        }

    def start(self) -> None:
        from tools.launch.supervisor import ServiceDiedError

        try:
            self._start()
        except ServiceDiedError as error:
            raise ExperimentError(f"{error}: {' | '.join(error.tail)}") from error
        except TimeoutError as error:
            raise ExperimentError(str(error)) from error

    def _start(self) -> None:
        from tools.launch.supervisor import alive_probe, router_reachable

        sup = self.supervisor
        sup.spawn("router", ["router", *self.common, "--robot", self.robots[0]])
        router_settings = self._settings(self.robots[0])
        sup.wait_for("router", lambda: router_reachable(router_settings), timeout=30)
        for robot in self.robots:
            sup.spawn(f"plant-{robot}", ["plant-sim", "--mode", "lockstep", *self.common, "--robot", robot])
            # each critic learns from its own worker's robot only (critic.robots; "*" would make
            # every critic fit every robot's transitions, W times the work)
            sup.spawn(f"critic-{robot}", ["critic", *self.common, "--robot", robot], {"SRL_CRITIC__ROBOTS": robot})
        for robot in self.robots:
            settings = self._settings(robot)
            sup.wait_for(f"plant of {robot}", alive_probe(settings, "plant"), timeout=60)
            sup.wait_for(f"critic of {robot}", alive_probe(settings, "critic"), timeout=60)

    def _settings(self, robot: str) -> Settings:
        data = self.base.model_dump(mode="json")
        data["transport"].update(self.transport_for(robot))
        return Settings.model_validate(data)

    def check(self) -> None:
        from tools.launch.supervisor import ServiceDiedError

        try:
            self.supervisor.check()
        except ServiceDiedError as error:
            raise ExperimentError(f"{error}: {' | '.join(error.tail)}") from error

    def pids(self) -> dict[str, int]:
        return {name: child.process.pid for name, child in self.supervisor.children.items()}

    def stop(self) -> dict[str, int | None]:
        self.supervisor.stop_all()  # SIGINT by process group (= pid), SIGKILL after the grace
        return {name: child.process.returncode for name, child in self.supervisor.children.items()}

    def resources(self) -> dict[str, Any]:
        """CPU seconds and peak RSS each service reported when it stopped (its last JSON line)."""
        report: dict[str, Any] = {}
        for name, child in self.supervisor.children.items():
            summary = child.summary() or {}
            report[name] = {
                **summary.get("resources", {}),
                **(
                    {"transitions": summary["transitions_received"], "fit_ms": summary.get("fit_ms")}
                    if "transitions_received" in summary
                    else {}
                ),
            }
        return report
