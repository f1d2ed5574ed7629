"""The broadcast test harness: a GameBroadcast attached to the in-memory moq pipe, with
the relay's side of it recorded (tests/test_session_broadcast.py, test_broadcast_ladder.py)."""

from __future__ import annotations

from collections.abc import Callable

from server.frames.frame import Camera, FrameMeta
from server.frames.timing import Stage, stamp
from server.media.encode import EncodedFrame
from server.moq import events as ev
from server.session.broadcast import GameBroadcast
from tests.moq_pipe import Pipe

CATALOG = b'{"video":{"renditions":{}}}'


class Harness:
    def __init__(
        self,
        audio: bool = False,
        *,
        catalog: bytes = CATALOG,
        rung_tracks: tuple[str, ...] = (),
        on_rung_keyframe_wanted: Callable[[], None] | None = None,
        on_rungs_watched: Callable[[frozenset[str]], None] | None = None,
    ) -> None:
        """The rung arguments are GameBroadcast's (tests/test_broadcast_ladder.py)."""
        self.pipe = Pipe()
        self.inputs: list[tuple[str, bytes]] = []
        self.keyframe_requests = 0
        self.ended: list[str] = []
        self.broadcast = GameBroadcast(
            "game",
            catalog,
            on_input=lambda path, payload: self.inputs.append((path, payload)),
            on_keyframe_wanted=self._want_keyframe,
            on_input_ended=self.ended.append,
            audio=audio,
            rung_tracks=rung_tracks,
            on_rung_keyframe_wanted=on_rung_keyframe_wanted,
            on_rungs_watched=on_rungs_watched,
        )
        self.broadcast.attach(self.pipe.client)
        self.relay_events: list[ev.Event] = []
        self.sync()

    def _want_keyframe(self) -> None:
        self.keyframe_requests += 1

    def sync(self) -> None:
        for _ in range(10):
            self.pipe.flush()
            self.broadcast.handle(self.pipe.client.take_events())
            self.relay_events += self.pipe.server.take_events()
            if not self.pipe.flush():
                break

    def frames(self, subscription: int) -> list[tuple[int, bytes]]:
        return [
            (e.sequence, e.payload)
            for e in self.relay_events
            if isinstance(e, ev.FrameReceived) and e.subscription_id == subscription
        ]

    def publish(self, frame_id: int, keyframe: bool, game_time_us: int | None = None) -> FrameMeta:
        if game_time_us is None:
            game_time_us = frame_id * 50_000
        meta = FrameMeta(
            frame_id, Camera.identity(), input_seq=frame_id * 10, game_time_us=game_time_us
        )
        stamp(meta.stamps, Stage.RENDER_START)
        stamp(meta.stamps, Stage.RENDER_END)
        encoded = EncodedFrame(
            frame_id, frame_id * 1000, keyframe, f"frag{frame_id}".encode(), 1.0, 0.1, 0.9
        )
        self.broadcast.publish_frame(encoded, meta)
        self.sync()
        return meta
