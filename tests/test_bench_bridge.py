"""``srl bench bridge``: a short run measures every path and its baseline, consistently."""

from __future__ import annotations

import pytest

from tests.harness import run_bench

pytestmark = [pytest.mark.slow, pytest.mark.integration, pytest.mark.timing]


def test_bench_bridge_short_run_reports_paths_and_baselines() -> None:
    r = run_bench("bridge", "bb")
    assert r["steps"] == 20
    # every command reached cmd_vel; the robot reports most new speeds (a command sent at a random
    # phase may be replaced by the next one before the robot's next 20 Hz odometry sample)
    assert r["action_to_cmd_n"] == 20
    assert r["command_to_odom_n"] >= 12 and r["direct_cmd_to_odom_n"] >= 12
    assert r["odom_to_state_n"] >= 20  # 20 Hz odometry over ~2 s
    assert r["process_echo_n"] >= 18  # the transport baseline: to a process that only echoes
    assert set(r["added_over_echo_ms"]) == {"median", "p99"}
    for key in (
        "zenoh_hop_ms",
        "process_echo_ms",
        "action_to_cmd_ms",
        "odom_to_state_ms",
        "command_to_odom_ms",
        "direct_cmd_to_odom_ms",
    ):
        s = r[key]
        assert 0 <= s["median"] <= s["p99"] <= s["max"], key
    # the robot answers within its odometry period (50 ms) plus slack, with or without the bridge
    assert r["direct_cmd_to_odom_ms"]["median"] < 60 and r["command_to_odom_ms"]["median"] < 60
    assert r["bridge_cpu_seconds"] > 0 and r["bridge_peak_rss_mb"] > 10
    assert set(r["bridge_internal"]) >= {"action_to_cmd_ms", "odom_to_state_ms"}
    assert all(v in ("PASS", "FAIL") for v in r["targets"].values())
