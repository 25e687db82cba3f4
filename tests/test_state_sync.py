"""The plant host's state sync (transport.state_sync, services/plant_sim/host.py StateSync):
a driven robot's state goes out only at the state ticks just before its actor's tick, and the
state its actor reads at an on-time tick is the one it would read with every state published."""

from __future__ import annotations

import numpy as np
import pytest

from common.config.settings import Settings
from common.math.fleet import circle_starts
from common.system.clock import STATE_SYNC_MARGIN_S, aligned_start, tick_phase_offset
from services.plant_sim.host import SYNC_MIN_ACTIONS, SYNC_WINDOW, FleetPlant, StateSync

DELTA, PERIOD = 0.1, 0.02  # the actor's delta, the state period (50 Hz)
GRID0 = 0.0031  # the plant's first state tick
T0 = 0.0137  # the actor's tick 0 (another phase than the plant's)


def simulate(
    delays: dict[int, float], steps: int = 40, default_delay: float = 0.0012, t0: float = T0
) -> tuple[list[float], list[float]]:
    """One robot: its actor's tick k at t0 + k delta, its action of step k arriving ``delays[k]``
    (else ``default_delay``) later. The state ticks up to the last tick, and which of them
    published (the actions that arrived by a state tick are taken in first)."""
    sync = StateSync(1, DELTA, PERIOD)
    arrivals = sorted((t0 + k * DELTA + delays.get(k, default_delay), k) for k in range(steps))
    grid = [GRID0 + j * PERIOD for j in range(int((t0 + steps * DELTA) / PERIOD))]
    published, a = [], 0
    for tick in grid:
        while a < len(arrivals) and arrivals[a][0] <= tick:
            sync.action(0, arrivals[a][1], arrivals[a][0])
            a += 1
        if sync.due(tick)[0]:
            published.append(tick)
    return grid, published


def newest_before(times: list[float], t: float) -> float:
    return max(x for x in times if x <= t)


def test_an_on_time_actor_reads_the_state_it_would_read_with_every_state_published() -> None:
    grid, published = simulate({})
    learned = SYNC_MIN_ACTIONS + 1  # ticks after the phase is learned
    for k in range(learned, 39):
        tick = T0 + k * DELTA
        assert newest_before(published, tick) == newest_before(grid, tick), k
    later = [t for t in published if t > T0 + learned * DELTA]
    span = (later[-1] - later[0]) / DELTA
    # 5 state ticks per delta; sync publishes 1 or 2 of them (2 when one falls within the margin)
    assert len(later) <= 2 * (span + 1)
    assert len(later) >= span
    # before the phase is learned, every state tick is published
    assert [t for t in grid if t < T0 + (SYNC_MIN_ACTIONS - 1) * DELTA] == [
        t for t in published if t < T0 + (SYNC_MIN_ACTIONS - 1) * DELTA
    ]


@pytest.mark.parametrize("transport", [0.0002, 0.002])  # a state's way from the plant to the actor
def test_an_actor_host_aligned_to_the_states_gets_one_state_a_period_the_newest(transport: float) -> None:
    """An actor host starts its ticks where the states' grid, as they arrive, puts them one state
    each period (services/actor/host.py run_host: common.system.clock.aligned_start); a tick
    as a state arrives gets two every period (the control)."""
    offset = tick_phase_offset(DELTA, 5, PERIOD)  # 5 tick groups: the default host of 50 robots
    assert offset == pytest.approx((PERIOD + STATE_SYNC_MARGIN_S) / 2)
    newest = GRID0 + 7 * PERIOD + transport  # the newest state's arrival when the host starts
    t0 = aligned_start(newest + 0.0003, newest, offset, PERIOD)
    assert newest + 0.0003 <= t0 < newest + 0.0003 + PERIOD
    learned = T0 + (SYNC_MIN_ACTIONS + 1) * DELTA
    for start, per_period in ((t0, {1}), (GRID0 + transport, {2})):
        grid, published = simulate({}, t0=start)
        counts = {sum(1 for t in published if start + (k - 1) * DELTA < t <= start + k * DELTA) for k in range(8, 39)}
        assert counts == per_period, (start, counts)
        for k in range(8, 39):  # and the newest state at each tick is the one of every state published
            tick = start + k * DELTA
            assert tick > learned and newest_before(published, tick) == newest_before(grid, tick), k


def test_the_tick_phase_keeps_every_group_as_far_as_it_can_from_a_states_arrival() -> None:
    centre = STATE_SYNC_MARGIN_S / 2
    for groups, least in ((1, 0.0075), (5, 0.0075), (10, 0.005), (15, 0.0033)):
        offset = tick_phase_offset(DELTA, groups, PERIOD)
        gaps = [(offset + g * DELTA / groups - centre) % PERIOD for g in range(groups)]
        assert min(min(gap, PERIOD - gap) for gap in gaps) >= least - 1e-9, groups
    assert tick_phase_offset(DELTA, 5, DELTA) == 0.0  # states no faster than ticks: nothing to place
    assert aligned_start(3.0, None, 0.0125, PERIOD) == 3.0  # no state yet: now


def test_a_late_action_gets_every_state_tick_until_it_arrives_and_does_not_move_the_phase() -> None:
    late = 20
    grid, published = simulate({late: 0.055})  # tick 20's action comes 55 ms late
    arrival = T0 + late * DELTA + 0.055
    window = [t for t in grid if T0 + late * DELTA - PERIOD < t <= arrival]
    assert window and all(t in published for t in window)  # every state tick while it is late
    for k in range(late + 1, 39):  # the ticks after it: as on time (the phase is the least delay)
        tick = T0 + k * DELTA
        assert newest_before(published, tick) == newest_before(grid, tick), k


def test_a_robot_without_recent_actions_or_in_a_new_episode_gets_every_state_tick() -> None:
    sync = StateSync(2, DELTA, PERIOD)
    for k in range(10):
        sync.action(0, k, T0 + k * DELTA + 0.001)
    now = T0 + 10 * DELTA - 0.05  # half-way to robot 0's tick 10
    assert sync.due(now).tolist() == [False, True]  # robot 1 never acted
    assert sync.due(T0 + 9 * DELTA + 2 * DELTA + 0.01).tolist() == [True, True]  # robot 0 silent for 2 delta
    sync.action(0, 0, now)  # step 0 again: a new episode or actor, its phase learned afresh
    assert sync.due(now + 0.01).tolist() == [True, True]


def test_the_phase_is_the_least_delay_of_the_window_only() -> None:
    sync = StateSync(1, DELTA, PERIOD)
    sync.action(0, 0, 0.0005)  # one early arrival, then SYNC_WINDOW later ones
    for k in range(1, SYNC_WINDOW + 1):
        sync.action(0, k, k * DELTA + 0.030)
    k = SYNC_WINDOW
    # the early arrival has left the window: the next tick is expected 30 ms after its nominal time
    opens = (k + 1) * DELTA + 0.030 - PERIOD - 0.005
    assert not sync.due(opens - 0.001)[0]
    assert sync.due(opens + 0.001)[0]


def test_the_fleet_plant_sends_only_the_robots_due() -> None:
    settings = Settings.load()
    robots = ["r1", "r2", "r3"]
    plant = FleetPlant(settings, robots, np.array(circle_starts(3, 1.5)))
    plant.hold(0, (0.2, 0.0))
    due = plant.advance(0.1, np.array([False, True, False]))
    assert due.robots == ["r2"] and [m.robot for m in due.items()] == ["r2"]
    every = list(plant.advance(0.1).items())
    assert [m.robot for m in every] == robots
    first, (x0, _, heading) = every[0], circle_starts(3, 1.5)[0]
    assert first.seq == 2  # robot 1 moved on while not published
    assert first.state[0] == pytest.approx(x0 + 0.2 * 0.2 * np.cos(heading))
