"""Run summaries are typed contracts (common/contracts/summaries.py): producers validate what they print,
consumers read it through the same models, and a drifted key is refused, not passed on."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest
from pydantic import TypeAdapter, ValidationError

from common.config.assembly import episode_summary, run_episode
from common.config.settings import PAPER_METHOD, Settings
from common.contracts.summaries import (
    ACTOR_SUMMARY,
    BridgeSummary,
    CriticSummary,
    EmulatorSummary,
    EpisodeSummary,
    LockstepActorSummary,
    PlantSummary,
    RouterSummary,
)
from services.robot_bridge.bridge import RobotBridge
from tests.harness import FakeCounts
from tools.launch.supervisor import CHILD_SUMMARIES, Child, optional_summary
from tools.launch.supervisor import contract_summary as _contract_summary


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


@pytest.mark.integration
def test_srl_up_says_in_one_line_which_child_summary_is_missing_or_wrong() -> None:
    process = subprocess.Popen([sys.executable, "-c", "pass"], text=True)
    process.wait()
    child = Child("critic", process)
    with pytest.raises(ValueError, match="critic ended without its JSON summary"):
        _contract_summary(child, TypeAdapter(CriticSummary))
    child.stdout_lines.append('{"service": "critic", "transitions_received": "many"}')
    with pytest.raises(ValueError, match=r"^critic's summary does not fit common/contracts/summaries.py: [^\n]*$"):
        _contract_summary(child, TypeAdapter(CriticSummary))


def _bridge_summary() -> dict[str, object]:
    """What services/robot_bridge/host.py prints (its timing from a real RobotBridge)."""
    settings = Settings.load(transport={"robot": "u0"})
    bridge = RobotBridge(settings, lambda s: None, lambda v, w: None, FakeCounts())
    return {
        "service": "robot_bridge",
        "profile": "rmw_zenoh",
        "ros_distro": "jazzy",
        "namespace": "",
        "goal": [0.0, 0.0, 0.0],
        "cmd_vel": [
            {"type": "geometry_msgs/msg/TwistStamped", "key": "0/cmd_vel/geometry_msgs::msg::dds_::TwistStamped_/x"}
        ],
        "fallback": False,
        "discovered": ["0/cmd_vel/geometry_msgs::msg::dds_::TwistStamped_/x"],
        "attachment_format": "compact",
        "final_state": None,
        "max_abs_command": bridge.max_abs_command,
        "timing": bridge.timing(),
        "counters": {"commands_sent": 3},
        "resources": {"rss_mb": 50.0},
    }


PRODUCED = {
    "plant": (
        PlantSummary,
        {
            "service": "plant",
            "mode": "realtime",
            "plant_model": "actuator",
            "final_state": [0.1, 0.2, 0.3],
            "true_final_state": [0.12, 0.2, 0.3],
            "saturated_commands": 4,
            "counters": {},
        },
    ),
    "robot_bridge": (BridgeSummary, _bridge_summary()),
    "tb3_emulator": (
        EmulatorSummary,
        {
            "service": "tb3_emulator",
            "profile": "ros2dds",
            "ros_distro": "humble",
            "cmd_type": "geometry_msgs/msg/Twist",
            "attachment": None,
            "cmd_key": "cmd_vel",
            "odom_key": "odom",
            "model": "ideal",
            "final_pose": [0.0, 0.0, 0.0],
            "final_odometry": [0.0, 0.0, 0.0],
            "saturated_commands": 0,
            "applied": [0.0, 0.0],
            "max_abs_applied": [0.2, 1.0],
            "cmd_timeouts": 0,
            "counters": {"odom_published": 10},
            "missed_ticks": 0,
            "initial_pose": [1.0, 1.0, 0.0],
            "resources": None,
        },
    ),
    "router": (RouterSummary, {"service": "router", "endpoint": "tcp/127.0.0.1:7447", "resources": None}),
}


@pytest.mark.parametrize("name", sorted(PRODUCED))
def test_the_plant_bridge_emulator_and_router_summaries_fit_and_refuse_a_drifted_key(name: str) -> None:
    model, summary = PRODUCED[name]
    parsed = model.model_validate(summary)
    assert {k: v for k, v in parsed.to_json_dict().items() if k in summary} == summary  # the keys printed stay
    with pytest.raises(ValidationError, match="extra"):
        model.model_validate({**summary, "final_sate": [0.0, 0.0, 0.0]})
    required = next(k for k, f in model.model_fields.items() if f.is_required())
    with pytest.raises(ValidationError, match=required):
        model.model_validate({k: v for k, v in summary.items() if k != required})
    with pytest.raises(ValidationError):  # a model is frozen: what was read is what was printed
        parsed.service = "other"  # type: ignore[misc]


@pytest.mark.integration
def test_srl_up_reads_the_plant_and_the_bridge_through_their_contracts() -> None:
    assert CHILD_SUMMARIES["plant"] is PlantSummary and CHILD_SUMMARIES["robot_bridge"] is BridgeSummary
    process = subprocess.Popen([sys.executable, "-c", "pass"], text=True)
    process.wait()
    bridge = Child("robot_bridge", process)
    bridge.stdout_lines.append(json.dumps(_bridge_summary()))
    read = _contract_summary(bridge, TypeAdapter(BridgeSummary))
    assert read.attachment_format == "compact" and math.isnan(read.timing.odom_to_state_ms.median)  # none measured
    plant = Child("plant", process)
    plant.stdout_lines.append(json.dumps({**PRODUCED["plant"][1], "final_sate": [0.0, 0.0, 0.0]}))
    with pytest.raises(ValueError, match=r"^plant's summary does not fit common/contracts/summaries.py: final_sate: "):
        _contract_summary(plant, TypeAdapter(CHILD_SUMMARIES["plant"]))
    with pytest.raises(ValueError, match="final_sate"):  # printed but drifted: never read as missing
        optional_summary(plant, TypeAdapter(PlantSummary))
    assert optional_summary(Child("plant", process), TypeAdapter(PlantSummary)) is None  # printed none (killed)


def _stage(state: np.ndarray, action: np.ndarray, r: tuple[float, ...]) -> float:
    chi = np.concatenate([state, action])
    return float(sum(r_i * c * c for r_i, c in zip(r, chi, strict=True)))


@pytest.mark.integration
def test_a_summary_on_the_actuator_plant_reports_the_truth_beside_the_odometry() -> None:
    """On the actuator plant the summary carries the truth beside the odometry, and the plant
    saturates a wheel."""
    settings = Settings.load(
        plant={"model": "actuator"},
        actuator={"slip": 0.1, "slip_std": 0.02, "imu_heading": False},
        actor={"agent": "mpc", **PAPER_METHOD["actor"]},  # the paper's actor: v and omega boxed apart
        episode={"duration": 6.0, "start": [1.5, -1.0]},
    )
    episode = run_episode(settings)
    summary = EpisodeSummary.model_validate(episode_summary(episode, settings))
    assert summary.plant_model == "actuator" and summary.truth is not None
    truth = np.array(episode.true_states)
    assert truth.shape == (episode.steps + 1, 3)
    assert summary.truth.start_state == summary.start_state  # the odometry starts where the robot is
    assert summary.truth.final_state == [float(c) for c in truth[-1]]
    # 10 % slip: the true pose is not what the robot reports
    assert np.hypot(*(np.array(summary.truth.final_state[:2]) - np.array(summary.final_state[:2]))) > 0.01
    r = settings.r_diag
    true_j = sum(0.1 * _stage(s, u, r) for s, u in zip(truth[:-1], episode.actions, strict=True))
    assert summary.truth.accumulated_cost == pytest.approx(true_j, rel=1e-12)
    assert summary.truth.accumulated_cost != pytest.approx(summary.accumulated_cost, rel=1e-6)
    # v and omega are boxed separately: full speed with a turn asks a wheel for twice its limit
    assert summary.saturated_commands is not None and summary.saturated_commands > 0
    # the robot's settings (srl.toml: the wheel-speed box) never ask a wheel beyond its limit
    boxed = settings.model_copy(update={"actor": Settings.load().actor.model_copy(update={"agent": "mpc"})})
    assert boxed.actor.wheel_speed_max > 0
    boxed_summary = EpisodeSummary.model_validate(episode_summary(run_episode(boxed), boxed))
    assert boxed_summary.saturated_commands == 0


@pytest.mark.integration
def test_on_the_ideal_plant_the_truth_is_what_the_robot_reports() -> None:
    settings = Settings.load(actor={"agent": "mpc"}, episode={"duration": 2.0})
    summary = EpisodeSummary.model_validate(episode_summary(run_episode(settings), settings))
    assert summary.plant_model == "ideal" and summary.truth is not None
    assert summary.truth.final_state == summary.final_state
    assert summary.truth.accumulated_cost == pytest.approx(summary.accumulated_cost, rel=1e-12)
    assert summary.saturated_commands == 0


@pytest.mark.integration
def test_a_plant_without_the_truth_gives_a_summary_that_says_so() -> None:
    from common.math.loop import ExactPlant

    class OdometryOnly(ExactPlant):  # a real robot: it reports, it does not know the truth
        @property
        def true_state(self) -> None:  # type: ignore[override]
            return None

        @property
        def saturated_commands(self) -> None:  # type: ignore[override]
            return None

    settings = Settings.load(actor={"agent": "mpc"}, episode={"duration": 1.0})
    summary = episode_summary(run_episode(settings, plant=OdometryOnly()), settings)
    assert summary["truth"] is None and summary["saturated_commands"] is None
    from tools.commands.run import format_run_summary

    text = format_run_summary({**summary, "wall_seconds": 0.0, "transport": "inproc"})
    assert "only its odometry is known" in text
