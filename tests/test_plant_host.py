"""The plant host's watchdogs as arrays (services/plant_sim/host.py): one test per state tick over
every robot's action arrival picks exactly the robots whose own watchdog stops them."""

from __future__ import annotations

import math

import numpy as np

from common.config.settings import Settings
from common.contracts.messages import Action
from services.plant_sim.host import FleetPlant, RobotIntake
from services.plant_sim.service import due_watchdogs
from tests.harness import FakeCounts

TIMEOUT = 0.25  # and now = 1024: now - TIMEOUT and back are exact


def test_the_watchdogs_due_are_each_robots_own_test_and_holding_zero_is_never_due() -> None:
    rng = np.random.default_rng(5)
    now = 1024.0
    arrivals = now - rng.uniform(0.0, 0.6, 300)
    arrivals[::7] = math.nan  # holding zero: nothing to stop
    arrivals[1] = now - TIMEOUT  # exactly at the timeout: not yet
    due = due_watchdogs(arrivals, now, TIMEOUT)
    own = [i for i, at in enumerate(arrivals) if not math.isnan(at) and now - at > TIMEOUT]
    assert due.tolist() == own and 0 < len(own) < 300 and 1 not in own


def test_a_plant_hosts_watchdog_stops_the_robots_due_and_leaves_the_others_driving() -> None:
    settings = Settings.load()
    robots = [f"r{i}" for i in range(4)]
    plant = FleetPlant(settings, robots, np.zeros((4, 3)))
    counts = FakeCounts()
    intakes = [RobotIntake(plant, i, counts) for i in range(4)]  # type: ignore[arg-type]
    for i, intake in enumerate(intakes):
        intake.gate.gate.update("actor1", True)
        message = Action(robot=robots[i], episode=1, step=i, stamp_ns=0, action=(0.1, 0.2), state_seq=-1)
        assert intake.take(message, "actor1") is not None
    assert np.isfinite(plant.arrivals).all() and (plant.held != 0.0).all()
    plant.arrivals[[1, 3]] -= 1.0  # two robots' actions are a second old
    now = float(np.nanmax(plant.arrivals)) + 0.01
    for i in due_watchdogs(plant.arrivals, now, TIMEOUT):
        intakes[i].watchdog(now, TIMEOUT)
    assert [intake.watchdog_stops for intake in intakes] == [0, 1, 0, 1]
    assert plant.held.tolist() == [[0.1, 0.2], [0.0, 0.0], [0.1, 0.2], [0.0, 0.0]]
    assert [intake.at is None for intake in intakes] == [False, True, False, True]
    assert counts.counters["watchdog_stops"] == 2
    assert due_watchdogs(plant.arrivals, now + 0.1, TIMEOUT).tolist() == []  # stopped: zero held, none due
