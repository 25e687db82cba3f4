"""The robot bridge and the TurtleBot3 emulator: logic against fakes, then the real processes.

Integration tests run the real ``srl robot-bridge`` and ``srl tb3-emulator`` processes on free
loopback ports (multicast scouting off) and watch the robot's own wire: the emulator reports the
velocity it applies in the twist of its odometry, as a TurtleBot3 does, so "the robot stopped"
is read from ROS messages, not from the bridge's word.
"""

from __future__ import annotations

import itertools
import json
import math
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import pytest
import zenoh
from pydantic import ValidationError

from common.config.settings import Settings
from common.contracts import ros_wire
from common.contracts.messages import Action, PlantState
from common.contracts.ros_wire import ODOMETRY, TWIST, TWIST_STAMPED, Attachment, Odometry, RosGraph
from common.math.dynamics import exact_step
from common.math.frames import Pose2D
from common.net.provenance import RESYNC_AFTER, SourceGate
from services.robot_bridge.bridge import CLOCK_RESET_AFTER, RobotBridge
from services.tb3_emulator.service import Tb3Model
from tests.harness import (
    ROOT,
    FakeCounts,
    cluster,
    declare_service_tokens,
    fake_bridge,
    free_port,
    odom_sample,
    open_session,
    wait_until,
)

DELTA = 0.1
TIMEOUT = 3 * DELTA  # bridge.watchdog_timeout_steps x delta (srl.toml)
ODOM_PERIOD = 0.05  # the emulator's 20 Hz
WATCHDOG_CHECK = DELTA / 10  # the bridge checks its watchdog every delta / 10 (services/robot_bridge/host.py)
SLACK = 0.05  # scheduling on a loaded 2-vCPU machine


def firmware(value: float) -> float:
    """What the TurtleBot3 applies for a command that is a whole number of 0.01 steps: n * 0.01f."""
    return float(np.float32(round(value * 100)) * np.float32(0.01))


# -- the logic, against fakes -----------------------------------------------------------------


_bridge = fake_bridge
_odom = odom_sample


def _action(step: int, v: float = 0.1, omega: float = 0.0, episode: int = 1, robot: str = "u0") -> Action:
    return Action(robot=robot, episode=episode, step=step, stamp_ns=0, action=(v, omega), state_seq=-1)


@pytest.mark.parametrize(
    "bad",
    [
        {"profile": "dds"},
        {"ros_distro": "iron"},
        {"namespace": "tb3 1"},
        {"namespace": "1tb"},
        {"goal": [0.0, math.nan, 0.0]},
        {"goal": [0.0, 0.0]},
        {"cmd_type": "twist_with_covariance"},
        {"watchdog_timeout_steps": 0},
        {"domain_id": -1},
        {"discovery_timeout": math.inf},
        {"odom_topic": "/odom"},
    ],
)
def test_bridge_settings_are_validated(bad: dict[str, Any]) -> None:
    with pytest.raises(ValidationError):
        Settings.load(bridge=bad)


def test_bridge_settings_normalize_the_namespace() -> None:
    assert Settings.load(bridge={"namespace": "/tb3_1/"}).bridge.namespace == "tb3_1"
    assert Settings.load().bridge.goal == (0.0, 0.0, 0.0)


def test_heading_is_unwrapped_across_pi() -> None:
    bridge, states, _, _ = _bridge()
    yaws = np.arange(0.0, 4 * math.pi, 0.1)  # two full turns; odometry reports yaw in (-pi, pi]
    for k, yaw in enumerate(yaws):
        bridge.on_odometry(_odom(k + 1, yaw=float(yaw)), time.monotonic())
    alphas = np.array([s.state[2] for s in states])
    np.testing.assert_allclose(alphas, yaws, atol=1e-9)
    assert [s.seq for s in states] == list(range(1, len(yaws) + 1))
    assert all(s.source == "robot" for s in states)


def test_state_is_in_the_goal_frame() -> None:
    bridge, states, _, _ = _bridge(goal=(1.0, 1.0, math.pi / 2))
    bridge.on_odometry(_odom(1, 1.0, 3.0, math.pi / 2), time.monotonic())
    bridge.on_odometry(_odom(2, 0.0, 1.0, -math.pi / 2), time.monotonic())
    np.testing.assert_allclose(states[0].state, (2.0, 0.0, 0.0), atol=1e-12)
    # 1 m to the goal's left (+y of the goal frame), facing back; heading continuous from 0
    np.testing.assert_allclose(states[1].state, (0.0, 1.0, -math.pi), atol=1e-12)


def test_bad_odometry_is_refused() -> None:
    bridge, states, _, counts = _bridge()
    bridge.on_odometry(_odom(100, 0.5), time.monotonic())
    bad = [
        _odom(101, math.nan),
        _odom(102, 0.0, math.inf),
        Odometry(103, "odom", "base_footprint", 0.0, 0.0, (0.0, 0.0, 0.0, 0.0), 0.0, 0.0),
        Odometry(104, "odom", "base_footprint", 0.0, 0.0, (math.nan, 0.0, 0.0, 1.0), 0.0, 0.0),
        _odom(104, 2e4),  # beyond the schema's physical bounds
        _odom(100, 9.0),
        _odom(50, 9.0),
    ]  # not newer: out of order
    for odom in bad:
        assert bridge.on_odometry(odom, time.monotonic()) is None
    assert len(states) == 1 and counts.counters["rejected.odom"] == len(bad)
    bridge.on_odometry(_odom(105, 0.6), time.monotonic())
    assert [s.state[0] for s in states] == [0.5, 0.6]
    # a robot whose clock went back (restart) is followed after CLOCK_RESET_AFTER stale samples
    for k in range(CLOCK_RESET_AFTER):
        bridge.on_odometry(_odom(1 + k, 0.7), time.monotonic())
    assert len(states) == 3 and counts.counters["odom_clock_resets"] == 1


def test_actions_are_checked_and_clamped() -> None:
    bridge, _, commands, counts = _bridge()
    bridge.on_action(_action(0), time.monotonic())
    assert commands == [] and counts.counters["rejected.action"] == 1  # no actor token yet
    bridge.set_actor_alive(True)
    bridge.on_action(_action(1, 5.0, -9.0), time.monotonic())
    assert commands == [(0.22, -2.84)]
    bridge.on_action(_action(1, 0.1), time.monotonic())  # the same step again
    bridge.on_action(_action(0, 0.1, episode=2, robot="other"), time.monotonic())
    bridge.on_action(_action(5, 0.1, episode=0), time.monotonic())  # an older episode
    nan_action = Action.model_construct(
        robot="u0", episode=1, step=9, stamp_ns=0, action=(math.nan, 0.0), state_seq=-1
    )  # bypasses the schema, which refuses NaN
    bridge.on_action(nan_action, time.monotonic())
    assert commands == [(0.22, -2.84)]
    assert counts.counters["rejected.action"] == 5
    bridge.on_action(_action(2, -0.1, 0.5), time.monotonic())
    assert commands[-1] == (-0.1, 0.5)
    bridge._command(math.nan, 1.0)  # the last guard before the wire
    assert commands[-1] == (0.0, 0.0) and counts.counters["nonfinite_commands_zeroed"] == 1


def test_watchdog_commands_zero_and_keeps_commanding_it() -> None:
    bridge, _, commands, counts = _bridge()
    bridge.set_actor_alive(True)
    bridge.on_action(_action(1, 0.2), 100.0)
    bridge.tick(100.0 + TIMEOUT - 0.01)
    assert commands == [(0.2, 0.0)]
    bridge.tick(100.0 + TIMEOUT + 0.01)
    assert commands[-1] == (0.0, 0.0) and counts.counters["watchdog_stops"] == 1
    bridge.tick(100.0 + TIMEOUT + 0.02)  # repeated every delta / 2, not every check
    assert len(commands) == 2
    bridge.tick(100.0 + TIMEOUT + 0.011 + DELTA / 2)
    assert commands[-1] == (0.0, 0.0) and len(commands) == 3
    assert counts.counters["watchdog_stops"] == 1
    # the actor's token vanishing stops the robot at once
    bridge.on_action(_action(2, 0.2), time.monotonic())
    bridge.set_actor_alive(False)
    assert commands[-2:] == [(0.2, 0.0), (0.0, 0.0)] and counts.counters["actor_lost_stops"] == 1
    bridge.on_action(_action(3, 0.2), time.monotonic())
    assert commands[-1] == (0.0, 0.0)  # refused while the actor is gone


def test_odometry_from_the_far_future_does_not_lock_out_the_real_samples() -> None:
    """One odometry sample stamped an hour ahead is refused without becoming the reference: the
    real samples after it are kept."""
    bridge, states, _, counts = _bridge()
    t0, second = 1_000_000.0, 10**9
    bridge.on_odometry(_odom(100 * second, 0.5), t0)
    for k in range(1, 6):  # a forged sample once a "second", each followed by real 20 Hz samples
        assert bridge.on_odometry(_odom((100 + 3600 + k) * second, 9.0), t0 + k) is None
        for j in range(20):
            stamp = 100 * second + k * second + j * (second // 20)
            assert bridge.on_odometry(_odom(stamp, 0.5), t0 + k + j / 20) is not None
    assert len(states) == 1 + 5 * 20 and counts.counters["rejected.odom"] == 5
    assert all(s.state[0] == 0.5 for s in states)
    # a robot clock that really jumped forward is followed after CLOCK_RESET_AFTER samples in a row
    for j in range(CLOCK_RESET_AFTER):
        bridge.on_odometry(_odom((5000 + j) * second, 0.6), t0 + 6 + j / 20)
    assert states[-1].state[0] == 0.6 and counts.counters["odom_clock_jumps"] == 1


def test_actions_only_from_the_live_actor_session() -> None:
    """Actions are followed only from the live actor session (one Action(episode=2**62) from
    another session locks nothing out), and a new session resyncs."""
    settings = Settings.load(transport={"robot": "u0"})
    commands: list[tuple[float, float]] = []
    counts = FakeCounts()
    gate = SourceGate("actor")
    bridge = RobotBridge(settings, lambda s: None, lambda v, w: commands.append((v, w)), counts, gate)
    gate.update("a1", True)  # as Bus.watch_identities does: the gate first, then the bridge
    bridge.on_actor_identity("a1", True)
    bridge.on_action(_action(1, 0.1), time.monotonic(), "a1")
    bridge.on_action(_action(0, 0.2, episode=2**62), time.monotonic(), "rogue")  # foreign session
    bridge.on_action(_action(2, 0.1), time.monotonic(), None)  # unstamped
    bridge.on_action(_action(2, 0.15), time.monotonic(), "a1")
    assert commands == [(0.1, 0.0), (0.15, 0.0)] and counts.counters["rejected.action.foreign"] == 2
    bridge.on_action(_action(2 + 20_000, 0.2), time.monotonic(), "a1")  # a step from the far future
    assert commands[-1] == (0.15, 0.0) and counts.counters["rejected.action"] == 1
    # a rogue identity beside the real one: a conflict, nothing is followed
    gate.update("rogue", True)
    bridge.on_action(_action(3, 0.2), time.monotonic(), "a1")
    assert commands[-1] == (0.15, 0.0) and counts.counters["rejected.action.conflict"] == 1
    gate.update("rogue", False)
    # the followed session dies while another actor token lingers: stop at once
    gate.update("a2", True)
    gate.update("a1", False)
    bridge.on_actor_identity("a1", False)
    assert commands[-1] == (0.0, 0.0) and counts.counters["actor_lost_stops"] == 1
    # the new actor session (a restart) starts its own episode and steps: followed
    bridge.on_action(_action(0, 0.05, episode=3), time.monotonic(), "a2")
    assert commands[-1] == (0.05, 0.0)


def test_a_forged_episode_with_the_live_actor_id_locks_nothing_out() -> None:
    """A forger that copies the live actor's session id with episode=2**62 locks nothing out:
    that action is refused alone, and
    a forged burst that was followed costs the real actor RESYNC_AFTER - 1 actions at most."""
    settings = Settings.load(transport={"robot": "u0"})
    commands: list[tuple[float, float]] = []
    counts = FakeCounts()
    gate = SourceGate("actor")
    bridge = RobotBridge(settings, lambda s: None, lambda v, w: commands.append((v, w)), counts, gate)
    gate.update("a1", True)
    bridge.on_actor_identity("a1", True)
    episode = 1_764_000_000_000  # the actor's episode ids are milliseconds since the epoch
    now = time.monotonic()
    bridge.on_action(_action(0, 0.1, episode=episode), now, "a1")
    bridge.on_action(_action(0, -0.2, episode=2**62), now + 0.01, "a1")  # forged, with the live id
    assert counts.counters["rejected.action"] == 1 and commands[-1] == (0.1, 0.0)
    for k in range(1, 10):
        bridge.on_action(_action(k, 0.1 + 0.001 * k, episode=episode), now + 0.1 * k, "a1")
    assert commands[-1][0] == pytest.approx(0.109) and counts.counters["actions_applied"] == 10
    # a forged burst that counts on is followed (it has the live id: only --secure stops it)...
    for k in range(RESYNC_AFTER):
        bridge.on_action(_action(k, -0.2, episode=2**62), now + 1.0 + 0.001 * k, "a1")
    assert commands[-1] == (-0.2, 0.0) and counts.counters["action_resyncs"] == 1
    # ...and the real actor, continuing from its own numbers, is followed again within RESYNC_AFTER
    applied = []
    for k in range(10, 10 + 2 * RESYNC_AFTER):
        bridge.on_action(_action(k, 0.15, episode=episode), now + 1.0 + 0.1 * (k - 9), "a1")
        applied.append(commands[-1] == (0.15, 0.0))
    assert applied == [False] * (RESYNC_AFTER - 1) + [True] * (RESYNC_AFTER + 1)
    assert counts.counters["action_resyncs"] == 2
    assert counts.counters["rejected.action"] == 1 + 2 * (RESYNC_AFTER - 1)


# -- the emulated robot's model ------------------------------------------------------------------
def test_emulator_integrates_exactly_with_latency_and_timeout() -> None:
    model = Tb3Model(
        Pose2D(1.0, 2.0, 0.3), 0.22, 2.84, latency=0.2, cmd_timeout=0.0, noise=(0.0, 0.0), seed=0, now=10.0
    )
    assert model.command(0.1, 0.5, 10.0) == (firmware(0.1), firmware(0.5))
    pose, applied = model.sample(10.1)
    assert applied == (0.0, 0.0)  # not yet: 0.2 s of latency
    np.testing.assert_array_equal(pose, (1.0, 2.0, 0.3))
    model.command(0.3, -3.0, 10.5)  # limited by the firmware, applied at 10.7
    pose, applied = model.sample(11.0)
    assert applied == (0.22, -2.84)
    # the oracle: exact sample-and-hold steps over the pieces, from the closed form
    expected = exact_step(np.array([1.0, 2.0, 0.3]), np.array([firmware(0.1), firmware(0.5)]), 0.5)
    expected = exact_step(expected, np.array([0.22, -2.84]), 0.3)
    np.testing.assert_allclose(pose, expected, rtol=0, atol=1e-12)
    # with a command timeout the robot stops by itself
    timed = Tb3Model(Pose2D(0.0, 0.0, 0.0), 0.22, 2.84, latency=0.0, cmd_timeout=0.5, noise=(0.0, 0.0), seed=0, now=0.0)
    timed.command(0.2, 0.0, 0.0)
    pose, applied = timed.sample(2.0)
    assert applied == (0.0, 0.0) and timed.timeouts == 1
    assert pose[0] == pytest.approx(firmware(0.2) * 0.5, abs=1e-12)


def test_emulator_noise_is_seeded() -> None:
    def poses(seed: int) -> np.ndarray:
        model = Tb3Model(Pose2D(0.0, 0.0, 0.0), 0.22, 2.84, 0.0, 0.0, (0.01, 0.02), seed, now=0.0)
        return np.array([model.sample(0.05 * k)[0] for k in range(50)])

    np.testing.assert_array_equal(poses(3), poses(3))
    assert not np.array_equal(poses(3), poses(4))
    assert 0.005 < np.std(poses(3)[:, 0]) < 0.02 and 0.01 < np.std(poses(3)[:, 2]) < 0.04


def test_emulator_with_the_actuator_model_reports_odometry_and_keeps_the_truth() -> None:
    """``--model actuator``: the TurtleBot3 model behind the firmware; the oracle is the model
    itself driven by the same commands at the same times (common/math/turtlebot.py has its own)."""
    import dataclasses

    from common.config.settings import Settings
    from common.math.turtlebot import TurtleBot
    from tools.launch.up import emulator_truth

    settings = Settings.load(actuator={"slip": 0.1, "imu_heading": False})
    params = settings.turtlebot_params()
    model = Tb3Model(
        Pose2D(1.0, 2.0, 0.3), 0.22, 2.84, 0.0, 0.0, (0.0, 0.0), 0, 0.0, "actuator", params, settings.physics_params()
    )
    oracle = TurtleBot(dataclasses.replace(params, v_max=0.22, omega_max=2.84), np.array([1.0, 2.0, 0.3]))
    for k, (v, omega) in enumerate([(0.2, 0.0), (0.22, 2.84), (-0.1, 0.5), (0.0, 0.0)]):
        model.command(v, omega, 0.5 * k)
        oracle.command(v, omega)
        oracle.advance(0.5)
    pose, velocity = model.sample(2.0)
    np.testing.assert_allclose(pose, oracle.odometry, atol=1e-12)
    np.testing.assert_allclose(model.state, oracle.true_pose, atol=1e-12)
    assert velocity == pytest.approx(oracle.velocity)  # the encoders' twist, not the command
    assert np.hypot(*(pose[:2] - model.state[:2])) > 0.01  # 10 % slip: odometry is not the truth
    assert model.robot.saturated_commands == 1  # (0.22, 2.84): the right wheel asked for 13.6 rad/s
    # srl up's view of it: the truth in the goal frame (goal at the odom origin here)
    truth = emulator_truth(
        {"model": "actuator", "final_pose": list(model.state), "final_odometry": list(pose), "saturated_commands": 1},
        settings,
    )
    assert truth is not None and truth["final_state"] == pytest.approx(list(model.state))
    assert truth["final_distance"] == pytest.approx(np.hypot(*model.state[:2]))


# -- processes ------------------------------------------------------------------------------------
class RobotWatch:
    """Subscribes, as a ROS tool would, to the robot's odometry; and to srl's state."""

    def __init__(self, session: zenoh.Session, graph: RosGraph, robot: str) -> None:
        self.odom: list[tuple[float, Odometry]] = []
        self.states: list[PlantState] = []
        self.lock = threading.Lock()

        def on_odom(sample: zenoh.Sample) -> None:
            odom = ros_wire.decode_odometry(graph.distro, bytes(sample.payload.to_bytes()))
            with self.lock:
                self.odom.append((time.monotonic(), odom))

        self.entities = [
            session.declare_subscriber(graph.data_key("odom", ODOMETRY, "*"), on_odom),
            session.declare_subscriber(
                f"srl/{robot}/state", lambda s: self.states.append(PlantState.model_validate_json(s.payload.to_bytes()))
            ),
        ]

    def applied(self) -> tuple[float, float]:
        with self.lock:
            return (self.odom[-1][1].v, self.odom[-1][1].omega) if self.odom else (math.nan, math.nan)

    def stops_before(self, t: float) -> int:
        """How often the robot's odometry went from moving to standing still before ``t``."""
        with self.lock:
            twists = [(odom.v, odom.omega) for at, odom in self.odom if at < t]
        return sum(1 for before, now in itertools.pairwise(twists) if before != (0.0, 0.0) and now == (0.0, 0.0))

    def twists_since(self, t: float) -> list[tuple[float, float, float]]:
        """``(seconds after t, v, omega)`` of each odometry sample after ``t`` (a failure's story)."""
        with self.lock:
            return [(round(at - t, 3), odom.v, odom.omega) for at, odom in self.odom if at > t]

    def first_stop_after(self, t: float) -> float | None:
        with self.lock:
            for at, odom in self.odom:
                if at > t and odom.v == 0.0 and odom.omega == 0.0:
                    return at
        return None


def _drive(
    session: zenoh.Session, robot: str, watch: RobotWatch, seconds: float, start_step: int, action: tuple[float, float]
) -> tuple[int, float]:
    """Publish one action every delta for ``seconds`` (as the actor would); (next step, last put time)."""
    publisher = session.declare_publisher(f"srl/{robot}/action")
    step, last = start_step, time.monotonic()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        seq = watch.states[-1].seq if watch.states else -1
        publisher.put(
            Action(
                robot=robot, episode=1, step=step, stamp_ns=time.monotonic_ns(), action=action, state_seq=seq
            ).encode()
        )
        last = time.monotonic()
        step += 1
        time.sleep(DELTA)
    publisher.undeclare()
    return step, last


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.timing  # the watchdog's stop within its timeout: a latency bound (tests/tiers.py)
@pytest.mark.alone  # within one odometry period and 50 ms: another test's processes on the cores break it
@pytest.mark.parametrize(
    ("profile", "distro", "emulator_cmd", "expected"),
    [
        ("rmw_zenoh", "humble", None, TWIST),
        ("rmw_zenoh", "jazzy", None, TWIST_STAMPED),
        ("rmw_zenoh", "jazzy", "twist", TWIST),  # discovered from the robot's token, not the distro default
        ("ros2dds", "jazzy", None, TWIST_STAMPED),
        ("ros2dds", "humble", None, TWIST),
    ],
)
def test_bridge_drives_the_emulated_robot(profile: str, distro: str, emulator_cmd: str | None, expected: str) -> None:
    robot = f"e_{profile[:3]}_{distro[:3]}"
    wire = ["--profile", profile, "--ros-distro", distro]
    with cluster(robot=robot) as c:
        assert c.session is not None
        graph = RosGraph(profile, distro, 0, "")
        watch = RobotWatch(c.session, graph, robot)
        c.start(
            "emulator",
            "tb3-emulator",
            *wire,
            "--initial-pose=-1,0.5,0",
            *(["--cmd-type", emulator_cmd] if emulator_cmd else []),
        )
        c.start("bridge", "robot-bridge", *wire)  # cmd_type auto
        c.wait_alive("plant")
        wait_until(lambda: len(watch.states) >= 5, 30, "srl state from the robot's odometry")
        first = watch.states[-1]
        assert first.source == "robot"
        np.testing.assert_allclose(first.state, (-1.0, 0.5, 0.0), atol=1e-9)
        tokens = declare_service_tokens(c.session, robot, "actor")

        step, last_put = _drive(c.session, robot, watch, 1.5, 0, (0.1, 0.2))
        assert watch.applied() == (firmware(0.1), firmware(0.2))  # int32(v * 100) * 0.01f
        moved = watch.states[-1].state
        assert moved[0] > first.state[0] + 0.1 and moved[2] > 0.2  # forward and turning left

        # watchdog: actions stop -> zero within the timeout, one watchdog check and one odometry period
        wait_until(lambda: watch.first_stop_after(last_put) is not None, 5, "the robot to stop")
        stopped_after = watch.first_stop_after(last_put) - last_put  # type: ignore[operator]
        assert TIMEOUT - 0.02 < stopped_after <= TIMEOUT + WATCHDOG_CHECK + ODOM_PERIOD + SLACK, stopped_after

        # actor liveliness: drive again, then the token vanishes -> zero at once
        step, _ = _drive(c.session, robot, watch, 0.5, step, (0.15, 0.0))
        assert watch.applied() == (firmware(0.15), 0.0)
        threading.Thread(target=_drive, args=(c.session, robot, watch, 1.0, step, (0.15, 0.0))).start()
        time.sleep(0.4)
        for token in tokens:
            token.undeclare()
        lost = time.monotonic()
        wait_until(lambda: watch.first_stop_after(lost) is not None, 5, "the robot to stop")
        assert watch.first_stop_after(lost) - lost <= DELTA + ODOM_PERIOD + SLACK  # type: ignore[operator]
        time.sleep(0.7)  # the remaining actions of the thread are refused: the robot stays stopped
        assert watch.applied() == (0.0, 0.0)

        assert c.procs["bridge"].stop() == 0
        assert c.procs["emulator"].stop() == 0
        bridge, emulator = c.procs["bridge"].summary(), c.procs["emulator"].summary()
    assert bridge["discovered"] == [expected] and not bridge["fallback"]
    assert emulator["cmd_type"] == expected
    counters = emulator["counters"]
    assert counters.get("rejected_cdr", 0) == counters.get("rejected_no_attachment", 0) == 0
    assert counters.get("nonfinite_commands", 0) == 0 and counters["cmd_applied"] > 20
    assert bridge["counters"]["watchdog_stops"] >= 1 and bridge["counters"]["actor_lost_stops"] == 1
    assert bridge["counters"]["rejected.action"] >= 1  # after the token vanished
    assert max(bridge["max_abs_command"]) <= 0.2 + 1e-12
    if profile == "rmw_zenoh":
        assert emulator["cmd_key"].endswith(
            "TypeHashNotSupported" if distro == "humble" else ros_wire.type_hash("jazzy", expected)
        )


@pytest.mark.integration
@pytest.mark.slow
def test_two_robots_by_namespace() -> None:
    """Two TurtleBot3s on one Zenoh network (namespaces tb3_1, tb3_2), one bridge and srl robot id each."""
    with cluster(robot="r1") as c:
        assert c.session is not None
        watches = {}
        for index in (1, 2):
            ns = f"tb3_{index}"
            graph = RosGraph("rmw_zenoh", "jazzy", 0, ns)
            watches[index] = RobotWatch(c.session, graph, f"r{index}")
            c.start(f"emulator{index}", "tb3-emulator", "--namespace", ns, f"--initial-pose={index},0,0")
            c.start(f"bridge{index}", "robot-bridge", "--namespace", ns, "--robot", f"r{index}")
        for index in (1, 2):
            wait_until(
                lambda i=index: len(watches[i].states) >= 3 and len(watches[i].odom) >= 3,
                30,
                f"odometry and state of robot r{index}",
            )
        assert watches[1].odom[-1][1].frame_id == "tb3_1/odom"  # TurtleBot3 prefixes its frames
        tokens = declare_service_tokens(c.session, "r1", "actor")
        _drive(c.session, "r1", watches[1], 1.0, 0, (0.2, 0.0))
        time.sleep(0.2)
        assert watches[1].states[-1].state[0] > 1.15
        assert watches[2].states[-1].state[0] == 2.0  # the other robot never moved
        assert all(odom.v == 0.0 for _, odom in watches[2].odom)
        for token in tokens:
            token.undeclare()
        for name in ("bridge1", "bridge2", "emulator1", "emulator2"):
            assert c.procs[name].stop() == 0
        emulators = [c.procs[f"emulator{i}"].summary() for i in (1, 2)]
    assert emulators[0]["cmd_key"].startswith("0/tb3_1/cmd_vel/geometry_msgs::msg::dds_::TwistStamped_/")
    assert emulators[1]["counters"]["cmd_applied"] >= 1  # zeros from its own bridge's watchdog only
    assert emulators[1]["max_abs_applied"] == [0.0, 0.0]


@pytest.mark.integration
@pytest.mark.slow
def test_emulator_requires_the_rmw_zenoh_attachment() -> None:
    with cluster(robot="att") as c:
        assert c.session is not None
        graph = RosGraph("rmw_zenoh", "jazzy", 0, "")
        watch = RobotWatch(c.session, graph, "att")
        c.start("emulator", "tb3-emulator", "--profile", "rmw_zenoh", "--ros-distro", "jazzy")
        wait_until(lambda: len(watch.odom) >= 3, 30, "odometry")
        key = graph.data_key("cmd_vel", TWIST_STAMPED)
        payload = ros_wire.encode_command("jazzy", TWIST_STAMPED, 0.2, 0.0, stamp_ns=time.time_ns())
        publisher = c.session.declare_publisher(key)
        publisher.put(payload)  # no attachment: dropped, as rmw_zenoh's subscription does
        publisher.put(payload, attachment=b"\x01" * 32)  # malformed
        time.sleep(0.5)
        assert watch.applied() == (0.0, 0.0)
        publisher.put(payload, attachment=Attachment(1, time.time_ns(), bytes(16)).encode())
        wait_until(lambda: watch.applied()[0] > 0.19, 5, "the valid command to be applied")
        assert c.procs["emulator"].stop() == 0
        counters = c.procs["emulator"].summary()["counters"]
    assert counters["rejected_no_attachment"] == 1
    assert counters["rejected_bad_attachment"] == 1
    assert counters["cmd_applied"] == 1


@pytest.mark.integration
@pytest.mark.slow
def test_bridge_survives_bad_odometry_and_never_sends_bad_commands(monkeypatch: pytest.MonkeyPatch) -> None:
    """The test plays the robot (rmw_zenoh, Jazzy) and feeds the bridge garbage."""
    monkeypatch.setenv("SRL_BRIDGE__DISCOVERY_TIMEOUT", "0.5")  # no robot tokens: fall back quickly
    with cluster(robot="fz") as c:
        assert c.session is not None
        graph = RosGraph("rmw_zenoh", "jazzy", 0, "")
        commands: list[tuple[float, float, Attachment]] = []

        def on_cmd(sample: zenoh.Sample) -> None:
            assert sample.attachment is not None
            commands.append(
                (
                    *ros_wire.decode_command("jazzy", TWIST_STAMPED, bytes(sample.payload.to_bytes())),
                    Attachment.decode(bytes(sample.attachment.to_bytes())),
                )
            )

        c.session.declare_subscriber(graph.data_key("cmd_vel", TWIST_STAMPED), on_cmd)
        states: list[PlantState] = []
        c.session.declare_subscriber(
            "srl/fz/state", lambda s: states.append(PlantState.model_validate_json(s.payload.to_bytes()))
        )
        c.start("bridge", "robot-bridge", "--profile", "rmw_zenoh", "--ros-distro", "jazzy")
        c.wait_alive("plant")
        time.sleep(1.0)  # fallback after 0.5 s; the watchdog's zeros wait for the attachment format
        assert commands == []  # no odometry yet: the robot's rmw_zenoh release is unknown

        odom_key = graph.data_key("odom", ODOMETRY)
        odom = c.session.declare_publisher(odom_key)
        seq = iter(range(1, 100))

        def put(payload: bytes, attachment: bytes | None = b"ok", key: str | None = None) -> None:
            if attachment == b"ok":
                attachment = Attachment(next(seq), time.time_ns(), bytes(16)).encode()
            if key is None:
                odom.put(payload, attachment=attachment)
            else:
                c.session.put(key, payload, attachment=attachment)

        def sample(stamp_s: int, x: float, quaternion: tuple[float, float, float, float] = (0, 0, 0, 1)) -> bytes:
            return ros_wire.encode_odometry(
                "jazzy", Odometry(stamp_s * 10**9, "odom", "base_footprint", x, 0.0, quaternion, 0.0, 0.0)
            )

        put(sample(10, 1.0))
        wait_until(lambda: len(states) == 1, 5, "the first state")
        wait_until(lambda: len(commands) >= 3, 10, "zero commands on the fallback TwistStamped key")
        assert all(cmd[:2] == (0.0, 0.0) for cmd in commands)  # no actor: the watchdog holds zero
        assert all(cmd[2].format == "compact" for cmd in commands)  # the format of the robot's odometry
        bad = 0
        for payload, attachment, key in [
            (sample(11, 2.0), None, None),  # no attachment
            (sample(11, 2.0), b"\x00" * 33, None),  # attachment with a bad GID length
            (b"\x00\x01\x00\x00garbage", b"ok", None),  # malformed CDR
            (ros_wire.encode_command("jazzy", TWIST, 0.1, 0.1), b"ok", None),  # wrong type
            (sample(11, math.nan), b"ok", None),  # NaN pose
            (sample(11, 2.0, (0.0, 0.0, 0.0, 0.0)), b"ok", None),  # no orientation
            (sample(9, 2.0), b"ok", None),  # out of order
            (sample(11, 2.0), b"ok", odom_key.rsplit("/", 1)[0] + "/RIHS01_" + "00" * 32),  # foreign hash
        ]:
            put(payload, attachment, key)
            bad += 1
        put(sample(12, 3.0))
        wait_until(lambda: len(states) == 2, 5, "the second valid state")
        time.sleep(0.3)
        assert [s.state[0] for s in states] == [1.0, 3.0]

        tokens = declare_service_tokens(c.session, "fz", "actor")
        time.sleep(0.2)
        actions = c.session.declare_publisher("srl/fz/action")
        actions.put(
            b'{"schema_version":1,"robot":"fz","episode":1,"step":0,"stamp_ns":0,"action":[NaN,0],"state_seq":0}'
        )
        actions.put(Action(robot="fz", episode=1, step=1, stamp_ns=0, action=(5.0, -10.0), state_seq=2).encode())
        actions.put(
            b'{"schema_version":1,"robot":"fz","episode":1,"step":2,"stamp_ns":0,"action":[1e300,0],"state_seq":0}'
        )  # huge: refused by the schema
        actions.put(Action(robot="fz", episode=1, step=3, stamp_ns=0, action=(-50.0, 50.0), state_seq=2).encode())
        wait_until(lambda: any(cmd[:2] == (-0.22, 2.84) for cmd in commands), 5, "the clamped command")
        for token in tokens:
            token.undeclare()
        time.sleep(0.2)
        assert c.procs["bridge"].stop() == 0
        summary = c.procs["bridge"].summary()
    assert all(math.isfinite(v) and math.isfinite(w) and abs(v) <= 0.22 and abs(w) <= 2.84 for v, w, _ in commands)
    assert (0.22, -2.84) in [cmd[:2] for cmd in commands]
    assert commands[-1][:2] == (0.0, 0.0)  # the shutdown zero
    seqs = [a.seq for _, _, a in commands]
    counters = summary["counters"]
    # one publisher, its sequence numbers from 1, one a command sent (none skipped: the last is the
    # bridge's count), seen in order. Zenoh's default congestion control drops a sample that meets
    # a full queue (docs/architecture.md, "Delivery"): on a loaded machine a sample may not arrive
    # (the parallel suite once saw 1, 2, 3, 4, 7, 8, ...), a newer command replaces it
    assert seqs[0] == 1 and seqs == sorted(set(seqs)), seqs
    assert seqs[-1] == counters["commands_sent"], (seqs[-1], counters["commands_sent"])
    assert len(seqs) >= 0.9 * seqs[-1], seqs  # a drop is the exception
    assert counters["rejected.odom"] == bad
    assert counters["states_published"] == 2
    assert counters["rejected.action"] >= 2  # the NaN and the huge action, refused by the schema
    assert counters["cmd_vel_fallback"] == 1 and summary["fallback"]
    assert counters["commands_format_unknown"] >= 5  # zeros held back before the first odometry
    assert summary["attachment_format"] == "compact"


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.parametrize("distro", ["jazzy", "humble"])
def test_bridge_speaks_the_legacy_attachment_of_an_older_robot(distro: str) -> None:
    """An emulated rmw_zenoh_cpp Jazzy 0.2.0-0.2.3 / Humble 0.1.0-0.1.1 robot (attachment with
    field names): the bridge reads the format from its odometry and drives it; the robot never
    sees an attachment its subscriber would throw on, and the GID is the token's XXH3-128."""
    robot = f"legacy_{distro}"
    wire = ["--profile", "rmw_zenoh", "--ros-distro", distro]
    with cluster(robot=robot) as c:
        assert c.session is not None
        graph = RosGraph("rmw_zenoh", distro, 0, "")
        watch = RobotWatch(c.session, graph, robot)
        attachments: list[Attachment] = []
        cmd_type = TWIST_STAMPED if distro == "jazzy" else TWIST
        c.session.declare_subscriber(
            graph.data_key("cmd_vel", cmd_type),
            lambda s: (
                attachments.append(Attachment.decode(bytes(s.attachment.to_bytes())))
                if s.attachment is not None
                else None
            ),
        )
        publishers: list[str] = []
        c.session.liveliness().declare_subscriber(
            f"@ros2_lv/0/*/*/*/MP/%/%/{ros_wire.BRIDGE_NODE}/%cmd_vel/**",
            lambda s: publishers.append(str(s.key_expr)) if s.kind == zenoh.SampleKind.PUT else None,
            history=True,
        )
        c.start("emulator", "tb3-emulator", *wire, "--attachment", "legacy", "--initial-pose=-1,0.5,0")
        c.start("bridge", "robot-bridge", *wire)
        c.wait_alive("plant")
        wait_until(lambda: len(watch.states) >= 5, 30, "srl state from the legacy robot's odometry")
        tokens = declare_service_tokens(c.session, robot, "actor")
        _drive(c.session, robot, watch, 1.5, 0, (0.1, 0.2))
        assert watch.applied() == (firmware(0.1), firmware(0.2))
        for token in tokens:
            token.undeclare()
        wait_until(lambda: watch.applied() == (0.0, 0.0), 5, "the robot to stop")
        assert c.procs["bridge"].stop() == 0
        assert c.procs["emulator"].stop() == 0
        bridge, emulator = c.procs["bridge"].summary(), c.procs["emulator"].summary()
    print(
        f"legacy {distro}: {emulator['counters']['cmd_applied']} cmd_vel applied, "
        f"{emulator['counters'].get('attachment_format_errors', 0)} format errors, "
        f"{bridge['counters'].get('commands_format_unknown', 0)} commands held before the format was known"
    )
    assert emulator["attachment"] == "legacy" and bridge["attachment_format"] == "legacy"
    assert emulator["counters"].get("attachment_format_errors", 0) == 0
    assert emulator["counters"].get("rejected_bad_attachment", 0) == 0
    assert emulator["counters"]["cmd_applied"] > 10
    assert bridge["counters"].get("rejected.odom", 0) == 0
    assert attachments and all(a.format == "legacy" for a in attachments)
    assert [a.seq for a in attachments] == list(range(1, len(attachments) + 1))
    assert len(publishers) == 1  # the bridge's MP token; the attachment GID is its XXH3-128
    assert {a.gid for a in attachments} == {ros_wire.gid_for(publishers[0])}


@pytest.mark.integration
@pytest.mark.slow
def test_a_compact_attachment_is_refused_by_a_legacy_robot() -> None:
    """The attack of finding 8, against the emulator: what srl sent before (compact attachment)
    is what an rmw_zenoh_cpp 0.2.0-0.2.3 subscriber throws on; the emulator counts it."""
    with cluster(robot="legacy_neg") as c:
        assert c.session is not None
        graph = RosGraph("rmw_zenoh", "jazzy", 0, "")
        watch = RobotWatch(c.session, graph, "legacy_neg")
        c.start("emulator", "tb3-emulator", "--attachment", "legacy")
        wait_until(lambda: len(watch.odom) >= 3, 30, "odometry")
        key = graph.data_key("cmd_vel", TWIST_STAMPED)
        payload = ros_wire.encode_command("jazzy", TWIST_STAMPED, 0.2, 0.0, stamp_ns=time.time_ns())
        publisher = c.session.declare_publisher(key)
        publisher.put(payload, attachment=Attachment(1, time.time_ns(), bytes(16)).encode())
        time.sleep(0.5)
        assert watch.applied() == (0.0, 0.0)
        publisher.put(payload, attachment=Attachment(2, time.time_ns(), bytes(16), "legacy").encode())
        wait_until(lambda: watch.applied()[0] > 0.19, 5, "the legacy command to be applied")
        assert c.procs["emulator"].stop() == 0
        counters = c.procs["emulator"].summary()["counters"]
    assert counters["attachment_format_errors"] == 1 and counters["cmd_applied"] == 1


@pytest.mark.integration
@pytest.mark.slow
def test_killing_the_actor_stops_the_robot() -> None:
    with cluster(robot="kill") as c:
        assert c.session is not None
        watch = RobotWatch(c.session, RosGraph("rmw_zenoh", "jazzy", 0, ""), "kill")
        c.start("emulator", "tb3-emulator", "--start=2,1.5")
        c.start("bridge", "robot-bridge")
        c.wait_alive("plant")
        actor = c.start("actor", "actor", "--mode", "realtime", "--agent", "mpc", "--run-seconds", "60")
        c.wait_alive("actor", timeout=120)
        wait_until(lambda: abs(watch.applied()[0]) > 0.05, 60, "the actor to drive the robot")
        time.sleep(1.0)
        # driving when the actor is killed: a loaded machine may starve the actor past the
        # bridge's watchdog for a moment (the robot stops, counted as a watchdog stop, and drives
        # on with the next action); every stop the odometry shows is the bridge's, counted below
        wait_until(lambda: watch.applied() != (0.0, 0.0), 10, "the robot to drive")
        actor.stop(signal.SIGKILL)
        killed = time.monotonic()
        wait_until(lambda: watch.first_stop_after(killed) is not None, 5, "the robot to stop")
        stopped_after = watch.first_stop_after(killed) - killed  # type: ignore[operator]
        assert stopped_after <= TIMEOUT + ODOM_PERIOD, stopped_after
        time.sleep(0.5)
        assert watch.applied() == (0.0, 0.0)
        assert c.procs["bridge"].stop() == 0
        counters = c.procs["bridge"].summary()["counters"]
    said = f"{counters}; odometry from 3 s before the kill: {watch.twists_since(killed - 3.0)}"
    # the kill is counted as the actor's loss, and so is no more than each stop before it (a
    # token that flickered); every stop the odometry showed is one the bridge counted (a starved
    # actor: the watchdog's), never a zero the actor sent while driving (a watchdog stop the
    # odometry did not catch, or the watchdog outrunning the token's loss at the kill, adds one)
    lost, watchdog, before = counters["actor_lost_stops"], counters.get("watchdog_stops", 0), watch.stops_before(killed)
    assert 1 <= lost <= 1 + before and lost + watchdog >= 1 + before, said


def _run_up(*argv: str, timeout: float = 240) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "tools.cli", "up", *argv],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


@pytest.mark.integration
@pytest.mark.slow
def test_up_with_the_emulated_robot() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    done = _run_up(
        "--plant", "robot", "--router", endpoint, "--robot", "uprob", "--start=1.5,1", "--duration", "8", "--json"
    )
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    assert "srl up: realtime run, plant robot" in done.stdout
    assert set(summary["services"]) == {"router", "tb3_emulator", "robot_bridge", "critic", "actor"}
    assert all(code == 0 for code in summary["exit_codes"].values()), summary["exit_codes"]
    assert summary["steps"] >= 60
    start, final = np.array(summary["start_state"]), np.array(summary["final_state"])
    assert np.hypot(*final[:2]) < np.hypot(*start[:2]) - 0.3, (start, final)
    bridge, emulator = summary["bridge"], summary["emulator"]
    # no localization source: the pose is the odometry's, said without --json too
    assert bridge["localization"] == "odometry only"
    assert "\n  localization   odometry only\n" in done.stdout
    assert bridge["discovered"] == [TWIST_STAMPED]
    assert bridge["counters"]["actions_applied"] >= summary["steps"] - 2
    assert emulator["counters"].get("nonfinite_commands", 0) == 0
    assert emulator["counters"].get("rejected_no_attachment", 0) == 0
    assert emulator["applied"] == [0.0, 0.0]  # stopped at the end
    assert summary["critic"]["transitions_received"] == summary["steps"]


def test_the_up_summary_says_what_the_robots_pose_is() -> None:
    """Odometry only or the localization source, for a robot plant; nothing for a simulated one."""
    from tools.commands.up import format_up_summary

    base = {"mode": "realtime", "plant": "robot", "services": {}, "steps": 1}
    odometry = format_up_summary({**base, "bridge": {"localization": "odometry only"}}).splitlines()
    located = "pose_with_covariance on amcl_pose (frame map)"
    localized = format_up_summary({**base, "bridge": {"localization": located}}).splitlines()
    assert "  localization   odometry only" in odometry
    assert f"  localization   {located}" in localized
    assert not any("localization" in line for line in format_up_summary({**base, "plant": "sim"}).splitlines())


@pytest.mark.integration
@pytest.mark.slow
def test_swap_sim_and_robot_agree() -> None:
    """The same real-time MPC episode with plant_sim and with the bridge + emulated TurtleBot3.

    Tolerances: the firmware truncates each command to 0.01 m/s and 0.01 rad/s (at most 0.1 m
    over 10 s), the robot's state comes at 20 Hz instead of 50 Hz (up to 50 ms old at a tick:
    11 mm at 0.22 m/s), and both runs are real time (tick jitter). So the end points must agree
    within 0.1 m and the accumulated costs within 5 %.

    Both runs must have parked (the arrival rule holds them still, common/math/arrival.py) before
    their end points are compared: mid-shuffle they are up to ~0.13 m apart along x. The approach
    takes ~8 s (1.8 m at 0.22 m/s); then the MPC shuffles back and forth to remove the last
    ~0.1 m of lateral offset (a unicycle cannot move sideways), and how long that takes depends on
    the small differences above: the arrival comes 14-18 s into a run, sometimes later, so a
    20 s episode ended some runs mid-shuffle. The episode is 30 s: the shuffle may take twice its
    usual time. Parked, the end points agree to a few mm and the costs to ~1 %.
    """

    def run(plant: str) -> subprocess.CompletedProcess[str]:
        return _run_up(
            "--plant",
            plant,
            "--agent",
            "mpc",
            "--start=1.5,1",
            "--duration",
            "30",
            "--json",
            "--router",
            f"tcp/127.0.0.1:{free_port()}",
            "--robot",
            f"swap_{plant}",
        )

    # the two runs side by side (own routers, own robot ids): each waits on real time
    with ThreadPoolExecutor(max_workers=2) as pool:
        done = dict(zip(("sim", "robot"), pool.map(run, ("sim", "robot")), strict=True))
    runs = {}
    for plant, finished in done.items():
        assert finished.returncode == 0, finished.stderr[-3000:]
        runs[plant] = json.loads(finished.stdout.strip().splitlines()[-1])
    sim, robot = runs["sim"], runs["robot"]
    np.testing.assert_allclose(sim["start_state"], robot["start_state"], atol=1e-9)
    for run in (sim, robot):
        assert np.hypot(*run["final_state"][:2]) < 0.2  # both parked near the target
    np.testing.assert_allclose(sim["final_state"][:2], robot["final_state"][:2], atol=0.1)
    assert robot["accumulated_cost"] == pytest.approx(sim["accumulated_cost"], rel=0.05)


@pytest.mark.integration
@pytest.mark.slow
def test_up_with_a_robot_endpoint_starts_no_emulator() -> None:
    robot_endpoint = f"tcp/127.0.0.1:{free_port()}"
    emulator = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "tools.cli",
            "tb3-emulator",
            "--listen",
            robot_endpoint,
            "--ros-distro",
            "humble",
            "--initial-pose=-1,-1,0.5",
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        open_session(robot_endpoint, 30, "the robot's router").close()
        done = _run_up(
            "--plant",
            "robot",
            "--router",
            f"tcp/127.0.0.1:{free_port()}",
            "--robot",
            "ep",
            "--robot-endpoint",
            robot_endpoint,
            "--ros-distro",
            "humble",
            "--duration",
            "5",
            "--json",
        )
        assert done.returncode == 0, done.stderr[-3000:]
        summary = json.loads(done.stdout.strip().splitlines()[-1])
    finally:
        emulator.send_signal(signal.SIGINT)
        out, _ = emulator.communicate(timeout=20)
    assert "tb3_emulator" not in summary["services"]
    assert summary["bridge"]["discovered"] == [TWIST]
    np.testing.assert_allclose(summary["start_state"][:2], (-1.0, -1.0), atol=0.05)
    robot = json.loads(out.strip().splitlines()[-1])
    assert robot["counters"]["cmd_applied"] > 20
    assert np.hypot(*robot["final_pose"][:2]) < np.hypot(-1.0, -1.0) - 0.1


@pytest.mark.integration
def test_up_robot_lockstep_is_a_clear_error() -> None:
    done = _run_up("--plant", "robot", "--mode", "lockstep", "--router", f"tcp/127.0.0.1:{free_port()}", timeout=60)
    assert done.returncode == 2
    assert "--plant robot runs in real time only" in done.stderr
    assert "Traceback" not in done.stderr
