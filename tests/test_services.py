"""Process-level tests: the real services on free loopback ports (multicast scouting off)."""

from __future__ import annotations

import itertools
import json
import math
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import zenoh

from common.config.assembly import run_episode
from common.config.settings import Settings
from common.contracts.keys import TRANSITION_BATCH
from common.contracts.messages import Action, CriticWeights, ServiceStatus
from tests.harness import ROOT, Proc, cluster, free_port, srl, wait_until

pytestmark = [pytest.mark.slow, pytest.mark.integration]


def _run_cli(*argv: str, timeout: float = 240) -> subprocess.CompletedProcess[str]:
    return srl(*argv, timeout=timeout)


@pytest.mark.parametrize("agent", ["rlqv", "rlq"])
def test_lockstep_through_zenoh_equals_inproc(agent: str) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    done = _run_cli(
        "run",
        "--transport",
        "zenoh",
        "--router",
        endpoint,
        "--robot",
        "lock",
        "--agent",
        agent,
        "--start=-1.5,1",
        "--duration",
        "4",
        "--json",
        "--trajectory",
    )
    assert done.returncode == 0, done.stderr[-2000:]
    distributed = json.loads(done.stdout.strip().splitlines()[-1])
    local = run_episode(Settings.load(actor={"agent": agent}, episode={"start": (-1.5, 1.0), "duration": 4}))

    assert distributed["steps"] == local.steps == 40
    assert math.isclose(distributed["accumulated_cost"], local.accumulated_cost, rel_tol=1e-9)
    np.testing.assert_allclose(np.array(distributed["trajectory"]), np.array(local.states), rtol=1e-9, atol=1e-12)
    # the synchronous critic delivered the weights of every previous step in time
    assert distributed["critic_timeouts"] == 0
    assert distributed["staleness_steps"]["max"] == 0
    assert distributed["critic"]["transitions_received"] == 40
    assert all(code == 0 for code in distributed["exit_codes"].values())


@pytest.mark.timing
def test_realtime_up_every_service_a_process() -> None:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    up = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "tools.cli",
            "up",
            "--router",
            endpoint,
            "--robot",
            "rt",
            "--agent",
            "rlqv",
            "--duration",
            "10",
            "--json",
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    versions: list[int] = []
    actions: list[tuple[float, float]] = []
    session = None
    try:
        config = zenoh.Config()
        config.insert_json5("mode", '"client"')
        config.insert_json5("scouting/multicast/enabled", "false")
        config.insert_json5("connect/endpoints", json.dumps([endpoint]))

        def connected() -> bool:
            nonlocal session
            try:
                session = zenoh.open(config)
            except zenoh.ZError:
                return False
            return True

        wait_until(connected, 60, "the router of srl up")
        assert session is not None
        session.declare_subscriber(
            "srl/rt/critic/weights",
            lambda s: versions.append(CriticWeights.model_validate_json(s.payload.to_bytes()).version),
        )
        session.declare_subscriber(
            "srl/rt/action", lambda s: actions.append(Action.model_validate_json(s.payload.to_bytes()).action)
        )
        out, err = up.communicate(timeout=180)
    finally:
        if session is not None:
            session.close()
        if up.poll() is None:
            up.kill()
    assert up.returncode == 0, err[-2000:]
    summary = json.loads(out.strip().splitlines()[-1])
    assert set(summary["services"]) == {"router", "plant", "critic", "actor"}
    assert summary["steps"] >= 90
    assert summary["loop"]["missed_deadlines"] == 0
    assert summary["critic"]["transitions_received"] == summary["steps"]
    assert summary["weights_version"] > 0
    assert len(versions) >= 80 and all(b > a for a, b in itertools.pairwise(versions))
    assert summary["weights_version"] in versions
    assert actions and all(abs(v) <= 0.22 and abs(w) <= 2.84 for v, w in actions)
    assert all(math.isfinite(v) and math.isfinite(w) for v, w in actions)


@pytest.mark.timing
def test_actor_keeps_its_loop_without_critic_and_resumes_with_new_weights() -> None:
    with cluster(robot="ck") as c:
        c.start_plant_and_critic()
        actor = c.start("actor", "actor", "--mode", "realtime", "--run-seconds", "9")
        weights: list[int] = []
        action_times: list[float] = []
        accepted: list[float] = []
        assert c.session is not None
        c.session.declare_subscriber(
            "srl/ck/critic/weights",
            lambda s: weights.append(CriticWeights.model_validate_json(s.payload.to_bytes()).version),
        )
        c.session.declare_subscriber("srl/ck/action", lambda s: action_times.append(time.monotonic()))
        c.session.declare_subscriber(
            "srl/ck/status/actor",
            lambda s: accepted.append(
                ServiceStatus.model_validate_json(s.payload.to_bytes()).counters.get("weights_version", 0)
            ),
        )
        c.wait_alive("actor")
        wait_until(lambda: len(weights) >= 5, 30, "first weights")

        c.procs["critic"].stop(signal.SIGKILL)
        killed_at = time.monotonic()
        last_version_before = max(weights)
        wait_until(lambda: time.monotonic() - killed_at > 2.0, 5, "two seconds without critic")
        during = [t for t in action_times if killed_at < t <= killed_at + 2.0]
        assert len(during) >= 15, f"actor published only {len(during)} actions in 2 s without the critic"

        c.start("critic", "critic")
        c.wait_alive("critic")
        wait_until(lambda: any(v > last_version_before for v in weights), 30, "weights from the new critic")
        new_version = max(weights)
        wait_until(
            lambda: any(a >= new_version for a in accepted) or actor.process.poll() is not None,
            15,
            "the actor using the new critic's weights",
        )
        assert actor.process.wait(timeout=30) == 0, actor.stderr[-10:]
        summary = actor.summary()
        assert summary["loop"]["missed_deadlines"] == 0
        assert summary["weights_version"] > last_version_before
        assert summary["staleness_steps"]["max"] >= 10  # the outage was seen and reported


GARBAGE = [
    b"",
    b"\x00\xff\x10garbage",
    b"{",
    b"[]",
    b'{"schema_version": 2}',
    b"null",
    b"x" * 70_000,
]


def _state(**kw: object) -> bytes:
    base = {
        "schema_version": 1,
        "robot": "fz",
        "episode": 0,
        "seq": 1,
        "stamp_ns": 1,
        "state": [0.0, 0.0, 0.0],
        "source": "sim",
    }
    base.update(kw)
    return json.dumps(base).replace('"NaN"', "NaN").encode()


BAD_BY_KEY = {
    "state": [
        _state(state=[float("nan"), 0, 0]),
        _state(state=[0, 0]),
        _state(schema_version=9),
        _state(seq=-1),
        _state(extra=1),
    ],
    "action": [
        b'{"schema_version":1,"robot":"fz","episode":0,"step":0,"stamp_ns":0,"action":[NaN,0],"state_seq":0}',
        b'{"schema_version":1,"robot":"fz","episode":0,"step":0,"stamp_ns":0,"action":[1e400,0],"state_seq":0}',
    ],
    "transition": [b'{"schema_version":1,"robot":"fz","episode":0,"step":0,"state":[0,0],"action":[0,0],"cost":1}'],
    "critic/weights": [
        json.dumps(
            {
                "schema_version": 1,
                "robot": "fz",
                "episode": 0,
                "version": 1,
                "trained_step": 0,
                "q_weights": [1.0] * 14,
                "v_weights": [1.0] * 6,
                "q_residual": 0,
                "v_residual": 0,
                "pairs": 0,
            }
        ).encode()
    ],
}


def test_malformed_messages_are_rejected_counted_and_survived() -> None:
    with cluster(robot="fz") as c:
        c.start("plant", "plant-sim", "--mode", "realtime")
        # plant/step and plant/reset exist in lockstep only: a lockstep plant of its own robot id
        # receives the malformed queries
        c.start("lockstep", "plant-sim", "--mode", "lockstep", "--robot", "fz_lock")
        c.start("critic", "critic")
        c.start("actor", "actor", "--mode", "realtime")
        for name in ("plant", "critic", "actor"):
            c.wait_alive(name)
        assert c.session is not None
        sent: dict[str, int] = {}
        for key, bad in BAD_BY_KEY.items():
            # BLOCK: the 70 kB payload must not make zenoh drop the samples after it (the
            # default DROP congestion control may, under load) - every one must arrive. The
            # critic reads transitions on the batch key alone (Batch.on_demand): sent there.
            where = TRANSITION_BATCH.pattern if key == "transition" else f"srl/fz/{key}"
            publisher = c.session.declare_publisher(where, congestion_control=zenoh.CongestionControl.BLOCK)
            for payload in [*GARBAGE, *bad]:
                publisher.put(payload)
            sent[key] = len(GARBAGE) + len(bad)
        errors = []
        wait_until(
            lambda: any(
                r.ok is not None
                for r in c.session.liveliness().get(  # type: ignore[union-attr]
                    "srl/fz_lock/alive/plant", timeout=0.5
                )
            ),
            60,
            "the lockstep plant",
        )
        for key in ("plant/step", "plant/reset"):
            for payload in GARBAGE[1:4]:
                for reply in c.session.get(f"srl/fz_lock/{key}", payload=payload, timeout=5):
                    errors.append(reply.err is not None)
        assert errors and all(errors), "every malformed query must get an error reply"
        counters: dict[str, dict[str, float]] = {}
        c.session.declare_subscriber(
            "srl/fz/status/*",
            lambda s: counters.__setitem__(
                str(s.key_expr).rsplit("/", 1)[-1], ServiceStatus.model_validate_json(s.payload.to_bytes()).counters
            ),
        )
        wait_until(
            lambda: (
                counters.get("actor", {}).get("rejected.critic/weights", 0) >= sent["critic/weights"]
                and counters.get("critic", {}).get("rejected.transition", 0) >= sent["transition"]
                and counters.get("plant", {}).get("rejected.action", 0) >= sent["action"]
            ),
            20,
            "the services to count every rejection",
        )
        for name in ("plant", "critic", "actor"):
            assert c.alive(name), f"{name} died"
        summaries = {}
        for name in ("actor", "critic", "plant", "lockstep"):
            assert c.procs[name].stop() == 0, c.procs[name].stderr[-10:]
            summaries[name] = c.procs[name].summary()["counters"]
    assert summaries["plant"]["rejected.action"] >= sent["action"]
    assert summaries["actor"]["rejected.state"] >= sent["state"]
    assert summaries["actor"]["rejected.critic/weights"] >= sent["critic/weights"]
    assert summaries["critic"]["rejected.transition"] >= sent["transition"]
    assert summaries["lockstep"]["rejected.plant/step"] + summaries["lockstep"]["rejected.plant/reset"] >= 6


def test_the_realtime_actor_logs_its_status_line_at_info() -> None:
    """compose shows the live status: the actor run at INFO, as compose runs
    it, logs its status line once a second (step, pose, distance, J, weights, missed deadlines)."""
    with cluster(robot="sl") as c:
        c.start_plant_and_critic()
        actor = Proc("actor", ["--log-level", "INFO", "actor", *c.common, "--mode", "realtime", "--run-seconds", "4"])
        c.procs["actor"] = actor
        assert actor.process.wait(timeout=90) == 0, actor.stderr[-10:]
        time.sleep(0.1)  # the reader threads drain
    lines = [line for line in actor.stderr if " status " in line]
    assert len(lines) >= 2, actor.stderr[-20:]
    pattern = re.compile(
        r"status +\d+\.\d s: step \d+  x [-+]\d\.\d\d y [-+]\d\.\d\d .* distance \d+\.\d\d m  J \d+\.\d{3}"
    )
    assert all(pattern.search(line) for line in lines[1:]), lines
    assert re.search(r"missed deadlines \d+  solver failures \d+$", lines[-1]), lines[-1]
