"""``/tf`` in recordings and the live view (docs/recordings.md "Frames").

Recordings are written in process (no service, no socket) and read back with the ``mcap`` reader
and ``mcap-ros2-support``'s own CDR decoder; the live view's sink takes the same :class:`Recorder`
output, checked here with a sink that keeps what it is given (its WebSocket end is in
tests/test_record.py).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.typesys import Stores, get_typestore

from common.config.settings import Settings
from common.math.frames import Pose2D, from_goal_frame, to_goal_frame
from common.math.loop import Episode
from tests.test_record import check_rosbag2_layout, on_disk, read
from tools.recording.record import (
    GOAL_EVERY,
    LATCHED_TOPICS,
    PATH_EVERY,
    PATH_POSES,
    PATH_STRIDE,
    SIMULATED,
    TF_MESSAGE,
    PoseFrames,
    Recorder,
    RosMapping,
    describe,
    episode_recorder,
    record_episode,
    robot_frames,
)
from tools.recording.sinks import McapSink, RecordingError, RowsByOne, SplitSink, part_path

ORIGIN_NS = 1_700_000_000_000_000_000
DELTA_NS = 100_000_000


def yaw(q: Any) -> float:
    return 2 * math.atan2(q.z, q.w)


def planar(transform: Any) -> Pose2D:
    t = transform.transform
    assert t.translation.z == 0.0 and t.rotation.x == 0.0 and t.rotation.y == 0.0
    return Pose2D(t.translation.x, t.translation.y, yaw(t.rotation))


def close(a: Pose2D, b: Pose2D, atol: float = 1e-9) -> bool:
    return (
        abs(a.x - b.x) <= atol
        and abs(a.y - b.y) <= atol
        and abs(math.remainder(a.theta - b.theta, 2 * math.pi)) <= atol
    )


def edges(messages: list[tuple[int, Any]]) -> list[tuple[int, str, str, Pose2D]]:
    """Every transform of ``/tf``: (log time, parent, child, planar pose), stamp = log time."""
    out = []
    for t_ns, message in messages:
        for transform in message.transforms:
            stamp = int(transform.header.stamp.sec) * 1_000_000_000 + int(transform.header.stamp.nanosec)
            assert stamp == t_ns
            out.append((t_ns, transform.header.frame_id, transform.child_frame_id, planar(transform)))
    return out


class ListSink(RowsByOne):
    """A sink that keeps every sample: what the live view's FoxgloveSink is handed."""

    def __init__(self) -> None:
        self.samples: list[tuple[str, str, str, bytes, int]] = []
        self.ros = RosMapping()

    def write(self, topic: str, ros_type: str, definition: str, data: bytes, t_ns: int) -> None:
        self.samples.append((topic, ros_type, definition, data, t_ns))

    def close(self) -> None:
        pass

    def decoded(self, topic: str) -> list[tuple[int, Any]]:
        return [(t, self.ros.deserialize(d, rt)) for tp, rt, _, d, t in self.samples if tp == topic]


def episode(seed: int, steps: int = 25) -> Episode:
    """A made-up trajectory (headings past +-pi, unwrapped): the recorder copies, it does not simulate."""
    rng = np.random.default_rng(seed)
    states = [
        np.array([2.0, -1.0, 3.0]) + np.cumsum(rng.normal(0, 0.2, (steps + 1, 3)), axis=0)[k] for k in range(steps + 1)
    ]
    return Episode(
        agent="rlqv",
        horizon=12,
        states=states,
        actions=[rng.normal(0, 0.1, 2) for _ in range(steps)],
        costs=[float(c) for c in rng.uniform(0, 1, steps)],
    )


def test_a_recording_carries_tf_odom_to_base_footprint_equal_to_every_state_and_the_goal(tmp_path: Path) -> None:
    run = episode(1)
    recorder = episode_recorder(tmp_path / "e.mcap", 0.1, {"agent": "rlqv", "horizon": 12})
    record_episode(recorder, run, "tb3_0", origin_ns=ORIGIN_NS)
    recorder.close()
    with (tmp_path / "e.mcap").open("rb") as file:
        summary = make_reader(file).get_summary()
    assert summary is not None
    [channel] = [c for c in summary.channels.values() if c.topic == "/tf"]
    schema = summary.schemas[channel.schema_id]
    # the library's definition of tf2_msgs/msg/TFMessage (rosbags' Humble store), not a hand-written one
    assert (schema.name, schema.encoding, channel.message_encoding) == (TF_MESSAGE, "ros2msg", "cdr")
    expected = get_typestore(Stores.ROS2_HUMBLE).generate_msgdef(TF_MESSAGE, ros_version=2)[0]
    assert schema.data.decode() == expected
    topics = read(tmp_path / "e.mcap")
    tf = edges(topics["/tf"])
    bases = [(t, pose) for t, parent, child, pose in tf if (parent, child) == ("odom", "tb3_0/base_footprint")]
    assert len(bases) == run.steps + 1 == len(tf) - len([e for e in tf if e[2] == "goal"])
    assert [t for t, _ in bases] == [ORIGIN_NS + k * DELTA_NS for k in range(run.steps + 1)]
    assert [t for t, _ in bases] == [t for t, _ in topics["/tb3_0/odom"]], "one transform per odometry message"
    for (_, pose), state in zip(bases, run.states, strict=True):
        assert close(pose, Pose2D(*state)), (pose, state)  # a simulated plant: odom is the goal frame
    goals = [(t, parent, pose) for t, parent, child, pose in tf if child == "goal"]
    assert [t for t, _, _ in goals] == [ORIGIN_NS + k * DELTA_NS for k in range(0, run.steps + 1, GOAL_EVERY)]
    assert all(parent == "odom" and pose == (0.0, 0.0, 0.0) for _, parent, pose in goals)
    frames = {m.header.frame_id for _, m in topics["/tb3_0/odom"]} | {topics["/target"][0][1].header.frame_id}
    assert frames == {"odom"} and {m.header.frame_id for _, m in topics["/tb3_0/path"]} == {"odom"}


def test_the_path_holds_the_last_minute_at_every_fifth_step_and_ends_at_its_own_step() -> None:
    sink = ListSink()
    recorder = Recorder(sink, 0.1, clock="steps")
    steps = 1000  # well past the path's minute
    for k in range(steps + 1):
        recorder.transition("tb3_0", 0, k, (0.001 * k, -0.002 * k, 0.01 * k), (0.1, 0.2), 0.5, ORIGIN_NS)
    paths = sink.decoded("/tb3_0/path")
    assert len(paths) == steps // PATH_EVERY + 1  # one each PATH_EVERY steps, the first at step 0
    assert PATH_EVERY % PATH_STRIDE == 0 and pytest.approx(60.0) == PATH_POSES * PATH_STRIDE * 0.1
    for t_ns, path in paths:
        k = (t_ns - ORIGIN_NS) // DELTA_NS
        expected = [j for j in range(0, k + 1, PATH_STRIDE)][-PATH_POSES:]  # ends at the path's own step
        stamps = [p.header.stamp.sec * 10**9 + p.header.stamp.nanosec for p in path.poses]
        assert stamps == [ORIGIN_NS + j * DELTA_NS for j in expected]
        last = path.poses[-1].pose.position
        assert (last.x, last.y) == pytest.approx((0.001 * k, -0.002 * k))


def test_a_recording_is_on_the_disk_within_its_chunk_age_not_when_the_chunk_fills(tmp_path: Path) -> None:
    """What a recorder killed outright (SIGKILL, no close) leaves: every message older than
    CHUNK_SECONDS is in the file's chunks, however few bytes they are."""

    def times(path: Path) -> list[int]:  # the log times of the messages the file holds so far
        return [t for topic in on_disk(path).values() for t in topic]

    path = tmp_path / "live.mcap"
    sink = McapSink(path)
    recorder = Recorder(sink, 0.1, clock="steps")
    for k in range(20):  # a few KB: far below a chunk's CHUNK_BYTES
        recorder.transition("tb3_0", 0, k, (0.1 * k, 0.0, 0.0), (0.1, 0.0), 0.5, ORIGIN_NS)
    assert times(path) == []  # all in the chunk in progress
    before = sink.messages
    sink.chunk_started -= sink.CHUNK_SECONDS  # as if that chunk had been open that long
    recorder.transition("tb3_0", 0, 20, (2.0, 0.0, 0.0), (0.1, 0.0), 0.5, ORIGIN_NS)
    # the chunk went to the disk with the first message written after its age: every one before it too
    assert len(times(path)) == before + 1
    assert {(t - ORIGIN_NS) // DELTA_NS for t in times(path)} == set(range(21))
    sink.close()
    assert len(read(path)["/tb3_0/srl/transition"]) == 21  # and the closed file is whole


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="no /dev/full")
def test_a_recording_whose_disk_is_full_says_so_once_and_writes_nothing_more(tmp_path: Path) -> None:
    """A sink whose file cannot be written (its descriptor on /dev/full: every write ENOSPC) says
    so at the chunk's flush with a RecordingError naming the file and the reason; every later
    write raises the same at once, without reaching the writer; close lets the file go quietly."""
    import os

    path = tmp_path / "full.mcap"
    sink = McapSink(path)
    recorder = Recorder(sink, 0.1, clock="steps")
    recorder.transition("tb3_0", 0, 0, (0.1, 0.0, 0.0), (0.1, 0.0), 0.5, ORIGIN_NS)
    full = os.open("/dev/full", os.O_WRONLY)
    try:
        os.dup2(full, sink.file.fileno())
    finally:
        os.close(full)
    sink.chunk_started -= sink.CHUNK_SECONDS  # the next write flushes the chunk
    with pytest.raises(RecordingError, match=r"cannot write .*full\.mcap: .*") as first:
        recorder.transition("tb3_0", 0, 1, (0.2, 0.0, 0.0), (0.1, 0.0), 0.5, ORIGIN_NS)
    assert "\n" not in str(first.value)
    written = sink.messages
    with pytest.raises(RecordingError) as again:
        recorder.transition("tb3_0", 0, 2, (0.3, 0.0, 0.0), (0.1, 0.0), 0.5, ORIGIN_NS)
    assert str(again.value) == str(first.value) and sink.messages == written
    sink.close()  # no second error: it was said
    assert sink.file.closed


def test_a_recording_split_in_parts_has_every_message_once_and_each_file_readable_alone(tmp_path: Path) -> None:
    path = tmp_path / "split.mcap"
    sink = SplitSink(path, {"sampling_time": "0.1"}, split_seconds=1.0, latched=LATCHED_TOPICS)
    recorder = Recorder(sink, 0.1, clock="steps")
    for k in range(35):  # 3.5 s of steps: files of [0, 1), [1, 2), [2, 3) and [3, 3.5) s
        state = (1.0 - 0.01 * k, 0.0, 0.0)
        recorder.state("tb3_0", 0, state, ORIGIN_NS)
        recorder.transition("tb3_0", 0, k, state, (0.1, 0.0), 0.5, ORIGIN_NS)
    recorder.close()
    assert sink.paths == [part_path(path, part) for part in range(4)] == sorted(tmp_path.iterdir())
    assert [p.name for p in sink.paths] == ["split.mcap", "split_1.mcap", "split_2.mcap", "split_3.mcap"]
    steps, odometry, in_files = [], 0, 0
    for file in sink.paths:
        info = check_rosbag2_layout(file)  # each a whole recording: summary, rosbag2 metadata
        topics = read(file)
        first = min(t for messages in topics.values() for t, _ in messages)
        assert [t for t, _ in topics["/target"]] == [first]  # the target again, at each file's start
        steps += [m.step for _, m in topics["/tb3_0/srl/transition"]]
        odometry += len(topics["/tb3_0/odom"])
        in_files += info["message_count"]
    assert steps == list(range(35)) and odometry == 35  # every message once, in order, none lost at a boundary
    assert sink.messages == in_files - 3 and sink.counts["/target"] == 1  # the target written again 3 times
    assert "to " + str(path) + " and 3 more files (split_3.mcap)" in describe(sink)
    with pytest.raises(RecordingError, match="positive time"):
        SplitSink(tmp_path / "bad.mcap", split_seconds=math.nan)
    (tmp_path / "split_7.mcap").write_bytes(b"an older, longer recording's part")
    (tmp_path / "split_notes.mcap").write_bytes(b"not a part")
    again = SplitSink(path, split_seconds=1.0)  # the same name again: replaces the recording, parts too
    again.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["split.mcap", "split_notes.mcap"]
    one = SplitSink(tmp_path / "one.mcap", split_seconds=0.0)  # 0: never split
    for k in range(50):
        one.write("/x", "std_msgs/msg/Empty", "", b"\x00\x01\x00\x00", ORIGIN_NS + k * 10**9)
    one.close()
    assert one.paths == [tmp_path / "one.mcap"] and "more file" not in describe(one)


def test_a_fleet_gets_one_base_footprint_per_robot_under_one_odom() -> None:
    sink = ListSink()
    recorder = Recorder(sink, 0.1, clock="wall")
    robots = {"tb3_0": (1.0, 2.0, 0.5), "tb3_1": (-1.5, 0.25, -2.0), "rlqv+-N12-s003": (0.3, -0.7, 7.0)}
    for n in range(3):
        for i, (robot, state) in enumerate(robots.items()):
            recorder.state(robot, 0, (state[0] + n, state[1], state[2]), ORIGIN_NS + 1000 * n + i)
    tf = edges(sink.decoded("/tf"))
    children = {child for _, parent, child, _ in tf if child != "goal"}
    assert children == {"tb3_0/base_footprint", "tb3_1/base_footprint", "rlqvplus_N12_s003/base_footprint"}
    assert {parent for _, parent, _, _ in tf} == {"odom"}
    for robot, state in robots.items():
        child = f"{robot.replace('+', 'plus').replace('-', '_')}/base_footprint"
        poses = [pose for _, _, c, pose in tf if c == child]
        assert len(poses) == 3
        assert all(close(pose, Pose2D(state[0] + n, state[1], state[2])) for n, pose in enumerate(poses))
    assert len([e for e in tf if e[2] == "goal"]) == len(robots), "with each robot's first state"


def test_a_recorder_that_gathers_tf_writes_many_states_transforms_in_one_message_each_at_its_state() -> None:
    """``Recorder.gather_tf`` (srl record's writer): the transforms of many states in one ``/tf``
    message, at most ``limit`` of them, the rest at ``flush_tf`` and at ``close``; each transform
    keeps its state's stamp and the message is logged at the newest. Without it (the negative
    control): one message per state."""
    states = {f"r{i}": (0.1 * i, -0.2 * i, 0.3 * i) for i in range(5)}

    def record(gather: bool) -> ListSink:
        sink = ListSink()
        recorder = Recorder(sink, 0.1, clock="wall")
        if gather:
            recorder.gather_tf(limit=4)
        for n in range(2):
            for i, (robot, state) in enumerate(states.items()):
                recorder.state(robot, 0, state, ORIGIN_NS + 10**8 * n + i)
            recorder.flush_tf()  # the writer's batch ends
        recorder.close()
        return sink

    one_each, gathered = record(False), record(True)
    assert len(one_each.decoded("/tf")) == 10
    # 5 states + 5 goals (each robot's first state) = 10 transforms, then 5: 4 + 4 + 2 and 4 + 1
    messages = gathered.decoded("/tf")
    assert [len(m.transforms) for _, m in messages] == [4, 4, 2, 4, 1]
    for t_ns, message in messages:
        stamps = [int(tf.header.stamp.sec) * 10**9 + int(tf.header.stamp.nanosec) for tf in message.transforms]
        assert t_ns == max(stamps)
    every = [(t.header.stamp.sec, t.header.stamp.nanosec, t.child_frame_id) for _, m in messages for t in m.transforms]
    assert every == [
        (t.header.stamp.sec, t.header.stamp.nanosec, t.child_frame_id)
        for _, m in one_each.decoded("/tf")
        for t in m.transforms
    ]
    odometry = [
        [(data, t) for topic, _, _, data, t in sink.samples if topic == "/r3/odom"] for sink in (gathered, one_each)
    ]
    assert odometry[0] == odometry[1] and len(odometry[0]) == 2  # the rest is as before


def test_a_robot_with_a_goal_publishes_its_odometry_pose_and_the_goal_as_a_frame() -> None:
    """bridge.goal g: odom -> base is g (+) s, odom -> goal is g; the goal-frame poses say `goal`."""
    goal = Pose2D(1.0, 0.5, 2.5)
    frames = PoseFrames(goal=goal)
    sink = ListSink()
    recorder = Recorder(sink, 0.1, clock="steps")
    states = [(0.8, -0.3, 3.5), (0.5, -0.1, 3.3), (0.2, 0.05, 3.2)]
    for state in states:
        recorder.state("tb", 0, state, 0, frames)
    recorder.transition("tb", 0, 0, states[0], (0.1, 0.0), 0.5, 0)
    recorder.path("tb", 0)
    tf = edges(sink.decoded("/tf"))
    bases = [pose for _, parent, child, pose in tf if (parent, child) == ("odom", "tb/base_footprint")]
    assert len(bases) == len(states)
    for pose, state in zip(bases, states, strict=True):
        assert close(pose, from_goal_frame(Pose2D(*state), goal))
        assert close(to_goal_frame(pose, goal), Pose2D(*state))  # the state, back from the transform
    assert [(p, pose) for _, p, c, pose in tf if c == "goal"] == [("odom", goal)]
    odometry = sink.decoded("/tb/odom")
    assert {m.header.frame_id for _, m in odometry} == {"goal"}
    assert [(m.pose.pose.position.x, m.pose.pose.position.y) for _, m in odometry] == [s[:2] for s in states]
    assert sink.decoded("/target")[0][1].header.frame_id == "goal"
    path = sink.decoded("/tb/path")[0][1]
    assert path.header.frame_id == "goal" and path.poses[0].header.frame_id == "goal"


@pytest.mark.parametrize("correction", [Pose2D(0.4, -0.2, 0.3), None])
def test_a_localized_robot_chains_map_odom_base_when_the_correction_is_known(correction: Pose2D | None) -> None:
    goal = Pose2D(-2.0, 1.0, -0.7)
    frames = PoseFrames(goal=goal, localized=True, map_to_odom=correction)
    sink = ListSink()
    recorder = Recorder(sink, 0.1)
    state = (0.6, 0.2, -3.9)
    recorder.state("tb", 0, state, ORIGIN_NS, frames)
    tf = {(parent, child): pose for _, parent, child, pose in edges(sink.decoded("/tf"))}
    in_map = from_goal_frame(Pose2D(*state), goal)
    assert close(tf[("map", "goal")], goal)
    if correction is None:  # the pose is known in map only: the base hangs from map
        assert set(tf) == {("map", "goal"), ("map", "tb/base_footprint")}
        assert close(tf[("map", "tb/base_footprint")], in_map)
    else:  # REP 105: map -> odom -> base, composing to the localized pose
        assert set(tf) == {("map", "goal"), ("map", "odom"), ("odom", "tb/base_footprint")}
        assert close(tf[("map", "odom")], correction)
        assert close(from_goal_frame(tf[("odom", "tb/base_footprint")], correction), in_map)
    assert {m.header.frame_id for _, m in sink.decoded("/tb/odom")} == {"goal"}


def test_the_feed_takes_a_robots_goal_from_the_bridge_settings_and_a_simulated_plants_as_odom() -> None:
    bridge = Settings.load(bridge={"goal": [1.0, -2.0, 0.5]}).bridge
    assert robot_frames(bridge, "sim", None) == SIMULATED
    assert robot_frames(bridge, "robot", None).goal == Pose2D(1.0, -2.0, 0.5)
    assert robot_frames(bridge, "robot", None).map_to_odom is None  # the state carries no correction
    # a localizing bridge whose state carries its map -> odom correction: map -> odom on /tf
    localizing = SimpleNamespace(goal=(0.0, 0.0, 0.0), pose_source="pose_with_covariance")
    frames = robot_frames(localizing, "robot", (0.5, -0.25, 0.1))
    assert frames == PoseFrames(goal=Pose2D(0.0, 0.0, 0.0), localized=True, map_to_odom=Pose2D(0.5, -0.25, 0.1))
    assert frames.root == "map" and frames.pose_frame == "goal"
    # a batch's row without a correction has NaN in its place: none
    assert robot_frames(localizing, "robot", (math.nan,) * 3).map_to_odom is None
    odometry_only = robot_frames(SimpleNamespace(goal=(0.0, 0.0, 0.0), pose_source="odom"), "robot", None)
    assert odometry_only == SIMULATED and odometry_only.pose_frame == "odom"


def test_the_shipped_layout_opens_on_the_3d_panel_following_a_recorded_base_frame(tmp_path: Path) -> None:
    layout = json.loads((Path(__file__).resolve().parents[1] / "docs" / "foxglove-layout.json").read_text())
    first = layout["content"]["items"][0]["content"]
    assert first["panelType"] == "ThreeDee"
    config = first["config"]
    recorder = episode_recorder(tmp_path / "e.mcap", 0.1, {"agent": "rlqv"})
    record_episode(recorder, episode(2, steps=3), "tb3_0", origin_ns=ORIGIN_NS)
    recorder.close()
    frames = {f for _, p, c, _ in edges(read(tmp_path / "e.mcap")["/tf"]) for f in (p, c)}
    assert config["fixedFrame"] == "odom" and config["followTf"] == "tb3_0/base_footprint"
    assert {config["fixedFrame"], config["followTf"], "goal"} <= frames


@pytest.mark.parametrize("frame", ["", "map", "odom", "tb3_0/odom"])
@pytest.mark.parametrize("count", [0, 1, 2, 600])
def test_the_path_written_with_numpy_is_the_cdr_rosbags_writes(frame: str, count: int) -> None:
    """``RosMapping.path_cdr`` gives byte for byte what rosbags serializes for the same
    ``nav_msgs/Path``: every alignment the header's frame and the poses' frame can leave
    (frame names of 0 to 10 characters), no pose to a full path, stamps past 2^53 ns."""
    from tools.recording.record import PATH, POSE_STAMPED, RosMapping

    ros = RosMapping()
    rng = np.random.default_rng(count)
    for own in ("odom", "map", "g", "goal_frame"):
        poses = [(int(rng.integers(0, 2 * 10**18)), *map(float, rng.normal(size=3))) for _ in range(count)]
        stamp = int(rng.integers(0, 2 * 10**18))
        message = ros.types[PATH](
            header=ros.header(stamp, frame),
            poses=[ros.types[POSE_STAMPED](header=ros.header(p[0], own), pose=ros.pose(p[1:])) for p in poses],
        )
        stamps, table = np.array([p[0] for p in poses], dtype=np.int64), np.array([p[1:] for p in poses]).reshape(-1, 3)
        assert ros.path_cdr(stamp, frame, stamps, table, [own] * count) == ros.cdr(message, PATH)
    if count >= 2:  # poses in two frames (a robot localized mid-path): the same bytes, through rosbags
        frames = ["odom"] * (count - 1) + ["map"]
        message = ros.types[PATH](
            header=ros.header(stamp, frame),
            poses=[
                ros.types[POSE_STAMPED](header=ros.header(p[0], f), pose=ros.pose(p[1:]))
                for p, f in zip(poses, frames, strict=True)
            ],
        )
        assert ros.path_cdr(stamp, frame, stamps, table, frames) == ros.cdr(message, PATH)


@pytest.mark.parametrize("frame", ["", "odom", "goal", "tb3_0/base_footprint"])
def test_the_hot_messages_packed_by_hand_are_the_cdr_rosbags_writes(frame: str) -> None:
    """Odometry, /tf, cmd_vel, transitions and critic weights (every state and step of every robot) packed by
    ``CdrLayout``: byte for byte what rosbags serializes for the same messages, for frame names
    that leave every alignment, stamps past 2^53 ns and any values."""
    from tools.recording.cdr import odometry_cdr, tf_cdr, transition_cdr, twist_stamped_cdr, weights_cdr
    from tools.recording.record import ODOMETRY, TF_MESSAGE, TRANSITION, TWIST_STAMPED, WEIGHTS, RosMapping

    ros = RosMapping()
    types = ros.types
    rng = np.random.default_rng(len(frame))
    for _ in range(20):
        t_ns = int(rng.integers(0, 2 * 10**18))
        x, y, alpha, v, omega, cost, total = map(float, rng.normal(size=7) * 10)
        odometry = types[ODOMETRY](
            header=ros.header(t_ns, frame),
            child_frame_id="base_footprint",
            pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=ros.pose((x, y, alpha)), covariance=np.zeros(36)),
            twist=types["geometry_msgs/msg/TwistWithCovariance"](twist=ros.twist(v, omega), covariance=np.zeros(36)),
        )
        assert odometry_cdr(t_ns, frame, "base_footprint", (x, y, alpha), (v, omega)) == ros.cdr(odometry, ODOMETRY)
        for count in (1, 2, 3):
            moves = [(frame, f"child{i}" * i, Pose2D(x + i, y - i, alpha * i)) for i in range(count)]
            message = types[TF_MESSAGE](transforms=[ros.transform(t_ns, p, c, pose) for p, c, pose in moves])
            assert tf_cdr([(t_ns, *move) for move in moves]) == ros.cdr(message, TF_MESSAGE)
        # many robots' transforms gathered in one message, each with its own stamp (srl record)
        stamped = [(t_ns + 7919 * i, frame, f"r{i}/base" + "x" * (i % 9), Pose2D(x - i, y, alpha)) for i in range(40)]
        gathered = types[TF_MESSAGE](transforms=[ros.transform(t, p, c, pose) for t, p, c, pose in stamped])
        assert tf_cdr(stamped) == ros.cdr(gathered, TF_MESSAGE)
        command = types[TWIST_STAMPED](header=ros.header(t_ns, frame), twist=ros.twist(v, omega))
        assert twist_stamped_cdr(t_ns, frame, v, omega) == ros.cdr(command, TWIST_STAMPED)
        episode, step = int(rng.integers(0, 2**63)), int(rng.integers(0, 2**32))
        sample = types[TRANSITION](
            header=ros.header(t_ns, frame),
            episode=episode,
            step=step,
            x=x,
            y=y,
            alpha=alpha,
            v=v,
            omega=omega,
            stage_cost=cost,
            accumulated_cost=total,
        )
        values = (x, y, alpha, v, omega, cost, total)
        assert transition_cdr(t_ns, frame, episode, step, values) == ros.cdr(sample, TRANSITION)
        q_weights, v_weights = rng.normal(size=15) * 10, rng.normal(size=6) * 10
        version, trained, pairs = int(rng.integers(0, 2**63)), int(rng.integers(-1, 2**31)), int(rng.integers(0, 2**32))
        fit = types[WEIGHTS](
            header=ros.header(t_ns, frame),
            episode=episode,
            version=version,
            trained_step=trained,
            q_weights=q_weights,
            v_weights=v_weights,
            q_residual=cost,
            v_residual=total,
            pairs=pairs,
        )
        packed = weights_cdr(t_ns, frame, episode, version, trained, q_weights, v_weights, (cost, total), pairs)
        assert packed == ros.cdr(fit, WEIGHTS)
    with pytest.raises(ValueError, match="critic weights are 15 \\+ 6 numbers, got 14 \\+ 6"):
        weights_cdr(0, frame, 0, 1, 0, np.zeros(14), np.zeros(6), (0.0, 0.0), 0)


@pytest.mark.parametrize("frame", ["", "odom", "goal", "tb3_0/base_footprint"])
def test_many_messages_packed_at_once_are_the_messages_packed_one_by_one(
    frame: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The numpy packers of a batch (``*_rows``, srl record's writer) give each row the bytes of
    the message packed alone (``*_cdr``, which the test above compares with rosbags): frame names
    that leave every alignment, stamps past 2^53 ns, any values; a value its field cannot hold is
    refused, never wrapped around."""
    import struct

    from tools.recording import cdr

    rng = np.random.default_rng(len(frame) + 1)
    rows = 50
    t_ns = rng.integers(0, 2 * 10**18, rows)
    states, actions = rng.normal(size=(rows, 3)) * 10, rng.normal(size=(rows, 2))
    episodes, steps = rng.integers(0, 2**63, rows), rng.integers(0, 2**32, rows)
    values = rng.normal(size=(rows, 7)) * 10
    poses = cdr.planar_rows(states[:, 0], states[:, 1], states[:, 2])
    odometry = cdr.odometry_rows(t_ns, frame, "base_footprint", poses, actions)
    commands = cdr.twist_stamped_rows(t_ns, frame, actions)
    samples = cdr.transition_rows(t_ns, frame, episodes, steps, values)
    for i in range(rows):
        t, (v, omega) = int(t_ns[i]), map(float, actions[i])
        assert odometry[i] == cdr.odometry_cdr(t, frame, "base_footprint", states[i], (v, omega))
        assert commands[i] == cdr.twist_stamped_cdr(t, frame, v, omega)
        assert samples[i] == cdr.transition_cdr(t, frame, int(episodes[i]), int(steps[i]), values[i].tolist())
    # the paths of many robots at once: each as its own path (RosMapping.path_cdr, compared with rosbags)
    ros = RosMapping()
    for count in (0, 1, 2, 120):
        stamps = rng.integers(0, 2 * 10**18, (3, count))
        tables = rng.normal(size=(3, count, 3))
        paths = cdr.path_rows(
            t_ns[:3], frame, "odom", stamps, cdr.planar_rows(*tables.reshape(-1, 3).T).reshape(3, count, 7)
        )
        for i in range(3):
            assert paths[i] == ros.path_cdr(int(t_ns[i]), frame, stamps[i], tables[i], ["odom"] * count)
    # /tf: a few transforms one by one, many with numpy; the same bytes either way
    moves = [(int(t_ns[i]), frame, f"r{i}/base" + "x" * (i % 9), Pose2D(*states[i])) for i in range(rows)]
    templates = [cdr.transform_template(parent, child) for _, parent, child, _ in moves]
    planar = [cdr.planar(*map(float, state)) for state in states]
    assert rows > cdr.TF_BY_NUMPY and cdr.tf_message(t_ns.tolist(), templates, planar) == cdr.tf_cdr(moves)
    few = [cdr.tf_message(t_ns[:n].tolist(), templates[:n], planar[:n]) for n in range(1, cdr.TF_BY_NUMPY + 1)]
    monkeypatch.setattr(cdr, "TF_BY_NUMPY", 0)
    assert few == [cdr.tf_message(t_ns[:n].tolist(), templates[:n], planar[:n]) for n in range(1, len(few) + 1)]
    with pytest.raises(ValueError, match="4294967296 does not fit a CDR uint32 field"):
        cdr.transition_rows(t_ns[:2], frame, episodes[:2], np.array([1, 2**32]), values[:2])
    with pytest.raises(struct.error):
        cdr.transition_cdr(int(t_ns[0]), frame, 0, 2**32, values[0].tolist())


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="no /dev/full")
def test_a_full_disk_met_by_a_full_chunk_stops_the_writes_at_the_next_message(tmp_path: Path) -> None:
    """A write the writer makes between two of srl's flushes (a chunk that fills up, a buffered
    file's seek) and fails: the next write raises RecordingError at once and the writer is handed
    nothing more (each message it refused would be a log line of its own)."""
    import os

    sink = McapSink(tmp_path / "full.mcap")
    full = os.open("/dev/full", os.O_WRONLY)
    try:
        os.dup2(full, sink.file.fileno())
    finally:
        os.close(full)
    payload = bytes(1000)
    raised = None
    for k in range(10_000):  # 4 MiB chunks: the first is full after ~4,000 of these
        try:
            sink.write("/x", "std_msgs/msg/String", "string data", payload, ORIGIN_NS + k)
        except RecordingError as error:
            raised = (k, str(error))
            break
    assert raised is not None and "No space left on device" in raised[1], raised
    assert sink.messages == raised[0]  # the message that met the error was not counted, none after
    sink.close()


def raw_messages(path: Path) -> list[tuple[str, int, bytes]]:
    """Every message of an MCAP file as written: (topic, log time, CDR bytes), in file order."""
    with path.open("rb") as file:
        return [
            (c.topic, m.log_time, bytes(m.data)) for _, c, m in make_reader(file).iter_messages(log_time_order=False)
        ]


class OneByOne(RowsByOne):
    """A sink's ``write`` alone: ``write_rows`` as a write per sample (the plain loop)."""

    def __init__(self, sink: McapSink) -> None:
        self.sink = sink

    def write(self, topic: str, ros_type: str, definition: str, data: bytes, t_ns: int) -> None:
        self.sink.write(topic, ros_type, definition, data, t_ns)

    def close(self) -> None:
        self.sink.close()


def fleet_steps(recorder: Recorder, robots: list[str], steps: range, failed: Any = None) -> tuple[int, int]:
    """Each step of ``steps``: every robot's state, then its transition, as batches; the rows taken."""
    count, rng, taken = len(robots), np.random.default_rng(5), (0, 0)
    episodes = np.ones(count, dtype=np.int64)
    for k in steps:
        states = rng.normal(size=(count, 3))
        actions, costs = rng.normal(size=(count, 2)), rng.random(count)
        extra = {} if failed is None else {"failed": failed}
        stamp = ORIGIN_NS + k * 10**8
        states_taken = recorder.states(robots, episodes, states, stamp, **extra)
        recorder.flush_tf()
        steps_taken = recorder.transitions(robots, episodes, np.full(count, k), states, actions, costs, stamp, **extra)
        taken = (taken[0] + states_taken, taken[1] + steps_taken)
    return taken


def test_a_batchs_rows_written_at_once_are_the_messages_written_one_by_one(tmp_path: Path) -> None:
    """McapSink.write_rows (the recorder's batches) writes what a write per sample writes: the
    same messages, bytes, stamps and order, the same counts in the rosbag2 metadata."""
    robots = [f"robot{i}" for i in range(7)]
    paths = {kind: tmp_path / f"{kind}.mcap" for kind in ("rows", "one")}
    rows_sink = McapSink(paths["rows"])
    for sink in (rows_sink, OneByOne(McapSink(paths["one"]))):
        recorder = Recorder(sink, 0.1)
        recorder.gather_tf()
        assert fleet_steps(recorder, robots, range(25)) == (7 * 25, 7 * 25)  # paths every 10 steps too
        recorder.close()
    rows, one = raw_messages(paths["rows"]), raw_messages(paths["one"])
    assert rows == one and len(rows) > 7 * 25 * 3
    assert {topic for topic, _, _ in rows} >= {
        "/robot6/odom",
        "/robot6/cmd_vel",
        "/robot6/srl/transition",
        "/robot6/path",
    }
    metadata = [check_rosbag2_layout(path) for path in paths.values()]
    for info in metadata:  # but the file's own name
        info.pop("relative_file_paths")
        [info["file"]] = info.pop("files")
        info["file"].pop("path")
    assert metadata[0] == metadata[1] and metadata[0]["message_count"] == len(rows)


@pytest.mark.parametrize("kind", ["rows by one", "mcap"])
def test_a_sample_the_sink_refuses_costs_its_row_only_and_the_rows_after_it_are_written(
    tmp_path: Path, kind: str
) -> None:
    """A sample the sink cannot write (Sink.write_rows raises RowWriteError at its row) is handed
    to ``failed`` and its row is not taken; a command refused takes its row's transition with it,
    as a write per sample did; every other row of the batch is written, in order. For a sink
    with a write alone and for McapSink's own write_rows (a channel whose log fails)."""
    refused = {"/robot2/cmd_vel", "/robot4/srl/transition", "/robot5/odom"}
    robots = [f"robot{i}" for i in range(7)]
    path = tmp_path / "refusing.mcap"
    mcap = McapSink(path)

    def refuse(data: bytes, t_ns: int | None = None, sink_id: int | None = None) -> None:
        raise RuntimeError("refused by the test")

    class Refusing(OneByOne):
        def write(self, topic: str, ros_type: str, definition: str, data: bytes, t_ns: int) -> None:
            if topic in refused and t_ns > ORIGIN_NS:
                refuse(data)
            self.sink.write(topic, ros_type, definition, data, t_ns)

    recorder = Recorder(Refusing(mcap) if kind == "rows by one" else mcap, 0.1)
    assert fleet_steps(recorder, robots, range(1)) == (7, 7)  # step 0: every channel made, none refused
    if kind == "mcap":
        for topic in refused:
            mcap.channels.logs[topic] = refuse
    errors: list[Exception] = []
    assert fleet_steps(recorder, robots, range(1, 2), errors.append) == (6, 5)
    assert [str(error) for error in errors] == ["refused by the test"] * 3
    mcap.close()
    later = [topic for topic, t_ns, _ in raw_messages(path) if t_ns > ORIGIN_NS and topic != "/tf"]
    expected = [f"/{robot}/odom" for robot in robots if robot != "robot5"]
    for robot in robots:
        expected += [f"/{robot}/cmd_vel", f"/{robot}/srl/transition"] if robot != "robot2" else []
    expected.remove("/robot4/srl/transition")
    assert later == expected
