"""The player reports what it receives, counts honestly and recovers by itself (issue 21).

Against the live stack (relay process, game, session) and headless Chromium:
- the page sends a ``feedback`` message on its input track every 250 ms; the session
  receives them (the broadcast's input callback is wrapped here: the router ignores
  them for now) and they validate against server/session/viewer_input.py;
- when a video group ends early (the page's fault hook cuts it short, as the relay's
  reset of a late viewer's group does) the page counts the skipped group and the lost
  frames (mfhd jumps), asks for a keyframe by itself and shows frames again within a
  second (the encoder makes no periodic IDR with intra refresh on, at most one a few
  seconds apart without);
- after 3 s in which every video frame is thrown away (a blackout) it asks again
  until a keyframe comes, and plays on without a reload or a reconnect;
- a garbled frame makes WebCodecs fail (the decoder closes itself): the page builds a
  new decoder, asks for a keyframe and decodes again;
- through the network emulator (server/net: a UDP proxy between the page and the
  relay), 3 s of 100 % loss both ways: the QUIC session survives, the relay resets
  the group the page lagged in, the page asks for a keyframe and plays on; 12 s of
  it: the connection dies (10 s idle timeout) and the page reconnects by itself.
- a 100 kbit/s link for 3 s: every frame the encoder made is received or counted
  lost by the page (the timing track's gaps, the old "lost", say far fewer).

The counters' and the recovery's logic alone (client_web/src/feedback.ts, recovery.ts,
fragment.ts) is checked in node first, on fragments server/media/cmaf.py wrote.
"""

from __future__ import annotations

import itertools
import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from server.media.cmaf import media_fragment
from server.net.emulator import EmulatorThread
from server.net.link_profile import LinkProfile, Schedule
from server.session.viewer_input import FeedbackMessage, KeyframeMessage, parse_viewer_message
from tests.e2e.conftest import Live, needs, open_player, start_live, stats
from tests.test_encode_catalog import HANG_MISSING, HANG_REASON, run_in_node

CABLE = LinkProfile.both_ways(rate_bps=20e6, rtt_ms=15.0)
DEAD = LinkProfile.both_ways(rate_bps=20e6, rtt_ms=15.0, loss=1.0)
CLIENT = Path(__file__).resolve().parents[2] / "client_web"
FAULT_REASON = "group dropped (test fault)"  # client_web/src/media.ts #fault()
E2E = [*needs("index.html"), pytest.mark.timeout(180)]


def e2e(test: Any) -> Any:
    """Marks of a test that needs Chromium and the built client (the node check does not)."""
    for mark in E2E:
        test = mark(test)
    return test


class InputTap:
    """Wraps the broadcast's input callback: keeps every viewer message it passes on."""

    def __init__(self, broadcast: Any) -> None:
        self._inner = broadcast._on_input
        self._lock = threading.Lock()
        self.messages: list[tuple[float, str, Any]] = []  # (monotonic s, source, parsed)
        broadcast._on_input = self

    def __call__(self, source: str, payload: bytes) -> None:
        message: Any
        try:
            message = parse_viewer_message(payload)
        except Exception as exc:  # the router refuses it too; keep it for the assertion
            message = exc
        with self._lock:
            self.messages.append((time.monotonic(), source, message))
        self._inner(source, payload)

    def of(self, kind: type, since: float = 0.0) -> list[tuple[float, str, Any]]:
        with self._lock:
            return [m for m in self.messages if isinstance(m[2], kind) and m[0] >= since]

    def refused(self) -> list[Any]:
        with self._lock:
            return [m for _, _, m in self.messages if isinstance(m, Exception)]


@pytest.fixture(scope="module")
def live() -> Iterator[tuple[Live, InputTap]]:
    with start_live("default") as live:
        session = live.stack.session
        assert session is not None
        yield live, InputTap(session.broadcast)


@pytest.fixture()
def page(live: tuple[Live, InputTap], browser: Any) -> Iterator[Any]:
    page = open_player(browser, live[0].player_url(), frames=10)
    try:
        # The session subscribes to the page's input broadcast shortly after it connects.
        page.wait_for_function("() => window.upcast.stats().feedbackSent >= 2", timeout=15_000)
        yield page
    finally:
        page.close()


@pytest.mark.skipif(HANG_MISSING, reason=HANG_REASON)
def test_counters_and_recovery_logic_in_node(tmp_path: Path) -> None:
    fragments = [(7, 2**33 + 5, True), (1, 0, False), (123456, 33_333, False)]
    args = []
    for i, (sequence, decode_time, key) in enumerate(fragments):
        path = tmp_path / f"f{i}.m4s"
        path.write_bytes(media_fragment(sequence, decode_time, 33_333, b"\0\0\0\1\x65", key))
        args.append(f"{path}:{sequence}:{decode_time}")
    out = run_in_node(tmp_path, CLIENT / "test" / "feedback_check.ts", *args)
    assert out == {"failures": []}


def _published(live: Live) -> int:
    session = live.stack.session
    assert session is not None
    return int(session.broadcast.stats.frames_published)


def _feedback(tap: InputTap, since: float = 0.0) -> list[FeedbackMessage]:
    return [m for _, _, m in tap.of(FeedbackMessage, since)]


@e2e
def test_page_sends_feedback(live: tuple[Live, InputTap], page: Any) -> None:
    stack, tap = live
    published = _published(stack)
    t0 = time.monotonic()
    page.wait_for_timeout(1500)
    got = _feedback(tap, t0)
    published = _published(stack) - published
    s = stats(page)
    print("feedback:", len(got), "last:", got[-1].model_dump() if got else None)
    # Every 250 ms: about 6 in 1.5 s (a loaded machine may delay a timer or two).
    assert 4 <= len(got) <= 8, len(got)
    assert not tap.refused()
    assert all(m.player for m in got)
    seqs = [m.seq for m in got]
    assert seqs == sorted(seqs)
    frames = [f for m in got for f in m.frames]
    # Each frame the session published in the window reported once, in order (30 fps
    # is the target; a loaded 2-core machine makes 5 to 30).
    assert len(frames) >= 0.6 * published - 2 and frames, (len(frames), published)
    pts = [p for p, _ in frames]
    arrivals = [a for _, a in frames]
    assert pts == sorted(set(pts)), "each frame reported once, in order"
    assert arrivals == sorted(arrivals)
    # pts in microseconds (the encoder's capture clock): ~1.5 s of them, frames apart.
    assert min(b - a for a, b in itertools.pairwise(pts)) > 10_000
    assert pts[-1] - pts[0] < 2.5e6, (pts[0], pts[-1])
    # Counters are cumulative and match the page's own.
    last = got[-1]
    assert last.bytes > 0 and last.bytes <= s["bytesReceived"]
    assert last.lost <= s["framesLost"] and last.skipped <= s["groupsSkipped"]
    assert [m.bytes for m in got] == sorted(m.bytes for m in got)
    assert s["feedbackSent"] >= len(got)


def _recovered(page: Any, before: dict[str, Any], timeout_ms: float) -> dict[str, Any]:
    page.wait_for_function(
        "n => window.upcast.stats().recovery.recoveries > n",
        arg=before["recovery"]["recoveries"],
        timeout=timeout_ms,
    )
    return stats(page)


@e2e
def test_skipped_group_counted_and_recovered_by_a_keyframe_request(
    live: tuple[Live, InputTap], page: Any
) -> None:
    stack, tap = live
    session = stack.stack.session
    assert session is not None
    forced = session.encoder.forced_keyframes
    first = stats(page)
    attempts = 3
    for attempt in range(attempts):
        before = stats(page)
        t0 = time.monotonic()
        page.evaluate("() => window.upcast.faults.dropGroup()")
        after = _recovered(page, before, 5000)
        # A wait that began for another reason at the same moment makes the recovery
        # the page reports that one's, not the fault's: a decoder that fell behind (its
        # queue overflowed: the page starved of CPU, seen in CI on 2 cores, 1.1 s with
        # two IDRs) or the relay resetting the group of a page that lagged (seen in CI,
        # 1.02 s with two requests: the first keyframe's group was reset too). Drop a
        # group again once frames flow: the fault's recovery is what this test times.
        if after["recovery"]["reason"] == FAULT_REASON or attempt == attempts - 1:
            break
        print(f"skip: the wait was for {after['recovery']['reason']!r}, not the fault; once more")
        page.wait_for_function(
            "n => window.upcast.stats().framesPresented >= n + 10", arg=after["framesPresented"]
        )
    presented = after["framesPresented"]
    page.wait_for_function("n => window.upcast.stats().framesPresented >= n + 10", arg=presented)
    end = stats(page)
    requests = tap.of(KeyframeMessage, t0)
    summary = {
        "recovery_ms": after["recovery"]["lastRecoveryMs"],
        "reason": after["recovery"]["reason"],
        "requests": after["recovery"]["keyframeRequests"] - before["recovery"]["keyframeRequests"],
        "skipped": end["groupsSkipped"] - first["groupsSkipped"],
        "lost": end["framesLost"] - first["framesLost"],
        "forced_idr": session.encoder.forced_keyframes - forced,
        "longest_freeze_ms": end["longestFreezeMs"],
        "status": end["status"],
    }
    print("skip:", json.dumps(summary))
    assert summary["skipped"] >= 1
    assert summary["lost"] >= 1  # the rest of the group never arrived: a jump in mfhd
    assert summary["requests"] >= 1 and requests, "the page asked for a keyframe itself"
    assert summary["forced_idr"] >= 1
    # Frames again within a second: the asked-for IDR, not a periodic one (none with
    # intra refresh, 2 s apart without).
    assert summary["reason"] == FAULT_REASON, summary
    assert summary["recovery_ms"] < 1000, summary
    assert end["status"].startswith("subscribed")
    # The session heard of it through the feedback too.
    page.wait_for_timeout(400)
    last = _feedback(tap)[-1]
    assert last.skipped >= end["groupsSkipped"] and last.lost >= end["framesLost"], last


@e2e
def test_three_seconds_of_total_loss_recovers_without_reload(
    live: tuple[Live, InputTap], page: Any
) -> None:
    stack, tap = live
    before = stats(page)
    t0 = time.monotonic()
    published = _published(stack)
    page.evaluate("() => window.upcast.faults.blackout(3000)")
    t_end = time.monotonic() + 3.0
    page.wait_for_timeout(3000)
    published = _published(stack) - published
    presented_at_end = stats(page)["framesPresented"]
    page.wait_for_function(
        "n => window.upcast.stats().framesPresented >= n + 5", arg=presented_at_end, timeout=5000
    )
    back_s = time.monotonic() - t_end
    end = stats(page)
    summary = {
        "frames_again_after_s": round(back_s, 2),
        "requests": end["recovery"]["keyframeRequests"] - before["recovery"]["keyframeRequests"],
        "recovery_ms": end["recovery"]["lastRecoveryMs"],
        "freezes": end["freezes"] - before["freezes"],
        "freeze_ms": end["freezeMs"] - before["freezeMs"],
        "skipped": end["groupsSkipped"] - before["groupsSkipped"],
        "lost": end["framesLost"] - before["framesLost"],
        "published_in_blackout": published,
        "status": end["status"],
        "version": [before["version"], end["version"]],
    }
    print("blackout:", json.dumps(summary))
    # Asked at once and again while nothing came (the asked keyframes fell in the blackout).
    assert summary["requests"] >= 3, summary
    assert len(tap.of(KeyframeMessage, t0)) >= 3  # and the session got them
    # The retry after the blackout: frames within about a second of its end.
    assert back_s < 1.6, summary
    assert end["recovery"]["recoveries"] > before["recovery"]["recoveries"]
    assert summary["freezes"] >= 1 and summary["freeze_ms"] >= 2900, summary
    assert summary["lost"] >= 0.8 * published, summary  # every frame of the 3 s
    # The same connection and subscription: no reload, no reconnect.
    assert end["status"].startswith("subscribed") and before["version"] == end["version"]
    assert not [e for e in end["errors"] if "decoder" in e], end["errors"]


@e2e
def test_decoder_error_rebuilds_the_decoder_and_asks_for_a_keyframe(
    live: tuple[Live, InputTap], page: Any
) -> None:
    before = stats(page)
    # A garbled frame (its first NAL length absurd): WebCodecs errors and closes the decoder.
    page.evaluate("() => window.upcast.faults.corrupt(1)")
    after = _recovered(page, before, 5000)
    page.wait_for_function(
        "n => window.upcast.stats().framesDecoded >= n + 10", arg=after["framesDecoded"]
    )
    end = stats(page)
    summary = {
        "reason": after["recovery"]["reason"],
        "recovery_ms": after["recovery"]["lastRecoveryMs"],
        "requests": end["recovery"]["keyframeRequests"] - before["recovery"]["keyframeRequests"],
        "errors": end["errors"][-2:],
    }
    print("decoder error:", json.dumps(summary))
    assert any(e.startswith("decoder:") for e in end["errors"]), summary
    assert summary["reason"] == "decoder error" and summary["requests"] >= 1, summary
    assert summary["recovery_ms"] < 1000, summary


def _through_dead_link(
    live: tuple[Live, InputTap],
    browser: Any,
    dead_s: float,
    link: LinkProfile = DEAD,
    settle_ms: float = 0.0,
) -> tuple[dict[str, Any], dict[str, Any], float]:
    """Plays through the emulator, then cuts the link both ways for ``dead_s`` (or
    makes it ``link``); returns the page's stats before the cut and once frames flow
    again (and ``settle_ms`` later), and how long after the link came back they did.
    Each has ``encoded``: the fragments the encoder had made when it was read."""
    stack, _ = live
    session = stack.stack.session
    assert session is not None
    lead_s = 3.0  # of normal play after the schedule restarts (the page loads before)
    schedule = Schedule.of([(0.0, CABLE), (lead_s, link), (lead_s + dead_s, CABLE)])
    with EmulatorThread(
        upstream=("127.0.0.1", stack.port), schedule=schedule, tcp_passthrough=True
    ) as net:
        page = open_player(browser, stack.stack.player_url(overlay="0", port=str(net.port)))
        try:
            page.wait_for_function("() => window.upcast.stats().feedbackSent >= 2", timeout=15_000)
            # Page loads take seconds here: the schedule counts from now on.
            net.restart_schedule()
            t_cut = time.monotonic() + lead_s
            page.wait_for_timeout(lead_s * 1000 - 300)
            before = {**stats(page), "encoded": session.encoder.fragments_out}
            page.wait_for_timeout((t_cut + dead_s - time.monotonic()) * 1000)
            t_back = time.monotonic()
            presented = stats(page)["framesPresented"]
            page.wait_for_function(
                "n => window.upcast.stats().framesPresented >= n + 5", arg=presented, timeout=15_000
            )
            back_s = time.monotonic() - t_back
            page.wait_for_timeout(settle_ms)
            end = {**stats(page), "encoded": session.encoder.fragments_out}
        finally:
            page.close()
        print("emulator:", json.dumps(net.stats()["down"]))
    return before, end, back_s


@e2e
def test_network_blackout_of_three_seconds_recovers_on_the_same_connection(
    live: tuple[Live, InputTap], browser: Any
) -> None:
    before, end, back_s = _through_dead_link(live, browser, 3.0)
    summary = {
        "frames_again_after_s": round(back_s, 2),
        "requests": end["recovery"]["keyframeRequests"] - before["recovery"]["keyframeRequests"],
        "recovery_ms": end["recovery"]["lastRecoveryMs"],
        "reason": end["recovery"]["reason"],
        "freezes": end["freezes"] - before["freezes"],
        "longest_freeze_ms": end["longestFreezeMs"],
        "skipped": end["groupsSkipped"] - before["groupsSkipped"],
        "lost": end["framesLost"] - before["framesLost"],
        "connections": end["connections"],
        "status": end["status"],
    }
    print("network blackout:", json.dumps(summary))
    assert end["connections"] == 1 and end["status"].startswith("subscribed"), summary
    # What was sent in the blackout is gone: the relay reset the group the page lagged in.
    assert summary["skipped"] >= 1 and summary["lost"] >= 5, summary
    # A keyframe request unless an IDR (periodic without intra refresh) fell in the blackout: then
    # the relay already holds a newer group that starts at it, and none is needed.
    assert (
        summary["requests"] >= 1
        or end["recovery"]["recoveries"] == before["recovery"]["recoveries"]
    )
    assert end["longestFreezeMs"] >= 2900, summary
    # QUIC probes the path again within its backoff; then a keyframe on request.
    assert back_s < 3.0, summary


@e2e
def test_connection_lost_to_a_long_blackout_reconnects(
    live: tuple[Live, InputTap], browser: Any
) -> None:
    # Longer than the relay's and the page's 10 s QUIC idle timeout: the connection dies.
    before, end, back_s = _through_dead_link(live, browser, 12.0)
    summary = {
        "frames_again_after_s": round(back_s, 2),
        "connections": [before["connections"], end["connections"]],
        "status": end["status"],
    }
    print("long blackout:", json.dumps(summary))
    assert before["connections"] == 1 and end["connections"] >= 2, summary
    assert end["status"].startswith("subscribed")
    # Reconnect back-off (0.5 s doubling to 5 s while the link is dead), connect, subscribe.
    assert back_s < 10.0, summary


@e2e
def test_lost_frames_are_counted_from_the_video_track(
    live: tuple[Live, InputTap], browser: Any
) -> None:
    # 100 kbit/s for 3 s, far below the stream: the relay skips the page ahead (resets
    # the groups it lags in) and frames never arrive.
    slow = LinkProfile.both_ways(rate_bps=100e3, rtt_ms=15.0)
    # Read 1 s after frames flow again: the backlog of the slow link has drained.
    before, end, back_s = _through_dead_link(live, browser, 3.0, slow, settle_ms=1000)
    encoded = end["encoded"] - before["encoded"]
    received = end["framesReceived"] - before["framesReceived"]
    lost = end["framesLost"] - before["framesLost"]
    summary = {
        "encoded": encoded,
        "received": received,
        "lost": lost,
        "skipped": end["groupsSkipped"] - before["groupsSkipped"],
        "timing_gaps": end["timingGaps"] - before["timingGaps"],
        "requests": end["recovery"]["keyframeRequests"] - before["recovery"]["keyframeRequests"],
        "frames_again_after_s": round(back_s, 2),
    }
    print("slow link:", json.dumps(summary))
    assert lost >= 1 and summary["skipped"] >= 1, summary
    # Every frame the encoder made is either received or counted lost (up to the few
    # in flight when each side was read).
    assert abs(received + lost - encoded) <= 6, summary
