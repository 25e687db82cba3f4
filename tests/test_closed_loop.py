"""Closed-loop episodes (Algorithm 1 in process) from the paper's grid corners."""

from __future__ import annotations

import numpy as np
import pytest

from common.config.assembly import run_episode
from common.config.settings import Settings
from common.math.dynamics import exact_step

pytestmark = [pytest.mark.slow, pytest.mark.integration]

# The four corners of the paper's 4 m x 4 m polygon: 2.8 m from the target, facing away.
CORNERS = [(2.0, 2.0), (-2.0, 2.0), (-2.0, -2.0), (2.0, -2.0)]
PARKED_M = 0.25


@pytest.mark.parametrize("agent", ["mpc", "rlqv"])
@pytest.mark.parametrize("start", CORNERS)
def test_agent_parks_from_a_corner(agent: str, start: tuple[float, float]) -> None:
    settings = Settings.load(actor={"agent": agent, "horizon": 12}, episode={"start": start, "duration": 30.0})
    episode = run_episode(settings)
    states = np.array(episode.states)
    actions = np.array(episode.actions)

    assert np.hypot(*states[0, :2]) == pytest.approx(2.0 * np.sqrt(2.0))
    assert states[0, 2] == pytest.approx(np.arctan2(start[1], start[0]))  # facing away
    final_distance = float(np.hypot(*states[-1, :2]))
    assert final_distance < PARKED_M, f"{agent} from {start} ended {final_distance:.3f} m away"
    # bounds held at every step, and no NaN anywhere
    assert np.all(np.isfinite(actions)) and np.all(np.isfinite(states))
    assert np.all(np.abs(actions[:, 0]) <= settings.plant.v_max + 1e-12)
    assert np.all(np.abs(actions[:, 1]) <= settings.plant.omega_max + 1e-12)
    # the trajectory is the exact plant driven by these actions, and J is the sum of delta r
    for k in range(0, episode.steps, 37):
        np.testing.assert_allclose(exact_step(states[k], actions[k], 0.1), states[k + 1], atol=1e-12)
    chi = np.hstack([states[:-1], actions])  # (s_k, u_k) per step
    expected_cost = 0.1 * float(np.sum(chi**2 @ np.array(settings.r_diag)))  # sum_k delta chi^T R chi
    assert episode.accumulated_cost == pytest.approx(expected_cost, rel=1e-12)
