"""The sampled systems' table (common/math/systems.py): the unicycle is one row of it, and a
system the user defines in their own file -- here a double integrator, defined below and nowhere
in srl -- is built into the actor's problem, the critic and the in-process plant, and Algorithm 1
stabilizes it, with no change to srl's modules."""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from common.config.settings import Settings
from common.math.actor import StackedActor
from common.math.actor_problem import ActorProblem
from common.math.dynamics import exact_step, unicycle_rhs
from common.math.features import quadratic_weights_for_diag
from common.math.loop import ExactPlant, LocalCritic, run_algorithm1
from common.math.systems import (
    BUILT_IN_SYSTEMS,
    SYSTEMS,
    UNICYCLE,
    System,
    register_system,
    system_row,
    vector,
)

NAME = "double_integrator"
DELTA = 0.1


def double_integrator(state: Any, action: Any) -> Any:
    """A cart on a line: position and speed, pushed by a bounded acceleration."""
    return vector(state[1], action[0])


DOUBLE_INTEGRATOR = System(
    what="a cart on a line pushed by a bounded acceleration",
    states=("p [m]", "v [m/s]"),
    actions=("a [m/s^2]",),
    rhs=double_integrator,
    action_max=(1.0,),
    cost_diag=(1.0, 0.5, 0.05),
    start=(1.0, 0.0),
)


@pytest.fixture
def registered() -> Iterator[System]:
    register_system(NAME, DOUBLE_INTEGRATOR)
    try:
        yield DOUBLE_INTEGRATOR
    finally:
        del SYSTEMS[NAME]  # other tests of this process see srl's rows only


def test_the_unicycle_row_is_the_paper_robot_and_the_settings_defaults() -> None:
    settings = Settings.load()
    assert BUILT_IN_SYSTEMS == ("unicycle",) and system_row("unicycle") is UNICYCLE
    assert (UNICYCLE.state_dim, UNICYCLE.action_dim, UNICYCLE.q_features, UNICYCLE.v_features) == (3, 2, 15, 6)
    rng = np.random.default_rng(0)
    for _ in range(20):
        state, action = rng.normal(size=3), rng.normal(size=2)
        assert np.array_equal(UNICYCLE.rhs(state, action), unicycle_rhs(state, action))
        assert np.array_equal(UNICYCLE.step(state, action, DELTA), exact_step(state, action, DELTA))
    assert UNICYCLE.cost_diag == tuple(settings.cost.r_diag)
    assert UNICYCLE.action_max == (settings.plant.v_max, settings.plant.omega_max)
    assert np.array_equal(np.array(UNICYCLE.start), settings.start_state())
    assert UNICYCLE.distance(np.array([0.03, 0.04, 2.0])) == pytest.approx(0.05)  # the heading aside


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"states": ()}, "at least one state"),
        ({"action_max": (1.0, 2.0)}, "action_max: 1 positive"),
        ({"action_max": (0.0,)}, "action_max: 1 positive"),
        ({"cost_diag": (1.0, 1.0)}, "cost_diag: 3 finite"),
        ({"cost_diag": (1.0, -1.0, 1.0)}, "cost_diag: 3 finite"),
        ({"start": (1.0, math.nan)}, "start: 2 finite"),
        ({"wheeled": True}, "wheeled"),
        ({"stabilized": 0.0}, "stabilized"),
        ({"substeps": 0}, "substeps"),
    ],
)
def test_a_system_that_cannot_be_is_refused_in_one_line(changes: dict[str, Any], message: str) -> None:
    fields = {name: getattr(DOUBLE_INTEGRATOR, name) for name in DOUBLE_INTEGRATOR.__dataclass_fields__}
    with pytest.raises(ValueError, match=message) as refused:
        System(**(fields | changes))
    assert "\n" not in str(refused.value)


def test_a_system_name_is_checked_and_never_replaces_a_row(registered: System) -> None:
    with pytest.raises(ValueError, match="exists already"):
        register_system("unicycle", DOUBLE_INTEGRATOR)
    with pytest.raises(ValueError, match="1-32 of"):
        register_system("Double Integrator", DOUBLE_INTEGRATOR)
    with pytest.raises(ValueError, match=r"unknown system 'pendulum' \(unicycle, double_integrator\)"):
        system_row("pendulum")
    assert system_row(NAME) is registered


def test_without_its_row_no_problem_names_the_system() -> None:
    # the negative control of the tests below: the system is the row, not a string srl knows
    with pytest.raises(ValueError, match="unknown system 'double_integrator'"):
        ActorProblem("mpc", 6, DELTA, DOUBLE_INTEGRATOR.cost_diag, DOUBLE_INTEGRATOR.action_max, system=NAME)


def test_a_system_without_a_closed_form_is_integrated_by_rk4_substeps(registered: System) -> None:
    # the double integrator's exact sample-and-hold: p + v h + a h^2 / 2, v + a h
    rng = np.random.default_rng(1)
    for _ in range(20):
        (p, v), a = rng.normal(size=2), rng.normal()
        exact = np.array([p + v * DELTA + a * DELTA**2 / 2, v + a * DELTA])
        np.testing.assert_allclose(registered.step(np.array([p, v]), np.array([a]), DELTA), exact, atol=1e-14)


def test_the_wheel_box_is_refused_for_a_system_without_wheels(registered: System) -> None:
    with pytest.raises(ValueError, match="double_integrator has no wheels"):
        ActorProblem("mpc", 6, DELTA, registered.cost_diag, registered.action_max, system=NAME, wheel_speed_max=6.67)


@pytest.mark.parametrize(("agent", "srl"), [("mpc", False), ("rlqv", False), ("rlqv", True), ("rlq", True)])
def test_algorithm1_stabilizes_the_users_own_system_in_process(registered: System, agent: str, srl: bool) -> None:
    """The user's system through every floor Algorithm 1 uses: the actor's CasADi problem (its
    dimensions, its predictor, its box), the critics' features and TD fit (sized by the
    weights), the plant (RK4 substeps), the loop. 12 s from p = 1 m at rest, with the settings'
    critic (discount, ridge, weight box, started at the discounted stage cost) and the paper's
    actor, or srl's (``srl``: the argmin and the convexified critics)."""
    system, n, settings = registered, registered.state_dim, Settings.load()
    problem = ActorProblem(
        agent,
        8,
        DELTA,
        system.cost_diag,
        system.action_max,
        system=NAME,
        jit=False,
        multistart=srl,
        convex_critics=srl,
    )
    discount = settings.discount
    scale = DELTA / (1.0 - discount)
    critic = LocalCritic(
        scale * quadratic_weights_for_diag(system.cost_diag),
        scale * quadratic_weights_for_diag(system.cost_diag[:n]),
        discount,
        settings.critic.ridge,
        settings.critic.bounds,
        30,
        1,
        learn=agent != "mpc",
    )
    (episode,) = run_algorithm1(
        StackedActor(problem),
        [ExactPlant(system)],
        [critic],
        [np.array(system.start)],
        120,
        DELTA,
        system.cost_diag,
    )
    actions = np.array(episode.actions)
    assert actions.shape == (120, 1) and np.all(np.abs(actions) <= system.action_max[0] + 1e-9)
    assert episode.solver_failures == 0
    assert system.distance(episode.final_state) < system.stabilized, episode.final_state
    assert np.array(episode.states).shape == (121, 2)
    fitted = not np.array_equal(episode.q_weights[-1], episode.q_weights[0])
    assert fitted == (agent != "mpc") and episode.q_weights[-1].shape == (6,) and episode.v_weights[-1].shape == (3,)
