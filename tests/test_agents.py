"""The agents' vocabulary is defined once (common/math/agents.py) and every reader agrees with it."""

from __future__ import annotations

import argparse

import numpy as np
import pytest
from pydantic import ValidationError

from common.config.arguments import add_settings_arguments
from common.config.settings import ActorSettings, Settings
from common.math.agents import (
    AGENT_ROWS,
    AGENTS,
    PAPER_AGENTS,
    REFERENCE_AGENT,
    AgentRow,
    agent_row,
    fit_due,
    learns,
    parse_agents,
    parse_horizons,
    register_agent,
    stage_cost_weights,
    uses_value_critic,
)

ACTOR = ActorSettings.model_validate(Settings.load().actor.model_dump()).model_dump()  # the packaged [actor]


def test_settings_and_command_line_take_the_agents_from_one_place() -> None:
    assert AGENTS == tuple(AGENT_ROWS) == ("mpc", "rlq", "rlqv", "rlqv+")
    for agent in AGENTS:
        assert ActorSettings.model_validate(ACTOR | {"agent": agent}).agent == agent
    with pytest.raises(ValidationError, match=r"unknown agent 'dqn' \(mpc, rlq, rlqv, rlqv\+\)"):
        ActorSettings.model_validate(ACTOR | {"agent": "dqn"})
    parser = argparse.ArgumentParser()
    add_settings_arguments(parser, ["agent"])
    (action,) = [a for a in parser._actions if a.dest == "agent"]
    assert tuple(action.choices or ()) == AGENTS
    assert set(PAPER_AGENTS) <= set(AGENTS)


def test_a_registered_agent_is_a_setting_a_choice_and_the_objective_its_row_says() -> None:
    """A user's agent is a row (register_agent, from a plugin: common/process/plugins.py): MPC with
    the value critic at the horizon end. The settings take it, the command line offers it, and the
    actor's objective is its row's: the MPC stage costs plus Jhat(s_N; v)."""
    from common.math.actor_problem import ActorProblem
    from common.math.actor_search import objective

    row = AgentRow("MPC+V", False, True, "each", False, "sum_i delta r(s_i, u_i) + Jhat(s_N; v)")
    register_agent("mpcv", row)
    try:
        assert ActorSettings.model_validate(ACTOR | {"agent": "mpcv"}).agent == "mpcv"
        parser = argparse.ArgumentParser()
        add_settings_arguments(parser, ["agent"])
        (action,) = [a for a in parser._actions if a.dest == "agent"]
        assert "mpcv" in (action.choices or ()) and learns("mpcv") and parse_agents("mpcv,mpc") == ("mpcv", "mpc")
        with pytest.raises(ValueError, match="exists already"):
            register_agent("mpcv", row)
        rng = np.random.default_rng(3)
        states = [rng.normal(size=3) for _ in range(4)]
        actions = [rng.normal(size=2) for _ in range(3)]
        w, v = rng.normal(size=15), rng.normal(size=6)
        values = {}
        for agent in ("mpc", "mpcv"):
            problem = ActorProblem(
                agent, 4, sampling_time=0.1, cost_diag=(1.0, 10.0, 1.0, 0.01, 0.01), action_max=(0.22, 2.84)
            )
            values[agent] = float(objective(problem, states, actions, w, v))
        from common.math.features import phi_v

        assert values["mpcv"] - values["mpc"] == pytest.approx(float(v @ phi_v(states[-1])), rel=1e-12)
    finally:
        del AGENT_ROWS["mpcv"]  # the other tests of this process see srl's rows only
    with pytest.raises(ValueError, match="a-z 0-9"):
        register_agent("MPC V", row)


def test_what_each_agent_learns() -> None:
    assert [a for a in AGENTS if learns(a)] == ["rlq", "rlqv", "rlqv+"]
    assert [a for a in AGENTS if uses_value_critic(a)] == ["rlqv", "rlqv+"]
    assert [s for s in range(1, 13) if fit_due(s, 4)] == [4, 8, 12]


def test_lists_parse_once_each_in_order_and_refuse_the_unknown() -> None:
    assert parse_agents(" rlqv,mpc,rlqv ") == ("rlqv", "mpc")
    assert parse_horizons("30, 6,30") == (30, 6)
    assert parse_horizons(" ", allow_empty=True) == ()
    with pytest.raises(ValueError, match=r"unknown agent.*dqn"):
        parse_agents("mpc,dqn")
    with pytest.raises(ValueError, match="--reference"):
        parse_horizons("1", "--reference")


def test_each_row_is_the_objective_the_actor_minimizes() -> None:
    """common/math/agents.py AGENT_ROWS is what common/math/actor_search.py's objective is made of:
    evaluated on numbers, each agent's objective equals the paper's formula for it (written out
    here, not derived from the row), and the rows that say so learn and end with V."""
    from common.math.actor_problem import ActorProblem
    from common.math.actor_search import objective
    from common.math.features import phi_q, phi_v, stage_cost

    rng = np.random.default_rng(3)
    horizon, delta, diag = 5, 0.1, (1.0, 2.0, 0.5, 0.1, 0.2)
    states = [rng.normal(size=3) for _ in range(horizon)]
    actions = [rng.normal(size=2) for _ in range(horizon - 1)]
    w, v = rng.normal(size=15), rng.normal(size=6)
    r = [delta * stage_cost(s, u, diag) for s, u in zip(states, actions, strict=False)]
    q = [float(w @ phi_q(s, u)) for s, u in zip(states, actions, strict=False)]
    end = float(v @ phi_v(states[-1]))
    paper = {
        "mpc": sum(r),
        "rlq": sum(q),
        "rlqv": sum(q) + end,
        "rlqv+": sum(q[i] + (horizon - (i + 1)) * r[i] for i in range(horizon - 1)) + end,
    }
    assert set(paper) == set(AGENT_ROWS)
    for agent, expected in paper.items():
        problem = ActorProblem(agent, horizon, sampling_time=delta, cost_diag=diag, action_max=(0.22, 2.84))
        got = float(objective(problem, states, actions, w, v))
        assert got == pytest.approx(expected, rel=1e-12), agent
        row = AGENT_ROWS[agent]
        assert learns(agent) == (row.q_critics or row.value_critic)
        assert uses_value_critic(agent) == row.value_critic
    assert stage_cost_weights("mpc", 4) == [1.0, 1.0, 1.0]
    assert stage_cost_weights("rlqv+", 4) == [3.0, 2.0, 1.0]
    assert stage_cost_weights("rlq", 4) == [0.0, 0.0, 0.0]
    assert PAPER_AGENTS == ("mpc", "rlq", "rlqv") and REFERENCE_AGENT == "mpc"


def test_an_unknown_agent_is_one_line_naming_the_known_ones() -> None:
    for call in (learns, uses_value_critic, agent_row):
        with pytest.raises(ValueError, match=r"^unknown agent 'dqn'; choose one of mpc, rlq, rlqv, rlqv\+$"):
            call("dqn")


def test_the_settings_and_help_describe_every_row() -> None:
    description = ActorSettings.model_fields["agent"].description or ""
    for name, row in AGENT_ROWS.items():
        assert f"{name}: {row.objective}" in description
