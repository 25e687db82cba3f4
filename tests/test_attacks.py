"""Valid but malicious states and weights against real processes, at the actor (docs/security.md).

Each test starts a router, a real-time plant_sim, a critic and an actor (real processes on a
free loopback port), lets a rogue client -- another Zenoh session on the same router, its
samples stamped with its own id like any client's -- run one attack of the issue's findings 1, 2,
6, 7 and 10 during the run, prints one ``figures:`` line and asserts that the attack no longer
works: the actor keeps following the real plant and the real critic.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import pytest
import zenoh

from common.config.settings import Settings
from common.contracts.keys import identity_key
from common.contracts.messages import Action, CriticWeights, MessageError, PlantState, ServiceStatus, Transition, decode
from tests.harness import Cluster, client_config, cluster, wait_until

pytestmark = [pytest.mark.slow, pytest.mark.integration]
DELTA = 0.1
OMEGA_MAX = Settings.load().plant.omega_max


def _source(sample: zenoh.Sample) -> str | None:
    return None if sample.timestamp is None else str(sample.timestamp.get_id())


@dataclass
class Watch:
    """What the test's own session sees of the run (arrival time, message), the rogue's excluded."""

    rogue: str
    transitions: list[tuple[float, Transition]] = field(default_factory=list)
    actions: list[tuple[float, Action]] = field(default_factory=list)
    states: list[PlantState] = field(default_factory=list)  # the real plant's
    weights: list[tuple[float, CriticWeights]] = field(default_factory=list)  # the real critic's
    status: list[tuple[float, dict[str, float]]] = field(default_factory=list)  # the actor's

    def subscribe(self, session: zenoh.Session, robot: str) -> list[zenoh.Subscriber]:
        def on(schema: type, sink: list, timed: bool, own_only: bool):  # type: ignore[no-untyped-def]
            def handler(sample: zenoh.Sample) -> None:
                if own_only and _source(sample) == self.rogue:
                    return
                try:
                    message = decode(schema, sample.payload.to_bytes())
                except MessageError:
                    return
                sink.append((time.monotonic(), message) if timed else message)

            return handler

        def on_status(sample: zenoh.Sample) -> None:
            self.status.append((time.monotonic(), decode(ServiceStatus, sample.payload.to_bytes()).counters))

        return [
            session.declare_subscriber(f"srl/{robot}/transition", on(Transition, self.transitions, True, True)),
            session.declare_subscriber(f"srl/{robot}/action", on(Action, self.actions, True, True)),
            session.declare_subscriber(f"srl/{robot}/state", on(PlantState, self.states, False, True)),
            session.declare_subscriber(f"srl/{robot}/critic/weights", on(CriticWeights, self.weights, True, True)),
            session.declare_subscriber(f"srl/{robot}/status/actor", on_status),
        ]

    def episode(self) -> int:
        return self.transitions[-1][1].episode

    def transitions_after(self, moment: float) -> list[Transition]:
        return [t for at, t in self.transitions if at > moment]


@contextmanager
def attack_run(robot: str, seconds: float) -> Iterator[tuple[Cluster, zenoh.Session, Watch]]:
    """Router, real-time plant_sim, critic and an actor for ``seconds``, commanding already; a
    rogue client session; the test's watch. The actor is left running (wait for it in the test)."""
    with cluster(robot=robot) as c:
        assert c.session is not None
        c.start_plant_and_critic()
        rogue = zenoh.open(client_config(c.endpoint))  # timestamping on: its samples carry ITS id
        try:
            watch = Watch(str(rogue.info.zid()))
            subscribers = watch.subscribe(c.session, robot)
            c.start("actor", "actor", "--mode", "realtime", "--run-seconds", str(seconds))
            wait_until(lambda: len(watch.transitions) >= 10, 60, "the actor's first transitions")
            yield c, rogue, watch
        finally:
            rogue.close()
            for subscriber in locals().get("subscribers", []):
                subscriber.undeclare()


def _finish(c: Cluster) -> dict:  # type: ignore[type-arg]
    actor = c.procs["actor"]
    assert actor.process.wait(timeout=60) == 0, actor.stderr[-10:]
    return actor.summary()


def test_one_far_future_plant_state_locks_nothing_out() -> None:
    """Before: one PlantState(episode=0, seq=2**62) made the actor refuse every real state (176
    stale-state stops in 17 s, only zero commands). After: it is refused as foreign and the actor
    keeps computing actions from the real plant."""
    robot = "atk_s"
    with attack_run(robot, 8) as (c, rogue, watch):
        real_seq = watch.states[-1].seq
        rogue.put(
            f"srl/{robot}/state",
            PlantState(
                robot=robot, episode=0, seq=2**62, stamp_ns=time.monotonic_ns(), state=(0.5, 0.5, 0.0), source="sim"
            ).encode(),
        )
        attacked = time.monotonic()
        summary = _finish(c)
    after = watch.transitions_after(attacked)
    commanded = [a for at, a in watch.actions if at > attacked and a.state_seq >= 0]
    counters = summary["counters"]
    print(
        f"\nfigures: one PlantState(seq=2**62) from another session: {counters.get('rejected.state.foreign', 0)} "
        f"refused as foreign; {len(after)} transitions and {len(commanded)} commands from real states after it "
        f"(real seq was {real_seq}); stale-state stops {summary['stale_state_stops']} in {summary['steps']} steps"
    )
    assert counters.get("rejected.state.foreign", 0) == 1
    assert counters.get("rejected.state", 0) == 0  # no real state refused after it
    assert summary["stale_state_stops"] < 5
    assert len(commanded) >= 0.8 * len(after) > 0
    assert all(max(abs(c_) for c_ in t.state) < 10 for t in after)  # the forged (0.5, 0.5) never followed...
    assert not any(t.state == (0.5, 0.5, 0.0) for t in after)
    assert summary["final_state"] != [0.5, 0.5, 0.0]


def test_critic_weights_from_the_future_lock_out_no_real_update() -> None:
    """Before: weights with a version 59 s ahead were accepted and every real update refused for
    59 s (150 in 15 s). After: they are refused (another session) and the real critic's updates
    keep being taken."""
    robot = "atk_w"
    with attack_run(robot, 8) as (c, rogue, watch):
        wait_until(lambda: bool(watch.status), 10, "the actor's status")
        accepted_before = watch.status[-1][1].get("weights_accepted", 0.0)
        forged: list[int] = []
        attacked = time.monotonic()
        for _ in range(3):  # resent each second, as the attacker kept it going
            version = time.time_ns() // 1000 + 59_000_000
            forged.append(version)
            rogue.put(
                f"srl/{robot}/critic/weights",
                CriticWeights(
                    robot=robot,
                    episode=watch.episode(),
                    version=version,
                    trained_step=watch.transitions[-1][1].step,
                    q_weights=(1.0,) * 15,
                    v_weights=(1.0,) * 6,
                    q_residual=0.0,
                    v_residual=0.0,
                    pairs=1,
                ).encode(),
            )
            time.sleep(1.0)
        summary = _finish(c)
    counters = summary["counters"]
    accepted_after = counters.get("weights_accepted", 0) - accepted_before
    versions_after = [s.get("weights_version") for at, s in watch.status if at > attacked]
    real = {w.version for _, w in watch.weights}
    real_after = [w.version for at, w in watch.weights if at > attacked]
    print(
        f"\nfigures: CriticWeights 59 s ahead, {len(forged)} times from another session: "
        f"{counters.get('rejected.critic/weights', 0)} refused; {accepted_after:.0f} real updates accepted after "
        f"the first (of {len(real_after)} the real critic published); final weights_version "
        f"{summary['weights_version']} (the real critic's: {summary['weights_version'] in real})"
    )
    assert counters.get("rejected.critic/weights", 0) >= len(forged)
    assert accepted_after >= 10  # the real critic publishes after every transition it fits
    assert summary["weights_version"] in real and summary["weights_version"] >= max(real_after)
    assert summary["weights_version"] not in forged
    assert not any(v in forged for v in versions_after)
    assert summary["staleness_steps"]["median"] <= 2


def test_weights_outside_the_box_do_not_spin_the_robot() -> None:
    """Before: -100 weights made the robot spin at full speed (|omega| = 2.84 on 70/70 ticks);
    1e300 weights: 69 solver failures in 7 s. After: refused (another session; and outside the
    box, from any session -- tests/test_provenance.py) and the robot does not spin."""
    robot = "atk_b"
    with attack_run(robot, 9) as (c, rogue, watch):
        sent = 0
        attacked = time.monotonic()
        while time.monotonic() < attacked + 5.0:  # every 0.1 s for 5 s, alternating -100 and 1e300
            value = -100.0 if sent % 2 == 0 else 1e300
            rogue.put(
                f"srl/{robot}/critic/weights",
                CriticWeights(
                    robot=robot,
                    episode=watch.episode(),
                    version=time.time_ns() // 1000,
                    trained_step=watch.transitions[-1][1].step,
                    q_weights=(value,) * 15,
                    v_weights=(value,) * 6,
                    q_residual=0.0,
                    v_residual=0.0,
                    pairs=1,
                ).encode(),
            )
            sent += 1
            time.sleep(DELTA)
        summary = _finish(c)
    after = [t for t in watch.transitions_after(attacked + 0.2)]
    spinning = sum(abs(t.action[1]) >= 0.99 * OMEGA_MAX for t in after)
    counters = summary["counters"]
    print(
        f"\nfigures: weights -100 / 1e300 from another session, {sent} times in 5 s: "
        f"{counters.get('rejected.critic/weights', 0)} refused; |omega| saturated on {spinning} of {len(after)} "
        f"transitions after the attack began; solver failures {summary['solver_failures']}"
    )
    assert counters.get("rejected.critic/weights", 0) >= sent
    assert len(after) >= 40
    assert spinning <= 0.25 * len(after)
    assert summary["solver_failures"] == 0


def test_forged_states_just_before_each_tick_are_not_followed() -> None:
    """Before: forged states timed just before each tick were followed (62/78 actions computed
    from the fake state). After: a forged state every 5 ms for 5 s (so one within 5 ms before
    every tick), numbered just past the real plant's, is never followed."""
    robot = "atk_f"
    fake = (1.5, -1.5, 0.3)
    with attack_run(robot, 9) as (c, rogue, watch):
        publisher = rogue.declare_publisher(f"srl/{robot}/state")
        sent = 0
        attacked = time.monotonic()
        while time.monotonic() < attacked + 5.0:
            real = watch.states[-1]
            publisher.put(
                PlantState(
                    robot=robot,
                    episode=real.episode,
                    seq=real.seq + 1,
                    stamp_ns=time.monotonic_ns(),
                    state=fake,
                    source="sim",
                ).encode()
            )
            sent += 1
            time.sleep(0.005)
        ended = time.monotonic()
        publisher.undeclare()
        summary = _finish(c)
    during = [t for at, t in watch.transitions if attacked < at <= ended]
    followed = sum(t.state == fake for _, t in watch.transitions)
    counters = summary["counters"]
    print(
        f"\nfigures: forged states every 5 ms for 5 s ({sent} sent, seq one past the real plant's): "
        f"{followed} of {len(during)} transitions during the attack carry the forged state; "
        f"{counters.get('rejected.state.foreign', 0)} refused as foreign; stale-state stops "
        f"{summary['stale_state_stops']}"
    )
    assert followed == 0
    assert len(during) >= 40
    assert counters.get("rejected.state.foreign", 0) >= 0.95 * sent  # a few may still be in flight at the end
    assert summary["stale_state_stops"] < 5


def test_a_second_plant_session_stops_the_actor_until_it_is_gone() -> None:
    """Before: with two plants for one robot the actor followed one and drove the other blind.
    After: while two plant identities are live the actor commands zero (and counts it); it
    resumes once the second one's token is gone."""
    robot = "atk_2"
    with attack_run(robot, 9) as (c, rogue, watch):
        token = rogue.liveliness().declare_token(identity_key(robot, "plant", str(rogue.info.zid())))
        declared = time.monotonic()
        publisher = rogue.declare_publisher(f"srl/{robot}/state")
        seq = 0
        while time.monotonic() < declared + 2.5:  # a second plant: its own states at 50 Hz
            publisher.put(
                PlantState(
                    robot=robot, episode=1, seq=seq, stamp_ns=time.monotonic_ns(), state=(-1.0, 1.0, 0.0), source="sim"
                ).encode()
            )
            seq += 1
            time.sleep(0.02)
        token.undeclare()
        undeclared = time.monotonic()
        publisher.undeclare()
        wait_until(
            lambda: any(at > undeclared and a.state_seq >= 0 for at, a in watch.actions),
            10,
            "commands from the real plant again",
        )
        summary = _finish(c)
    # the token reaches the actor within ms; allow one tick in flight on either side
    during = [a for at, a in watch.actions if declared + DELTA < at < undeclared]
    moving = [a for a in during if a.action != (0.0, 0.0)]
    resumed = next(at for at, a in watch.actions if at > undeclared and a.state_seq >= 0)
    counters = summary["counters"]
    print(
        f"\nfigures: a second plant session for {undeclared - declared:.1f} s: {len(moving)} of {len(during)} "
        f"commands non-zero meanwhile; plant_conflict_stops {summary['plant_conflict_stops']}, "
        f"{counters.get('rejected.state.conflict', 0)} states refused in conflict; commanding again "
        f"{1e3 * (resumed - undeclared):.0f} ms after the second one left"
    )
    assert summary["plant_conflict_stops"] >= 15
    assert len(during) >= 15 and not moving
    assert counters.get("plant_conflicts", 0) >= 1
    assert resumed - undeclared < 1.0
    assert summary["plant_sources"] and len(summary["plant_sources"]) == 1
