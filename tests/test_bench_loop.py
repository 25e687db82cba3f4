"""``srl bench loop``: a short real run prints the table and a consistent JSON object."""

from __future__ import annotations

import pytest

from tests.harness import run_bench

pytestmark = [pytest.mark.slow, pytest.mark.integration, pytest.mark.timing]


def test_bench_loop_short_run_reports_every_figure() -> None:
    result = run_bench("loop", "bl")
    assert 30 <= result["steps"] <= 41  # 4 s at delta = 0.1 s
    assert result["transitions_received"] == result["steps"]  # none lost on loopback
    for name in ("period_ms", "jitter_ms", "solve_ms", "latency_ms", "critic_fit_ms"):
        stats = result[name]
        assert 0 <= stats["median"] <= stats["p99"] <= stats["max"], name
    assert 95 <= result["period_ms"]["median"] <= 105
    assert set(result["resources"]) == {"router", "plant", "critic", "actor"}
    assert all(r["peak_rss_mb"] > 10 for r in result["resources"].values())
    assert result["machine"]["cpus"] >= 1 and len(result["machine"]["load_before"]) == 3
    assert set(result["targets"]) >= {"missed_deadlines == 0", "jitter p99 <= 2 ms", "latency p99 <= 1 ms"}
    assert all(v in ("PASS", "FAIL") for v in result["targets"].values())
    assert "srl bench loop" in result["stdout"] and "targets:" in result["stdout"]
