"""``srl bench bridge``: what the robot bridge adds to the loop, against the robot alone.

Starts a router, the TurtleBot3 emulator and the robot bridge (the settings' wire profile and
distro), and plays the actor itself: it holds the actor's liveliness token, publishes a new
``srl/<robot>/action`` every ``delta`` (a different speed each time) and listens to the srl
state, the raw ROS ``cmd_vel`` and the raw ``odom`` on the same router, all on one clock:

* ``action -> cmd_vel``: from the srl action to the bridge's ROS command carrying it;
* ``odom -> state``: from the robot's odometry sample to the srl state the bridge made of it;
* ``command -> odometry``: from the srl action to the first odometry that reports the new
  speed (bridge + robot; the emulator publishes odometry at 20 Hz, so up to 50 ms of this is
  waiting for the robot's next sample).

Baselines in the same run: ``zenoh hop`` (a sample to the router and back to this process),
``another process and back`` (to a process that only republishes, and back: the same two
Zenoh legs and two Python wake-ups the ``action -> cmd_vel`` path has, without the bridge's
work), and, with the bridge stopped, ``cmd_vel -> odometry`` sent straight to the robot as a
ROS node would (the robot alone). The bridge also times its own processing (sample in ->
output out). The bridge's CPU and peak RSS come from its own summary. Targets: the bridge
adds at most 1 ms p99: inside it on both paths, and on the command path over the echo.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import subprocess
import sys
import threading
import time
from bisect import bisect_right
from typing import Any

import zenoh
from pydantic import TypeAdapter

from common.config.settings import Settings
from common.contracts import ros_wire
from common.contracts.keys import ACTION, STATE, identity_key, liveliness_key
from common.contracts.messages import Action
from common.contracts.ros_wire import Attachment, RosGraph
from common.contracts.summaries import BridgeSummary
from common.math.stats import summarize
from common.math.turtlebot import firmware_velocity
from common.net.transport import zenoh_config
from tools.bench.meta import run_info
from tools.launch.supervisor import Supervisor, alive_probe, optional_summary, router_reachable, state_probe

TARGET_P99_MS = 1.0
SPEEDS = [round(0.02 + 0.01 * i, 2) for i in range(15)]  # 0.02 .. 0.16 m/s, all below the limits


class Recorder:
    """Arrival times (monotonic) of everything the benchmark listens to."""

    def __init__(self, distro: str) -> None:
        self.distro = distro
        self.lock = threading.Lock()
        self.odom: list[tuple[float, float]] = []  # (arrival, reported v)
        self.states: list[float] = []
        self.commands: list[tuple[float, float]] = []  # (arrival, commanded v)
        self.pongs: list[float] = []
        self.echoes: list[float] = []

    def on_odom(self, sample: zenoh.Sample) -> None:
        now = time.monotonic()
        try:
            odom = ros_wire.decode_odometry(self.distro, bytes(sample.payload.to_bytes()))
        except ros_wire.WireError:
            return
        with self.lock:
            self.odom.append((now, odom.v))

    def on_state(self, _sample: zenoh.Sample) -> None:
        now = time.monotonic()
        with self.lock:
            self.states.append(now)

    def on_command(self, ros_type: str) -> Any:
        def handler(sample: zenoh.Sample) -> None:
            now = time.monotonic()
            try:
                v, _ = ros_wire.decode_command(self.distro, ros_type, bytes(sample.payload.to_bytes()))
            except ros_wire.WireError:
                return
            with self.lock:
                self.commands.append((now, v))

        return handler


def _round_trip(
    publisher: Any, payload: bytes, arrivals: list[float], sink: list[float], timeout: float = 0.05
) -> None:
    """Put ``payload`` and wait (bounded) for the next arrival; record the round trip."""
    before = len(arrivals)
    sent = time.monotonic()
    publisher.put(payload)
    deadline = sent + timeout
    while len(arrivals) == before and time.monotonic() < deadline:
        time.sleep(0.0001)
    if len(arrivals) > before:
        sink.append(arrivals[-1] - sent)


def _first_after(events: list[tuple[float, float]], start: float, value: float, until: float) -> float | None:
    for at, v in events:
        if start <= at <= until and abs(v - value) < 1e-9:
            return at
    return None


def _latencies(
    sent: list[tuple[float, float]], events: list[tuple[float, float]], expect: Any, horizon: float
) -> list[float]:
    out = []
    for index, (at, v) in enumerate(sent):
        until = sent[index + 1][0] if index + 1 < len(sent) else at + horizon
        got = _first_after(events, at, expect(v), until)
        if got is not None:
            out.append(got - at)
    return out


def _odom_to_state(odom: list[tuple[float, float]], states: list[float]) -> list[float]:
    """Each state against the latest odometry sample that arrived before it."""
    times = [at for at, _ in odom]
    out = []
    for at in states:
        i = bisect_right(times, at) - 1
        if i >= 0 and at - times[i] < 0.04:  # the odometry period is 50 ms
            out.append(at - times[i])
    return out


def echo_main(argv: list[str]) -> None:
    """``python -m tools.bench.bridge ENDPOINT ROBOT``: the transport baseline's far end, a
    process that only republishes what it gets (what any service pays for two Zenoh legs)."""
    endpoint, robot = argv
    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("listen/endpoints", "[]")
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    session = zenoh.open(config)
    out = session.declare_publisher(f"srl/{robot}/bench/echo_out", express=True)
    keep = session.declare_subscriber(f"srl/{robot}/bench/echo_in", lambda s: out.put(s.payload.to_bytes()))
    keep_token = session.liveliness().declare_token(f"srl/{robot}/alive/bench_echo")
    threading.Event().wait()  # until killed
    del keep, keep_token


def run_bridge_benchmark(
    args: argparse.Namespace, settings: Settings, settings_args: list[str], bridge_args: list[str]
) -> int:
    robot = settings.transport.robot
    delta = settings.plant.sampling_time
    graph = RosGraph.from_settings(settings.bridge)
    ros_type = ros_wire.TWIST if settings.bridge.ros_distro == "humble" else ros_wire.TWIST_STAMPED
    v_max = min(settings.plant.v_max, 0.22)
    supervisor = Supervisor(settings_args, {**os.environ, "PYTHONUNBUFFERED": "1"}, quiet=True)
    recorder = Recorder(settings.bridge.ros_distro)
    session = None
    result: dict[str, Any] = {}
    supervisor_extra: list[subprocess.Popen[bytes]] = []
    try:
        supervisor.spawn("router", ["router", *settings_args])
        supervisor.wait_for("router", lambda: router_reachable(settings), timeout=30)
        supervisor.spawn("tb3_emulator", ["tb3-emulator", *settings_args, *bridge_args])
        supervisor.spawn("robot_bridge", ["robot-bridge", *settings_args, *bridge_args])
        supervisor.wait_for("robot_bridge", alive_probe(settings, "plant"), timeout=60)
        supervisor.wait_for("odometry through the bridge", state_probe(settings), timeout=60)
        echo = subprocess.Popen(
            [sys.executable, "-m", "tools.bench.bridge", settings.transport.router, robot], start_new_session=True
        )
        supervisor_extra.append(echo)
        session = zenoh.open(zenoh_config(settings.transport))
        keep = [
            session.declare_subscriber(
                graph.data_key(settings.bridge.odom_topic, ros_wire.ODOMETRY, "*"), recorder.on_odom
            ),
            session.declare_subscriber(STATE.key(robot), recorder.on_state),
            session.declare_subscriber(
                graph.data_key(settings.bridge.cmd_vel_topic, ros_type, "*"), recorder.on_command(ros_type)
            ),
            session.declare_subscriber(f"srl/{robot}/bench/ping", lambda _s: recorder.pongs.append(time.monotonic())),
            session.declare_subscriber(
                f"srl/{robot}/bench/echo_out", lambda _s: recorder.echoes.append(time.monotonic())
            ),
            session.liveliness().declare_token(liveliness_key(robot, "actor")),
            # the bridge follows only the live actor session's actions (common.net.provenance)
            session.liveliness().declare_token(identity_key(robot, "actor", str(session.info.zid()))),
        ]
        ping = session.declare_publisher(f"srl/{robot}/bench/ping", express=True)
        echo_pub = session.declare_publisher(f"srl/{robot}/bench/echo_in", express=True)
        action_pub = session.declare_publisher(ACTION.key(robot), express=True)
        deadline = time.monotonic() + 30
        while not any(r.ok for r in session.liveliness().get(f"srl/{robot}/alive/bench_echo", timeout=0.5)):
            if time.monotonic() > deadline or echo.poll() is not None:
                raise RuntimeError("the benchmark's echo process did not come up")
        time.sleep(0.5)  # the bridge sees the actor's token

        # phase 1: through the bridge
        sent: list[tuple[float, float]] = []
        pings: list[float] = []
        echoes: list[float] = []
        steps = max(20, int(args.seconds / 2 / delta))
        # Commands go out at a random phase within each period: the robot's odometry runs at its
        # own 20 Hz, and a fixed phase would turn "waiting for its next sample" into a constant.
        rng = random.Random(1)
        start = time.monotonic()
        for k in range(steps):
            due = start + (k + rng.random()) * delta
            time.sleep(max(0.0, due - time.monotonic()))
            v = SPEEDS[k % len(SPEEDS)] if k % 2 == 0 else SPEEDS[(k + 7) % len(SPEEDS)]
            at = time.monotonic()
            action_pub.put(
                Action(
                    robot=robot, episode=1, step=k, stamp_ns=time.monotonic_ns(), action=(v, 0.0), state_seq=0
                ).encode()
            )
            sent.append((at, v))
            _round_trip(ping, b"p", recorder.pongs, pings)
            # an Action-sized sample to another process and back: the transport both bridge paths pay
            time.sleep(0.01)
            _round_trip(echo_pub, b"e" * 180, recorder.echoes, echoes)
        time.sleep(0.3)
        with recorder.lock:
            commands, odom, states = list(recorder.commands), list(recorder.odom), list(recorder.states)
        action_to_cmd = _latencies(sent, commands, lambda v: v, 0.1)
        # the robot reports the speed its firmware applies: truncated to 0.01 m/s
        command_to_odom = _latencies(sent, odom, lambda v: firmware_velocity(v, v_max), 0.2)
        odom_to_state = _odom_to_state([o for o in odom if o[0] >= start], [s for s in states if s >= start])

        # phase 2: the robot alone (bridge stopped, commands straight to the robot)
        supervisor.stop_one("robot_bridge")
        bridge_summary = optional_summary(supervisor.children["robot_bridge"], TypeAdapter(BridgeSummary))
        endpoint = graph.cmd_endpoint(settings.bridge.cmd_vel_topic, ros_type)
        cmd_pub = session.declare_publisher(endpoint.key, express=True)
        gid = ros_wire.gid_for(f"srl-bench-{robot}")
        direct: list[tuple[float, float]] = []
        start2 = time.monotonic()
        for k in range(steps):
            due = start2 + (k + rng.random()) * delta
            time.sleep(max(0.0, due - time.monotonic()))
            v = SPEEDS[k % len(SPEEDS)] if k % 2 == 0 else SPEEDS[(k + 7) % len(SPEEDS)]
            payload = ros_wire.encode_command(settings.bridge.ros_distro, ros_type, v, 0.0, stamp_ns=time.time_ns())
            at = time.monotonic()
            if graph.profile == "rmw_zenoh":
                cmd_pub.put(payload, attachment=Attachment(k, time.time_ns(), gid).encode())
            else:
                cmd_pub.put(payload)
            direct.append((at, v))
        time.sleep(0.3)
        with recorder.lock:
            odom2 = [o for o in recorder.odom if o[0] >= start2]
        direct_to_odom = _latencies(direct, odom2, lambda v: firmware_velocity(v, v_max), 0.2)
        del keep
        resources = (bridge_summary.resources if bridge_summary is not None else None) or {}
        result = {
            "profile": graph.profile,
            "ros_distro": graph.distro,
            "cmd_type": ros_type,
            "steps": steps,
            "zenoh_hop_ms": summarize(pings, 1e3),
            "process_echo_ms": summarize(echoes, 1e3),
            "process_echo_n": len(echoes),
            "action_to_cmd_ms": summarize(action_to_cmd, 1e3),
            "action_to_cmd_n": len(action_to_cmd),
            "odom_to_state_ms": summarize(odom_to_state, 1e3),
            "odom_to_state_n": len(odom_to_state),
            "command_to_odom_ms": summarize(command_to_odom, 1e3),
            "command_to_odom_n": len(command_to_odom),
            "direct_cmd_to_odom_ms": summarize(direct_to_odom, 1e3),
            "direct_cmd_to_odom_n": len(direct_to_odom),
            "bridge_cpu_seconds": resources.get("cpu_seconds"),
            "bridge_peak_rss_mb": resources.get("peak_rss_mb"),
            "bridge_wall_seconds": start2 - start,
            "bridge_internal": None if bridge_summary is None else bridge_summary.timing.to_json_dict(),
        }
    finally:
        if session is not None:
            session.close()
        for process in supervisor_extra:
            process.kill()
            process.wait()
        supervisor.stop_all()
    # What the bridge adds: its own processing (timed inside it, from a sample's arrival to its
    # output), and, seen from outside, the command path against the same round trip through a
    # process that only echoes (both are this process -> router -> process -> router -> here).
    internal = result.get("bridge_internal") or {}
    nan = {"median": float("nan"), "p99": float("nan")}
    echo = result["process_echo_ms"]
    result["added_over_echo_ms"] = {q: result["action_to_cmd_ms"][q] - echo[q] for q in ("median", "p99")}
    checks = {
        f"inside the bridge action -> cmd_vel p99 <= {TARGET_P99_MS:g} ms": internal.get("action_to_cmd_ms", nan)["p99"]
        <= TARGET_P99_MS,
        f"inside the bridge odom -> state p99 <= {TARGET_P99_MS:g} ms": internal.get("odom_to_state_ms", nan)["p99"]
        <= TARGET_P99_MS,
        f"action -> cmd_vel over the echo baseline, p99 <= {TARGET_P99_MS:g} ms": result["added_over_echo_ms"]["p99"]
        <= TARGET_P99_MS,
    }
    result["targets"] = {name: ("PASS" if ok else "FAIL") for name, ok in checks.items()}
    print(format_table(result))
    if args.json:
        print(json.dumps({**result, "run": run_info()}))
    return 0


def format_table(r: dict[str, Any]) -> str:
    def row(name: str, key: str, n: str | None = None) -> str:
        s = r[key]
        count = f"  n = {r[n]}" if n else ""
        return f"  {name:<40} {s['median']:>9.3f} {s['p99']:>9.3f} {s['max']:>9.3f}  ms{count}"

    lines = [
        f"srl bench bridge: {r['profile']} ({r['ros_distro']}, {r['cmd_type']}), {r['steps']} commands per phase",
        f"  {'':<40} {'median':>9} {'p99':>9} {'max':>9}",
        row("zenoh hop via the router (baseline)", "zenoh_hop_ms"),
        row("another process and back (baseline)", "process_echo_ms", "process_echo_n"),
        row("bridge: action -> cmd_vel", "action_to_cmd_ms", "action_to_cmd_n"),
        row("bridge: odom -> state", "odom_to_state_ms", "odom_to_state_n"),
        row("command -> odometry (bridge + robot)", "command_to_odom_ms", "command_to_odom_n"),
        row("cmd_vel -> odometry (robot alone, baseline)", "direct_cmd_to_odom_ms", "direct_cmd_to_odom_n"),
    ]
    internal = r.get("bridge_internal") or {}
    for key, name in (
        ("action_to_cmd_ms", "inside the bridge: action -> cmd_vel"),
        ("odom_to_state_ms", "inside the bridge: odom -> state"),
    ):
        if key in internal:
            s = internal[key]
            lines.append(f"  {name:<40} {s['median']:>9.3f} {s['p99']:>9.3f} {s['max']:>9.3f}  ms")
    added = r.get("added_over_echo_ms")
    if added:
        lines.append(
            f"  {'action -> cmd_vel minus the echo baseline':<40} {added['median']:>9.3f} {added['p99']:>9.3f}"
            f" {'':>9}  ms"
        )
    if r.get("bridge_cpu_seconds") is not None:
        lines.append(
            f"  bridge process: {r['bridge_cpu_seconds']:.2f} CPU s over {r['bridge_wall_seconds']:.0f} s, "
            f"peak RSS {r['bridge_peak_rss_mb']:.1f} MB"
        )
    lines.append("  targets: " + ", ".join(f"{k}: {v}" for k, v in r["targets"].items()))
    return "\n".join(lines)


if __name__ == "__main__":
    echo_main(sys.argv[1:])
