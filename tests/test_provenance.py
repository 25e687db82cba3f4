"""Provenance (docs/security.md) without a network: SourceGate, SequenceGuard and the actor's WeightsInbox.

The gate decides whose samples a receiver believes (the one live session of a singleton
service); the guard keeps one stream's order without letting a far-future value lock it out; the
inbox takes critic weights only from the live critic session, inside the weight box, trained on a
step the actor published. Each refusal is counted (a fake bus records them).
"""

from __future__ import annotations

import time
from collections import Counter

import pytest

from common.config.settings import Settings
from common.contracts.messages import CriticWeights
from common.net.provenance import (
    LATE_WITHIN_S,
    QUIET_REFUSALS,
    RESYNC_AFTER,
    ActionGate,
    ActionOrder,
    RefusalRun,
    SequenceGuard,
    SourceGate,
    yields_to,
)
from common.process.counts import RobotCounts
from services.actor.ports import MAX_VERSION_AHEAD_US, WeightsInbox

CRITIC, ROGUE, RESTARTED = "aa01", "bb02", "cc03"
EPISODE = 17


class FakeBus:
    """The two methods WeightsInbox uses: count and reject (the reasons kept for the asserts)."""

    def __init__(self) -> None:
        self.counters: Counter[str] = Counter()
        self.reasons: list[str] = []

    def count(self, name: str, amount: int = 1) -> None:
        self.counters[name] += amount

    def reject(self, what: str, reason: str) -> None:
        self.count(f"rejected.{what}")
        self.reasons.append(reason)


# -- SourceGate ---------------------------------------------------------------------------


def test_gate_verdicts_unknown_accept_foreign_conflict() -> None:
    gate = SourceGate("plant")
    assert gate.verdict(CRITIC) == "unknown"  # nobody live: believe nobody
    assert gate.verdict(None) == "unknown"
    gate.update(CRITIC, True)
    assert gate.verdict(CRITIC) == "accept"
    assert gate.verdict(ROGUE) == "foreign"
    assert gate.verdict(None) == "foreign"  # an unstamped sample is nobody's
    assert not gate.conflict
    gate.update(ROGUE, True)  # a second live session of a singleton service
    assert gate.conflict
    assert gate.verdict(CRITIC) == "conflict" and gate.verdict(ROGUE) == "conflict"
    assert gate.sources() == sorted([CRITIC, ROGUE])
    gate.update(ROGUE, False)  # the second one leaves: the first is believed again
    assert not gate.conflict
    assert gate.verdict(CRITIC) == "accept" and gate.verdict(ROGUE) == "foreign"
    gate.update(CRITIC, False)
    assert gate.verdict(CRITIC) == "unknown" and gate.sources() == []


def test_gate_generation_counts_changes_only() -> None:
    gate = SourceGate("critic")
    gate.update(CRITIC, True)
    gate.update(CRITIC, True)  # the same token again (history + query): no change
    gate.update(ROGUE, False)  # an unknown one leaving: no change
    assert gate.generation == 1
    gate.update(CRITIC, False)
    assert gate.generation == 2


# -- SequenceGuard ------------------------------------------------------------------------


def test_guard_accepts_first_and_newer_refuses_old_and_equal() -> None:
    guard = SequenceGuard(max_jump=100, restart_after=5)
    assert guard.check(CRITIC, 10) is None  # the first value of a source sets the reference
    assert guard.check(CRITIC, 11) is None
    assert guard.check(CRITIC, 111) is None  # exactly max_jump ahead: accepted
    refusal = guard.check(CRITIC, 111)
    assert refusal is not None and "not newer" in refusal
    assert guard.check(CRITIC, 50) is not None
    assert guard.last[CRITIC] == 111
    assert guard.check(ROGUE, 0) is None  # sources are independent
    assert guard.last[CRITIC] == 111


def test_guard_refuses_a_far_jump_without_moving_the_reference() -> None:
    guard = SequenceGuard(max_jump=100)
    assert guard.check(CRITIC, 5) is None
    refusal = guard.check(CRITIC, 2**62)  # one forged PlantState(seq=2**62)
    assert refusal is not None and "jumps more than 100" in refusal
    assert guard.last[CRITIC] == 5
    # ...so every real value after it is still accepted: no lockout
    assert all(guard.check(CRITIC, seq) is None for seq in range(6, 60))
    assert guard.check(CRITIC, 59 + 101) is not None  # 101 past the last real one: still a jump
    assert guard.check(CRITIC, 60) is None


def test_guard_restarts_after_consecutive_old_values() -> None:
    guard = SequenceGuard(max_jump=10_000, restart_after=4)
    for seq in range(1000, 1010):
        assert guard.check(CRITIC, seq) is None
    # the source restarted its count under the same identity: 0, 1, 2 refused, the 4th accepted
    assert [guard.check(CRITIC, seq) is None for seq in range(4)] == [False, False, False, True]
    assert guard.last[CRITIC] == 3
    assert guard.check(CRITIC, 4) is None


def test_guard_old_run_is_reset_by_an_accepted_value() -> None:
    guard = SequenceGuard(max_jump=10_000, restart_after=3)
    assert guard.check(CRITIC, 100) is None
    assert guard.check(CRITIC, 1) is not None
    assert guard.check(CRITIC, 2) is not None
    assert guard.check(CRITIC, 101) is None  # a real newer value: the run of old ones is broken
    assert guard.check(CRITIC, 3) is not None
    assert guard.check(CRITIC, 4) is not None  # only 2 consecutive old ones since: still refused
    assert guard.last[CRITIC] == 101


def test_guard_forget_drops_vanished_sources() -> None:
    guard = SequenceGuard(max_jump=10)
    guard.check(CRITIC, 500)
    guard.check(ROGUE, 7)
    guard.forget({CRITIC})
    assert set(guard.last) == {CRITIC} and set(guard.old_run) == {CRITIC}
    guard.forget(set())
    assert guard.last == {} and guard.old_run == {}
    assert guard.check(CRITIC, 0) is None  # a returning source starts fresh


def test_guard_repeated_old_values_never_restart_and_a_forged_restart_is_undone() -> None:
    """Before, any 20 old values restarted the count: 20 forged seq=1 states with the live plant's
    id made the real seq (50,000 on) a jump "more than 10,000 ahead" for the rest of the run."""
    guard = SequenceGuard(max_jump=10_000, restart_after=4)
    assert guard.check(CRITIC, 50_000) is None
    assert all(guard.check(CRITIC, 1) is not None for _ in range(50))  # a replay: no restart
    assert guard.last[CRITIC] == 50_000 and guard.resyncs == 0
    # a forged stream that counts on (1, 2, 3, 4) does take over...
    assert [guard.check(CRITIC, seq) is None for seq in range(1, 5)] == [False, False, False, True]
    assert guard.last[CRITIC] == 4 and guard.resyncs == 1
    # ...and the real stream, now "too far ahead", is followed again after restart_after of its own
    real = [guard.check(CRITIC, seq) is None for seq in range(50_001, 50_009)]
    assert real == [False, False, False, True, True, True, True, True]
    assert guard.resyncs == 2


def test_refusal_run_counts_only_an_increasing_stream_within_its_time() -> None:
    run = RefusalRun(after=3, within=1.0)
    assert not run.refused((5,), 0.0) and not run.refused((6,), 0.1)
    assert not run.refused((6,), 0.2)  # not newer: the run starts again from this one
    assert not run.refused((7,), 0.3) and run.refused((8,), 0.4)  # 6, 7, 8
    assert not run.refused((1,), 10.0) and not run.refused((2,), 10.5)
    assert not run.refused((3,), 11.6)  # the run is older than 1 s: it starts again
    assert not run.refused((4,), 11.7) and run.refused((5,), 11.8)
    assert not run.refused((9,), 12.0)
    run.accepted()  # an accepted value ends the run
    assert not run.refused((10,), 12.1) and not run.refused((11,), 12.2) and run.refused((12,), 12.3)


def test_action_order_refuses_a_far_future_episode_alone() -> None:
    """One Action(episode=2**62) with the live actor's session id is refused alone: the real
    stream goes on."""
    order = ActionOrder(max_step_jump=100, max_episode_jump=1000)
    assert order.check(500, 0, 0.0) is None
    refusal = order.check(2**62, 0, 0.05)
    assert refusal is not None and "episode" in refusal and "jumps more than 1000" in refusal
    assert all(order.check(500, step, 0.1 * step) is None for step in range(1, 50))
    assert order.check(500, 49 + 101, 5.0) is not None  # a step from the far future
    assert order.check(501, 101, 5.0) is not None  # a new episode must start near step 0
    assert order.check(499, 60, 5.0) is not None  # an older episode
    assert order.check(500, 49, 5.0) is not None  # not newer
    assert order.check(501, 0, 5.1) is None  # a newer episode, close ahead: the actor's next one
    assert order.last == (501, 0) and order.resyncs == 0


def test_action_order_a_followed_forged_burst_costs_the_real_actor_a_bounded_run() -> None:
    order = ActionOrder(max_step_jump=100, max_episode_jump=1000)
    assert order.check(500, 0, 0.0) is None
    forged = [order.check(2**62, step, 0.01 * step) is None for step in range(RESYNC_AFTER)]
    assert forged == [False] * (RESYNC_AFTER - 1) + [True]  # a forged burst that counts on: followed
    real = [order.check(500, step, 1.0 + 0.1 * step) is None for step in range(1, 2 * RESYNC_AFTER)]
    assert real == [False] * (RESYNC_AFTER - 1) + [True] * RESYNC_AFTER  # the real actor again
    assert order.resyncs == 2 and order.last == (500, 2 * RESYNC_AFTER - 1)
    order.reset()  # a new actor session: anything first
    assert order.check(3, 7, 9.0) is None


def test_action_gate_calls_the_left_actors_in_flight_actions_late_only_briefly() -> None:
    """A stopping actor's last queued action may arrive after its token vanished (the CI run of
    81f1fd2 logged one as a WARNING at the end of a clean `srl up`): refused, counted as
    ``action.late``; any other source, or the same one later, is refused as before."""
    gate = ActionGate(SourceGate("actor"))
    gate.gate.update("a", True)
    assert gate.admit(1, 0, "a", now=10.0) is None
    gate.gate.update("a", False)
    assert gate.lost("a", now=10.0)
    late = gate.admit(1, 1, "a", now=10.0 + LATE_WITHIN_S / 2)
    assert late is not None and late[0] == "action.late" and late[0] in QUIET_REFUSALS
    assert gate.admit(1, 2, "a", now=10.0 + 2 * LATE_WITHIN_S)[0] == "action.unknown"  # type: ignore[index]
    assert gate.admit(1, 1, "b", now=10.0)[0] == "action.unknown"  # type: ignore[index]  # never followed
    gate.gate.update("c", True)
    assert gate.admit(1, 1, "a", now=10.0)[0] == "action.late"  # type: ignore[index]  # c is live, a just left
    assert gate.admit(1, 1, "b", now=10.0)[0] == "action.foreign"  # type: ignore[index]
    assert not gate.lost("b", now=11.0) and gate.left == "a"  # a session never followed leaves no trace


def test_a_quiet_refusal_is_counted_and_logged_at_info(caplog: pytest.LogCaptureFixture) -> None:
    counts = RobotCounts("r1", "plant")
    with caplog.at_level("INFO", logger="common.process.counts"):
        counts.reject("action.late", "from session a")
        counts.reject("action.foreign", "from session b")
    assert counts.counters["rejected.action.late"] == counts.counters["rejected.action.foreign"] == 1
    levels = {record.getMessage().split("rejected ")[1].split(":")[0]: record.levelname for record in caplog.records}
    assert levels == {"action.late": "INFO", "action.foreign": "WARNING"}


def test_yields_to_is_the_same_answer_on_both_sides() -> None:
    a, b = "1f3a", "9c02"
    assert yields_to(a, [b]) == [] and yields_to(b, [a]) == [a]  # exactly one of the two yields
    assert yields_to(b, [a, "0001", "ffff"]) == ["0001", a]
    assert yields_to(a, []) == []


# -- WeightsInbox -------------------------------------------------------------------------


def _weights(version: int, *, value: float = 1.0, trained_step: int = 0, episode: int = EPISODE) -> CriticWeights:
    return CriticWeights(
        robot="pv",
        episode=episode,
        version=version,
        trained_step=trained_step,
        q_weights=(value,) * 15,
        v_weights=(value,) * 6,
        q_residual=0.0,
        v_residual=0.0,
        pairs=0,
    )


def _inbox() -> tuple[WeightsInbox, FakeBus, SourceGate]:
    bus, gate = FakeBus(), SourceGate("critic")
    gate.update(CRITIC, True)
    settings = Settings.load()
    assert settings.critic.bounds == (0.0, 100.0)  # the box these tests expect (common/config/srl.toml)
    inbox = WeightsInbox(settings, bus, gate)  # type: ignore[arg-type]
    inbox.reset(EPISODE)
    inbox.published(50)
    return inbox, bus, gate


def _now_us() -> int:
    return time.time_ns() // 1000


def test_inbox_accepts_the_live_critic() -> None:
    inbox, bus, _ = _inbox()
    inbox.offer(_weights(_now_us(), value=2.0, trained_step=40), CRITIC)
    held = inbox.current()
    assert held.trained_step == 40 and float(held.q[0]) == 2.0
    assert bus.counters["weights_accepted"] == 1 and not bus.reasons


def test_inbox_refuses_a_foreign_session_and_while_no_critic_is_live() -> None:
    inbox, bus, gate = _inbox()
    before = inbox.current().version
    inbox.offer(_weights(_now_us(), value=2.0), ROGUE)
    inbox.offer(_weights(_now_us(), value=2.0), None)
    gate.update(CRITIC, False)
    inbox.offer(_weights(_now_us(), value=2.0), CRITIC)  # its token is gone: unknown
    assert inbox.current().version == before
    assert bus.counters["rejected.critic/weights"] == 3 and bus.counters["weights_accepted"] == 0
    assert "foreign" in bus.reasons[0] and "unknown" in bus.reasons[2]


@pytest.mark.parametrize("value", [-100.0, 1e300, 100.5, -1e-9])
def test_inbox_refuses_weights_outside_the_box_and_keeps_the_last_good(value: float) -> None:
    """Weights outside the box (-100 would spin the robot at full speed, 1e300 fail the solver),
    from the live critic session too, are refused and the last good weights kept."""
    inbox, bus, _ = _inbox()
    good = _now_us()
    inbox.offer(_weights(good, value=3.0), CRITIC)
    inbox.offer(_weights(good + 1, value=value), CRITIC)
    mixed = _weights(good + 2, value=3.0).model_copy(update={"q_weights": (3.0,) * 14 + (value,)})
    inbox.offer(mixed, CRITIC)
    held = inbox.current()
    assert held.version == good and float(held.q.max()) == 3.0 and float(held.q.min()) == 3.0
    assert bus.counters["rejected.critic/weights"] == 2
    assert all("outside the box" in r for r in bus.reasons)
    # the box bounds themselves are inside
    inbox.offer(_weights(good + 3, value=100.0), CRITIC)
    inbox.offer(_weights(good + 4, value=0.0), CRITIC)
    assert inbox.current().version == good + 4


def test_inbox_refuses_a_trained_step_beyond_the_published_step() -> None:
    """A forged trained_step beyond the published step is refused (it would make the staleness
    negative)."""
    inbox, bus, _ = _inbox()
    inbox.offer(_weights(_now_us(), trained_step=1_000_000), CRITIC)
    inbox.offer(_weights(_now_us(), trained_step=51), CRITIC)
    assert inbox.current().trained_step == -1
    assert bus.counters["rejected.critic/weights"] == 2 and "published only up to 50" in bus.reasons[0]
    inbox.offer(_weights(_now_us(), trained_step=50), CRITIC)  # the newest published step: fine
    assert inbox.current().trained_step == 50
    inbox.published(51)
    inbox.offer(_weights(_now_us(), trained_step=51), CRITIC)
    assert inbox.current().trained_step == 51
    inbox.reset(EPISODE + 1)  # a new episode: nothing of it published yet
    inbox.offer(_weights(_now_us(), trained_step=0, episode=EPISODE + 1), CRITIC)
    assert inbox.current().trained_step == -1


def test_inbox_refuses_another_episode_and_an_old_version() -> None:
    inbox, bus, _ = _inbox()
    now = _now_us()
    inbox.offer(_weights(now, episode=EPISODE - 1), CRITIC)
    inbox.offer(_weights(now), CRITIC)
    inbox.offer(_weights(now), CRITIC)  # the same version again
    inbox.offer(_weights(now - 1), CRITIC)
    assert inbox.current().version == now
    assert bus.counters["rejected.critic/weights"] == 3 and bus.counters["weights_accepted"] == 1


def test_a_new_critic_session_resynchronizes_versions() -> None:
    """A restarted critic (a new session, maybe with a clock behind the old one's) is followed
    at once instead of being refused until its versions pass the old session's."""
    inbox, bus, gate = _inbox()
    now = _now_us()
    inbox.offer(_weights(now + 5_000_000, value=2.0), CRITIC)  # the old session, clock 5 s ahead
    gate.update(CRITIC, False)
    gate.update(RESTARTED, True)
    inbox.offer(_weights(now, value=4.0), RESTARTED)  # lower version, new session: accepted
    held = inbox.current()
    assert held.version == now and float(held.q[0]) == 4.0
    assert bus.counters["critic_resyncs"] == 1
    inbox.offer(_weights(now - 1), RESTARTED)  # within the new session, order holds again
    assert inbox.current().version == now and bus.counters["rejected.critic/weights"] == 1
    inbox.offer(_weights(now + 5_000_000), CRITIC)  # the old session is no longer live
    assert inbox.current().version == now and bus.counters["rejected.critic/weights"] == 2


def test_a_version_ahead_of_the_clock_is_accepted_only_within_the_bound() -> None:
    inbox, bus, _ = _inbox()
    far = _now_us() + MAX_VERSION_AHEAD_US + 10_000_000  # 10 s beyond the allowed skew
    inbox.offer(_weights(far), CRITIC)
    assert inbox.current().version == 0
    assert bus.counters["rejected.critic/weights"] == 1 and "from the future" in bus.reasons[0]
    near = _now_us() + MAX_VERSION_AHEAD_US - 10_000_000  # within the skew: the live critic's
    inbox.offer(_weights(near), CRITIC)
    assert inbox.current().version == near
    # from a rogue session, even a version just ahead of the clock is refused (provenance first)
    inbox.offer(_weights(near + 1), ROGUE)
    assert inbox.current().version == near and bus.counters["rejected.critic/weights"] == 2


def test_a_forged_version_with_the_live_critic_id_costs_a_bounded_run_of_updates() -> None:
    """A version 59 s ahead with the live critic's id costs a bounded run: the window is 5 s, and a
    run of the real critic's versions refused in a row is followed again: at most
    RESYNC_AFTER - 1 real updates are lost."""
    inbox, bus, _ = _inbox()
    start = _now_us() - 3_600_000_000  # a critic that started an hour ago counts from then
    inbox.offer(_weights(start, value=2.0), CRITIC)
    inbox.offer(_weights(_now_us() + MAX_VERSION_AHEAD_US - 1_000_000, value=50.0), CRITIC)  # the forgery
    assert inbox.current().q[0] == 50.0
    accepted = []
    for n in range(1, 2 * RESYNC_AFTER):
        inbox.offer(_weights(start + n, value=3.0), CRITIC)
        accepted.append(inbox.current().version == start + n)
    assert accepted == [False] * (RESYNC_AFTER - 1) + [True] * RESYNC_AFTER
    assert bus.counters["critic_version_resyncs"] == 1 and float(inbox.current().q[0]) == 3.0
    assert bus.counters["rejected.critic/weights"] == RESYNC_AFTER - 1
    # one far-future version is refused alone; a replayed old one does not start a run
    inbox.offer(_weights(_now_us() + MAX_VERSION_AHEAD_US + 1_000_000), CRITIC)
    for _ in range(3 * RESYNC_AFTER):
        inbox.offer(_weights(start + 1), CRITIC)
    assert inbox.current().version == start + 2 * RESYNC_AFTER - 1
    assert bus.counters["critic_version_resyncs"] == 1
    inbox.offer(_weights(start + 2 * RESYNC_AFTER), CRITIC)
    assert inbox.current().version == start + 2 * RESYNC_AFTER


def test_a_version_ten_seconds_ahead_is_from_the_future() -> None:
    """Before, 59 s ahead was accepted; the window is a few seconds of clock skew now."""
    inbox, bus, _ = _inbox()
    inbox.offer(_weights(_now_us() + 10_000_000), CRITIC)
    assert inbox.current().version == 0 and "from the future" in bus.reasons[0]
