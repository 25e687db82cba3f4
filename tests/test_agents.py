"""The agents' vocabulary is defined once (common/math/agents.py) and every reader agrees with it."""

from __future__ import annotations

import argparse
from typing import get_args

import pytest

from common.config.arguments import add_settings_arguments
from common.config.settings import ActorSettings
from common.math.agents import AGENTS, PAPER_AGENTS, fit_due, learns, parse_agents, parse_horizons, uses_value_critic


def test_settings_and_command_line_take_the_agents_from_one_place() -> None:
    assert get_args(ActorSettings.model_fields["agent"].annotation) == AGENTS
    parser = argparse.ArgumentParser()
    add_settings_arguments(parser, ["agent"])
    (action,) = [a for a in parser._actions if a.dest == "agent"]
    assert tuple(action.choices or ()) == AGENTS
    assert set(PAPER_AGENTS) <= set(AGENTS)


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
