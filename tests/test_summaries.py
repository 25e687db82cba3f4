"""Run summaries are typed contracts (common/summaries.py): producers validate what they print,
consumers read it through the same models, and a drifted key is refused, not passed on."""

from __future__ import annotations

import math
import subprocess
import sys

import pytest
from pydantic import TypeAdapter, ValidationError

from common.assembly import episode_summary, run_episode
from common.settings import Settings
from common.summaries import ACTOR_SUMMARY, CriticSummary, EpisodeSummary, LockstepActorSummary
from tools.up import Child, _contract_summary


def _episode() -> dict[str, object]:
    settings = Settings.load(episode={"duration": 0.5}, actor={"agent": "mpc", "horizon": 4, "jit": False})
    return episode_summary(run_episode(settings), settings)


def test_an_episode_summary_fits_its_contract_and_round_trips() -> None:
    summary = _episode()
    parsed = EpisodeSummary.model_validate(summary)
    assert parsed.steps == 5 and parsed.agent == "mpc"
    assert parsed.to_json_dict() == summary
    assert math.isclose(parsed.final_distance, math.hypot(*parsed.final_state[:2]))


def test_a_drifted_or_missing_key_is_refused() -> None:
    summary = _episode()
    with pytest.raises(ValidationError, match="extra"):
        EpisodeSummary.model_validate({**summary, "acumulated_cost": 1.0})
    without = {k: v for k, v in summary.items() if k != "steps"}
    with pytest.raises(ValidationError, match="steps"):
        EpisodeSummary.model_validate(without)
    with pytest.raises(ValidationError):
        EpisodeSummary.model_validate({**summary, "agent": "dqn"})


def test_the_actor_summary_is_told_apart_by_its_mode() -> None:
    lockstep = {
        **_episode(),
        "service": "actor",
        "mode": "lockstep",
        "episode_id": 7,
        "weights_version": 0,
        "staleness_steps": {"median": 0.0, "p99": 0.0, "max": 0.0},
        "critic_timeouts": 0,
        "trajectory": [[1.0, 2.0, 3.0]],
        "counters": {},
    }
    assert isinstance(ACTOR_SUMMARY.validate_python(lockstep), LockstepActorSummary)
    with pytest.raises(ValidationError):  # a lockstep summary does not pass as a real-time one
        ACTOR_SUMMARY.validate_python({**lockstep, "mode": "realtime"})


def test_srl_up_says_in_one_line_which_child_summary_is_missing_or_wrong() -> None:
    process = subprocess.Popen([sys.executable, "-c", "pass"], text=True)
    process.wait()
    child = Child("critic", process)
    with pytest.raises(ValueError, match="critic ended without its JSON summary"):
        _contract_summary(child, TypeAdapter(CriticSummary))
    child.stdout_lines.append('{"service": "critic", "transitions_received": "many"}')
    with pytest.raises(ValueError, match=r"^critic's summary does not fit common/summaries.py: [^\n]*$"):
        _contract_summary(child, TypeAdapter(CriticSummary))
