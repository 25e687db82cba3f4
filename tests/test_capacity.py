"""``srl bench capacity``: the per-robot costs and the model of what a large fleet needs."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from typing import Any

import pytest

from tests.harness import srl
from tools.bench.capacity import component, fit_line, model
from tools.launch.measure import message_kind


def test_services_map_to_components_and_keys_to_message_kinds() -> None:
    assert [component(s) for s in ("router", "plant", "critic", "actor", "actor-2", "plant-robot3")] == [
        "router",
        "plant",
        "critic",
        "actor",
        "actor",
        "plant",
    ]
    assert component("observer") == "observer"  # not a component: not folded into one
    assert message_kind("srl/robot7/state") == "state"
    assert message_kind("srl/robot7/status/actor") == "status/actor"


def test_the_line_splits_a_cost_into_fixed_and_per_robot() -> None:
    fixed, per_robot = fit_line([10, 25, 50], [0.3 + 0.01 * n for n in (10, 25, 50)])
    assert fixed == pytest.approx(0.3) and per_robot == pytest.approx(0.01)
    assert fit_line([4], [0.2]) == (0.0, pytest.approx(0.05))  # one size: all of it per robot


def _row(robots: int, seconds: float = 10.0) -> dict[str, Any]:
    """A run where every component costs 1 % of a core per robot plus its fixed part, and each
    robot sends 50 states and 10 actions a second."""
    fixed = {"router": 0.02, "plant": 0.01, "critic": 0.0, "actor": 0.05}
    cpu = {name: 100.0 * (f + 0.01 * robots) for name, f in fixed.items()}
    cpu["actor-2"], cpu["actor"] = cpu["actor"] / 2, cpu["actor"] / 2  # two actor hosts: one component
    messages = {"state": [50 * robots * seconds, 200 * 50 * robots * seconds], "action": [10 * robots * seconds, 0]}
    return {"robots": robots, "run_seconds": seconds, "cpu_percent_by_service": cpu, "messages": messages}


def test_the_model_scales_the_measured_costs_to_large_fleets() -> None:
    result = model([_row(10), _row(50), {"robots": 25, "error": "did not start"}], utilisation=0.5, host_cores=8)
    assert result["cpu"]["actor"]["per_robot_cores"] == pytest.approx(0.01)
    assert result["cpu"]["actor"]["fixed_cores"] == pytest.approx(0.05)
    assert result["messages"]["state"]["per_robot_per_s"] == pytest.approx(50.0)
    thousand = result["fleets"]["1000"]
    assert thousand["cores"]["router"] == pytest.approx(0.02 + 10.0)
    assert thousand["robots_per_actor_host"] == 50  # 1 % each, a core at 50 %
    assert thousand["actor_host_processes"] == 20
    total_cores = (0.02 + 0.01 + 0.0 + 0.05 + 4 * 10.0) / 0.5
    assert thousand["hosts"] == math.ceil(total_cores / 8)
    assert thousand["routers"] >= thousand["hosts"]  # one router per host at least
    assert thousand["messages_per_s"] == pytest.approx(60_000)
    assert thousand["megabytes_per_s"] == pytest.approx(1000 * 50 * 200 / 1e6)
    assert result["fleets"]["10000"]["actor_host_processes"] == 200


@pytest.mark.integration
@pytest.mark.slow
def test_the_capacity_bench_measures_every_component_and_the_messages() -> None:
    """A miniature run: two sizes, every component's CPU, each robot's states (synced to its
    actor's ticks: transport.state_sync) and 10 Hz actions counted, the model printed and in the
    JSON."""
    done = srl("bench", "capacity", "--robots", "1,3", "--seconds", "6", "--json", timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "what a fleet needs" in done.stdout and "10000 robots:" in done.stdout
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert [row["robots"] for row in result["rows"]] == [1, 3]
    for row in result["rows"]:
        assert {"router", "plant", "critic", "actor"} <= set(row["cpu_percent_by_service"])
        assert all(p >= 0 for p in row["cpu_percent_by_service"].values())
    rates = result["model"]["messages"]
    # state sync: at least one state per delta reaches each actor, far fewer than the plant's 50 Hz
    # (all 50 while the robots start, 1-2 per delta once their actors act)
    assert 10.0 * 0.85 <= rates["state"]["per_robot_per_s"] <= 30.0
    assert rates["action"]["per_robot_per_s"] == pytest.approx(10.0, rel=0.15)
    assert rates["transition"]["per_robot_per_s"] == pytest.approx(10.0, rel=0.15)
    assert result["model"]["cpu"]["actor"]["per_robot_cores"] > 0


@pytest.mark.integration
def test_bad_options_are_refused_in_one_line() -> None:
    for argv, says in (
        (["--robots", "x"], "--robots"),
        (["--utilisation", "0"], "--utilisation"),
        (["--host-cores", "0"], "--host-cores"),
        (["--seconds", "1"], "--seconds"),
    ):
        done = subprocess.run(
            [sys.executable, "-m", "tools.cli", "bench", "capacity", *argv],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        assert done.returncode == 2, (argv, done.stderr)
        assert says in done.stderr and len(done.stderr.strip().splitlines()) == 1, done.stderr


def test_the_rss_series_is_bounded_and_its_growth_starts_after_warm_up() -> None:
    from tools.launch.measure import RSS_POINTS, RssSeries

    series = RssSeries()
    for second in range(0, 3600):  # an hour, one call a second: the series stays bounded
        total = 400.0 + (50.0 if second < 300 else 0.0) + second / 3600.0
        series.add(float(second), total, {"actor": total - 100.0, "critic": 100.0})
    assert len(series.points) <= RSS_POINTS and len(series.by_service) == len(series.points)
    grown = series.growth_by_service()
    assert grown["critic"] == [100.0, 100.0] and grown["actor"][1] - grown["actor"][0] == pytest.approx(0.9, abs=0.1)
    # warm-up (the first tenth: 360 s) is left out: 400.1 .. 401.0 MB, not the 450 MB of start-up
    assert series.growth_percent() == pytest.approx(100 * (401.0 / 400.1 - 1), abs=0.05)
    short = RssSeries()
    short.add(0.0, 400.0)
    assert math.isnan(short.growth_percent())
