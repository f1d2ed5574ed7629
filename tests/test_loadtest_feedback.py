"""The load-test viewer's honest counters and its feedback messages.

Counters: synthetic CMAF fragments and moq-lite group events fed to a LoadViewer
as the link would (no network): frames lost from mfhd gaps (late fragments of an
interleaved group are not lost), skipped and reset groups, freezes. Feedback: the
message validates as the session's FeedbackMessage and stays under the input
limit. Live: the real stack (LiveStack, as ``upcast up`` runs it) receives the
viewers' feedback on its input router.
"""

from __future__ import annotations

import asyncio
import time

import pytest

from server.loadtest.feedback_sender import FeedbackCounts, FeedbackSender
from server.loadtest.plan import RunPlan
from server.loadtest.viewer import LoadViewer, ViewerConfig, run_viewers
from server.loadtest.viewer_stats import REORDER_FRAGMENTS, DeliveryCounters
from server.media.cmaf import media_fragment
from server.moq.events import FrameReceived, GroupClosed, GroupOpened
from server.session.feedback import MAX_FEEDBACK_FRAMES
from server.session.viewer_input import (
    MAX_MESSAGE_BYTES,
    FeedbackMessage,
    parse_viewer_message,
)

VIDEO_SUB = 7


def _viewer() -> LoadViewer:
    viewer = LoadViewer(0, ViewerConfig("http://127.0.0.1:1/", "game", None, 1.0), (0.0, 1e12))
    viewer._video_track = "video0"
    viewer._tracks[VIDEO_SUB] = "video0"
    return viewer


def _feed(viewer: LoadViewer, events: list[object]) -> None:
    viewer._on_events(None, events)  # type: ignore[arg-type]


def _fragment(group: int, sequence: int) -> FrameReceived:
    payload = media_fragment(sequence, sequence * 33_333, 33_333, b"\0\0\0\1x", sequence == 1)
    return FrameReceived(VIDEO_SUB, group, stream_id=group * 4 + 3, payload=payload)


def test_counts_lost_fragments_skipped_and_reset_groups() -> None:
    viewer = _viewer()
    _feed(viewer, [GroupOpened(VIDEO_SUB, 0, 3)])
    _feed(viewer, [_fragment(0, s) for s in (1, 2, 3)])
    # Group 1 opens; its first fragments overtake the end of group 0 (4 and 5 come late).
    _feed(viewer, [GroupOpened(VIDEO_SUB, 1, 7), _fragment(1, 6), _fragment(1, 7)])
    _feed(viewer, [_fragment(0, 4), _fragment(0, 5)])
    # Group 1 is reset by the relay after fragment 8 (9, 10 never come); group 2 is
    # skipped; group 3 starts at 21.
    _feed(viewer, [_fragment(1, 8), GroupClosed(VIDEO_SUB, 1, 7, False, 1)])
    _feed(viewer, [GroupOpened(VIDEO_SUB, 3, 15)])
    _feed(viewer, [_fragment(3, s) for s in range(21, 21 + REORDER_FRAGMENTS + 2)])
    d = viewer.stats.delivery
    assert d.lost == 12  # 9..20: the reset group's tail and the whole skipped group
    assert (d.skipped_groups, d.reset_groups, d.skipped) == (1, 1, 2)
    assert viewer.stats.bad_fragments == 0
    assert viewer.stats.summary()["delivery"]["lost"] == 12


def test_open_gaps_count_only_after_reordering_or_at_the_end() -> None:
    d = DeliveryCounters()
    for s in (1, 2, 5):
        d.on_fragment(s, 0.0)
    assert d.lost == 0  # 3 and 4 may still come
    d.on_fragment(3, 0.0)
    d.settle()
    assert d.lost == 1  # 4 never came
    # A publisher that numbers afresh (new encoder) is not a loss.
    d.on_fragment(1, 0.0)
    d.on_fragment(2, 0.0)
    d.settle()
    assert d.lost == 1


def test_freezes_and_the_window() -> None:
    d = DeliveryCounters()
    window = DeliveryCounters()
    arrivals = [0.0, 0.033, 0.066, 0.5, 0.533, 1.5, 1.533]  # gaps of 434 and 967 ms
    for i, t in enumerate(arrivals):
        d.on_fragment(i + 1, t)
        window.on_fragment(i + 1, t, counting=t >= 1.0)
    assert d.freezes == 2
    assert d.freeze_ms == pytest.approx(434 + 967, abs=1)
    assert d.longest_freeze_ms == pytest.approx(967, abs=1)
    # The window opened at 1.0 s: its freeze is the one that ended inside it.
    assert (window.freezes, round(window.freeze_ms)) == (1, 967)


def test_feedback_message_is_what_the_session_accepts() -> None:
    sender = FeedbackSender("game", player=True, source_id="t")
    assert sender.path == "game/input/t"
    for i in range(MAX_FEEDBACK_FRAMES + 10):
        sender.note_frame(10**12 + i * 16_667, 9.9e9 + i * 16.7)
    wire = sender.message(FeedbackCounts(bytes=123, lost=2, skipped=1, freezes=1, freeze_ms=250))
    assert len(wire) <= MAX_MESSAGE_BYTES
    message = parse_viewer_message(wire)
    assert isinstance(message, FeedbackMessage)
    assert message.player and message.seq == 1
    assert (message.bytes, message.lost, message.skipped, message.freezes) == (123, 2, 1, 1)
    assert 0 < len(message.frames) <= MAX_FEEDBACK_FRAMES
    assert message.frames[-1][0] == 10**12 + (MAX_FEEDBACK_FRAMES + 9) * 16_667  # newest kept
    again = parse_viewer_message(sender.message(FeedbackCounts()))
    assert isinstance(again, FeedbackMessage) and again.seq == 2 and again.frames == []


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_the_session_receives_the_viewers_feedback() -> None:
    from server.bench.latency import LiveStack
    from server.stack.local import SessionConfig

    config = SessionConfig(render_size="160x90", display_size="320x180", fps=30.0)
    with LiveStack(config) as live:
        session = live.session
        assert session is not None
        accepted0 = session.router.accepted
        frames0 = session.broadcast.stats.input_frames
        viewer_config = ViewerConfig(
            f"http://localhost:{live.port}/",
            live.broadcast,
            live.endpoint.cert_sha256 if live.endpoint else None,
            10.0,
            token=live.tokens.player,
            feedback=True,
            player=True,
        )
        start = time.monotonic() + 0.1
        plan = RunPlan(
            start, 10.0, window_start=start + 1.0, window_end=start + 4.0, stop=start + 4.5
        )
        result = asyncio.run(run_viewers(viewer_config, plan, [0, 1], lambda _snap: None))
        live.check()
        received = session.broadcast.stats.input_frames - frames0
        accepted = session.router.accepted - accepted0
    stats = result.stats
    assert all(s.error is None and s.frames > 0 for s in stats), [s.summary() for s in stats]
    # Two viewers, about 4 messages a second each once the session subscribed.
    assert received >= 10, received
    assert accepted >= 10, accepted
