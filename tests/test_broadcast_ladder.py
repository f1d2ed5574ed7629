"""GameBroadcast with a rendition ladder, over the in-memory moq pipe: rung tracks are
served from their IDRs, ask the ladder (not the player's encoder) for a keyframe, and a
dropped rung ends its subscriptions while the player's track goes on."""

from __future__ import annotations

import json
from collections.abc import Callable

from server.media.encode import EncodedFrame
from server.moq import events as ev
from server.moq.errors import ErrorCode
from tests.broadcast_harness import Harness

RUNGS = ("video.320x180", "video.160x90")
CATALOG = json.dumps({"video": {"renditions": {key: {} for key in ("video", *RUNGS)}}}).encode()


class LadderHarness(Harness):
    """The broadcast harness with the ladder's rungs and callbacks counted."""

    def __init__(self, on_rungs_watched: Callable[[frozenset[str]], None] | None = None) -> None:
        self.rung_keyframes = 0
        super().__init__(
            catalog=CATALOG,
            rung_tracks=RUNGS,
            on_rung_keyframe_wanted=self._rung_keyframe,
            on_rungs_watched=on_rungs_watched,
        )

    @property
    def player_keyframes(self) -> int:
        return self.keyframe_requests

    def _rung_keyframe(self) -> None:
        self.rung_keyframes += 1

    def rung(self, track: str, frame_id: int, keyframe: bool) -> None:
        payload = f"{track}:{frame_id}".encode()
        encoded = EncodedFrame(frame_id, frame_id * 1000, keyframe, payload, 1.0, 0.1, 0.9)
        self.broadcast.publish_rung(track, encoded)
        self.sync()


def test_rung_subscribers_get_groups_from_rung_idrs_and_ask_the_ladder() -> None:
    h = LadderHarness()
    small = h.pipe.server.subscribe("game", "video.160x90")
    h.sync()
    assert (h.rung_keyframes, h.player_keyframes) == (1, 0)
    h.rung("video.160x90", 1, keyframe=False)  # mid-group: waits for the next IDR
    h.rung("video.160x90", 2, keyframe=True)
    h.rung("video.320x180", 2, keyframe=True)  # another rung's frame: not this track's
    h.rung("video.160x90", 3, keyframe=False)
    h.rung("video.160x90", 4, keyframe=True)
    assert h.frames(small) == [
        (0, b"video.160x90:2"),
        (0, b"video.160x90:3"),
        (1, b"video.160x90:4"),
    ]


def test_unknown_rungs_are_refused_and_listed_rungs_counted() -> None:
    h = LadderHarness()
    h.pipe.server.subscribe("game", "video.1280x720")
    h.pipe.server.subscribe("game", "video.320x180")
    h.sync()
    refused = [e for e in h.relay_events if isinstance(e, ev.SubscribeClosed)]
    assert [e.error_code for e in refused] == [ErrorCode.NOT_FOUND]
    assert h.broadcast.stats.subscribers["video.320x180"] == 1


def test_a_dropped_rung_ends_its_subscribers_and_republishes_the_catalog() -> None:
    h = LadderHarness()
    catalog = h.pipe.server.subscribe("game", "catalog.json")
    small = h.pipe.server.subscribe("game", "video.160x90")
    big = h.pipe.server.subscribe("game", "video.320x180")
    h.sync()
    h.rung("video.160x90", 1, keyframe=True)
    h.rung("video.320x180", 1, keyframe=True)
    without = json.dumps({"video": {"renditions": {"video": {}, "video.320x180": {}}}}).encode()
    h.broadcast.drop_rung("video.160x90", without)
    h.sync()
    ended = [e.subscription_id for e in h.relay_events if isinstance(e, ev.SubscribeClosed)]
    assert ended == [small]
    assert h.frames(catalog)[-1] == (1, without)
    assert "video.160x90" not in h.broadcast.tracks
    h.rung("video.160x90", 2, keyframe=True)  # a late frame of the dropped rung: ignored
    h.rung("video.320x180", 2, keyframe=True)
    assert h.frames(big)[-1] == (1, b"video.320x180:2")
    assert h.frames(small) == [(0, b"video.160x90:1")]


def test_the_ladder_is_told_which_rungs_someone_watches() -> None:
    watched: list[frozenset[str]] = []
    h = LadderHarness(on_rungs_watched=watched.append)
    small = h.pipe.server.subscribe("game", "video.160x90")
    h.sync()
    h.pipe.server.subscribe("game", "video.320x180")
    h.sync()
    h.pipe.server.unsubscribe(small)
    h.sync()
    h.broadcast.detach()  # the relay connection is gone: nobody watches
    assert watched == [
        frozenset({"video.160x90"}),
        frozenset({"video.160x90", "video.320x180"}),
        frozenset({"video.320x180"}),
        frozenset(),
    ]
