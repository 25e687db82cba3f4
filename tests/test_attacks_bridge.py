"""Valid but malicious messages against real processes, at the robot bridge and the plants (docs/security.md).

Each test runs one attack against the real bridge (with the emulated
TurtleBot3 behind it) or plant_sim processes, prints one ``figures:`` line, and asserts that the
attack no longer works: a far-future action or odometry stamp from a rogue session locks nothing
out, and a second plant for one robot refuses to start.
"""

from __future__ import annotations

import signal
import threading
import time

import pytest
import zenoh

from common.contracts import ros_wire
from common.contracts.keys import identity_of, identity_pattern, liveliness_key
from common.contracts.messages import Action
from common.contracts.ros_wire import ODOMETRY, Attachment, Odometry, RosGraph
from common.net.provenance import RESYNC_AFTER, PlantConflictError
from common.net.transport import Bus
from tests.harness import client_config, cluster, declare_service_tokens, wait_until
from tests.test_robot_bridge import DELTA, TIMEOUT, RobotWatch

pytestmark = [pytest.mark.slow, pytest.mark.integration]
GRAPH = RosGraph("rmw_zenoh", "jazzy", 0, "")


def _rogue(endpoint: str) -> zenoh.Session:
    """Another client on the same router, as a hostile or buggy process would be (its own id)."""
    return zenoh.open(client_config(endpoint))


def test_one_far_future_action_from_another_session_locks_nothing_out() -> None:
    """Before: one Action(episode=2**62) made the bridge refuse every later real action (145 real
    non-zero actions, 0 non-zero cmd_vel in 14 s). After: the rogue action is refused as foreign
    and the real actor's actions keep driving the robot."""
    robot = "atk_a"
    with cluster(robot=robot) as c:
        assert c.session is not None
        watch = RobotWatch(c.session, GRAPH, robot)
        c.start("emulator", "tb3-emulator", "--initial-pose=-1,0,0")
        c.start("bridge", "robot-bridge")
        c.wait_alive("plant")
        wait_until(lambda: len(watch.states) >= 3, 30, "the robot's state")
        tokens = declare_service_tokens(c.session, robot, "actor")  # this session is the real actor
        actions = c.session.declare_publisher(f"srl/{robot}/action")
        rogue = _rogue(c.endpoint)
        try:
            moved_from = watch.states[-1].state[0]
            for step in range(40):
                if step == 5:  # the attack, once
                    rogue.put(
                        f"srl/{robot}/action",
                        Action(
                            robot=robot, episode=2**62, step=0, stamp_ns=0, action=(-0.2, 0.0), state_seq=-1
                        ).encode(),
                    )
                actions.put(
                    Action(
                        robot=robot,
                        episode=1,
                        step=step,
                        stamp_ns=time.monotonic_ns(),
                        action=(0.15, 0.0),
                        state_seq=-1,
                    ).encode()
                )
                time.sleep(DELTA)
            moved = watch.states[-1].state[0] - moved_from
            driving = watch.applied()
        finally:
            rogue.close()
            for token in tokens:
                token.undeclare()
        assert c.procs["bridge"].stop() == 0
        counters = c.procs["bridge"].summary()["counters"]
    print(
        f"\nfigures: far-future action from another session: {counters.get('actions_applied', 0)} of 40 real "
        f"actions applied, {counters.get('rejected.action.foreign', 0)} foreign refused, robot moved {moved:.2f} m "
        f"forward, still commanded {driving}"
    )
    assert counters.get("rejected.action.foreign", 0) == 1
    assert counters["actions_applied"] >= 38  # every real action (the first may race the token)
    assert moved > 0.4 and driving[0] > 0.1  # 0.15 m/s for 4 s, still driving at the end


def test_a_far_future_episode_with_the_live_actor_id_locks_nothing_out() -> None:
    """A forger that copies the live actor's session id (Zenoh client ids can be forged) sends
    Action(episode=2**62): no later real action may be refused for it. Here the forged actions
    come from the actor's own session (what the bridge sees of a perfect forgery): one is
    refused alone; a burst of RESYNC_AFTER that counts on is followed, then the real actor is
    followed again after RESYNC_AFTER - 1 refused actions."""
    robot = "atk_e"
    with cluster(robot=robot) as c:
        assert c.session is not None
        watch = RobotWatch(c.session, GRAPH, robot)
        c.start("emulator", "tb3-emulator", "--initial-pose=-1,0,0")
        c.start("bridge", "robot-bridge")
        c.wait_alive("plant")
        wait_until(lambda: len(watch.states) >= 3, 30, "the robot's state")
        tokens = declare_service_tokens(c.session, robot, "actor")
        actions = c.session.declare_publisher(f"srl/{robot}/action")

        def forged(step: int) -> bytes:
            return Action(robot=robot, episode=2**62, step=step, stamp_ns=0, action=(-0.2, 0.0), state_seq=-1).encode()

        try:
            moved_from = watch.states[-1].state[0]
            for step in range(40):
                if step == 5:  # one forged action
                    actions.put(forged(0))
                if step == 20:  # a forged burst that counts on
                    for k in range(RESYNC_AFTER):
                        actions.put(forged(k))
                actions.put(
                    Action(
                        robot=robot,
                        episode=1_764_000_000_000,
                        step=step,
                        stamp_ns=time.monotonic_ns(),
                        action=(0.15, 0.0),
                        state_seq=-1,
                    ).encode()
                )
                time.sleep(DELTA)
            moved = watch.states[-1].state[0] - moved_from
            driving = watch.applied()
        finally:
            for token in tokens:
                token.undeclare()
        assert c.procs["bridge"].stop() == 0
        counters = c.procs["bridge"].summary()["counters"]
    refused = counters.get("rejected.action", 0)
    real_applied = counters["actions_applied"] - 1  # the burst's last forged action was followed
    print(
        f"\nfigures: forged episode 2**62 with the live actor's id (1, then a burst of {RESYNC_AFTER}): "
        f"{real_applied} of 40 real actions applied, {refused} refused, {counters.get('action_resyncs', 0)} resyncs, "
        f"robot moved {moved:.2f} m forward, still commanded {driving}"
    )
    real_refused = 40 - real_applied
    assert refused - real_refused == 1 + (RESYNC_AFTER - 1)  # forged: the single one, the burst's first 4
    # real: the 4 before the resync back (and the first, if it raced the actor's token to the bridge)
    assert real_refused in (RESYNC_AFTER - 1, RESYNC_AFTER)
    assert counters["action_resyncs"] == 2
    assert moved > 0.3 and driving[0] > 0.1


def test_odometry_from_the_far_future_drops_no_real_sample() -> None:
    """Before: odometry stamped 1 h ahead, once a second, made the bridge drop the next 19 real
    samples each time (190 in total). After: each forged sample is refused alone."""
    robot = "atk_o"
    with cluster(robot=robot) as c:
        assert c.session is not None
        c.start("emulator", "tb3-emulator", "--initial-pose=0.5,0,0")
        c.start("bridge", "robot-bridge")
        c.wait_alive("plant")
        watch = RobotWatch(c.session, GRAPH, robot)
        wait_until(lambda: len(watch.states) >= 3, 30, "the robot's state")
        rogue = _rogue(c.endpoint)
        forged = 0
        try:
            publisher = rogue.declare_publisher(GRAPH.data_key("odom", ODOMETRY))
            for k in range(6):
                stamp = time.time_ns() + 3600 * 10**9
                payload = ros_wire.encode_odometry(
                    "jazzy", Odometry(stamp, "odom", "base_footprint", 9.0, 9.0, (0.0, 0.0, 0.0, 1.0), 0.0, 0.0)
                )
                publisher.put(payload, attachment=Attachment(k + 1, stamp, bytes(16)).encode())
                forged += 1
                time.sleep(1.0)
        finally:
            rogue.close()
        # the robot's odometry stops first: a sample the bridge is still turning into a state when
        # it is stopped would count as received and not published (one CI run: 1 of 128)
        c.procs["emulator"].stop()
        time.sleep(0.5)
        assert c.procs["bridge"].stop() == 0
        counters = c.procs["bridge"].summary()["counters"]
    dropped = counters["odom_received"] - counters["states_published"] - forged
    print(
        f"\nfigures: odometry stamped 1 h ahead, {forged} times in 6 s: {counters.get('rejected.odom', 0)} refused, "
        f"{dropped} real samples dropped of {counters['odom_received'] - forged}; states "
        f"{counters['states_published']}"
    )
    assert counters["rejected.odom"] == forged
    assert dropped == 0
    assert all(abs(s.state[0]) < 5 for s in watch.states)  # the forged pose (9, 9) never became a state


@pytest.mark.parametrize("second", ["plant-sim", "robot-bridge"])
def test_a_second_plant_for_one_robot_refuses_to_start(second: str) -> None:
    """Before: plant_sim and the emulated TurtleBot3 ran for one robot id and the actor followed
    one while driving the other blind. After: the second plant exits 2 with one clear line."""
    robot = "atk_p"
    with cluster(robot=robot) as c:
        c.start("plant", "plant-sim", "--mode", "realtime")
        c.wait_alive("plant")
        started = time.monotonic()
        proc = c.start("second", second)
        wait_until(lambda: proc.process.poll() is not None, 30, f"the second plant ({second}) to exit")
        took = time.monotonic() - started
        code = proc.process.returncode
        time.sleep(0.1)
        errors = [line for line in proc.stderr if "another plant" in line]
        assert c.alive("plant")  # the first one is untouched
    print(f"\nfigures: a second plant ({second}) for robot {robot}: exit {code} after {took:.1f} s: {errors[:1]}")
    assert code == 2
    assert len(errors) == 1 and "one plant per robot" in errors[0]


def test_two_plants_racing_past_the_start_check_leave_exactly_one() -> None:
    """Two plants that start at the same moment both pass the "another plant's
    token exists" check before either declares. Reproduced exactly here: two plant sessions both
    pass Bus.refuse_other_plant, then declare at once; the tie-break after declaring leaves one."""
    robot = "atk_r"
    with cluster(robot=robot) as c:
        buses = [Bus(zenoh.open(client_config(c.endpoint)), "plant") for _ in range(2)]
        try:
            for bus in buses:
                bus.refuse_other_plant(robot)  # neither sees the other yet: the race
            errors: list[str | None] = [None, None]

            def claim(i: int) -> None:
                try:
                    buses[i].declare_sole_plant(robot)
                except PlantConflictError as error:
                    errors[i] = str(error)

            threads = [threading.Thread(target=claim, args=(i,)) for i in range(2)]
            started = time.monotonic()
            for thread in threads:
                thread.start()
            for thread in threads:
                thread.join(timeout=10)
            took = time.monotonic() - started
            survivors = [i for i in range(2) if errors[i] is None]
            assert len(survivors) == 1, errors
            winner, loser = buses[survivors[0]], buses[1 - survivors[0]]
            assert winner.zid < loser.zid  # the deterministic rule: the smaller session id stays
            # the loser withdrew its identity: only the winner is alive for the robot
            wait_until(lambda: c.session is not None and _identities(c.session, robot) == [winner.zid], 5, "one id")
        finally:
            for bus in buses:
                bus.close()
    print(f"\nfigures: two plants declared at once: one yielded after {took:.2f} s: {errors}")
    message = next(e for e in errors if e is not None)
    assert "one plant per robot" in message and took < 3.0


def _identities(session: zenoh.Session, robot: str) -> list[str]:
    replies = session.liveliness().get(identity_pattern(robot, "plant"), timeout=1.0)
    return sorted(identity_of(str(r.ok.key_expr)) for r in replies if r.ok is not None)


@pytest.mark.parametrize("second", ["plant-sim", "robot-bridge"])
def test_two_plant_processes_started_at_once_leave_exactly_one(second: str) -> None:
    """compose starts plant_sim and robot_bridge at the same moment: exactly one keeps running,
    the other exits 2 with the one-line PlantConflictError (whichever check caught it)."""
    robot = "atk_s"
    with cluster(robot=robot) as c:
        procs = [c.start("first", "plant-sim", "--mode", "realtime"), c.start("second", second)]
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not any(p.process.poll() is not None for p in procs):
            time.sleep(0.05)
        time.sleep(1.0)  # the survivor stays up
        codes = [p.process.poll() for p in procs]
        assert c.session is not None
        alive = _identities(c.session, robot)
        lines = [line for p in procs for line in p.stderr if "another plant" in line]
    print(f"\nfigures: plant-sim and {second} started at once: exit codes {codes}, live plants {len(alive)}")
    assert sorted(codes, key=lambda code: code is None) == [2, None]  # one exited 2, one runs
    assert len(alive) == 1
    assert len(lines) == 1 and "one plant per robot" in lines[0]


def test_a_rogue_alive_actor_token_does_not_delay_the_stop() -> None:
    """A rogue ``alive/actor`` token must not hide the real actor's death (the robot would stop
    only by the bridge's watchdog): the bridge follows the actor session's identity token, so the
    robot stops when that session vanishes, whatever other actor token lingers."""
    robot = "atk_t"
    with cluster(robot=robot) as c:
        assert c.session is not None
        watch = RobotWatch(c.session, GRAPH, robot)
        rogue = _rogue(c.endpoint)
        try:
            token = rogue.liveliness().declare_token(liveliness_key(robot, "actor"))  # the rogue token, first
            c.start("emulator", "tb3-emulator", "--start=2,1.5")
            c.start("bridge", "robot-bridge")
            c.wait_alive("plant")
            actor = c.start("actor", "actor", "--mode", "realtime", "--agent", "mpc", "--run-seconds", "60")
            wait_until(lambda: abs(watch.applied()[0]) > 0.05, 120, "the actor to drive the robot")
            time.sleep(0.5)
            actor.stop(signal.SIGKILL)
            killed = time.monotonic()
            wait_until(lambda: watch.first_stop_after(killed) is not None, 5, "the robot to stop")
            stopped_after = watch.first_stop_after(killed) - killed  # type: ignore[operator]
            assert c.alive("actor")  # the rogue token is still there
            token.undeclare()
        finally:
            rogue.close()
        assert c.procs["bridge"].stop() == 0
        counters = c.procs["bridge"].summary()["counters"]
    print(
        f"\nfigures: actor kill -9 beside a rogue alive/actor token: robot stopped {stopped_after * 1e3:.0f} ms "
        f"after the kill (watchdog {TIMEOUT * 1e3:.0f} ms); actor_lost_stops {counters.get('actor_lost_stops', 0)}, "
        f"watchdog_stops {counters.get('watchdog_stops', 0)}"
    )
    assert counters["actor_lost_stops"] == 1 and counters.get("watchdog_stops", 0) == 0
    assert stopped_after < TIMEOUT  # not by the watchdog
