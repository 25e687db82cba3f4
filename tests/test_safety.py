"""Safety (docs/security.md), the process side: each attack or fault run against real processes.

* a rogue client steps and resets a real-time plant_sim (finding 3);
* srl's router is killed while the robot drives (finding 4), with the robot on its own router
  and with the robot's traffic through srl's router;
* ``srl up`` gets SIGTERM, SIGHUP or SIGKILL (finding 5);
* smaller points (finding 10): stale checkpoint temporaries, late ticks, 10 MB payloads.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from common.config.settings import Settings
from common.contracts import ros_wire
from common.contracts.messages import Action, PlantState, ResetRequest, StepRequest
from common.contracts.ros_wire import ODOMETRY, RosGraph
from common.process.runtime import SignalWatch
from common.system.checkpoint import atomic_write_json, remove_stale_temporaries
from common.system.clock import Ticker
from services.tb3_emulator.command import CMD_TIMEOUT_DEFAULT
from tests.harness import ROOT, client_config, cluster, declare_service_tokens, free_port, open_session, wait_until

V_MAX = 0.22  # the TurtleBot3 Burger's limit (srl.toml plant.v_max)
ODOM_PERIOD = 0.05  # the emulator's 20 Hz odometry


# -- helpers ---------------------------------------------------------------------------------------
def process_alive(pid: int) -> bool:
    """Running (a zombie, already dead and waiting to be reaped, counts as gone)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def survivors(pids: list[int]) -> str:
    """The processes of ``pids`` still running, each with its state, kernel wait and command (for
    a failure's message: which service did not end, and where it sleeps)."""
    found = []
    for pid in pids:
        if process_alive(pid):
            try:
                state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
                wchan = Path(f"/proc/{pid}/wchan").read_text()
                argv = Path(f"/proc/{pid}/cmdline").read_text().replace("\0", " ")[:120]
            except OSError:
                continue
            found.append(f"{pid} {state} {wchan}: {argv}")
    return "; ".join(found) or "none left"


def children_of(pid: int) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except (FileNotFoundError, ProcessLookupError):
            continue
        if int(fields[1]) == pid:
            found.append(int(entry.name))
    return found


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    raise AssertionError(f"no VmRSS for {pid}")


class Odometry:
    """The emulated robot's odometry as a ROS tool reads it: pose and applied velocity."""

    def __init__(self, session: zenoh.Session, graph: RosGraph) -> None:
        self.samples: list[tuple[float, float, float, float]] = []  # (t, x, y, v)
        self.lock = threading.Lock()

        def on_odom(sample: zenoh.Sample) -> None:
            odom = ros_wire.decode_odometry(graph.distro, bytes(sample.payload.to_bytes()))
            with self.lock:
                self.samples.append((time.monotonic(), odom.x, odom.y, odom.v))

        self.subscriber = session.declare_subscriber(graph.data_key("odom", ODOMETRY, "*"), on_odom)

    def last(self) -> tuple[float, float, float, float] | None:
        with self.lock:
            return self.samples[-1] if self.samples else None

    def after(self, t: float) -> list[tuple[float, float, float, float]]:
        with self.lock:
            return [s for s in self.samples if s[0] > t]


def _open(endpoint: str) -> zenoh.Session:
    return open_session(endpoint, 60, f"a session to {endpoint}")


# -- finding 3: a real-time plant serves no step and no reset -------------------------------------
@pytest.mark.integration
@pytest.mark.slow
def test_realtime_plant_sim_ignores_rogue_steps_and_resets() -> None:
    with cluster(robot="rq") as c:
        c.start("plant", "plant-sim", "--mode", "realtime")
        c.start("lockstep", "plant-sim", "--mode", "lockstep", "--robot", "rq_lock")  # the control
        c.wait_alive("plant")
        assert c.session is not None
        states: list[PlantState] = []
        c.session.declare_subscriber(
            "srl/rq/state", lambda s: states.append(PlantState.model_validate_json(s.payload.to_bytes()))
        )
        wait_until(lambda: len(states) >= 5, 10, "real-time states")
        start = states[-1].state
        replies = []
        for step in range(3):  # the attack: 2.2 m per step at full speed for 10 s
            request = StepRequest(robot="rq", episode=0, step=step, action=(0.22, 0.0), duration=10.0)
            replies += list(c.session.get("srl/rq/plant/step", payload=request.encode(), timeout=1.0))
        reset = ResetRequest(robot="rq", episode=0, state=(50.0, 50.0, 0.0))
        replies += list(c.session.get("srl/rq/plant/reset", payload=reset.encode(), timeout=1.0))
        time.sleep(0.3)
        after = states[-1].state
        # the same valid reset reaches a lockstep plant: the queries are well-formed
        control: list[zenoh.Reply] = []
        session = c.session

        def answered() -> bool:
            control.extend(
                session.get(
                    "srl/rq_lock/plant/reset",
                    timeout=1.0,
                    payload=reset.model_copy(update={"robot": "rq_lock"}).encode(),
                )
            )
            return bool(control)

        wait_until(answered, 30, "the lockstep plant's reply")
        assert c.procs["plant"].stop() == 0
        counters = c.procs["plant"].summary()["counters"]
    assert replies == []
    assert control[0].ok is not None
    np.testing.assert_allclose(after, start, atol=1e-12)  # not moved, not teleported
    assert not any(k.startswith(("served.plant", "rejected.plant")) for k in counters), counters
    print(
        f"\nfigures: real-time plant_sim: 3 rogue steps + 1 reset -> {len(replies)} replies, moved "
        f"{math.dist(after[:2], start[:2]):.3f} m (before: 2.2 m per step, reset to (50, 50))"
    )


@pytest.mark.integration
def test_realtime_plant_sim_applies_actions_of_the_live_actor_session_only() -> None:
    """Provenance at the simulator (docs/security.md): like the robot bridge, a real-time plant_sim drives
    only by the live actor session's actions; another session publishing on the same key (a stray
    client, a second actor) is refused and counted, and the robot stops at once when the followed
    actor session is gone."""
    with cluster(robot="pv") as c:
        c.start("plant", "plant-sim", "--mode", "realtime")
        c.wait_alive("plant")
        assert c.session is not None
        states: list[PlantState] = []
        c.session.declare_subscriber(
            "srl/pv/state", lambda s: states.append(PlantState.model_validate_json(s.payload.to_bytes()))
        )
        wait_until(lambda: len(states) >= 5, 10, "real-time states")
        rogue = zenoh.open(client_config(c.endpoint))  # a session without an actor identity
        actor = zenoh.open(client_config(c.endpoint))
        try:

            def drive(session: zenoh.Session, episode: int, steps: range) -> None:
                for step in steps:
                    action = Action(robot="pv", episode=episode, step=step, stamp_ns=0, state_seq=0, action=(0.22, 0.0))
                    session.put("srl/pv/action", action.encode())
                    time.sleep(0.05)

            start = states[-1].state
            drive(rogue, 1, range(10))  # nobody is the actor: refused
            time.sleep(0.2)
            after_rogue = states[-1].state
            tokens = declare_service_tokens(actor, "pv", "actor")
            time.sleep(0.3)
            drive(rogue, 2, range(10))  # the live actor is another session: refused
            time.sleep(0.2)
            after_foreign = states[-1].state
            drive(actor, 3, range(10))  # the live actor: applied
            # the plant sends a driven robot's state just before its actor's next tick (state_sync):
            # the newest seen may predate the last actions; the one after them shows where it is
            acted = time.monotonic_ns()
            wait_until(lambda: states[-1].stamp_ns > acted, 2, "a state after the live actor's actions")
            moved = math.dist(states[-1].state[:2], after_foreign[:2])
            for token in tokens:  # the actor session's tokens vanish: the robot stops at once
                token.undeclare()
            time.sleep(0.15)
            stopped_at = states[-1].state
            time.sleep(0.3)
            coasted = math.dist(states[-1].state[:2], stopped_at[:2])
        finally:
            rogue.close()
            actor.close()
        assert c.procs["plant"].stop() == 0
        counters = c.procs["plant"].summary()["counters"]
    np.testing.assert_allclose(after_rogue, start, atol=1e-12)
    np.testing.assert_allclose(after_foreign, start, atol=1e-12)
    assert moved > 0.05, moved
    assert coasted < 1e-9, coasted
    assert counters.get("rejected.action.unknown", 0) >= 9, counters
    assert counters.get("rejected.action.foreign", 0) >= 9, counters
    assert counters.get("actor_lost_stops", 0) == 1, counters
    print(
        f"\nfigures: real-time plant_sim: {counters.get('rejected.action.unknown', 0)} actions without a live actor "
        f"and {counters.get('rejected.action.foreign', 0)} from another session refused, moved 0.000 m; the live "
        f"actor's moved it {moved:.3f} m; stopped at once when it vanished (before: any session drove it)"
    )


# -- finding 4: the router dies while the robot drives ---------------------------------------------
def _wait_driving(odometry: Odometry, timeout: float) -> None:
    def driving() -> bool:
        last = odometry.last()
        return last is not None and abs(last[3]) >= 0.1

    wait_until(driving, timeout, "the robot to drive (|v| >= 0.1 m/s)")


def _distance_after(odometry: Odometry, killed: float, reference: tuple[float, float, float, float]) -> float:
    return max((math.dist(s[1:3], reference[1:3]) for s in odometry.after(killed)), default=0.0)


@pytest.mark.integration
@pytest.mark.slow
def test_router_kill_robot_on_its_own_router_stops_within_5cm() -> None:
    """``srl up --plant robot`` (the default topology): kill -9 srl's router while the robot drives."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    up = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "tools.cli",
            "--log-level",
            "INFO",
            "up",
            "--plant",
            "robot",
            "--agent",
            "mpc",
            "--router",
            endpoint,
            "--robot",
            "rk",
            "--start=2,1.5",
            "--duration",
            "60",
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    lines: list[str] = []

    def read_stderr() -> None:
        assert up.stderr is not None
        lines.extend(up.stderr)

    reader = threading.Thread(target=read_stderr, daemon=True)
    reader.start()
    session = None
    try:

        def found(pattern: str) -> re.Match[str] | None:
            return next((m for line in list(lines) if (m := re.search(pattern, line))), None)

        wait_until(
            lambda: found(r"emulated robot's Zenoh router: (\S+)") is not None or up.poll() is not None,
            60,
            "the emulated robot's router",
        )
        robot_endpoint = found(r"emulated robot's Zenoh router: (\S+)").group(1)  # type: ignore[union-attr]
        router_pid = int(found(r"started router \(pid (\d+)\)").group(1))  # type: ignore[union-attr]
        session = _open(robot_endpoint)  # the robot's own router: still there after srl's dies
        odometry = Odometry(session, RosGraph("rmw_zenoh", "jazzy", 0, ""))
        _wait_driving(odometry, 180)
        reference = odometry.last()
        assert reference is not None
        os.kill(router_pid, signal.SIGKILL)
        killed = time.monotonic()
        wait_until(lambda: any(s[3] == 0.0 for s in odometry.after(killed)), 5, "the robot to stop")
        stopped_at = next(s[0] for s in odometry.after(killed) if s[3] == 0.0)
        time.sleep(1.0)
        distance = _distance_after(odometry, killed, reference)
        up.wait(timeout=60)
        reader.join(timeout=10)  # srl up has ended; its last lines may still be in the pipe
    finally:
        if session is not None:
            session.close()
        if up.poll() is None:
            os.killpg(up.pid, signal.SIGKILL)
            up.wait()
    assert up.returncode == 1  # srl up reports the dead router and stops everything
    assert odometry.last()[3] == 0.0  # type: ignore[index]
    # the bridge stopped the robot itself: its srl session lost the actor's liveliness token with
    # the router (before srl up's own cleanup reached it)
    # the bridge saw the actor go (its session's identity token, common.net.provenance) and stopped the robot
    stopped = ("liveliness token vanished", "is gone: stopping the robot")
    assert any("[robot_bridge]" in line and any(s in line for s in stopped) for line in lines), lines[-20:]
    print(
        f"\nfigures: srl up --plant robot, router kill -9 at |v| = {abs(reference[3]):.2f} m/s: the robot "
        f"stopped {1e3 * (stopped_at - killed):.0f} ms later (odometry at 20 Hz), drove {100 * distance:.1f} cm "
        f"after the kill (before: 0.67 m in a 3 s outage)"
    )
    assert distance <= 0.05


@pytest.mark.integration
@pytest.mark.slow
def test_router_kill_robot_through_srl_router_stops_by_its_own_timeout() -> None:
    """The robot's traffic through srl's router: no zero can reach it; its cmd_vel timeout stops it."""
    with cluster(robot="rt4") as c:
        assert c.session is not None
        odometry = Odometry(c.session, RosGraph("rmw_zenoh", "jazzy", 0, ""))
        c.start("emulator", "tb3-emulator", "--start=2,1.5")  # the default --cmd-timeout
        c.start("bridge", "robot-bridge")
        c.wait_alive("plant")
        c.start("actor", "actor", "--mode", "realtime", "--agent", "mpc", "--run-seconds", "60")
        _wait_driving(odometry, 180)
        reference = odometry.last()
        assert reference is not None
        c.procs["router"].stop(signal.SIGKILL)
        killed = time.monotonic()
        time.sleep(1.5)
        assert c.procs["emulator"].stop() == 0
        emulator = c.procs["emulator"].summary()
    distance = math.dist(emulator["final_pose"][:2], reference[1:3])
    bound = V_MAX * (CMD_TIMEOUT_DEFAULT + ODOM_PERIOD) + 0.01
    print(
        f"\nfigures: robot through srl's router, router kill -9 at |v| = {abs(reference[3]):.2f} m/s: the "
        f"emulator's {CMD_TIMEOUT_DEFAULT} s cmd_vel timeout stopped it after {100 * distance:.1f} cm "
        f"(bound v_max x timeout = {100 * V_MAX * CMD_TIMEOUT_DEFAULT:.0f} cm; before: 0.67 m in 3 s, holding)"
    )
    assert emulator["cmd_timeouts"] >= 1 and emulator["applied"] == [0.0, 0.0]
    assert distance <= bound
    assert time.monotonic() - killed < 30


# -- finding 5: signals to srl up --------------------------------------------------------------------
def _start_up(tmp_path: Path, *argv: str) -> tuple[subprocess.Popen[str], Path]:
    temp = tmp_path / "tmp"
    temp.mkdir()
    up = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "tools.cli",
            "up",
            "--router",
            f"tcp/127.0.0.1:{free_port()}",
            "--duration",
            "120",
            *argv,
        ],
        cwd=ROOT,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,
        env={**os.environ, "TMPDIR": str(temp)},
    )
    return up, temp


def _wait_children(up: subprocess.Popen[str], count: int) -> list[int]:
    wait_until(lambda: len(children_of(up.pid)) >= count or up.poll() is not None, 120, f"{count} children")
    assert up.poll() is None, up.communicate()[1][-3000:]
    return children_of(up.pid)


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.parametrize(
    ("signum", "argv"),
    [(signal.SIGTERM, ["--secure"]), (signal.SIGHUP, []), (signal.SIGINT, ["--secure"])],
    ids=["SIGTERM-secure", "SIGHUP", "SIGINT-secure"],
)
def test_srl_up_cleans_up_on_sigterm_and_sighup(tmp_path: Path, signum: int, argv: list[str]) -> None:
    up, temp = _start_up(tmp_path, "--robot", "sg", *argv)
    try:
        children = _wait_children(up, 4)  # router, plant, critic, actor
        if "--secure" in argv:
            assert [d.name.startswith("srl-secure-") for d in temp.iterdir()] == [True]
        time.sleep(1.0)
        sent = time.monotonic()
        up.send_signal(signum)
        _, err = up.communicate(timeout=60)
        took = time.monotonic() - sent
    finally:
        if up.poll() is None:
            os.killpg(up.pid, signal.SIGKILL)
            up.wait()
    assert up.returncode == 128 + signum, err[-3000:]
    assert f"stopped by {signal.Signals(signum).name}" in err
    assert [pid for pid in children if process_alive(pid)] == []
    assert list(temp.iterdir()) == [], "srl up left its credentials behind"
    print(
        f"\nfigures: {signal.Signals(signum).name} to srl up {' '.join(argv)}: exit {up.returncode} after "
        f"{took:.1f} s, {len(children)} children stopped, credentials removed: "
        f"{not any(temp.iterdir())}"
        + ("" if signum == signal.SIGINT else " (before: exit -15, credentials kept, 4 children running)")
    )


@pytest.mark.integration
@pytest.mark.slow
def test_kill_9_of_srl_up_takes_every_service_with_it(tmp_path: Path) -> None:
    up, _ = _start_up(tmp_path, "--robot", "k9", "--plant", "robot")
    children: list[int] = []
    try:
        children = _wait_children(up, 5)  # router, emulator, bridge, critic, actor
        time.sleep(1.0)
        os.kill(up.pid, signal.SIGKILL)
        killed = time.monotonic()
        up.wait()
        try:
            wait_until(lambda: not any(process_alive(pid) for pid in children), 15, "every child to end")
        except AssertionError as error:
            raise AssertionError(f"{error}; still running: {survivors(children)}") from error
        took = time.monotonic() - killed
    finally:
        if up.poll() is None:
            os.kill(up.pid, signal.SIGKILL)
            up.wait()
        for pid in children:  # only if the test failed: never leave a service behind
            if process_alive(pid):
                os.kill(pid, signal.SIGKILL)
    print(
        f"\nfigures: kill -9 of srl up --plant robot: all {len(children)} services gone {took:.2f} s later "
        "(before: they kept running)"
    )
    assert took <= 5.0


@pytest.mark.integration
def test_die_with_parent_stops_at_once_when_the_parent_is_already_gone() -> None:
    """In a child process (the guard arms PR_SET_PDEATHSIG and an exit watchdog on the process
    that calls it: never on the test runner): a process whose SRL_PARENT_PID is not its parent
    stops at once, and exits with code 3 if it is still running after the grace period; without
    the variable nothing is armed."""
    script = (
        "import os, sys, threading, time\n"
        "import common.system.lifeline as lifeline\n"
        "lifeline.EXIT_GRACE_SECONDS = 0.5\n"
        "os.environ['SRL_PARENT_PID'] = str(os.getppid() + 10**6)\n"
        "stop = threading.Event()\n"
        "assert lifeline.die_with_parent(stop) == os.getppid() + 10**6\n"
        "assert stop.is_set()\n"
        "del os.environ['SRL_PARENT_PID']\n"
        "other = threading.Event()\n"
        "assert lifeline.die_with_parent(other) is None and not other.is_set()\n"
        "print('armed', flush=True)\n"
        "time.sleep(10)\n"  # still running after the grace: the watchdog ends it with code 3
    )
    started = time.monotonic()
    done = subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=60, check=False
    )
    took = time.monotonic() - started
    assert done.stdout.strip() == "armed", done.stderr[-2000:]
    assert done.returncode == 3 and took < 8.0, (done.returncode, took, done.stderr[-2000:])


@pytest.mark.integration
@pytest.mark.parametrize("bounded", [True, False])
def test_a_stop_that_hangs_holding_the_gil_still_ends(bounded: bool) -> None:
    """A service's stop on a signal (common.process.runtime.stop_within_bounds) that then hangs in native
    code holding the GIL -- where no Python thread, signal handler or lifeline can run -- ends
    HARD_EXIT_SECONDS later by faulthandler's C watchdog, with every thread's traceback on stderr.
    The negative control (the handler before: only ``stop.set()``) is still running."""
    script = (
        "import ctypes, signal, sys, threading\n"
        "import common.system.lifeline as lifeline\n"
        "from common.process.runtime import SignalWatch, stop_within_bounds\n"
        "lifeline.HARD_EXIT_SECONDS = 1.0\n"
        "stop = threading.Event()\n"
        f"if {bounded}: SignalWatch(lambda _signum: stop_within_bounds(stop)).start()  # as serve()\n"
        "else: signal.signal(signal.SIGTERM, lambda *_: stop.set())\n"
        "print('ready', flush=True)\n"
        "stop.wait()\n"
        "ctypes.PyDLL(None).sleep(30)  # hangs_holding_the_gil\n"
    )
    process = subprocess.Popen(
        [sys.executable, "-c", script], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        assert process.stdout is not None and process.stdout.readline().strip() == "ready"
        os.kill(process.pid, signal.SIGTERM)
        signalled = time.monotonic()
        with contextlib.suppress(subprocess.TimeoutExpired):
            process.wait(timeout=6.0)
        took = time.monotonic() - signalled
        if bounded:
            stderr = process.stderr.read() if process.stderr is not None else ""
            assert process.returncode == 1 and 0.9 <= took < 6.0, (process.returncode, took, stderr[-2000:])
            assert "hangs_holding_the_gil" in stderr or '<string>", line 10' in stderr, stderr[-2000:]
        else:
            assert process.poll() is None, "the control should still hang"
    finally:
        if process.poll() is None:
            process.kill()
        process.wait()
        for stream in (process.stdout, process.stderr):
            if stream is not None:
                stream.close()


SIGNAL_STORM = (
    "import signal, sys, threading, time\n"
    "from common.process.runtime import SignalWatch\n"
    "stop = threading.Event()\n"
    "if sys.argv[1] == 'watch': SignalWatch(lambda _signum: stop.set(), signals=(signal.SIGALRM,)).start()\n"
    "else: signal.signal(signal.SIGALRM, lambda *_: stop.set())  # the handler before\n"
    "signal.setitimer(signal.ITIMER_REAL, 0.0005, 0.0005)\n"
    "count, end = 0, time.monotonic() + 8.0\n"
    "while count < 1000 and time.monotonic() < end:\n"
    "    if stop.wait(0.00001):  # the main thread holds the event's lock most of the time\n"
    "        stop.clear()\n"
    "        count += 1\n"
    "signal.setitimer(signal.ITIMER_REAL, 0)\n"
    "print('stops', count, flush=True)\n"
)


@pytest.mark.integration
@pytest.mark.parametrize("watch", [True, False])
def test_a_signal_while_the_main_thread_waits_on_the_stop_never_deadlocks(watch: bool) -> None:
    """A signal handler runs in the main thread, possibly inside ``stop.wait()`` while that thread
    holds the event's non-reentrant lock; a handler calling ``stop.set()`` then waits on its own
    thread forever (CI: services that "did not stop", their main thread stuck in ``Event.set``
    inside ``Condition.wait``). common.process.runtime.SignalWatch sets the stop from a thread of its own:
    1,000 signals, each heard, while the main thread waits on the stop. The control, the
    handler before, deadlocks on one of them (here it hangs, or dies of nested handlers)."""
    mode = "watch" if watch else "handler"
    try:
        done = subprocess.run(
            [sys.executable, "-c", SIGNAL_STORM, mode], cwd=ROOT, capture_output=True, text=True, timeout=20.0
        )
        output, code = done.stdout.strip(), done.returncode
    except subprocess.TimeoutExpired:  # subprocess.run kills and reaps the child
        output, code = "hung", None
    if watch:
        assert (output, code) == ("stops 1000", 0), (output, code)
    else:
        assert output != "stops 1000", "the control should deadlock"


def test_a_signal_watch_restores_the_handlers_and_wakeup_fd_it_replaced() -> None:
    heard: list[int] = []
    got = threading.Event()
    previous = signal.getsignal(signal.SIGUSR1)
    wakeup = signal.set_wakeup_fd(-1)
    signal.set_wakeup_fd(wakeup)
    with SignalWatch(lambda signum: (heard.append(signum), got.set()), signals=(signal.SIGUSR1,)) as watch:
        assert signal.getsignal(signal.SIGUSR1) == watch._handle
        os.kill(os.getpid(), signal.SIGUSR1)
        assert got.wait(5.0)
    assert heard[0] == signal.SIGUSR1 and set(heard) == {signal.SIGUSR1}
    assert signal.getsignal(signal.SIGUSR1) == previous
    old = signal.set_wakeup_fd(-1)
    signal.set_wakeup_fd(old)
    assert old == wakeup  # the watch's pipe is no longer the wakeup fd
    assert watch._thread is None and watch._read == -1 and watch._write == -1


# -- finding 10: smaller points ----------------------------------------------------------------------
@pytest.mark.integration
def test_stale_checkpoint_temporaries_are_removed_at_start(tmp_path: Path) -> None:
    path = tmp_path / "critic-r.json"
    atomic_write_json(path, {"a": 1})
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        dead = subprocess.run(
            [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True, check=True
        )
        dead_pid = int(dead.stdout)
        stale = [
            tmp_path / f".critic-r.json.{dead_pid}.abc123.tmp",  # a writer killed mid-write
            tmp_path / ".critic-r.json.k2j_x9q1.tmp",  # the older name, without a pid
            tmp_path / f".critic-r.json.{os.getpid()}.zz.tmp",
        ]  # this process's own, from before
        live = tmp_path / f".critic-r.json.{sleeper.pid}.live.tmp"  # a running writer's: kept
        others = [tmp_path / ".critic-other.json.1.x.tmp", tmp_path / "critic-r.json.unusable"]
        for file in [*stale, live, *others]:
            file.write_bytes(b"")
        removed = remove_stale_temporaries(path)
        assert sorted(removed) == sorted(stale)
        assert sorted(p.name for p in tmp_path.iterdir()) == sorted([path.name, live.name, *(p.name for p in others)])
        assert json.loads(path.read_text()) == {"a": 1}
    finally:
        sleeper.kill()
        sleeper.wait()


@pytest.mark.integration
@pytest.mark.slow
def test_critic_removes_a_killed_writes_temporary_at_start(critic_checkpoint: Path) -> None:
    checkpoint = Path(str(critic_checkpoint).format(robot="tm"))
    checkpoint.parent.mkdir(parents=True, exist_ok=True)
    leftover = checkpoint.with_name(f".{checkpoint.name}.999999999.q1w2e3.tmp")
    leftover.write_bytes(b"")  # what kill -9 during a checkpoint write can leave: 0 bytes
    with cluster(robot="tm") as c:
        c.start("critic", "critic")
        c.wait_alive("critic")
        assert not leftover.exists()
        assert c.procs["critic"].stop() == 0


class FakeClock:
    """Time that moves only when the ticker sleeps (plus an injected oversleep per tick)."""

    def __init__(self, oversleep: list[float]) -> None:
        self.now = 100.0
        self.oversleep = oversleep

    def clock(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> bool:
        self.now += seconds + (self.oversleep.pop(0) if self.oversleep else 0.0)
        return False


def test_a_tick_that_wakes_up_late_is_a_missed_deadline() -> None:
    # delta = 0.1 s, threshold 25 % = 25 ms: 24 ms late is jitter, 26 ms and the 54 ms are missed
    fake = FakeClock([0.0, 0.024, 0.026, 0.054, 0.0, 0.0])
    ticker = Ticker(0.1, clock=fake.clock, sleep=fake.sleep)
    assert ticker.late_threshold == pytest.approx(0.025)
    ticks = [ticker.wait() for _ in range(6)]
    assert ticks == pytest.approx([100.1, 100.224, 100.326, 100.454, 100.5, 100.6])
    assert ticker.late == 2 and ticker.missed == 2
    # an overrun (the loop came back after the due time) is missed once, not twice
    fake.now += 0.25
    ticker.wait()
    assert ticker.missed == 4 and ticker.late == 2  # 100.7 skipped and 100.8 overrun: 2 more, no "late"


@pytest.mark.integration
@pytest.mark.slow
def test_a_10_mb_payload_does_not_grow_the_receiving_service() -> None:
    with cluster(robot="big") as c:
        c.start("plant", "plant-sim", "--mode", "realtime")
        c.wait_alive("plant")
        assert c.session is not None
        states: list[float] = []
        c.session.declare_subscriber("srl/big/state", lambda s: states.append(time.monotonic()))
        time.sleep(1.0)
        pid = c.procs["plant"].process.pid
        before = rss_mb(pid)
        c.session.put("srl/big/action", b"x" * 10_000_000)
        time.sleep(2.0)
        growth = rss_mb(pid) - before
        mark = time.monotonic()
        wait_until(lambda: sum(t > mark for t in states) >= 20, 5, "states still flowing")
        assert c.procs["plant"].stop() == 0
        counters = c.procs["plant"].summary()["counters"]
    print(
        f"\nfigures: one 10 MB put on srl/big/action: plant RSS +{growth:.1f} MB (before: +49-79 MB), "
        f"rejected.action {counters.get('rejected.action', 0)}"
    )
    assert counters.get("rejected.action", 0) == 0  # dropped by Zenoh before it was reassembled
    assert growth < 5.0


def test_zenoh_config_bounds_the_message_size() -> None:
    settings = Settings.load()
    from common.net.transport import zenoh_config

    config = zenoh_config(settings.transport)
    assert json.loads(config.get_json("transport/link/rx/max_message_size")) == settings.transport.max_message_bytes
    assert settings.transport.max_message_bytes == 1_048_576
