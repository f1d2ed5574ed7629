"""Ring U -> encoder: presentation times handed to the encoder always increase.

The session starts its media clock (shared with the sound) after the game has already
filled the ring, so the first frames it reads were rendered before the origin and all
map to pts 0. Two of them used to reach the encoder, which refused the second
("pts_us must increase: 0 after 0") with a traceback in `upcast up`'s log (a
fresh-clone CI run of tests/e2e/test_up_command.py on a loaded machine).
"""

from __future__ import annotations

import time

import numpy as np

from server.frames.frame import Size
from server.frames.ring_frames import create_display_ring
from server.frames.timing import Stage
from server.media.encode import EncoderConfig, VideoEncoder
from server.session.capture import CapturedFrame, CaptureThread

SIZE = Size(64, 36)


def _until_seen(capture: CaptureThread, count: int, timeout_s: float = 5.0) -> None:
    """Until the capture has taken ``count`` frames (encoded or left out)."""
    deadline = time.monotonic() + timeout_s
    while capture.stats.frames + capture.stats.not_after_last < count:
        assert time.monotonic() < deadline, f"timed out: {capture.stats}"
        time.sleep(0.005)


def test_frames_from_before_the_clock_origin_are_not_encoded_twice_at_pts_zero(
    ring_name: str,
) -> None:
    ring = create_display_ring(ring_name, SIZE)
    delivered: list[CapturedFrame] = []
    origin = time.monotonic_ns()
    # Rendered 50 and 20 ms before the origin (both pts 0), then 10, 43 and 43 ms
    # after it (the last: a repeated stamp).
    render_ms = [-50, -20, 10, 43, 43, 76]
    capture = CaptureThread(
        ring, VideoEncoder(EncoderConfig(SIZE.width, SIZE.height, fps=30)), delivered.append,
        pts_origin_ns=origin,
    )  # fmt: skip
    try:
        capture.start()
        for i, ms in enumerate(render_ms):
            lease = ring.acquire_write(1.0)
            assert lease is not None
            lease.views(SIZE.width, SIZE.height)["color"][...] = np.uint8(40 * i)
            lease.header["frame_id"] = i
            lease.header["game_time_us"] = 1_000_000 + i
            lease.header["stamps"][Stage.RENDER_START] = (origin + ms * 1_000_000, 1)
            lease.commit(stamp_stage=Stage.RING_U_READY)
            # One frame at a time: the capture reads only the newest.
            _until_seen(capture, i + 1)
    finally:
        capture.stop()
        ring.unlink()
        ring.close()
    assert capture.stats.errors == 0
    assert [c.meta.frame_id for c in delivered] == [0, 2, 3, 5]
    # The game time rides along to the timing record (see test_session_broadcast).
    assert [c.meta.game_time_us for c in delivered] == [1_000_000, 1_000_002, 1_000_003, 1_000_005]
    assert [c.encoded.pts_us for c in delivered] == [0, 10_000, 43_000, 76_000]
    assert capture.stats.not_after_last == 2
