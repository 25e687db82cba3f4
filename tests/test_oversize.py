"""Oversized messages are refused at the link and leave no memory behind (docs/security.md#limits).

Zenoh bounds a reassembled message (``transport.max_message_bytes``); its shared memory, on by
default, would carry a large put between processes of one host past that bound, so every session
and router srl builds turns it off (``transport.shared_memory``). The live test floods a running
router, plant, critic and actor with 10 MB puts from an intruder whose session keeps Zenoh's
defaults, and reads each process's resident memory before and after.
"""

from __future__ import annotations

import json
import re
import time

import pytest
import zenoh

from common.config.settings import Settings
from common.net.transport import plain_config, zenoh_config
from services.robot_bridge.robot_router import robot_client_config, robot_router_config
from tests.harness import wait_until
from tests.test_attacks import attack_run
from tests.test_safety import rss_mb

ROBOT = "ov"
PUTS = 50
PUT_BYTES = 10_000_000
# Each process may grow by this much [MB] during the flood and its settling: a service's own
# growth over those seconds plus Zenoh's buffers on the link (the router reassembles up to
# max_message_bytes per channel before it drops a message). A put that got through costs each
# process at least its 10 MB, retained by the allocator (about +29 MB per service and +22 MB for
# the router with shared memory on).
GROWTH_MB = 6.0


def test_every_config_srl_builds_bounds_messages_and_keeps_shared_memory_off() -> None:
    settings = Settings.load()
    transport = settings.transport
    bridge = settings.bridge.model_copy(update={"robot_endpoint": "tcp/127.0.0.1:7448"})
    assert transport.shared_memory is False
    configs = {
        "client": zenoh_config(transport),
        "router": zenoh_config(transport, router=True),
        "robot link": plain_config(transport, "tcp/127.0.0.1:7448"),
        "robot bridge at the robot": robot_client_config(bridge, transport, login=False),
        "emulated robot's router": robot_router_config(settings, "tcp/127.0.0.1:7448"),
    }
    for name, config in configs.items():
        assert json.loads(config.get_json("transport/shared_memory/enabled")) is False, name
        assert json.loads(config.get_json("transport/link/rx/max_message_size")) == transport.max_message_bytes, name
    on = zenoh_config(transport.model_copy(update={"shared_memory": True}))
    assert json.loads(on.get_json("transport/shared_memory/enabled")) is True


def _intruder(endpoint: str) -> zenoh.Session:
    """A client of srl's router with Zenoh's defaults: shared memory on, no size bound of its own."""
    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    config.insert_json5("transport/shared_memory/enabled", "true")
    return zenoh.open(config)


@pytest.mark.integration
@pytest.mark.slow
def test_fifty_10_mb_puts_leave_no_memory_behind_and_a_small_bad_one_is_refused_in_one_line() -> None:
    with attack_run(ROBOT, 60) as (c, _, watch):
        intruder = _intruder(c.endpoint)
        try:
            pids = {name: c.procs[name].process.pid for name in ("router", "plant", "critic", "actor")}
            before = {name: rss_mb(pid) for name, pid in pids.items()}
            keys = ["state", "transition", "critic/weights", "action"]  # what the actor, critic and plant read
            for i in range(PUTS):
                intruder.put(f"srl/{ROBOT}/{keys[i % len(keys)]}", b"x" * PUT_BYTES)
            time.sleep(2.0)  # what got through is decoded (and refused) by now
            growth = {name: rss_mb(pid) - before[name] for name, pid in pids.items()}
            mark = time.monotonic()
            wait_until(lambda: len(watch.transitions_after(mark)) >= 5, 5, "the actor's transitions after the flood")
            intruder.put(f"srl/{ROBOT}/state", b'{"robot": "ov", "state": [0, 0,')  # small and malformed
            refusal = re.compile(r"actor: rejected state: PlantState: .*\(total 1\)$")
            wait_until(lambda: any(refusal.search(line) for line in c.procs["actor"].stderr), 5, "the refusal")
        finally:
            intruder.close()
        alive = {name: c.procs[name].process.poll() is None for name in pids}
        assert c.procs["actor"].stop() == 0, c.procs["actor"].stderr[-10:]
        counters = c.procs["actor"].summary()["counters"]
    print(
        f"\nfigures: {PUTS} puts of {PUT_BYTES / 1e6:.0f} MB: RSS growth [MB] "
        + ", ".join(f"{name} {mb:+.1f}" for name, mb in growth.items())
        + f"; actor rejected.state {counters.get('rejected.state', 0)}"
    )
    assert alive == dict.fromkeys(pids, True)
    assert all(mb < GROWTH_MB for mb in growth.values()), growth
    assert counters.get("rejected.state", 0) == 1  # only the small one reached the decoder
    assert counters.get("rejected.critic/weights", 0) == 0
