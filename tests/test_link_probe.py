"""LinkProbe: whether a probe's padded frames came through, from their delay trend."""

from __future__ import annotations

from collections.abc import Callable

from server.session.link_probe import (
    FIRST_GAIN,
    MAX_PROBE_S,
    MIN_FRAMES,
    NEXT_GAIN,
    PROBE_S,
    RESULT_TIMEOUT_S,
    RETRY_S,
    LinkProbe,
)

FPS = 30
OFFSET_MS = 55_555.0  # the viewer's clock is not ours
Wobble = Callable[[int], float]


def run_probe(
    capacity_bps: float, *, link_bps: float = 2e6, wobble: Wobble = lambda i: 0.0
) -> tuple[LinkProbe, float | None]:
    """A probe at ``FIRST_GAIN x link_bps`` through a bottleneck of ``capacity_bps``;
    ``wobble(i)``: extra ms on frame i's arrival stamp."""
    probe = LinkProbe()
    target = probe.start(link_bps, 1e9, ["v"], 0.0)
    size = int(target / FPS / 8)
    free_at = 0.0
    arrivals = []
    i = 0
    while probe.padding_bps(i / FPS) > 0:
        sent = i / FPS
        probe.frame_sent(i, size, size, sent)
        free_at = max(sent, free_at) + size * 8 / capacity_bps
        arrivals.append((i, (free_at + 0.02) * 1000 + wobble(i) + OFFSET_MS))
        i += 1
    # Before the probe the path's least delay was its 20 ms of propagation.
    proved = probe.report("v", arrivals, 20.0 + OFFSET_MS, i / FPS + 0.1)
    assert probe.current is None  # every frame reported: the result is in
    return probe, proved


def test_a_wide_link_proves_the_target_and_the_next_probe_goes_higher() -> None:
    probe, proved = run_probe(20e6)
    assert proved == FIRST_GAIN * 2e6
    assert probe.gain == NEXT_GAIN and probe.succeeded == 1
    assert not probe.idle(PROBE_S + 0.2) and probe.idle(PROBE_S + 0.2 + 0.5)


def test_a_link_slower_than_the_probe_queues_it_and_fails_it() -> None:
    # 2.5 Mbit/s asked of a 2.1: each frame queues 6 ms more than the one before.
    probe, proved = run_probe(2.1e6)
    assert proved is None
    assert probe.gain == FIRST_GAIN and probe.succeeded == 0
    done = PROBE_S + 0.2
    assert not probe.idle(done + RETRY_S - 0.2) and probe.idle(done + RETRY_S)


def test_one_frame_stamped_late_by_a_busy_page_does_not_fail_it() -> None:
    for late in (0, 1, MIN_FRAMES):  # the first, the second, the last
        _, proved = run_probe(20e6, wobble=lambda i, late=late: 40.0 if i == late else 0.0)
        assert proved == FIRST_GAIN * 2e6, late


def test_a_first_frame_held_behind_a_lost_packet_does_not_pass_a_narrow_link() -> None:
    # The first frame waits for a retransmission; the others still queue behind the
    # bottleneck, so the trend over them fails the probe as it should.
    _, proved = run_probe(2.0e6, wobble=lambda i: 60.0 if i == 0 else 0.0)
    assert proved is None
    # On a wide link the same hold proves nothing wrong: the rest came through.
    _, proved = run_probe(20e6, wobble=lambda i: 60.0 if i == 0 else 0.0)
    assert proved == FIRST_GAIN * 2e6


def test_a_start_held_behind_a_lost_packet_proves_nothing() -> None:
    # The first two frames wait 60 ms for a retransmission (head-of-line: one QUIC
    # stream): the growth after them would be hidden, so the probe fails, on a narrow
    # link as it should, on a wide one for nothing (the next probe tries again).
    held = lambda i: 60.0 if i < 2 else 0.0  # noqa: E731
    assert run_probe(2.1e6, wobble=held)[1] is None
    assert run_probe(20e6, wobble=held)[1] is None


def test_without_a_delay_before_it_a_probe_proves_nothing() -> None:
    probe = LinkProbe()
    probe.start(2e6, 1e9, ["v"], 0.0)
    for i in range(6):
        probe.frame_sent(i, 10_000, 10_000, i / FPS)
    assert probe.report("v", [(i, 100.0 + i * 33.3) for i in range(6)], None, 0.5) is None
    assert probe.current is None and probe.succeeded == 0


def test_a_frame_never_reported_fails_it_at_the_timeout() -> None:
    probe = LinkProbe()
    probe.start(2e6, 1e9, ["v"], 0.0)
    for i in range(6):
        probe.frame_sent(i, 10_000, 10_000, i / FPS)
    # Five of six arrived; made-up pts are ignored and do not complete it.
    reported = [(i, 100.0 + i * 33.3) for i in range(5)] + [(99, 300.0), (98, 333.0)]
    assert probe.report("v", reported, 90.0, 0.5) is None
    assert probe.current is not None  # still waiting for the sixth
    probe.expire(MAX_PROBE_S + RESULT_TIMEOUT_S, ["v"])
    assert probe.current is None and probe.succeeded == 0 and probe.gain == FIRST_GAIN


def test_unpadded_frames_and_frames_after_its_end_are_not_the_probes() -> None:
    probe = LinkProbe()
    probe.start(2e6, 1e9, ["v"], 0.0)
    probe.frame_sent(1, 10_000, 0, 0.03)  # not padded: the encoder had not heard yet
    for i in range(2, 2 + MIN_FRAMES):
        probe.frame_sent(i, 10_000, 10_000, i / FPS)
    probe.frame_sent(50, 10_000, 10_000, PROBE_S + 0.05)  # padded late: after its end
    assert probe.current is not None
    assert sorted(probe.current.frames) == list(range(2, 2 + MIN_FRAMES))


def test_a_slow_stream_is_padded_until_it_has_enough_frames_but_not_for_ever() -> None:
    probe = LinkProbe()
    probe.start(2e6, 1e9, ["v"], 0.0)
    for i in range(3):  # 10 fps: three frames by the end of PROBE_S
        probe.frame_sent(i, 10_000, 10_000, i / 10)
    assert probe.padding_bps(PROBE_S + 0.05) > 0  # still short of MIN_FRAMES
    assert probe.padding_bps(MAX_PROBE_S) == 0  # but never longer than this


def test_a_viewer_that_leaves_does_not_hold_the_probe() -> None:
    probe = LinkProbe()
    probe.start(2e6, 1e9, ["v", "gone"], 0.0)
    for i in range(MIN_FRAMES + 1):
        probe.frame_sent(i, 10_000, 10_000, i / FPS)
    probe.report("v", [(i, 100.0 + i * 33.3) for i in range(MIN_FRAMES + 1)], 90.0, 0.5)
    assert probe.current is not None
    probe.expire(0.6, ["v"])
    assert probe.current is None and probe.succeeded == 1
