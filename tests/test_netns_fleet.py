"""A fleet across hosts: one router per host, the routers linked, robots on two hosts, the critic on a third.

Three network namespaces on a bridge (:mod:`tests.netns`), laid out as docs/fleets.md tells
a user to (rmw_zenoh's multi-robot way: one router per host, services connect to their own host's
router on loopback, routers connect to each other):

* host ``a``: its router (``srl router --router tcp/0.0.0.0:7447 --connect tcp/<c>:7447``), a
  plant host for robots a1..a3 and an actor host for them;
* host ``d``: the same for robots d1..d3;
* host ``c``: its router (the other two connect to it), the critic of all six robots, and an
  observer (:mod:`tests.netns_tools` ``observe-fleet``) that sees what crosses the links.

Invariants, under a 4 s partition of host ``a`` (every packet of its link dropped where it is
received: shorter than Zenoh's 10 s session lease, so the router link survives):

* every robot's actions come from its own host's actor host (the sending session's id is the
  id in that host's actor identity token), and its processes talk to other hosts only through
  their router: the only TCP connection that leaves host ``a`` is its router's to ``c``'s;
* every robot gets weights from the critic across the router link, their staleness bounded;
* during the partition the robots of ``a`` keep their deadlines on their last weights (no
  weights reach them, their staleness grows and is reported), the robots of ``d`` go on getting
  fresh weights; after it, the critic fits what ``a``'s robots sent during the cut, their actors
  hold newer weights whose staleness is back within the bound (a fit on a transition recovered
  late is labelled with the newest step it was trained on, never an older one) and stays there;
* every transition of every robot reaches the critic (its replay is each actor's record), and
  every robot approaches the target (from a 1.5 m circle).

Needs root, ``ip`` (iproute2) and ``iptables`` (marker ``needs_root``); ``pytest -s`` shows the figures.
"""

from __future__ import annotations

import itertools
import math
import os
import sys
import time
from typing import Any

import pytest

from tests.netns import NsProc, Topology, wait_for

PORT = 7447  # each host's router (the namespaces are private: a fixed port cannot collide)
HOSTS = {"a": ["a1", "a2", "a3"], "d": ["d1", "d2", "d3"]}  # robot hosts and their robots
ROBOTS = [robot for robots in HOSTS.values() for robot in robots]
CIRCLE_M = 1.5  # where the plant hosts start their robots (srl plant-sim's default --circle)
RUN_S = 30.0  # each actor host's run
PARTITION_S = 4.0
START_TIMEOUT_S = 120.0  # two actor hosts JIT-compile at once on a loaded 2-core machine
CATCH_UP_S = 20.0
STALENESS_BOUND_STEPS = 10  # a robot that is not cut off: weights never older than 1 s
MISSED_ALLOWED = int(0.01 * RUN_S / 0.1)  # ticks per robot (see the assertion)
APPROACHED_M = 0.5  # from 1.5 m: every robot ends at most this far from the target

pytestmark = [pytest.mark.slow, pytest.mark.needs_root, pytest.mark.integration, pytest.mark.timing]


class Fleet:
    """The three hosts' routers, services and the observer (next to the critic)."""

    def __init__(self, topo: Topology) -> None:
        self.topo = topo
        self.routers = {"c": self.router("c")}
        for host in HOSTS:
            self.routers[host] = self.router(host, f"tcp/{topo.hosts['c'].ip}:{PORT}")
        for router in self.routers.values():
            router.wait_output("router listening", START_TIMEOUT_S)
        self.observer = topo.python("c", "observer", "tests.netns_tools", "observe-fleet", "--router", local())
        self.observer.wait_record(lambda r: r.get("kind") == "ready", START_TIMEOUT_S, "observer ready")
        # services need no --router: the default is their own host's router on loopback
        no_checkpoint = {"SRL_CRITIC__CHECKPOINT": ""}
        self.critic = topo.spawn("c", "critic", srl("critic", f"--robots={','.join(ROBOTS)}"), env=no_checkpoint)
        self.plants = {
            host: topo.spawn(host, f"plant-{host}", srl("plant-sim", f"--robots={','.join(robots)}"))
            for host, robots in HOSTS.items()
        }
        self.actors: dict[str, NsProc] = {}
        self.wait_alive("plant", ROBOTS)
        self.wait_alive("critic", ROBOTS)

    def router(self, host: str, *connect: str) -> NsProc:
        argv = srl("router", f"--router=tcp/0.0.0.0:{PORT}", *(f"--connect={endpoint}" for endpoint in connect))
        # off loopback without login and TLS: the namespaces are the private network (docs/security.md)
        return self.topo.spawn(host, f"router-{host}", argv, env={"SRL_TRANSPORT__ALLOW_INSECURE_NETWORK": "true"})

    def start_actors(self) -> None:
        for host, robots in HOSTS.items():
            self.actors[host] = self.topo.spawn(
                host, f"actor-{host}", srl("actor", f"--robots={','.join(robots)}", "--run-seconds", str(RUN_S))
            )
        self.wait_alive("actor", ROBOTS)

    # -- what the observer saw -----------------------------------------------------------
    def records(self, kind: str) -> list[dict[str, Any]]:
        return [r for r in list(self.observer.records) if r.get("kind") == kind]

    def alive(self, service: str) -> set[str]:
        """Robots whose ``service`` token the observer holds (newest change: alive)."""
        newest: dict[str, bool] = {}
        for r in self.records("alive"):
            if r["service"] == service and r["zid"] is None:
                newest[r["robot"]] = r["alive"]
        return {robot for robot, alive in newest.items() if alive}

    def wait_alive(self, service: str, robots: list[str]) -> None:
        procs = [self.critic, *self.plants.values(), *self.actors.values(), *self.routers.values()]

        def ready() -> bool:
            for proc in procs:
                if not proc.running():
                    raise AssertionError(f"{proc.name} exited {proc.process.returncode}: {proc.stderr[-10:]}")
            return set(robots) <= self.alive(service)

        wait_for(ready, START_TIMEOUT_S, f"{service} of {robots} alive at the critic's host")

    def identities(self, service: str) -> dict[str, set[str]]:
        """Each robot's ``service`` sessions, by their identity tokens' Zenoh ids."""
        found: dict[str, set[str]] = {}
        for r in self.records("alive"):
            if r["service"] == service and r["zid"] is not None and r["alive"]:
                found.setdefault(r["robot"], set()).add(r["zid"])
        return found

    def weights(self, robot: str, after: float = -math.inf, before: float = math.inf) -> list[dict[str, Any]]:
        return [w for w in self.records("weights") if w["robot"] == robot and after < w["t"] < before]

    def critic_holds(self) -> int:
        statuses = [r for r in self.records("status") if r["service"] == "critic"]
        if not statuses:
            return 0
        c = statuses[-1]["counters"]
        return int(c.get("transitions_received", 0) - c.get("duplicates", 0) - c.get("too_old", 0))


def local() -> str:
    return f"tcp/127.0.0.1:{PORT}"


def srl(command: str, *args: str) -> list[str]:
    return [sys.executable, "-m", "tools.cli", command, *args]


def steps_of(runs: list[list[int]]) -> int:
    return sum(last - first + 1 for first, last in runs)


def strictly_increasing(values: list[int]) -> bool:
    return all(b > a for a, b in itertools.pairwise(values))


# six robots on three hosts keep their deadlines on the two cores only without another test's
# processes beside them (one CI run beside the status-line test: 2-4 missed per robot at load 4.3)
@pytest.mark.alone
def test_fleet_across_three_hosts_with_linked_routers_survives_a_partition() -> None:
    load_before = "/".join(f"{x:.1f}" for x in os.getloadavg())
    with Topology(roles=("a", "d", "c")) as topo:
        fleet = Fleet(topo)
        fleet.start_actors()
        started = time.monotonic()
        # every robot learns across the link before the fault
        wait_for(
            lambda: all(any(w["trained_step"] >= 20 for w in fleet.weights(r)) for r in ROBOTS),
            40,
            "weights trained on 20 steps for every robot",
        )
        leaving_a = topo.tcp_peers("a")  # remote ends of a's established connections
        version_at_cut = {r: max(w["version"] for w in fleet.weights(r)) for r in HOSTS["a"]}
        topo.cut("a", "drop")
        cut = time.monotonic()
        time.sleep(PARTITION_S)  # the fault itself
        dropped = topo.restore("a", "drop")
        restored = time.monotonic()
        # a's actors went on stepping (10 a second) and publishing transitions during the cut; the
        # critic gets them once the link is back and fits them: each of a's actors then holds
        # weights newer than at the cut, fresh within the bound again by its own count (which
        # knows that a robot at rest waits for no fit: weights "trained on the live edge" never
        # come for a robot that came to rest before it), as its status across the link says
        back = {
            r: fleet.observer.wait_record(
                lambda s, r=r: (
                    s.get("kind") == "status"
                    and s["service"] == "actor"
                    and s["robot"] == r
                    and s["t"] > restored
                    and s["counters"].get("weights_version", -1) > version_at_cut[r]
                    and s["counters"].get("staleness_steps", math.inf) <= STALENESS_BOUND_STEPS
                ),
                CATCH_UP_S,
                f"{r}'s actor holding fresh weights again after the partition",
            )
            for r in HOSTS["a"]
        }
        summaries: dict[str, dict[str, Any]] = {}
        accepted = {}  # weights accepted by each actor host (its counter for all its robots)
        for host, actor in fleet.actors.items():
            assert actor.wait(RUN_S + 60) == 0, actor.stderr[-10:]
            summaries.update(actor.summary()["per_robot"])
            accepted[host] = actor.summary()["counters"].get("weights_accepted", 0)
        ended = time.monotonic()
        total = sum(steps_of(summaries[r]["transition_steps"]) for r in ROBOTS)
        caught_up = wait_for(
            lambda: fleet.critic_holds() >= total, CATCH_UP_S, f"all {total} transitions at the critic"
        )
        actor_ids = fleet.identities("actor")
        assert fleet.critic.stop() == 0, fleet.critic.stderr[-10:]
        critic = fleet.critic.summary()
        exit_codes = topo.stop_all()
        observed = fleet.observer.summary()
        weights_during = {r: fleet.weights(r, cut + 0.5, restored) for r in ROBOTS}
        weights_all = {r: fleet.weights(r) for r in ROBOTS}
        # each actor's own 1 Hz status, as seen across the link: the last one before its run ended
        last_status = {
            r: [s for s in fleet.records("status") if s["service"] == "actor" and s["robot"] == r][-1]["counters"]
            for r in ROBOTS
        }
        ran = time.monotonic() - started

    rows = []
    for r in ROBOTS:
        s = summaries[r]
        distance = s["truth"]["final_distance"] if s["truth"] else math.hypot(*s["final_state"][:2])
        rows.append(
            f"| {r} | {s['steps']} | {s['loop']['missed_deadlines']} | {s['staleness_steps']['p99']:.0f}/"
            f"{s['staleness_steps']['max']:.0f} | {len(weights_during[r])} | {len(weights_all[r])} | {distance:.3f} |"
        )
    print(
        f"\n**Fleet across 3 hosts, host a partitioned {restored - cut:.1f} s ({dropped.dropped} packets dropped)**; "
        f"a's actors fresh again after "
        + ", ".join(f"{r} {back[r]['t'] - restored:.2f} s" for r in HOSTS["a"])
        + f"; all {total} transitions at the critic {caught_up:.1f} s after the actors' end; {ran:.0f} s run "
        f"(cut at {cut - started:.1f} s, restored at {restored - started:.1f} s, "
        f"actors ended at {ended - started:.1f} s); "
        f"load average before {load_before}\n\n"
        "| robot | steps | missed | staleness p99/max | weights during cut | weights | final distance m |\n"
        "|---|---|---|---|---|---|---|\n" + "\n".join(rows)
    )

    assert set(exit_codes.values()) == {0}, exit_codes
    # a's hosts talk across the network only through their router's link to c's
    assert leaving_a, "host a has no established connection"
    c_router = f"{topo.hosts['c'].ip}:{PORT}"
    assert all(peer.startswith("127.0.0.1:") or peer == c_router for peer in leaving_a), leaving_a
    assert c_router in leaving_a
    # every robot's actions were sent by its own host's actor host: one session per robot host
    sources = observed["action_sources"]
    for host, robots in HOSTS.items():
        host_ids = set().union(*(actor_ids.get(r, set()) for r in robots))
        assert len(host_ids) == 1, f"host {host}'s robots have actor sessions {host_ids}"
        for r in robots:
            assert set(sources.get(r, {})) == host_ids, (r, sources.get(r), host_ids)
            assert sources[r][next(iter(host_ids))] >= 0.5 * summaries[r]["steps"]
    assert actor_ids["a1"] != actor_ids["d1"]
    assert all(accepted[host] >= len(robots) for host, robots in HOSTS.items()), accepted
    for r in ROBOTS:
        s = summaries[r]
        # deadlines kept by every robot, the cut ones included (their plant and actor are local):
        # an actor that waited on the cut link would miss 40 ticks; up to 1 % is the machine's own
        # hiccups (seen once: 1 tick 18 ms late at load average 11.7 on 2 cores)
        assert s["loop"]["missed_deadlines"] <= MISSED_ALLOWED, (r, s["loop"])
        assert s["steps"] >= 0.8 * RUN_S / 0.1, (r, s["steps"])
        # weights came across the router link, versions only grew
        versions = [w["version"] for w in weights_all[r]]
        # held the critic's, not its initial: in the critic's range (the observer is a subscriber
        # like any other and may lose one of the critic's samples under load, so its list is not
        # the judge; seen once at load 5.4: the held version missing from it)
        assert versions[0] <= s["weights_version"] <= critic["last_version"], (r, s["weights_version"], versions[0])
        assert strictly_increasing(versions), r
        # nothing lost: the critic holds every transition the actor published, its replay the actor's tail
        assert critic["seen_steps"][r] == s["transition_steps"], r
        assert critic["replay"][r] == s["transitions_tail"], r
        # every robot approached the target from the 1.5 m circle
        assert s["truth"] is not None and abs(math.hypot(*s["truth"]["start_state"][:2]) - CIRCLE_M) < 0.05, r
        distance = s["truth"]["final_distance"] if s["truth"] else math.hypot(*s["final_state"][:2])
        assert distance <= APPROACHED_M, (r, distance)
    for r in HOSTS["d"]:  # not cut off: fresh weights all along
        assert summaries[r]["staleness_steps"]["max"] <= STALENESS_BOUND_STEPS, (r, summaries[r]["staleness_steps"])
        assert len(weights_during[r]) >= 0.5 * PARTITION_S / 0.1, (r, len(weights_during[r]))
    for r in HOSTS["a"]:  # cut off: ran on their last weights, the staleness grew and was reported
        assert not weights_during[r], (r, weights_during[r][:3])
        assert summaries[r]["staleness_steps"]["max"] >= 0.8 * PARTITION_S / 0.1, (r, summaries[r]["staleness_steps"])
        # and caught up: at the end its weights were as fresh as the others'
        assert last_status[r]["staleness_steps"] <= STALENESS_BOUND_STEPS, (r, last_status[r])
