"""Recordings (docs/recordings.md), read back by readers that did not write them.

srl writes CDR with ``rosbags`` into foxglove-sdk's MCAP writer; these tests read with the
``mcap`` reader and decode with ``mcap-ros2-support`` (its own CDR decoder, from the schema text in
the file), and compare with what the run itself reported (``--json --trajectory``,
``trajectories.npz``). The live view's test speaks the Foxglove WebSocket protocol with a plain
``websockets`` client. Every process on a free loopback port, multicast scouting off (srl's
default), stopped by pid.
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import re
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory

from tests import harness
from tests.harness import ROOT, FakeSample, Proc, buses_on_a_fake_session, free_port, open_session, wait_until
from tools.recording.sinks import RowsByOne

DELTA_NS = 100_000_000  # delta = 0.1 s


def srl(*argv: str, timeout: float = 240) -> subprocess.CompletedProcess[str]:
    return harness.srl(*argv, timeout=timeout)


def read(path: Path) -> dict[str, list[tuple[int, Any]]]:
    """Every message of a recording, decoded by mcap-ros2-support, per topic: (log time, message)."""
    topics: dict[str, list[tuple[int, Any]]] = {}
    with path.open("rb") as file:
        reader = make_reader(file, decoder_factories=[DecoderFactory()])
        for _schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            topics.setdefault(channel.topic, []).append((message.log_time, decoded))
    return topics


def on_disk(path: Path) -> dict[str, list[int]]:
    """The log times of the messages per topic in the chunks of a recording already on the disk
    (a recorder still writing it, or killed: its file ends in the middle of a record, or has no
    summary or footer yet)."""
    topics: dict[int, str] = {}
    times: dict[str, list[int]] = {}
    with path.open("rb") as file:
        try:
            for record in StreamReader(file).records:
                if isinstance(record, Channel):
                    topics[record.id] = record.topic
                elif isinstance(record, Message):
                    times.setdefault(topics[record.channel_id], []).append(record.log_time)
        except (McapError, struct.error, EOFError):  # the end of what is written so far
            pass
    return times


def check_rosbag2_layout(path: Path) -> dict[str, Any]:
    """Profile ros2, every schema a ros2msg definition, every channel cdr, the rosbag2 metadata
    record whose counts are the file's; returns the metadata."""
    with path.open("rb") as file:
        reader = make_reader(file)
        header = reader.get_header()
        summary = reader.get_summary()
        metadata = {record.name: record.metadata for record in reader.iter_metadata()}
    assert header.profile == "ros2"
    assert summary is not None and summary.statistics is not None
    assert summary.schemas and all(s.encoding == "ros2msg" for s in summary.schemas.values())
    assert all(c.message_encoding == "cdr" for c in summary.channels.values())
    assert all("offered_qos_profiles" in c.metadata for c in summary.channels.values())
    info = json.loads(metadata["rosbag2"]["serialized_metadata"])["rosbag2_bagfile_information"]
    assert info["storage_identifier"] == "mcap"
    counts = {summary.channels[i].topic: n for i, n in summary.statistics.channel_message_counts.items()}
    assert {t["topic_metadata"]["name"]: t["message_count"] for t in info["topics_with_message_count"]} == counts
    assert info["message_count"] == summary.statistics.message_count
    return info


def stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def check_steps(
    topics: dict[str, list[tuple[int, Any]]],
    robot: str,
    states: np.ndarray,
    r_diag: list[float],
    total: float,
    said: str | None = None,
) -> None:
    """One action and one transition per step, delta apart in sim time, the values of the run
    (its states; its costs recomputed as delta r(s_k, u_k) from them and the recorded actions)."""
    steps = len(states) - 1
    transitions = topics[f"/{robot}/srl/transition"]
    commands = topics[f"/{robot}/cmd_vel"]
    recorded = [m.step for _, m in transitions]
    missing = sorted(set(range(steps)) - set(recorded))
    assert len(transitions) == len(commands) == steps, f"/{robot}: steps {missing} of {steps} not recorded; {said}"
    actions = np.array([[m.twist.linear.x, m.twist.angular.z] for _, m in commands])
    chi = np.hstack([states[:-1], actions])
    costs = 0.1 * (chi**2) @ np.array(r_diag)
    times = [t for t, _ in transitions]
    assert np.all(np.diff(times) == DELTA_NS), "transitions are delta = 0.1 s apart"
    assert [t for t, _ in commands] == times
    assert all(stamp_ns(m.header) == t for t, m in transitions)
    assert [m.step for _, m in transitions] == list(range(steps))
    recorded = np.array([[m.x, m.y, m.alpha] for _, m in transitions])
    np.testing.assert_allclose(recorded, states[:-1], rtol=0, atol=1e-9)
    np.testing.assert_allclose([m.stage_cost for _, m in transitions], costs, rtol=0, atol=1e-9)
    np.testing.assert_allclose(transitions[-1][1].accumulated_cost, total, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(actions, [[m.v, m.omega] for _, m in transitions])
    odometry = topics[f"/{robot}/odom"]
    assert len(odometry) == steps + 1  # s_0 .. s_steps, one per step (clock "steps")
    assert np.all(np.diff([t for t, _ in odometry]) == DELTA_NS)
    assert all(m.header.frame_id == "odom" and m.child_frame_id == "base_footprint" for _, m in odometry)
    positions = np.array([[m.pose.pose.position.x, m.pose.pose.position.y] for _, m in odometry])
    np.testing.assert_allclose(positions, states[:, :2], rtol=0, atol=1e-9)
    yaw = np.array([2 * math.atan2(m.pose.pose.orientation.z, m.pose.pose.orientation.w) for _, m in odometry])
    np.testing.assert_allclose(np.remainder(yaw - states[:, 2] + math.pi, 2 * math.pi) - math.pi, 0, atol=1e-9)
    # /tf: odom -> <robot>/base_footprint with every odometry message, equal to the state (a
    # simulated plant's odom is its goal frame, docs/recordings.md "Frames"), stamped as the state
    # (srl record gathers many states' transforms in one /tf message)
    base = [
        (stamp_ns(transform.header), transform.transform)
        for _, m in topics["/tf"]
        for transform in m.transforms
        if transform.child_frame_id == f"{robot}/base_footprint"
    ]
    assert [t for t, _ in base] == [t for t, _ in odometry]
    assert all(
        transform.header.frame_id == "odom"
        for _, m in topics["/tf"]
        for transform in m.transforms
        if transform.child_frame_id == f"{robot}/base_footprint"
    )
    np.testing.assert_allclose([[b.translation.x, b.translation.y] for _, b in base], states[:, :2], rtol=0, atol=1e-9)
    tf_yaw = np.array([2 * math.atan2(b.rotation.z, b.rotation.w) for _, b in base])
    np.testing.assert_allclose(np.remainder(tf_yaw - states[:, 2] + math.pi, 2 * math.pi) - math.pi, 0, atol=1e-9)


@pytest.mark.integration
@pytest.mark.slow
def test_srl_run_and_srl_up_record_the_runs_trajectory_and_srl_plot_draws_it(tmp_path: Path) -> None:
    args = ["--agent", "rlqv", "--horizon", "12", "--start", "1.5,1", "--duration", "3", "--no-jit"]
    run = srl("run", *args, "--json", "--trajectory", "--record", str(tmp_path / "run.mcap"))
    assert run.returncode == 0, run.stderr
    summary = json.loads(run.stdout.splitlines()[-1])
    states = np.array(summary["trajectory"])
    up = srl(
        "up", "--mode", "lockstep", *args, "--router", f"tcp/127.0.0.1:{free_port()}", "--robot", "rec1",
        "--json", "--summary-dir", str(tmp_path / "up"), "--record", str(tmp_path / "up.mcap"),
    )  # fmt: skip
    assert up.returncode == 0, up.stderr
    up_summary = json.loads(up.stdout.splitlines()[-1])
    assert up_summary["recording"] == str(tmp_path / "up.mcap") and "srl record: recorded" in up_summary["recorder"]
    for name, robot in (("run.mcap", "tb3_0"), ("up.mcap", "rec1")):
        path = tmp_path / name
        info = check_rosbag2_layout(path)
        topics = read(path)
        # the lockstep services reproduce the in-process run bit for bit: both match its --json
        said = up_summary["recorder"] if name == "up.mcap" else None  # srl record's summary line
        check_steps(topics, robot, states, summary["settings"]["cost"]["r_diag"], summary["accumulated_cost"], said)
        assert info["message_count"] > 0 and topics["/target"][0][1].pose.position.x == 0.0
        weights = topics[f"/{robot}/srl/critic_weights"]
        assert [m.version for _, m in weights] == sorted({m.version for _, m in weights}), "versions increase"
        assert all(len(m.q_weights) == 15 and len(m.v_weights) == 6 for _, m in weights)
        assert topics[f"/{robot}/path"][-1][1].poses, "the path"
    plotted = srl("plot", str(tmp_path / "up.mcap"), "--out", str(tmp_path / "up.png"))
    assert plotted.returncode == 0, plotted.stderr
    assert (tmp_path / "up.png").stat().st_size > 10_000
    assert f"J = {summary['accumulated_cost']:.4f}" in plotted.stdout


@pytest.mark.integration
@pytest.mark.slow
def test_the_experiment_records_every_run_as_trajectories_npz_holds_it(tmp_path: Path) -> None:
    out, path = tmp_path / "exp", tmp_path / "exp.mcap"
    done = srl(
        "experiment", "paper", "--grid", "2", "--duration", "2", "--agents", "mpc,rlqv+", "--horizons", "6",
        "--workers", "1", "--no-plots", "--no-progress", "--out", str(out), "--record", str(path),
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    check_rosbag2_layout(path)
    topics = read(path)
    settings = json.loads((out / "settings.json").read_text())
    with np.load(out / "trajectories.npz") as npz:
        runs, all_states, all_costs = list(npz["run_id"]), npz["states"], npz["costs"]
    assert len(runs) == 8
    origins = set()
    for run_id, states, costs in zip(runs, all_states, all_costs, strict=True):
        robot = re.sub(r"[^A-Za-z0-9_]", "_", str(run_id).replace("+", "plus"))  # a ROS name: rlqvplus_N6_s000
        check_steps(topics, robot, states, settings["cost"]["r_diag"], float(np.sum(costs)))
        origins.add(topics[f"/{robot}/srl/transition"][0][0])
    assert len(origins) == 1, "every run starts at the same moment"


@pytest.mark.integration
def test_a_bad_recording_path_is_one_line_before_anything_runs(tmp_path: Path) -> None:
    for argv in (
        ["run", "--duration", "1", "--record", str(tmp_path / "missing" / "x.mcap")],
        ["run", "--duration", "1", "--record", str(tmp_path / "x.bag")],
        ["up", "--duration", "1", "--router", f"tcp/127.0.0.1:{free_port()}", "--record", str(tmp_path)],
        ["record", str(tmp_path / "missing" / "x.mcap"), "--router", f"tcp/127.0.0.1:{free_port()}"],
        ["record", str(tmp_path / "x.mcap"), "--split-minutes", "-1", "--router", f"tcp/127.0.0.1:{free_port()}"],
        ["plot", str(tmp_path / "none.mcap")],
        # the monitor role may not read transitions and weights: refused before anything starts
        ["up", "--secure", "--duration", "1", "--router", f"tcp/127.0.0.1:{free_port()}", "--view"],
    ):
        done = srl(*argv, timeout=60)
        assert done.returncode == 2, (argv, done.stderr)
        errors = [line for line in done.stderr.splitlines() if "error" in line.lower()]
        assert len(errors) == 1 and ("record" in errors[0] or "recording" in errors[0]), done.stderr
        assert "Traceback" not in done.stderr


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM])
def test_srl_record_joins_a_running_system_and_closes_the_file_on_a_signal(tmp_path: Path, stop: int) -> None:
    """Two real-time plants (no actor: each holds its start) publish states at 50 Hz; srl record
    joins, is stopped by SIGINT or SIGTERM, and leaves one complete file of both and one summary line."""
    router = f"tcp/127.0.0.1:{free_port()}"
    path = tmp_path / "live.mcap"
    procs = [Proc("router", ["router", "--router", router])]
    try:
        for robot, start in (("r7", "1,-0.5,0.3"), ("r8", "-1,2,0")):  # a fleet: one file carries both
            plant = ["plant-sim", "--mode", "realtime", "--router", router, "--robot", robot, "--start", start]
            procs.append(Proc(robot, plant))
        session = open_session(router)
        try:  # both plants up before the recorder joins: then both are in the file from its start
            for robot in ("r7", "r8"):
                wait_until(
                    lambda r=robot: any(x.ok for x in session.liveliness().get(f"srl/{r}/alive/plant", timeout=0.5)),
                    60,
                    f"plant {robot}",
                )
        finally:
            session.close()
        recorder = Proc("record", ["record", str(path), "--router", router])
        procs.append(recorder)
        wait_until(lambda: any("srl record: recording" in line for line in recorder.stderr), 60, "the recorder")
        # on the disk, a chunk at least every 2 s (McapSink.CHUNK_SECONDS): stopped once 20 states of
        # each robot are (~0.4 s of 50 Hz; a recorder starved of CPU, niced as it is, may take longer)
        wait_until(
            lambda: all(len(on_disk(path).get(f"/{r}/odom", [])) >= 20 for r in ("r7", "r8")),
            60,
            "20 states of each robot in the file",
        )
        assert recorder.stop(stop, timeout=20) == 0, recorder.stderr
        summary = [line for line in recorder.stdout if line.startswith("srl record: recorded")]
        assert len(summary) == 1 and "2 robots: r7, r8" in summary[0], recorder.stdout
    finally:
        for proc in reversed(procs):
            proc.stop()
    check_rosbag2_layout(path)
    topics = read(path)
    for robot, pose in (("r7", (1.0, -0.5, 0.3)), ("r8", (-1.0, 2.0, 0.0))):
        odometry = topics[f"/{robot}/odom"]
        assert len(odometry) >= 20
        times = [t for t, _ in odometry]
        assert times == sorted(times)
        for _, m in odometry:
            assert (m.pose.pose.position.x, m.pose.pose.position.y) == pose[:2]
            yaw = 2 * math.atan2(m.pose.pose.orientation.z, m.pose.pose.orientation.w)
            assert math.isclose(yaw, pose[2], abs_tol=1e-12)
        # a fleet's /tf: one base_footprint per robot, one transform per state, at the state
        bases = [tf for _, m in topics["/tf"] for tf in m.transforms if tf.child_frame_id == f"{robot}/base_footprint"]
        assert len(bases) == len(odometry) and all(tf.header.frame_id == "odom" for tf in bases)
        assert {(tf.transform.translation.x, tf.transform.translation.y) for tf in bases} == {pose[:2]}


async def foxglove_poses(url: str, topic: str, want: int, timeout: float) -> tuple[list[Any], dict[str, Any]]:
    """A plain WebSocket client speaking the Foxglove protocol: wait for ``topic``'s advertisement,
    subscribe, decode ``want`` messages with mcap-ros2-support from the advertised schema."""
    import websockets

    async with websockets.connect(url, subprotocols=["foxglove.sdk.v1"], open_timeout=10) as socket:
        assert socket.subprotocol == "foxglove.sdk.v1"
        channel: dict[str, Any] | None = None
        decoded: list[Any] = []
        decoder = None
        deadline = time.monotonic() + timeout
        subscriptions: list[int] = []  # ours; one more when a subscription brought nothing for 2 s
        asked = 0.0
        while len(decoded) < want:
            if channel is not None and not decoded and time.monotonic() - asked > 2.0 and len(subscriptions) < 5:
                # foxglove-sdk may advertise a channel a moment before it accepts subscriptions to
                # it ("subscribe to unknown channel"): ask again, as a client reconnecting would
                subscriptions.append(7 + len(subscriptions))
                subscribe = {
                    "op": "subscribe",
                    "subscriptions": [{"id": subscriptions[-1], "channelId": channel["id"]}],
                }
                await socket.send(json.dumps(subscribe))
                asked = time.monotonic()
            try:
                frame = await asyncio.wait_for(socket.recv(), min(0.5, max(0.1, deadline - time.monotonic())))
            except TimeoutError:
                if time.monotonic() > deadline:
                    raise
                continue
            if isinstance(frame, str):
                message = json.loads(frame)
                if message["op"] == "advertise" and channel is None:
                    channel = next((c for c in message["channels"] if c["topic"] == topic), None)
                    if channel is not None:
                        assert channel["encoding"] == "cdr" and channel["schemaEncoding"] == "ros2msg"
                        text = channel["schema"].encode()
                        schema = Schema(id=1, name=channel["schemaName"], encoding="ros2msg", data=text)
                        decoder = DecoderFactory().decoder_for("cdr", schema)
            elif frame[0] == 0x01:  # MessageData: subscription id, log time, payload
                subscription, _log_time = struct.unpack_from("<IQ", frame, 1)
                assert subscription in subscriptions and decoder is not None
                decoded.append(decoder(bytes(frame[13:])))
        assert channel is not None
        return decoded, channel


@pytest.mark.integration
@pytest.mark.slow
def test_srl_view_serves_the_running_robots_poses_over_the_foxglove_websocket_protocol() -> None:
    router = f"tcp/127.0.0.1:{free_port()}"
    procs = [Proc("router", ["router", "--router", router])]
    try:
        for robot, start in (("v1", "1,-0.5,0.3"), ("v2", "-1.5,2,0")):  # one view carries every robot
            procs.append(
                Proc(robot, ["plant-sim", "--mode", "realtime", "--router", router, "--robot", robot, "--start", start])
            )
        view = Proc("view", ["view", "--router", router, "--port", "0", "--seconds", "60"])
        procs.append(view)
        wait_until(lambda: any("srl view: serving" in line for line in view.stderr), 60, "the view")
        line = next(line for line in view.stderr if "srl view: serving" in line)
        url = re.search(r"ws://127\.0\.0\.1:\d+", line)
        assert url is not None, line  # bound to loopback by default
        for robot, expected in (("v1", (1.0, -0.5, 0.3)), ("v2", (-1.5, 2.0, 0.0))):
            try:
                poses, channel = asyncio.run(foxglove_poses(url.group(0), f"/{robot}/odom", 5, timeout=30))
            except TimeoutError:  # say what the services said: the cause is theirs or the view's
                tails = {p.name: (p.process.poll(), p.stderr[-5:]) for p in procs}
                raise AssertionError(f"no /{robot}/odom from srl view in 30 s; exit codes, stderr: {tails}") from None
            assert channel["schemaName"] == "nav_msgs/msg/Odometry"
            for odom in poses:
                assert odom.header.frame_id == "odom" and odom.child_frame_id == "base_footprint"
                position, q = odom.pose.pose.position, odom.pose.pose.orientation
                assert (position.x, position.y) == expected[:2]
                assert math.isclose(2 * math.atan2(q.z, q.w), expected[2], abs_tol=1e-12)
        # /tf: each robot's base_footprint in odom, at its pose (docs/recordings.md "Frames")
        messages, channel = asyncio.run(foxglove_poses(url.group(0), "/tf", 20, timeout=30))
        assert channel["schemaName"] == "tf2_msgs/msg/TFMessage"
        bases = {t.child_frame_id: t for m in messages for t in m.transforms if t.child_frame_id != "goal"}
        assert set(bases) == {"v1/base_footprint", "v2/base_footprint"}
        for robot, expected in (("v1", (1.0, -0.5, 0.3)), ("v2", (-1.5, 2.0, 0.0))):
            tf = bases[f"{robot}/base_footprint"]
            assert tf.header.frame_id == "odom"
            assert (tf.transform.translation.x, tf.transform.translation.y) == expected[:2]
            q = tf.transform.rotation
            assert math.isclose(2 * math.atan2(q.z, q.w), expected[2], abs_tol=1e-12)
        assert view.stop(signal.SIGINT, timeout=20) == 0, view.stderr
    finally:
        for proc in reversed(procs):
            proc.stop()


@pytest.mark.integration
def test_the_shipped_foxglove_layout_is_the_generated_one_and_names_recorded_topics(tmp_path: Path) -> None:
    from tools.recording.view import foxglove_layout

    shipped = (ROOT / "docs" / "foxglove-layout.json").read_text()
    assert shipped == foxglove_layout(["tb3_0"]), (
        "regenerate: python -c 'from tools.recording.view import foxglove_layout; ...'"
    )
    run = srl("run", "--duration", "1", "--no-jit", "--record", str(tmp_path / "r.mcap"), timeout=120)
    assert run.returncode == 0, run.stderr
    recorded = set(read(tmp_path / "r.mcap"))
    named = set(re.findall(r'"(/[A-Za-z0-9_/]+)', shipped))
    assert named <= recorded, named - recorded


@pytest.mark.integration
@pytest.mark.slow
def test_srl_up_with_the_robot_records_its_odometry_and_srl_plot_replays_it(tmp_path: Path) -> None:
    """--plant robot: the emulated TurtleBot3's odometry, through the bridge, in real time."""
    path = tmp_path / "robot.mcap"
    up = srl(
        "up", "--plant", "robot", "--duration", "6", "--router", f"tcp/127.0.0.1:{free_port()}", "--robot", "tb",
        "--json", "--summary-dir", str(tmp_path / "up"), "--record", str(path),
    )  # fmt: skip
    assert up.returncode == 0, up.stderr[-3000:]
    summary = json.loads(up.stdout.splitlines()[-1])
    check_rosbag2_layout(path)
    topics = read(path)
    transitions, odometry = topics["/tb/srl/transition"], topics["/tb/odom"]
    assert len(transitions) == len(topics["/tb/cmd_vel"]) == summary["steps"]
    # each transition at origin + k delta, and exactly the steps the actor published: on a loaded
    # machine a tick may publish none (a skipped tick, a stale-state stop: the critic sees a gap,
    # never a false pair), and the recording then has the same gap, never one of its own
    steps = np.array([m.step for _, m in transitions])
    assert np.all(np.diff([t for t, _ in transitions]) == DELTA_NS * np.diff(steps))
    published = [k for first, last in summary["transition_steps"] for k in range(first, last + 1)]
    assert steps.tolist() == published, (summary["transition_steps"], summary["loop"], summary["stale_state_stops"])
    assert len(odometry) > len(transitions)  # the robot's odometry rate (20 Hz) over the 10 Hz loop
    times = [t for t, _ in odometry]
    assert times == sorted(times)
    # a robot with bridge.goal [0, 0, 0] and odometry only: odom -> tb/base_footprint is its odometry,
    # each transform stamped as its state (srl record gathers many states' transforms in one /tf)
    bases = [
        (stamp_ns(tf.header), tf)
        for _, m in topics["/tf"]
        for tf in m.transforms
        if tf.child_frame_id == "tb/base_footprint"
    ]
    assert [t for t, _ in bases] == times and all(tf.header.frame_id == "odom" for _, tf in bases)
    assert [(tf.transform.translation.x, tf.transform.translation.y) for _, tf in bases] == [
        (m.pose.pose.position.x, m.pose.pose.position.y) for _, m in odometry
    ]
    last = odometry[-1][1].pose.pose.position
    np.testing.assert_allclose([last.x, last.y], summary["final_state"][:2], atol=0.02)  # the same odometry
    plotted = srl("plot", str(path), "--out", str(tmp_path / "robot.png"))
    assert plotted.returncode == 0 and (tmp_path / "robot.png").exists(), plotted.stderr


@pytest.mark.integration
@pytest.mark.slow
def test_srl_bench_loop_record_compares_the_loop_without_and_with_a_recorder() -> None:
    done = srl(
        "bench", "loop", "--record", "--seconds", "4", "--rounds", "1", "--json",
        "--router", f"tcp/127.0.0.1:{free_port()}", "--robot", "benchrec",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout.splitlines()[-1])
    assert [r["record"] for r in result["runs"]] == [False, True]
    assert result["runs"][0]["recording_bytes"] is None and result["runs"][1]["recording_bytes"] > 1000
    assert "srl record: recorded" in result["runs"][1]["recorder"]
    assert set(result["jitter_p99_ms"]) == {"without", "with", "difference"}
    assert "jitter p99 with recorder" in done.stdout
    refused = srl("bench", "loop", "--rounds", "2", "--seconds", "1", timeout=60)
    assert refused.returncode == 2 and "--rounds is for --record" in refused.stderr


@pytest.mark.slow
def test_srl_plot_reads_back_the_episode_that_plot_episode_draws(tmp_path: Path) -> None:
    """What srl plot draws from a recording is what --plot draws from the run: the same states,
    actions, costs, the weights the actor used at every step and each fit's TD residuals (all but
    the last fit's: its weights were never used, so the recording has no message for it)."""
    from common.config.assembly import run_episode
    from common.config.settings import Settings
    from tools.recording.record import episode_recorder, read_episodes, record_episode

    settings = Settings.load(actor={"agent": "rlqv", "jit": False}, episode={"start": [1.0, -1.5], "duration": 4.0})
    episode = run_episode(settings)
    recorder = episode_recorder(tmp_path / "e.mcap", 0.1, {"agent": "rlqv", "horizon": settings.actor.horizon})
    record_episode(recorder, episode, "tb3_0", origin_ns=1_700_000_000_000_000_000)
    recorder.close()
    episodes, sampling_time = read_episodes(tmp_path / "e.mcap")
    replayed = episodes["tb3_0"]
    assert sampling_time == 0.1 and (replayed.agent, replayed.horizon) == ("rlqv", settings.actor.horizon)
    for name in ("states", "actions", "q_weights", "v_weights"):
        np.testing.assert_array_equal(np.array(getattr(replayed, name)), np.array(getattr(episode, name)), name)
    np.testing.assert_array_equal(replayed.costs, episode.costs)
    np.testing.assert_array_equal(np.array(replayed.td_residuals)[:-1], np.array(episode.td_residuals)[:-1])
    assert replayed.accumulated_cost == episode.accumulated_cost


@pytest.mark.slow
def test_a_recorded_episode_keeps_each_solve_time_after_the_robot_arrives(tmp_path: Path) -> None:
    """record_episode (srl run --record, the live view's figure): the status of a step that solved
    carries its solve time, that of a step the arrival rule held at rest none (NaN): a robot that
    arrives within the run keeps the solve times of its drive."""
    from common.config.assembly import run_episode
    from common.config.settings import Settings
    from tools.recording.record import Recorder, RosMapping, record_episode
    from tools.recording.sinks import MemorySink

    settings = Settings.load(actor={"agent": "rlqv", "jit": False}, episode={"start": [2.0, 2.0], "duration": 20.0})
    episode = run_episode(settings)
    assert 0 < episode.held.count(True) < episode.steps, "the run must both drive and arrive"
    sink = MemorySink()
    record_episode(Recorder(sink, 0.1, clock="steps"), episode, "tb3_0", origin_ns=0)
    ros = RosMapping()
    solve_ms = [
        ros.store.deserialize_cdr(data, kind).solve_ms for _, kind, data in sink.samples["/tb3_0/srl/actor_status"]
    ]
    assert len(solve_ms) == episode.steps
    assert [math.isnan(ms) for ms in solve_ms] == episode.held
    solved = [ms for ms in solve_ms if not math.isnan(ms)]
    np.testing.assert_allclose(solved, np.array(episode.solve_seconds) * 1e3, rtol=1e-12)


@pytest.mark.integration
def test_lower_priority_lowers_every_thread_and_the_threads_started_after() -> None:
    """common.process.runtime.lower_priority (the recorder's nice +10): the threads already running (a
    BLAS pool) and those started after it (Zenoh's) run at the lowered niceness; 0 changes none."""
    script = (
        "import os, threading, time\n"
        "from common.process.runtime import lower_priority\n"
        "def nice(tid): return os.getpriority(os.PRIO_PROCESS, tid)\n"
        "tids, go = [], threading.Event()\n"
        "def worker(): tids.append(threading.get_native_id()); go.wait(10)\n"
        "before = threading.Thread(target=worker); before.start()\n"
        "lower_priority(0, 'test'); unchanged = nice(0)\n"
        "lower_priority(5, 'test')\n"
        "after = threading.Thread(target=worker); after.start()\n"
        "while len(tids) < 2: time.sleep(0.01)\n"
        "print(unchanged, nice(0), *(nice(t) for t in tids))\n"
        "go.set()\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=30, check=True
    )
    own = os.getpriority(os.PRIO_PROCESS, 0)
    lowered = min(19, own + 5)
    assert done.stdout.split() == [str(own), str(lowered), str(lowered), str(lowered)], done.stderr


# The autogroup niceness of the process running a script, "none" where its session has no autogroup
# of its own (the kernel's default group, whose file is empty: a container's first session).
AUTOGROUP_NICE = "def nice(): return (open('/proc/self/autogroup').read().split() or ['none'])[-1]\n"


def output_of(script: str, own_session: bool) -> str:
    """What a Python ``script`` prints, run in a session of its own (as srl up starts a service) or
    in this one (as from a shell); ``nice()`` (AUTOGROUP_NICE) is defined for it."""
    done = subprocess.run(
        [sys.executable, "-c", AUTOGROUP_NICE + script],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=30,
        check=True,
        start_new_session=own_session,
    )
    return done.stdout


@pytest.mark.integration
@pytest.mark.skipif(not os.path.exists("/proc/self/autogroup"), reason="the kernel has no autogroups")
@pytest.mark.parametrize("own_session", [True, False])
def test_lower_priority_lowers_the_sessions_autogroup_only_where_the_process_leads_its_session(
    own_session: bool,
) -> None:
    """common.process.runtime.session_priority (through lower_priority): a recorder that leads
    its session (srl up and srl bench start each service in one of its own) lowers its autogroup,
    so it yields to the other services' sessions; one started from a shell (not the session's
    leader: the negative control) leaves the shell's autogroup as it is."""
    script = (
        "from common.process.runtime import lower_priority\n"
        "before = nice()\n"
        "lower_priority(10, 'test')\n"
        "print(before, nice())\n"
    )
    before, after = output_of(script, own_session).split()
    assert after == ("10" if own_session else before), (before, after)


@pytest.mark.integration
@pytest.mark.skipif(not os.path.exists("/proc/self/autogroup"), reason="the kernel has no autogroups")
def test_a_session_is_raised_where_allowed_and_left_with_one_line_where_not() -> None:
    """common.process.runtime.session_priority (critic.session_niceness = -5): a critic leading its
    session raises its autogroup where it may (root, CAP_SYS_NICE); where not, one INFO line says
    so and the autogroup stays; 0 changes nothing."""
    script = (
        "import logging, sys\n"
        "logging.basicConfig(level=logging.INFO, format='%(message)s', stream=sys.stdout)\n"
        "from common.process.runtime import session_priority\n"
        "before = nice(); unchanged = session_priority(0, 'critic')\n"
        "raised = session_priority(-5, 'critic')\n"
        "print(before, unchanged, raised, nice())\n"
    )
    lines = output_of(script, own_session=True).strip().splitlines()
    if os.geteuid() == 0:
        assert lines == ["critic: its session's niceness is -5", "0 False True -5"], lines
    else:
        assert lines[-1] == "0 False False 0", lines
        assert lines[0].startswith("critic: its session keeps its CPU share (niceness -5 refused: "), lines


def test_a_subscription_runs_its_handler_on_a_thread_of_its_own_when_asked_whatever_the_default() -> None:
    # Bus._callback: transport.callback_threads is the default; ``threaded`` overrides it for one
    # subscription (a recorder's wildcards, which take every robot's samples).
    from common.net.transport import Bus

    for default in (False, True):
        bus = Bus(object(), "test", callback_threads=default)  # type: ignore[arg-type]  # no session needed
        assert bus._callback(print).indirect is default
        assert bus._callback(print, threaded=True).indirect is True
        assert bus._callback(print, threaded=False).indirect is False


class KeptSink(RowsByOne):
    """A sink that keeps (topic, data, t_ns) of every write; ``fail`` makes every write raise it."""

    def __init__(self) -> None:
        self.written: list[tuple[str, bytes, int]] = []
        self.fail: Exception | None = None

    def write(self, topic: str, ros_type: str, definition: str, data: bytes, t_ns: int) -> None:
        if self.fail is not None:
            raise self.fail
        self.written.append((topic, data, t_ns))

    def close(self) -> None:
        pass


def feed_on_a_fake_bus(monkeypatch: pytest.MonkeyPatch, settings: Any = None) -> tuple[Any, dict[str, Any], KeptSink]:
    """A recorder's Feed on a Bus whose Zenoh session only notes its subscriptions (key -> the put
    that Zenoh would call, and whether it recovers), writing to a :class:`KeptSink`: no Zenoh, no
    file."""
    from common.config.settings import Settings
    from tools.recording.record import Feed, Recorder

    subscribed = buses_on_a_fake_session(monkeypatch)
    sink = KeptSink()
    return Feed(settings or Settings.load(), Recorder(sink, 0.1)), subscribed, sink


def fleet_state(robot: str, seq: int = 1) -> Any:
    from common.contracts.messages import PlantState

    position = (0.1 * seq, 0.2, 0.3)
    return PlantState(robot=robot, episode=1, seq=seq, stamp_ns=seq, state=position, source="sim",
                      true_state=position, saturated_commands=0)  # fmt: skip


def fleet_transition(robot: str, step: int) -> Any:
    from common.contracts.messages import Transition

    return Transition(robot=robot, episode=1, step=step, state=(0.1 * step, 0.2, 0.3), action=(0.1, 0.2), cost=0.5)


def one_batch(messages: list[Any]) -> bytes:
    """``messages`` as one columnar batch (the payload srl's hosts send)."""
    from common.contracts.columns import batch_payloads

    (payload,) = batch_payloads(messages)
    return payload


def put(subscribed: dict[str, Any], key: str, payload: bytes) -> None:
    """Zenoh hands ``payload`` on ``key`` to the subscription of ``key`` (a robot's, or a batch key)."""
    pattern = key if key in subscribed else re.sub(r"^srl/[^/@]+/", "srl/*/", key)
    (callback, threaded), _ = subscribed[pattern]
    assert threaded is False  # on Zenoh's thread: a put is an append
    callback(FakeSample(key, payload))


def test_the_recorder_takes_every_robots_samples_and_srls_batches_of_them(monkeypatch: pytest.MonkeyPatch) -> None:
    """Feed: a subscription on every robot's key and one on the batch key of each topic that has
    a batch form; transitions (the actors' advanced publishers) on their batch key alone (srl's
    hosts send them only in batches: Batch.on_demand), with their history."""
    from common.contracts.keys import BATCHES, STATE, STATUS, TRANSITION, WEIGHTS, every_robot

    feed, subscribed, _ = feed_on_a_fake_bus(monkeypatch)
    feed.close()
    keys = [every_robot(STATE), every_robot(WEIGHTS), every_robot(STATUS, service="actor")]
    batches = [BATCHES[topic.pattern].pattern for topic in (STATE, TRANSITION, WEIGHTS)]
    assert sorted(subscribed) == sorted(keys + batches)
    recovering = {key for key, (_, recover) in subscribed.items() if recover}
    assert recovering == {BATCHES[TRANSITION.pattern].pattern}


def test_a_batch_is_recorded_as_its_rows_would_be_one_by_one(monkeypatch: pytest.MonkeyPatch) -> None:
    """Feed: the rows of a columnar batch (states, then transitions) are written byte for byte as
    the same messages arriving one by one (states on their robots' keys, transitions in batches of
    one, as an actor host of one robot sends them) are, in the order they came."""
    import common.net.transport as transport
    import tools.recording.record as record
    from common.config.settings import Settings
    from common.contracts.keys import STATE, STATE_BATCH, TRANSITION_BATCH

    monkeypatch.setattr(record, "BATCH_SECONDS", 30.0)
    monkeypatch.setattr(transport.time, "time_ns", lambda: 1_700_000_000 * 10**9)  # every arrival's stamp
    robots = [f"robot{i}" for i in range(5)]
    states = [fleet_state(robot, seq) for seq, robot in enumerate(robots, 1)]
    # robot bridges' states beside the simulator's: localized (map -> odom), and by odometry only
    bridged = {"source": "robot", "true_state": None, "saturated_commands": None}
    states[1] = states[1].model_copy(update=bridged | {"map_to_odom": (0.5, -0.25, 0.1)})
    states[3] = states[3].model_copy(update=bridged)
    transitions = [fleet_transition(robot, 3) for robot in robots]
    settings = Settings.load()  # robots localized on a map, their goal away from its origin
    bridge = settings.bridge.model_copy(update={"pose_source": "tf", "goal": (1.0, 0.5, 0.2)})
    settings = settings.model_copy(update={"bridge": bridge})
    written = []
    for batched in (False, True):
        feed, subscribed, sink = feed_on_a_fake_bus(monkeypatch, settings)
        time.sleep(0.2)  # the writer's first (empty) round is done: it waits for close
        if batched:
            put(subscribed, STATE_BATCH.pattern, one_batch(states))
            put(subscribed, TRANSITION_BATCH.pattern, one_batch(transitions))
        else:
            for state in states:
                put(subscribed, STATE.key(state.robot), state.encode())
            for transition in transitions:
                put(subscribed, TRANSITION_BATCH.pattern, one_batch([transition]))
        feed.close()
        assert feed.received == 10 and feed.errors == 0 and feed.dropped == 0
        written.append(sink.written)
    # the reference: the recorder called with each message's fields, as srl run's recording is
    direct = record.Recorder(KeptSink(), 0.1)
    direct.gather_tf()
    now_ns = transport.time.time_ns()
    for m in states:
        direct.state(m.robot, m.episode, m.state, now_ns, record.robot_frames(bridge, m.source, m.map_to_odom))
    for m in transitions:
        direct.transition(m.robot, m.episode, m.step, m.state, m.action, m.cost, now_ns)
    direct.flush_tf()
    assert written[0] == written[1] == direct.sink.written  # type: ignore[attr-defined]  # a KeptSink
    topics = [topic for topic, _, _ in written[1]]
    assert topics[0] == "/target" and topics[1:6] == [f"/{robot}/odom" for robot in robots]
    assert topics[6:8] == ["/robot0/cmd_vel", "/robot0/srl/transition"] and topics[-1] == "/tf"


@pytest.mark.parametrize("clock", ["wall", "steps"])
@pytest.mark.parametrize("gathered", [1, 5, 256])
def test_the_recorder_writes_a_batch_of_many_robots_as_it_writes_their_rows_one_by_one(
    clock: str, gathered: int
) -> None:
    """Recorder.states / Recorder.transitions (srl record's writer, a fleet's batches) write the
    samples Recorder.state / Recorder.transition write for the same rows one by one (srl run):
    every topic's messages, bytes, log times and order, and the late steps counted. A mixed fleet:
    several robots (ids that need renaming), robot bridges localized on a map away from their goal
    (one with its map -> odom correction in every state, one in every other), a robot's new
    episode, a step that comes twice in a batch and one that comes late, paths, /tf gathered in
    messages of at most ``gathered`` transforms; a row whose step its message cannot hold is
    refused alone, the rest of its batch written."""
    from types import SimpleNamespace

    import tools.recording.record as record

    class Sink(RowsByOne):
        def __init__(self) -> None:
            self.topics: dict[str, list[tuple[str, bytes, int]]] = {}

        def write(self, topic: str, ros_type: str, definition: str, data: bytes, t_ns: int) -> None:
            self.topics.setdefault(topic, []).append((ros_type, data, t_ns))

        def close(self) -> None:
            pass

    bridge = SimpleNamespace(goal=(1.0, 0.5, 0.2), pose_source="tf")
    robots = ["tb3_0", "tb3_1", "rlqv+-N12-s003", "bridge_a", "bridge_b"]
    bridged = np.array([robot.startswith("bridge") for robot in robots])
    rng = np.random.default_rng(11)
    by_rows, batched = record.Recorder(Sink(), 0.1, clock), record.Recorder(Sink(), 0.1, clock)  # type: ignore[arg-type]
    for recorder in (by_rows, batched):
        recorder.gather_tf(gathered)
    refused: list[Exception] = []
    episodes = dict.fromkeys(robots, 1)
    for k in range(23):
        now_ns = 1_700_000_000 * 10**9 + k * DELTA_NS + int(rng.integers(0, 30_000_000))
        states = rng.normal(0, 2, (len(robots), 3))
        corrections = np.full((len(robots), 3), np.nan)
        corrections[3] = (0.5, -0.25, 0.1 + 0.01 * k)
        if k % 2:
            corrections[4] = (-0.3, 0.2, -2.9)
        for robot, state, source, correction in zip(robots, states, bridged, corrections, strict=True):
            frames = record.robot_frames(bridge, "robot" if source else "sim", tuple(correction))
            by_rows.state(robot, 1, state, now_ns, frames)
        frames_of_rows = record.robot_frame_rows(bridge, bridged, corrections)
        taken = batched.states(robots, np.ones(len(robots)), states, now_ns, frames_of_rows, refused.append)
        assert taken == len(robots)
        if k == 12:
            episodes["tb3_1"] = 2  # a new episode: its steps from 0 again
        steps = [(robot, episodes[robot], k if episodes[robot] == 1 else k - 12) for robot in robots]
        if k == 15:
            steps += [("tb3_0", 1, 15), ("tb3_1", 2, 1)]  # twice in the batch, and late
        actions, costs = rng.normal(0, 0.2, (len(steps), 2)), rng.uniform(0, 1, len(steps))
        moves = np.vstack([states, states[:2]])[: len(steps)]
        for (robot, episode, step), state, action, cost in zip(steps, moves, actions, costs, strict=True):
            by_rows.transition(robot, episode, step, state, action, cost, now_ns)
        names, episode_column, step_column = (list(column) for column in zip(*steps, strict=True))
        if k == 20:  # a step no uint32 holds: that row alone is refused
            names.insert(1, "bad")
            episode_column.insert(1, 1)
            step_column.insert(1, 2**32)
            moves, actions, costs = (np.insert(c, 1, c[0], axis=0) for c in (moves, actions, costs))
        columns = (np.array(episode_column), np.array(step_column), moves, actions, costs)
        taken = batched.transitions(names, *columns, now_ns, refused.append)
        assert taken == len(steps)
        if k % 2:
            by_rows.flush_tf()
            batched.flush_tf()
    for recorder in (by_rows, batched):
        recorder.close()
    assert [str(error) for error in refused] == ["4294967296 does not fit a CDR uint32 field (0 to 4294967295)"]
    rows, batches = by_rows.sink.topics, batched.sink.topics  # type: ignore[attr-defined]
    assert rows == batches and by_rows.late == batched.late == 2
    paths = {topic: len(rows[topic]) for topic in ("/tb3_0/path", "/tb3_1/path", "/bridge_a/path")}
    assert paths == {"/tb3_0/path": 3, "/tb3_1/path": 4, "/bridge_a/path": 3}  # steps 0, 10, 20; a new episode
    assert {ros_type for messages in rows.values() for ros_type, _, _ in messages} >= {
        record.ODOMETRY,
        record.TWIST_STAMPED,
        record.TRANSITION,
        record.PATH,
        record.TF_MESSAGE,
        record.POSE_STAMPED,
    }
    transforms = sum(len(by_rows.ros.deserialize(data, record.TF_MESSAGE).transforms) for _, data, _ in rows["/tf"])
    assert transforms == 23 * 5 + 23 + 11 + 5 * 3  # a base per state, the two map -> odom, each robot's goal
    if gathered != 5:  # a message per state, or per flush (every other batch, and at close)
        assert len(rows["/tf"]) == (23 * 5 if gathered == 1 else 12)


def test_the_recorders_writer_keeps_a_bounded_backlog_counts_what_it_drops_and_writes_the_rest_at_close(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Feed: Zenoh's threads append, the writer takes everything waiting every BATCH_SECONDS. At
    most QUEUE_LIMIT rows wait: a sample, or a whole batch, that would pass it is counted as
    dropped; close writes what waits at once, without waiting out the pause."""
    import tools.recording.record as record
    from common.contracts.keys import STATE, STATE_BATCH

    monkeypatch.setattr(record, "QUEUE_LIMIT", 4)
    monkeypatch.setattr(record, "BATCH_SECONDS", 30.0)
    feed, subscribed, sink = feed_on_a_fake_bus(monkeypatch)
    time.sleep(0.3)  # the writer's first batch (nothing yet) is done: it waits BATCH_SECONDS
    put(subscribed, STATE_BATCH.pattern, one_batch([fleet_state("a"), fleet_state("b")]))
    for i in range(10):
        put(subscribed, STATE.key(f"robot{i}"), fleet_state(f"robot{i}").encode())
    assert feed.dropped == 8 and sink.written == [] and feed.inbox.waiting == 4
    put(subscribed, STATE_BATCH.pattern, one_batch([fleet_state("c")]))
    assert feed.dropped == 9
    started = time.monotonic()
    feed.close()
    assert time.monotonic() - started < 5.0
    odometry = [topic for topic, _, _ in sink.written if topic.endswith("/odom")]
    assert odometry == ["/a/odom", "/b/odom", "/robot0/odom", "/robot1/odom"] and feed.received == 4
    assert feed.inbox.waiting == 0


def test_a_malformed_sample_is_refused_and_counted_before_the_writer_and_the_rest_is_written(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Feed: a sample that does not decode (a batch with one NaN row, a message on another robot's
    key) is counted as rejected on the bus and never written; what came beside it is."""
    import tools.recording.record as record
    from common.contracts.keys import STATE, STATE_BATCH

    monkeypatch.setattr(record, "BATCH_SECONDS", 30.0)
    feed, subscribed, sink = feed_on_a_fake_bus(monkeypatch)
    good = one_batch([fleet_state("a"), fleet_state("b")])
    nan = good.replace(struct.pack("<d", 0.2), struct.pack("<d", math.nan), 1)
    assert nan != good
    put(subscribed, STATE_BATCH.pattern, nan)
    put(subscribed, STATE.key("b"), fleet_state("a").encode())  # robot a's state on robot b's key
    put(subscribed, STATE.key("c"), fleet_state("c").encode())
    feed.close()
    assert feed.bus.counters["rejected.state"] == 2 and feed.received == 1 and feed.errors == 0
    assert [topic for topic, _, _ in sink.written if topic.endswith("/odom")] == ["/c/odom"]


def test_the_recorders_backlog_is_bounded_in_memory_by_the_rows_it_holds(monkeypatch: pytest.MonkeyPatch) -> None:
    """QUEUE_LIMIT bounds the writer's backlog in rows; the samples a fleet sends at every step
    (states with their truth, transitions, critic weights), each alone on its robot's key (a
    message's bytes: the most a row can take) or in batches of 100, measured as they wait, keep
    it under 512 MB at the limit (an actor's status, once a second, is under 4 KB)."""
    import tracemalloc

    import tools.recording.record as record
    from common.contracts.keys import BATCHES, STATE, STATUS, TRANSITION, WEIGHTS
    from common.contracts.messages import CriticWeights, ServiceStatus

    def weights(robot: str, i: int) -> CriticWeights:
        q, v = tuple(0.5 * i + j for j in range(15)), tuple(0.25 * i + j for j in range(6))
        return CriticWeights(robot=robot, episode=1, version=i + 1, trained_step=i, q_weights=q, v_weights=v,
                             q_residual=0.1, v_residual=0.2, pairs=29)  # fmt: skip

    def status(robot: str, i: int) -> ServiceStatus:
        counters = {f"counter_{j}": float(i + j) for j in range(24)}
        return ServiceStatus(robot=robot, service="actor", stamp_ns=i, counters=counters)

    monkeypatch.setattr(record, "BATCH_SECONDS", 30.0)
    feed, subscribed, _ = feed_on_a_fake_bus(monkeypatch)
    time.sleep(0.3)  # the writer waits BATCH_SECONDS: what is put waits
    robots = [f"robot{i}" for i in range(2000)]
    samples: dict[tuple[str, bool], list[tuple[str, bytes]]] = {}
    for topic, make in ((STATE, fleet_state), (TRANSITION, fleet_transition), (WEIGHTS, weights)):
        messages = [make(robot, i) for i, robot in enumerate(robots)]
        batch = BATCHES[topic.pattern].pattern
        # alone: on its robot's key, or (read only in batches: Batch.on_demand) a batch of one
        alone = [
            (batch, one_batch([m])) if BATCHES[topic.pattern].on_demand else (topic.key(m.robot), m.encode())
            for m in messages
        ]
        samples[topic.pattern, False] = alone
        samples[topic.pattern, True] = [(batch, one_batch(messages[i : i + 100])) for i in range(0, 2000, 100)]
    statuses = [status(robot, i) for i, robot in enumerate(robots)]
    samples[STATUS.pattern, False] = [(STATUS.key(m.robot, service="actor"), m.encode()) for m in statuses]
    sizes = {}
    try:
        for kind, putting in samples.items():
            waiting = feed.inbox.waiting
            tracemalloc.start()
            try:
                before = tracemalloc.get_traced_memory()[0]
                for key, payload in putting:
                    put(subscribed, key, payload)
                sizes[kind] = (tracemalloc.get_traced_memory()[0] - before) / len(robots)
            finally:
                tracemalloc.stop()
            assert feed.inbox.waiting == waiting + len(robots)
    finally:
        feed.inbox.limit = 0  # nothing more is taken in; close writes what waits
        feed.close()
    steps = [size for (pattern, _), size in sizes.items() if pattern != STATUS.pattern]  # each robot's, every step
    assert all(20 < size < 2_600 for size in steps) and sizes[STATUS.pattern, False] < 4_000, sizes
    # statuses come once a second per robot, against 20 and more of the others
    assert record.QUEUE_LIMIT * max(steps) < 512e6, sizes


def test_a_fleets_recording_summary_names_its_first_robots_and_counts_them_all() -> None:
    import tools.recording.record as record

    class Sink(RowsByOne):
        path = Path("/nonexistent/fleet.mcap")
        counts = {f"/robot{i}/odom": 3 for i in range(300)} | {"/target": 1}

    line = record.describe(Sink())  # type: ignore[arg-type]  # the part of a sink describe reads
    robots = sorted(f"robot{i}" for i in range(300))[: record.NAMED_ROBOTS]
    assert f"(300 robots: {', '.join(robots)}, ...) " in line and "robot99" not in line, line
    assert line.startswith("recorded 901 messages on 301 topics"), line
    alone = record.describe(type("One", (), {"path": Sink.path, "counts": {"/r1/odom": 2}})())  # type: ignore[arg-type]
    assert "(1 robot: r1) " in alone, alone
    # what the fleet bench reads back from the line: the samples its writer dropped
    assert record.dropped_by_writer(line + record.DROPPED_NOTE.format(count=6) + "; 2 late transitions skipped") == 6
    assert record.dropped_by_writer(line) == 0 and record.dropped_by_writer(None) == 0


def test_a_recorder_that_cannot_write_its_file_counts_every_sample_and_says_why_once(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """Feed: a file that cannot be written (RecordingError from the sink, a full disk) does not
    end the recording; every row it could not write is counted in ``errors`` and the reason is
    logged once, not once per row; a row that fails otherwise (here: a robot whose frames cannot
    be named) is still logged with its own line, and costs only itself, not its batch."""
    import logging

    import tools.recording.record as record
    from common.contracts.keys import STATE, STATE_BATCH

    monkeypatch.setattr(record, "BATCH_SECONDS", 30.0)
    feed, subscribed, sink = feed_on_a_fake_bus(monkeypatch)
    naming = record.base_frame

    def base_frame(robot: str) -> str:
        if robot == "bad":
            raise ValueError("a malformed sample")
        return naming(robot)

    monkeypatch.setattr(record, "base_frame", base_frame)
    sink.fail = record.RecordingError("cannot write /x.mcap: [Errno 28] No space left on device")
    with caplog.at_level(logging.ERROR, logger=record.log.name):
        put(subscribed, STATE_BATCH.pattern, one_batch([fleet_state("a"), fleet_state("bad")]))
        for robot in ("b", "c"):
            put(subscribed, STATE.key(robot), fleet_state(robot).encode())
        feed.close()
    assert feed.errors == 4 and feed.received == 0
    full = [r for r in caplog.records if "No space left" in r.getMessage()]
    assert len(full) == 1 and len([r for r in caplog.records if "a state sample" in r.getMessage()]) == 1


@pytest.mark.integration
@pytest.mark.skipif(not os.path.exists("/proc/self/autogroup"), reason="the kernel has no autogroups")
def test_a_session_changed_twice_in_a_row_takes_the_second_change_too() -> None:
    """common.process.runtime.session_priority: without CAP_SYS_ADMIN the kernel takes one
    autogroup change per 0.1 s, machine-wide, and refuses the rest with EAGAIN (services that start
    together, tests in parallel); a refused change is tried again until taken. As root there is no
    such limit."""
    script = (
        "from common.process.runtime import session_priority\n"
        "print(session_priority(10, 'first'), session_priority(12, 'second'), nice())\n"
    )
    assert output_of(script, own_session=True).split() == ["True", "True", "12"]


def test_a_fleets_steps_are_stamped_by_their_step_however_many_robots() -> None:
    """Recorder.step_time: a robot's step k is stamped origin + k delta (its origin fixed by its
    first message), however late it arrives, in a fleet of more robots than a fixed number of
    remembered origins (64 were kept in all: from the 65th robot on, each step took its arrival
    time). The origins stay bounded: a few episodes per robot."""
    import tools.recording.record as record

    sink = KeptSink()
    recorder = record.Recorder(sink, 0.1)
    robots = [f"robot{i}" for i in range(300)]
    start = 1_700_000_000 * 10**9
    for step in range(3):
        for i, robot in enumerate(robots):
            late = (i % 7) * 3_000_000 * step  # arrival jitter, growing with the step
            recorder.transition(robot, 1, step, (1.0, 2.0, 0.3), (0.1, 0.0), 0.5, start + step * DELTA_NS + late)
    stamps: dict[str, list[int]] = {}
    for topic, _, t_ns in sink.written:
        if topic.endswith("/srl/transition"):
            stamps.setdefault(topic, []).append(t_ns)
    assert len(stamps) == 300
    assert all(times == [start, start + DELTA_NS, start + 2 * DELTA_NS] for times in stamps.values()), stamps
    for episode in range(2, 30):  # episodes come and go: what is remembered stays bounded
        recorder.transition("robot0", episode, 0, (1.0, 2.0, 0.3), (0.1, 0.0), 0.5, start)
    assert len(recorder.origins) <= record.ORIGINS_PER_ROBOT * len(robots)


def test_a_robot_heard_first_after_step_0_is_held_until_the_caches_answer_then_written_in_step_order(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Feed: the subscription's history can come after the first live transitions, or not at all
    (a live sample ends zenoh-ext's recovery of older ones; seen as `srl up --record` missing a
    run's first steps on a loaded machine). A robot whose stream starts after step 0 is held, the
    actors' caches are asked once for the steps before it, and then its steps are written in
    order, each once, stamped as if they had come in time; a robot heard from step 0 is not held."""
    import common.net.transport as transport
    import tools.recording.record as record
    from common.contracts.keys import TRANSITION, TRANSITION_BATCH
    from common.net.transport import Bus

    monkeypatch.setattr(record, "BATCH_SECONDS", 0.05)
    arrival = 1_700_000_000 * 10**9
    monkeypatch.setattr(transport.time, "time_ns", lambda: arrival)
    asked: list[tuple[list[str], Any, Any]] = []
    monkeypatch.setattr(
        Bus, "history", lambda self, topic, keys, handler, done=None: asked.append((keys, handler, done))
    )
    feed, subscribed, sink = feed_on_a_fake_bus(monkeypatch)
    put(subscribed, TRANSITION_BATCH.pattern, one_batch([fleet_transition("a", 3), fleet_transition("b", 0)]))
    put(subscribed, TRANSITION_BATCH.pattern, one_batch([fleet_transition("a", 4)]))
    wait_until(lambda: feed.received == 1, 5, "robot b's step 0 written")
    time.sleep(0.3)  # several of the writer's rounds
    assert not [topic for topic, _, _ in sink.written if topic.startswith("/a/")]  # held
    assert [keys for keys, _, _ in asked] == [[TRANSITION.key("a")]]
    _, answer, done = asked[0]
    for step in range(5):  # the cache's steps, two of them also come live
        answer(fleet_transition("a", step))
    done()
    wait_until(lambda: feed.received == 6, 5, "robot a's five steps")
    feed.close()
    # the reference: the recorder given a's steps in order, its origin where step 3's arrival puts it
    direct = record.Recorder(KeptSink(), 0.1)
    direct.begin("a", 1, arrival - 3 * direct.delta_ns)
    for step in range(5):
        m = fleet_transition("a", step)
        direct.transition(m.robot, m.episode, m.step, m.state, m.action, m.cost, 0)
    robot_a = [entry for entry in sink.written if entry[0].startswith("/a/")]
    assert robot_a == [entry for entry in direct.sink.written if entry[0].startswith("/a/")]  # type: ignore[attr-defined]
    assert feed.errors == 0 and feed.recorder.late == 0


def test_steps_a_held_robot_never_got_are_counted_and_said_not_silently_left_out(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A robot heard first at step 3 whose actors' caches answer only step 2: steps 0 and 1 are
    written nowhere, and the recorder says so (its count, srl record's summary line, a warning)."""
    import tools.recording.record as record
    from common.contracts.keys import TRANSITION_BATCH
    from common.net.transport import Bus

    monkeypatch.setattr(record, "BATCH_SECONDS", 0.05)
    asked: list[tuple[list[str], Any, Any]] = []
    monkeypatch.setattr(
        Bus, "history", lambda self, topic, keys, handler, done=None: asked.append((keys, handler, done))
    )
    feed, subscribed, sink = feed_on_a_fake_bus(monkeypatch)
    put(subscribed, TRANSITION_BATCH.pattern, one_batch([fleet_transition("a", 3)]))
    wait_until(lambda: len(asked) == 1, 5, "the caches asked")
    _, answer, done = asked[0]
    answer(fleet_transition("a", 2))
    done()
    wait_until(lambda: feed.received == 2, 5, "robot a's steps 2 and 3")
    with caplog.at_level("WARNING", logger=record.__name__):
        feed.close()
    assert feed.unreceived == 2 and "a: 2 of its first 4 steps never came" in caplog.text
    assert (
        record.UNRECEIVED_NOTE.format(count=2)
        == "; 2 steps never received (before a robot's first, not in the actors' caches)"
    )
    steps = [t for topic, _, t in sink.written if topic == "/a/srl/transition"]
    assert len(steps) == 2


def test_the_inbox_settles_before_a_recorder_closes() -> None:
    """On Ctrl-C a recorder takes what is still coming: it closes once nothing came for ``quiet``
    seconds, and at most ``longest`` after it was asked, however long the samples keep coming."""
    import threading

    from common.net.transport import Inbox

    inbox = Inbox(None, 10)  # type: ignore[arg-type]  # settle needs no bus
    inbox.last_put = time.monotonic() - 10.0  # long quiet: at once
    started = time.monotonic()
    assert inbox.settle(0.2, 1.0) and time.monotonic() - started < 0.1
    stop = threading.Event()

    def arriving(until: float) -> None:  # a sample every 20 ms until ``until``
        while not stop.is_set() and time.monotonic() < until:
            inbox.last_put = time.monotonic()
            time.sleep(0.02)

    for lasting, quiet, longest in ((0.3, 0.15, 2.0), (10.0, 0.15, 0.6)):
        stop.clear()
        started = time.monotonic()
        feeder = threading.Thread(target=arriving, args=(started + lasting,))
        feeder.start()
        went_quiet = inbox.settle(quiet, longest)
        took = time.monotonic() - started
        stop.set()
        feeder.join()
        if lasting < longest:  # the samples stopped: quiet after the last one
            assert went_quiet and lasting + quiet - 0.05 <= took < lasting + quiet + 0.5, took
        else:  # they go on: no longer than ``longest``
            assert not went_quiet and longest - 0.05 <= took < longest + 0.5, took
