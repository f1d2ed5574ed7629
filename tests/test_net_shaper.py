"""The emulated link's decisions, without sockets: rate, delay, jitter, order, loss, queue."""

from __future__ import annotations

import statistics

import pytest

from server.net.link_profile import Direction, GilbertElliott, LinkProfile, Schedule
from server.net.profiles import PROFILES
from server.net.shaper import Decision, DirectionShaper, Fate, LinkShaper

PACKET = 1200


def _down(**direction: object) -> DirectionShaper:
    profile = LinkProfile(down=Direction.model_validate(direction))
    return DirectionShaper(Schedule.constant(profile), "down", seed=1)


def _offer_evenly(
    shaper: DirectionShaper, count: int, interval_s: float, size: int = PACKET
) -> list[tuple[float, Decision]]:
    return [(i * interval_s, shaper.offer(size, i * interval_s)) for i in range(count)]


def _delivered(decisions: list[tuple[float, Decision]]) -> list[tuple[float, float]]:
    return [(t, d.depart_at) for t, d in decisions if d.fate is Fate.DELIVER]


def test_an_overloaded_link_delivers_at_its_rate() -> None:
    shaper = _down(rate_bps=20e6)
    # Offered at twice the rate for 2 s: the link runs flat out, the queue drops the rest.
    out = _delivered(_offer_evenly(shaper, 8000, PACKET * 8 / 40e6))
    departures = [d for _, d in out]
    rate = (len(departures) - 1) * PACKET * 8 / (departures[-1] - departures[0])
    assert rate == pytest.approx(20e6, rel=0.02)
    assert shaper.counters.queue_dropped > 3000


def test_below_the_rate_nothing_waits_but_serialization() -> None:
    shaper = _down(rate_bps=10e6)
    out = _delivered(_offer_evenly(shaper, 1000, 0.002))  # 4.8 Mbit/s
    tx_s = PACKET * 8 / 10e6
    assert len(out) == 1000
    assert all(depart - t == pytest.approx(tx_s) for t, depart in out)


def test_delay_is_exact_without_jitter() -> None:
    shaper = _down(delay_ms=25)
    out = _delivered(_offer_evenly(shaper, 100, 0.001))
    assert all(depart - t == pytest.approx(0.025) for t, depart in out)


def test_jitter_stays_within_its_bounds_and_fills_them() -> None:
    shaper = _down(delay_ms=20, jitter_ms=5)
    # Sparse packets: the order floor never binds, the delay is the draw itself.
    delays = [depart - t for t, depart in _delivered(_offer_evenly(shaper, 2000, 0.05))]
    assert 0.015 <= min(delays) < 0.0155
    assert 0.0245 < max(delays) <= 0.025
    assert statistics.mean(delays) == pytest.approx(0.020, abs=0.0005)
    assert statistics.pstdev(delays) == pytest.approx(0.010 / 12**0.5, rel=0.1)


def test_jitter_keeps_packet_order() -> None:
    shaper = _down(delay_ms=20, jitter_ms=10)
    out = _delivered(_offer_evenly(shaper, 5000, 0.0002))
    departures = [d for _, d in out]
    assert departures == sorted(departures)
    # The floor delays, never hastens: every packet still leaves within delay + jitter.
    assert all(0.010 <= depart - t <= 0.030 + 1e-12 for t, depart in out)


def test_reorder_lets_packets_overtake() -> None:
    shaper = _down(delay_ms=20, reorder=0.1)
    out = _delivered(_offer_evenly(shaper, 5000, 0.001))
    # A packet overtook if it left before some packet that arrived before it did.
    overtook, latest = 0, 0.0
    for _, depart in out:
        overtook += depart < latest
        latest = max(latest, depart)
    assert overtook / len(out) == pytest.approx(0.1, abs=0.02)


def test_random_loss_rate() -> None:
    shaper = _down(loss=0.05)
    _offer_evenly(shaper, 50_000, 0.0001)
    assert shaper.counters.lost / shaper.counters.packets_in == pytest.approx(0.05, abs=0.004)


def _loss_runs(fates: list[Fate]) -> list[int]:
    runs, current = [], 0
    for fate in fates:
        if fate is Fate.LOST:
            current += 1
        elif current:
            runs.append(current)
            current = 0
    return runs


def test_bursty_loss_has_its_mean_rate_and_burst_length() -> None:
    chain = GilbertElliott.from_mean(0.02, 3.0)
    assert chain.mean_loss == pytest.approx(0.02)
    shaper = _down(burst_loss=chain)
    fates = [d.fate for _, d in _offer_evenly(shaper, 100_000, 0.0001)]
    assert fates.count(Fate.LOST) / len(fates) == pytest.approx(0.02, abs=0.003)
    assert statistics.mean(_loss_runs(fates)) == pytest.approx(3.0, rel=0.1)


def test_random_loss_comes_alone() -> None:
    shaper = _down(loss=0.02)
    fates = [d.fate for _, d in _offer_evenly(shaper, 100_000, 0.0001)]
    assert statistics.mean(_loss_runs(fates)) == pytest.approx(1.0 / 0.98, rel=0.03)


def test_the_queue_drops_what_the_link_cannot_carry() -> None:
    shaper = _down(rate_bps=10e6, queue_ms=100)
    out = _delivered(_offer_evenly(shaper, 4000, PACKET * 8 / 20e6))  # 2x the rate for 2 s
    waits = [depart - t for t, depart in out]
    assert max(waits) <= 0.100 + 1e-9
    assert max(waits) > 0.095  # it did fill up
    dropped = shaper.counters.queue_dropped
    assert dropped / 4000 == pytest.approx(0.5, abs=0.04)
    assert shaper.counters.delivered + dropped == 4000


def test_a_queue_in_bytes() -> None:
    shaper = _down(rate_bps=8e6, queue_bytes=12_000)  # 12 ms at 8 Mbit/s
    waits = [depart - t for t, depart in _delivered(_offer_evenly(shaper, 2000, 0.0005))]
    assert 0.0105 < max(waits) <= 0.012 + 1e-9


def test_a_packet_bigger_than_the_queue_still_passes_an_idle_link() -> None:
    shaper = _down(rate_bps=1e6, queue_bytes=500)
    assert shaper.offer(PACKET, 0.0).fate is Fate.DELIVER
    assert shaper.offer(PACKET, 0.0).fate is Fate.QUEUE_FULL


def test_schedule_steps_switch_at_their_time() -> None:
    link = LinkShaper(PROFILES["drop"], seed=3, origin=100.0)
    assert link.step_index(109.999) == 0
    assert link.step_index(110.0) == 1
    assert link.step_index(120.0) == 2
    tx = PACKET * 8
    before = link.down.offer(PACKET, 109.99)
    assert before.depart_at == pytest.approx(109.99 + tx / 20e6 + 0.010)
    after = link.down.offer(PACKET, 110.5)
    assert after.depart_at == pytest.approx(110.5 + tx / 2e6 + 0.010)
    link.restart_schedule(200.0)
    assert link.step_index(205.0) == 0


def test_blackout_loses_everything_for_three_seconds() -> None:
    link = LinkShaper(PROFILES["blackout"], seed=0)
    fates = {t / 10: link.down.offer(PACKET, t / 10).fate for t in range(0, 120)}
    lost = [t for t, fate in fates.items() if fate is Fate.LOST]
    assert lost == [t / 10 for t in range(50, 80)]


def test_the_uplink_is_unlimited_unless_given_a_rate() -> None:
    link = LinkShaper(PROFILES["cable"])
    depart = [link.up.offer(PACKET, 0.0).depart_at for _ in range(100)]
    assert depart == [pytest.approx(0.0075)] * 100


def test_same_seed_same_run_and_directions_independent() -> None:
    def run(seed: int, uplink_traffic: bool) -> list[Fate]:
        link = LinkShaper(PROFILES["lte"], seed=seed)
        fates = []
        for i in range(5000):
            if uplink_traffic:
                link.up.offer(100, i * 0.001)
            fates.append(link.down.offer(PACKET, i * 0.001).fate)
        return fates

    assert run(7, False) == run(7, True)
    assert run(7, False) != run(8, False)
