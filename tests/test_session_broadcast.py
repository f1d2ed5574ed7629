"""GameBroadcast over the in-memory moq pipe: tracks, groups at keyframes, timing, inputs."""

from __future__ import annotations

import json

from server.frames.timing import Stage
from server.moq import events as ev
from tests.broadcast_harness import CATALOG, Harness


def test_relay_learns_the_broadcast_and_gets_the_catalog() -> None:
    h = Harness()
    interest = h.pipe.server.request_announces("")
    h.sync()
    announces = [e for e in h.relay_events if isinstance(e, ev.AnnounceReceived)]
    assert [(a.handle, a.path, a.active) for a in announces] == [(interest, "game", True)]
    sub = h.pipe.server.subscribe("game", "catalog.json")
    h.sync()
    assert h.frames(sub) == [(0, CATALOG)]
    closed = [e for e in h.relay_events if isinstance(e, ev.GroupClosed)]
    assert closed and closed[0].complete
    # A new catalog (say, a new size) reaches subscribers as a new group.
    h.broadcast.set_catalog(b"{}")
    h.sync()
    assert h.frames(sub)[-1] == (1, b"{}")


def test_video_groups_start_at_keyframes_and_timing_follows() -> None:
    h = Harness()
    h.broadcast.stream_state.update(upscaler="temporal", scale=2.0)
    video = h.pipe.server.subscribe("game", "video")
    timing = h.pipe.server.subscribe("game", "timing")
    h.sync()
    assert h.keyframe_requests == 2  # each new subscriber asks for a keyframe
    h.publish(1, keyframe=False)  # mid-group: nothing until a keyframe, never a broken group
    assert h.frames(video) == []
    # Frame 3 comes from a source without a game clock: game time unknown (0).
    metas = [h.publish(2, keyframe=True), h.publish(3, keyframe=False, game_time_us=0)]
    h.publish(4, keyframe=True)
    assert h.frames(video) == [(0, b"frag2"), (0, b"frag3"), (1, b"frag4")]
    records = [json.loads(p) for _, p in h.frames(timing)]
    assert [r["frame"] for r in records] == [2, 3, 4]
    assert [r["n"] for r in records] == [1, 2, 3]  # frame 1 was published too (n=0)
    assert [r["pts_us"] for r in records] == [2000, 3000, 4000]
    assert records[0]["keyframe"] and not records[1]["keyframe"]
    assert records[1]["input_seq"] == 30
    assert records[0]["game_time_us"] == 100_000 and records[2]["game_time_us"] == 200_000
    assert "game_time_us" not in records[1]  # unknown: left out, not sent as 0
    assert records[0]["upscaler"] == "temporal" and records[0]["scale"] == 2.0
    stamps = records[0]["stamps"]
    assert stamps["render_start"] <= stamps["render_end"] <= stamps["publish"]
    assert metas[0].stamps[Stage.PUBLISH, 0] > 0  # publish is stamped on the frame itself
    groups_done = [e for e in h.relay_events if isinstance(e, ev.GroupClosed) and e.sequence == 0]
    assert len(groups_done) == 2 and all(g.complete for g in groups_done)


def test_unknown_track_or_broadcast_is_refused_and_the_session_goes_on() -> None:
    h = Harness()
    bad_track = h.pipe.server.subscribe("game", "audio")
    bad_broadcast = h.pipe.server.subscribe("other", "video")
    video = h.pipe.server.subscribe("game", "video")
    h.sync()
    refused = {
        e.subscription_id
        for e in h.relay_events
        if isinstance(e, ev.SubscribeClosed) and not e.accepted
    }
    assert refused == {bad_track, bad_broadcast}
    h.publish(1, keyframe=True)
    assert h.frames(video) == [(0, b"frag1")]


def test_viewer_input_broadcasts_are_subscribed_and_delivered() -> None:
    h = Harness()
    h.pipe.server.publish("game/input/v1")
    h.pipe.server.publish("elsewhere/input/v2")  # not under game/input: ignored
    h.sync()
    requests = [e for e in h.relay_events if isinstance(e, ev.SubscribeRequested)]
    assert [(r.broadcast, r.track) for r in requests] == [("game/input/v1", "input")]
    # A viewer's whole input is one long group: the relay must never skip it ahead
    # because the session lagged (that lost every later message, feedback included).
    assert requests[0].max_latency_ms >= 60_000
    request_id = requests[0].request_id
    assert h.pipe.server.accept_subscribe(request_id)
    group = h.pipe.server.open_group(request_id, 0)
    assert group is not None
    h.pipe.server.write_frame(group, b'{"type":"keyframe"}')
    h.sync()
    assert h.inputs == [("game/input/v1", b'{"type":"keyframe"}')]
    # The viewer leaves: its input subscription is dropped.
    h.pipe.server.unpublish("game/input/v1")
    h.sync()
    assert h.broadcast.stats.input_broadcasts == 1
    assert h.broadcast._input_paths == {}
    assert h.ended == ["game/input/v1"]


def test_a_new_encoded_size_moves_the_video_to_a_new_track_named_by_the_catalog() -> None:
    h = Harness()
    catalog = h.pipe.server.subscribe("game", "catalog.json")
    old = h.pipe.server.subscribe("game", "video")
    h.sync()
    h.publish(1, keyframe=True)
    h.publish(2, keyframe=False)
    # The new size's catalog goes out before its first frame; the old track's open
    # group ends complete (FIN), not reset: the viewer counts nothing skipped.
    h.broadcast.switch_video("video.1", b'{"new":1}')
    h.sync()
    assert h.frames(catalog)[-1] == (1, b'{"new":1}')
    closed = [
        e for e in h.relay_events if isinstance(e, ev.GroupClosed) and e.subscription_id == old
    ]
    assert closed and all(g.complete for g in closed)
    h.publish(3, keyframe=True)
    assert h.frames(old) == [(0, b"frag1"), (0, b"frag2")]  # nothing more on the old track
    # A viewer that read the catalog subscribes to the new track and starts at a keyframe.
    requests = h.keyframe_requests
    new = h.pipe.server.subscribe("game", "video.1")
    stale = h.pipe.server.subscribe("game", "video")  # a catalog it no longer may follow
    h.sync()
    assert h.keyframe_requests == requests + 1
    refused = {
        e.subscription_id
        for e in h.relay_events
        if isinstance(e, ev.SubscribeClosed) and not e.accepted
    }
    assert stale in refused and new not in refused
    h.publish(4, keyframe=False)
    h.publish(5, keyframe=True)
    assert h.frames(new) == [(2, b"frag5")]
    assert h.broadcast.stats.subscribers["video.1"] == 1
    # The old subscription is still counted until the viewer closes it.
    assert h.broadcast.stats.subscribers["video"] == 1
    # Switching to the track already in use changes nothing.
    h.broadcast.switch_video("video.1", b"{}")
    h.sync()
    assert h.frames(catalog)[-1] == (1, b'{"new":1}')
