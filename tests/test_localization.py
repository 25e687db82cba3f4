"""A localized pose as the state (docs/turtlebot-localization.md): the fusion math, the bridge's
rules against fakes, the emulator's update rule, and one ``srl up`` with AMCL's pose end to end."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from typing import Any

import numpy as np
import pytest
from pydantic import ValidationError

from common.config.settings import Settings
from common.contracts.messages import Action, PlantState
from common.contracts.ros_wire import PoseFix
from common.math.frames import Pose2D, quaternion_from_yaw, wrap_angle
from common.math.localization import CorrectionBlend, OdomHistory, compose, correction, inverse, motion
from services.robot_bridge.bridge import RobotBridge
from services.tb3_emulator.service import FixRule, LocalizationConfig
from tests.harness import ROOT, fake_bridge, free_port, odom_sample

SECOND = 10**9


# -- the math ---------------------------------------------------------------------------------


def test_composition_and_the_map_to_odom_correction() -> None:
    a, b = Pose2D(1.0, 2.0, 0.5), Pose2D(-0.3, 0.7, -2.0)
    np.testing.assert_allclose(compose(a, inverse(a)), (0.0, 0.0, 0.0), atol=1e-12)
    # a quarter turn: (1, 0) in a frame at (1, 2) rotated by pi/2 is (1, 3)
    np.testing.assert_allclose(compose(Pose2D(1.0, 2.0, math.pi / 2), Pose2D(1.0, 0.0, 0.0)), (1.0, 3.0, math.pi / 2))
    # the correction maps the odometry pose at the fix onto the fix, and any later pose along
    c = correction(a, b)
    np.testing.assert_allclose(compose(c, b)[:2], a[:2], atol=1e-12)
    assert wrap_angle(compose(c, b).theta - a.theta) == pytest.approx(0.0, abs=1e-12)
    later = compose(b, Pose2D(0.4, 0.0, 0.1))  # odometry after 0.4 m of driving
    np.testing.assert_allclose(compose(c, later)[:2], compose(a, Pose2D(0.4, 0.0, 0.1))[:2], atol=1e-12)
    assert motion(Pose2D(0, 0, 3.0), Pose2D(3.0, 4.0, -3.0)) == pytest.approx((5.0, 2 * math.pi - 6.0))


def test_odometry_history_interpolates_at_a_stamp() -> None:
    history = OdomHistory(size=3)
    assert history.at(5) is None
    history.add(10, Pose2D(0.0, 0.0, 3.0))
    history.add(20, Pose2D(1.0, 0.0, -3.0))  # across pi: the shorter arc
    np.testing.assert_allclose(history.at(15), (0.5, 0.0, 3.0 + (2 * math.pi - 6.0) / 2))
    assert history.at(1) == Pose2D(0.0, 0.0, 3.0) and history.at(99) == Pose2D(1.0, 0.0, -3.0)
    history.add(30, Pose2D(2.0, 0.0, 0.0))
    history.add(40, Pose2D(3.0, 0.0, 0.0))  # bounded: the first sample is gone
    assert history.at(1) == Pose2D(1.0, 0.0, -3.0)
    history.add(5, Pose2D(9.0, 0.0, 0.0))  # the robot's clock went back: start over
    assert history.at(40) == Pose2D(9.0, 0.0, 0.0)


def test_a_new_correction_is_blended_in_without_a_jump() -> None:
    blend = CorrectionBlend(1.0)
    assert blend.apply(Pose2D(0, 0, 0), 0.0) is None
    blend.set(Pose2D(1.0, 0.0, 0.0), 0.0)  # the first: at once
    assert blend.value(0.0) == Pose2D(1.0, 0.0, 0.0)
    blend.set(Pose2D(1.2, 0.0, 0.2), 10.0)
    values = [blend.value(10.0 + k * 0.05) for k in range(25)]
    steps = np.abs(np.diff([[v.x, v.theta] for v in values if v is not None], axis=0))
    assert steps.max(axis=0) == pytest.approx([0.2 * 0.05, 0.2 * 0.05])  # |dC| dt / blend_time
    np.testing.assert_allclose(values[-1], (1.2, 0.0, 0.2), atol=1e-12)
    blend.set(Pose2D(0.0, 0.0, 0.0), 20.0, snap=True)
    assert blend.value(20.0) == Pose2D(0.0, 0.0, 0.0)
    with pytest.raises(ValueError):
        CorrectionBlend(math.nan)


# -- the bridge, against fakes -----------------------------------------------------------------


_bridge = fake_bridge
_odom = odom_sample


def _fix(stamp: int, x: float, y: float, yaw: float = 0.0, frame: str = "map", child: str = "") -> PoseFix:
    return PoseFix(stamp, frame, child, x, y, quaternion_from_yaw(yaw))


def _action(step: int, v: float) -> Action:
    return Action(robot="u0", episode=1, step=step, stamp_ns=0, action=(v, 0.0), state_seq=-1)


def _drive(bridge: RobotBridge, t0: float, k: int, x: float, yaw: float = 0.0) -> PlantState | None:
    """Odometry sample ``k`` (20 Hz) at odom pose (x, 0, yaw), received at t0 + k / 20."""
    return bridge.on_odometry(_odom(k * SECOND // 20 + SECOND, x, 0.0, yaw), t0 + k / 20)


def test_odom_is_the_default_and_unchanged() -> None:
    bridge, states, _, counts = _bridge()
    bridge.on_localization(_fix(1, 5.0, 5.0), time.monotonic())  # ignored: not localized
    bridge.on_odometry(_odom(SECOND, 0.5, 0.25, 0.1), time.monotonic())
    np.testing.assert_allclose(states[0].state, (0.5, 0.25, 0.1))
    assert states[0].map_to_odom is None and b"map_to_odom" not in states[0].encode()
    assert bridge.localization() == "odometry only" and counts.counters["localization_fixes"] == 0


def test_amcl_pose_localizes_the_state_and_the_goal_is_in_map() -> None:
    bridge, states, _, counts = _bridge(pose_source="pose_with_covariance", goal=(1.0, 0.0, 0.0))
    t0 = time.monotonic()
    # AMCL's transient-local pose comes before any odometry: kept, fused with the first sample
    bridge.on_localization(_fix(SECOND, 3.0, 2.0, math.pi / 2), t0)
    assert states == []
    assert _drive(bridge, t0, 0, 0.0) is not None  # odometry at its origin: the robot is at (3, 2) in map
    np.testing.assert_allclose(states[-1].state, (2.0, 2.0, math.pi / 2), atol=1e-12)  # goal frame: map - (1, 0)
    _drive(bridge, t0, 1, 0.1)  # 0.1 m forward along odom x = map +y (heading pi/2)
    np.testing.assert_allclose(states[-1].state, (2.0, 2.1, math.pi / 2), atol=1e-12)
    assert bridge.localization() == "pose_with_covariance on amcl_pose (frame map)"
    assert counts.counters["localization_fixes"] == 1


def test_a_correction_moves_the_state_smoothly() -> None:
    bridge, states, _, _ = _bridge(pose_source="pose_with_covariance")
    t0 = time.monotonic()
    _drive(bridge, t0, 0, 0.0)
    bridge.on_localization(_fix(SECOND, 0.0, 0.0), t0)
    for k in range(1, 5):
        _drive(bridge, t0, k, 0.0)
    # AMCL now says the robot is 0.2 m further along x (odometry drifted); its stamp is odometry k = 4's
    bridge.on_localization(_fix(SECOND + 4 * SECOND // 20, 0.2, 0.0), t0 + 4 / 20)
    xs = [s.state[0] for s in states]
    for k in range(5, 40):  # 1.75 s standing still
        _drive(bridge, t0, k, 0.0)
        xs.append(states[-1].state[0])
    steps = np.diff(xs)
    # blended over pose_blend_time (1 s): at most 0.2 m x 0.05 s / 1 s per 20 Hz sample, never a jump
    assert steps.max() <= 0.2 * 0.05 + 1e-9 and steps.min() >= -1e-12
    assert xs[-1] == pytest.approx(0.2)


def test_a_stale_localization_stops_the_robot_and_says_so(caplog: pytest.LogCaptureFixture) -> None:
    bridge, states, commands, counts = _bridge(pose_source="pose_with_covariance")
    t0 = time.monotonic()
    bridge.on_localization(_fix(SECOND, 0.0, 0.0), t0)
    bridge.set_actor_alive(True)
    _drive(bridge, t0, 0, 0.0)
    step = 0
    for k in range(1, 11):  # the robot drives 0.5 m by odometry, AMCL silent: still fresh at 0.5 m
        step += 1
        bridge.on_action(_action(step, 0.2), t0 + k / 20)
        assert _drive(bridge, t0, k, 0.05 * k) is not None
    assert commands[-1] == (0.2, 0.0)
    assert _drive(bridge, t0, 11, 0.55) is None  # 0.55 m: stale
    assert commands[-1] == (0.0, 0.0) and counts.counters["localization_stale_stops"] == 1
    assert "localization stale (odometry moved 0.55 m" in caplog.text
    step += 1
    bridge.on_action(_action(step, 0.2), t0 + 0.6)  # refused while stale
    assert commands[-1] == (0.0, 0.0) and counts.counters["rejected.action"] == 1
    n = len(states)
    assert _drive(bridge, t0, 12, 0.6) is None and len(states) == n
    # a fresh fix: the states resume, from the fix at once (the robot was stopped)
    bridge.on_localization(_fix(SECOND + 12 * SECOND // 20, 0.7, 0.0), t0 + 0.6)
    assert _drive(bridge, t0, 13, 0.6) is not None
    assert states[-1].state[0] == pytest.approx(0.7)
    step += 1
    bridge.on_action(_action(step, 0.1), t0 + 0.65)
    assert commands[-1] == (0.1, 0.0) and counts.counters["localization_stale_stops"] == 1


def test_a_silent_streaming_source_is_stale_after_its_timeout() -> None:
    bridge, _, commands, counts = _bridge(pose_source="pose_stamped", pose_timeout=0.5)
    t0 = time.monotonic()
    _drive(bridge, t0, 0, 0.0)
    bridge.on_localization(_fix(SECOND, 1.0, 0.0), t0)
    bridge.tick(t0 + 0.4)
    assert counts.counters["localization_stale_stops"] == 0
    bridge.tick(t0 + 0.6)  # motion capture silent for 0.6 s, the robot standing: stale by age
    assert commands[-1] == (0.0, 0.0) and counts.counters["localization_stale_stops"] == 1
    assert _drive(bridge, t0, 13, 0.0) is None


def test_no_localization_publishes_no_state_and_warns_once(caplog: pytest.LogCaptureFixture) -> None:
    bridge, states, _, counts = _bridge(pose_source="odometry", pose_timeout=0.1)
    t0 = bridge.started_at
    for k in range(10):
        assert _drive(bridge, t0, k, 0.0) is None
    assert states == [] and counts.counters["localization_missing"] == 1
    assert caplog.text.count("no localization on odometry/filtered") == 1
    bridge.on_localization(_fix(SECOND + 9 * SECOND // 20, 2.0, 1.0), t0 + 0.5)
    assert _drive(bridge, t0, 10, 0.0) is not None
    np.testing.assert_allclose(states[-1].state, (2.0, 1.0, 0.0))


def test_tf_takes_map_to_odom_of_its_own_namespace_only() -> None:
    bridge, states, _, counts = _bridge(pose_source="tf", namespace="tb3_1")
    t0 = time.monotonic()
    bridge.on_localization(_fix(SECOND, 9.0, 9.0, child="odom"), t0)  # another robot's odom
    bridge.on_localization(_fix(SECOND, 9.0, 9.0, frame="tb3_1/odom", child="tb3_1/base_footprint"), t0)
    assert counts.counters["localization_fixes"] == 0
    bridge.on_localization(_fix(SECOND, 1.0, -1.0, math.pi / 2, frame="map", child="tb3_1/odom"), t0)
    _drive(bridge, t0, 0, 0.5)  # 0.5 m along odom x = map +y
    np.testing.assert_allclose(states[-1].state, (1.0, -0.5, math.pi / 2), atol=1e-12)
    # the state says which correction made it (the recorder's map -> odom on /tf)
    np.testing.assert_allclose(states[-1].map_to_odom, (1.0, -1.0, math.pi / 2), atol=1e-12)


def test_bad_fixes_are_refused() -> None:
    bridge, states, _, counts = _bridge(pose_source="pose_with_covariance")
    t0 = time.monotonic()
    _drive(bridge, t0, 0, 0.0)
    bad = [
        _fix(SECOND, math.nan, 0.0),
        _fix(SECOND, 0.0, math.inf),
        _fix(SECOND, 2e4, 0.0),
        PoseFix(SECOND, "map", "", 0.0, 0.0, (0.0, 0.0, 0.0, 0.0)),
    ]
    for fix in bad:
        bridge.on_localization(fix, t0)
    assert counts.counters["rejected.localization"] == len(bad) and states == []
    bridge.on_localization(_fix(2 * SECOND, 0.5, 0.0), t0)
    bridge.on_localization(_fix(2 * SECOND, 0.9, 0.0), t0)  # not newer: the same fix twice
    assert counts.counters["rejected.localization"] == len(bad) + 1


@pytest.mark.parametrize(
    "bad",
    [
        {"pose_source": "amcl"},
        {"pose_topic": "/amcl_pose"},
        {"pose_timeout": 0.0},
        {"pose_stale_distance": math.inf},
        {"pose_blend_time": -1.0},
    ],
)
def test_localization_settings_are_validated(bad: dict[str, Any]) -> None:
    with pytest.raises(ValidationError):
        Settings.load(bridge=bad)


# -- the emulator's update rule -----------------------------------------------------------------


def test_the_emulator_publishes_like_amcl_or_motion_capture() -> None:
    amcl = FixRule(LocalizationConfig("pose_with_covariance", "amcl_pose"))
    assert amcl.due(Pose2D(0, 0, 0), 0.0)  # the first fix at once
    assert not amcl.due(Pose2D(0.2, 0, 0.1), 5.0)  # standing or creeping: no update
    assert amcl.due(Pose2D(0.25, 0, 0), 5.1)  # update_min_d 0.25 m
    assert not amcl.due(Pose2D(0.25, 0, 0.15), 5.2)
    assert amcl.due(Pose2D(0.25, 0, 0.2), 5.3)  # update_min_a 0.2 rad
    mocap = FixRule(LocalizationConfig("pose_stamped", "mocap/pose", rate=10.0))
    fixes = [t for t in np.arange(0.0, 1.0, 0.05) if mocap.due(Pose2D(0, 0, 0), float(t))]
    assert len(fixes) == 10  # 10 Hz from a 20 Hz loop


# -- end to end ----------------------------------------------------------------------------------


@pytest.mark.integration
@pytest.mark.slow
def test_up_parks_on_amcl_pose_with_one_setting() -> None:
    """``srl up --plant robot`` with ``bridge.pose_source = "pose_with_covariance"``: the emulated
    robot's odometry starts at its own origin (where it stands), so only AMCL's pose, published
    once at start (transient local: before the bridge subscribed) and then every 0.25 m / 0.2 rad,
    says where it is in map. The robot parks by the truth: within 0.05 m of the goal and at rest (its
    last applied command zero) after 20 s, from 1.8 m away (the arrival bound of
    docs/turtlebot-parking.md's criteria is 16 s from there)."""
    env = {**os.environ, "SRL_BRIDGE__POSE_SOURCE": "pose_with_covariance"}
    argv = ["--plant", "robot", "--router", f"tcp/127.0.0.1:{free_port()}", "--robot", "amcl", "--start=1.5,1"]
    done = subprocess.run(
        [sys.executable, "-m", "tools.cli", "up", *argv, "--duration", "20", "--json"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    bridge, emulator = summary["bridge"], summary["emulator"]
    assert bridge["localization"] == "pose_with_covariance on amcl_pose (frame map)"
    assert emulator["localization"] == "pose_with_covariance"
    truth_start, truth_final = np.array(emulator["initial_pose"]), np.array(emulator["final_pose"])
    assert np.hypot(*truth_start[:2]) > 1.5
    assert np.hypot(*truth_final[:2]) <= 0.05, (truth_start, truth_final)  # parked, by the truth
    assert emulator["applied"] == [0.0, 0.0]  # and at rest
    # the first fix came from the publisher's cache; more came as the robot moved
    assert bridge["counters"]["localization_fixes"] >= 3
    assert bridge["counters"]["localization_fixes"] == emulator["counters"]["localization_published"]
    assert bridge["counters"].get("localization_stale_stops", 0) == 0
    # the odometry the robot reported is far from the truth in map: only the localization parks it
    assert np.hypot(*np.array(emulator["final_odometry"][:2]) - truth_final[:2]) > 1.0
    np.testing.assert_allclose(summary["final_state"][:2], truth_final[:2], atol=0.05)
