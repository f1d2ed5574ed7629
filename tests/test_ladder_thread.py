"""The ladder's thread: only the newest frame waits, a skipped frame's player IDR carries
over to the next one, a failing encode is counted and the thread goes on."""

from __future__ import annotations

import threading
from typing import Any

import numpy as np

from server.media.ladder import RungFrame
from server.session.ladder_thread import LadderThread


class GatedLadder:
    """Stands in for RenditionLadder: records what it was given, waits on a gate."""

    idle = False

    def __init__(self) -> None:
        self.calls: list[tuple[int, bool]] = []
        self.gate = threading.Event()
        self.entered = threading.Event()
        self.fail_on: set[int] = set()

    def encode(
        self, frame: Any, frame_id: int, pts_us: int, *, align: bool = False
    ) -> tuple[list[RungFrame], list[str]]:
        self.entered.set()
        assert self.gate.wait(5.0)
        self.calls.append((frame_id, align))
        if frame_id in self.fail_on:
            raise RuntimeError("encoder gone")
        return [], []


def test_only_the_newest_frame_waits_and_a_skipped_idr_carries_over() -> None:
    ladder = GatedLadder()
    delivered: list[int] = []
    done = threading.Event()

    def deliver(frames: list[RungFrame], failed: list[str]) -> None:
        delivered.append(len(ladder.calls))
        if len(ladder.calls) == 2:
            done.set()

    thread = LadderThread(ladder, deliver)  # type: ignore[arg-type]
    thread.start()
    frame = np.zeros((4, 4, 3), np.uint8)
    thread.submit(frame, None, 0, 0, False)
    assert ladder.entered.wait(5.0)  # frame 0 is being encoded; the rest queue up
    thread.submit(frame, None, 1, 1, True)  # the player's IDR
    thread.submit(frame, None, 2, 2, align=False)  # replaces frame 1
    thread.submit(frame, None, 3, 3, align=False)  # replaces frame 2
    ladder.gate.set()
    assert done.wait(5.0)
    thread.stop()
    assert ladder.calls == [(0, False), (3, True)]
    assert thread.stats.skipped == 2 and thread.stats.encoded == 2


def test_a_failing_frame_is_counted_and_the_next_is_encoded() -> None:
    ladder = GatedLadder()
    ladder.gate.set()
    ladder.fail_on = {0}
    encoded = threading.Event()
    thread = LadderThread(ladder, lambda frames, failed: encoded.set())  # type: ignore[arg-type]
    thread.start()
    frame = np.zeros((4, 4, 3), np.uint8)
    thread.submit(frame, None, 0, 0, False)
    for _ in range(500):
        if thread.stats.errors:
            break
        threading.Event().wait(0.01)
    thread.submit(frame, None, 1, 1, False)
    assert encoded.wait(5.0)
    thread.stop()
    assert thread.stats.errors == 1 and [c[0] for c in ladder.calls] == [0, 1]


def test_the_rgb_is_copied_before_the_ring_slot_is_reused() -> None:
    seen: list[int] = []

    class Keeper(GatedLadder):
        def encode(
            self, frame: Any, frame_id: int, pts_us: int, *, align: bool = False
        ) -> tuple[list[RungFrame], list[str]]:
            seen.append(int(frame[0, 0, 0]))
            return super().encode(frame, frame_id, pts_us, align=align)

    ladder = Keeper()
    done = threading.Event()
    thread = LadderThread(ladder, lambda frames, failed: done.set())  # type: ignore[arg-type]
    slot = np.full((4, 4, 3), 7, np.uint8)
    thread.submit(slot, None, 0, 0, False)
    slot[:] = 99  # the ring reuses the slot before the thread runs
    ladder.gate.set()
    thread.start()
    assert done.wait(5.0)
    thread.stop()
    assert seen == [7]


def test_the_ladder_metrics_count_each_rungs_frames_bytes_and_cpu() -> None:
    from prometheus_client import CollectorRegistry

    from server.frames.frame import Size
    from server.media.ladder import RenditionLadder
    from server.session.ladder_metrics import LadderMetrics

    registry = CollectorRegistry()
    ladder = RenditionLadder(Size(128, 72), 30.0, (2, 4))
    thread = LadderThread(ladder, lambda frames, failed: None)
    metrics = LadderMetrics(registry, ladder, thread)
    sizes = {}
    for i in range(3):
        frames, _ = ladder.encode(np.full((72, 128, 3), 40 * i, np.uint8), i, i * 33_333)
        metrics.published(frames)
        for f in frames:
            sizes[f.track] = sizes.get(f.track, 0) + len(f.encoded.fragment)
    for track in ("video.64x36", "video.32x18"):
        labels = {"track": track}
        assert registry.get_sample_value("upcast_ladder_frames_total", labels) == 3
        assert registry.get_sample_value("upcast_ladder_bytes_total", labels) == sizes[track]
        cpu = registry.get_sample_value("upcast_ladder_cpu_seconds", labels)
        assert cpu is not None and cpu > 0
    assert registry.get_sample_value("upcast_ladder_skipped_frames") == 0


def test_nothing_is_queued_or_copied_while_no_rung_is_watched() -> None:
    ladder = GatedLadder()
    ladder.idle = True
    thread = LadderThread(ladder, lambda frames, failed: None)  # type: ignore[arg-type]
    thread.submit(np.zeros((4, 4, 3), np.uint8), None, 0, 0, True)
    assert thread.stats.submitted == 0 and thread._pending is None
