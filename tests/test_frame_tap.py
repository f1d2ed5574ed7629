"""The session's frame tap over HTTP (server/serve/frame_tap.py): what deploy/smoke.sh
compares a browser's canvas with when the session runs in a container."""

from __future__ import annotations

import base64
import io
import json
import logging
import socket
import time
import urllib.error
import urllib.request
from collections.abc import Iterator

import numpy as np
import pytest

from server.serve.frame_tap import FrameTapServer, start_frame_tap
from server.serve.snapshots import THUMB, FrameThumbs, page_thumbnail, thumbnail


def get(port: int, path: str) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=5) as r:
            return int(r.status), bytes(r.read())
    except urllib.error.HTTPError as exc:
        return int(exc.code), bytes(exc.read())


def frame(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (72, 128, 3), dtype=np.uint8)


@pytest.fixture
def tapped() -> Iterator[tuple[FrameThumbs, FrameTapServer]]:
    thumbs = FrameThumbs(keep=3)
    server = FrameTapServer(thumbs, "127.0.0.1", 0)
    try:
        yield thumbs, server
    finally:
        server.close()


def test_a_kept_frame_comes_back_as_its_thumbnail(
    tapped: tuple[FrameThumbs, FrameTapServer],
) -> None:
    thumbs, server = tapped
    for frame_id in (7, 8):
        thumbs(frame_id, frame(frame_id))
    status, body = get(server.port, "/frames/8")
    assert status == 200
    got = np.load(io.BytesIO(body), allow_pickle=False)
    assert got.dtype == np.float32 and got.shape == (72 // THUMB, 128 // THUMB, 3)
    np.testing.assert_array_equal(got, thumbnail(frame(8)))
    assert not np.array_equal(got, thumbnail(frame(7)))


def test_the_summary_names_the_kept_ids(tapped: tuple[FrameThumbs, FrameTapServer]) -> None:
    thumbs, server = tapped
    assert json.loads(get(server.port, "/frames")[1])["count"] == 0
    for frame_id in range(10, 15):
        thumbs(frame_id, frame(frame_id))
    status, body = get(server.port, "/frames/")
    assert status == 200
    assert json.loads(body) == {"first": 12, "last": 14, "count": 3, "factor": THUMB}


@pytest.mark.parametrize("path", ["/frames/11", "/frames/-1", "/frames/x", "/", "/metrics"])
def test_unknown_frames_and_paths_are_404(
    tapped: tuple[FrameThumbs, FrameTapServer], path: str
) -> None:
    thumbs, server = tapped
    for frame_id in range(12, 15):
        thumbs(frame_id, frame(frame_id))  # 11 was never kept
    status, _ = get(server.port, path)
    assert status == 404


def test_a_taken_port_leaves_the_session_without_a_tap(caplog: pytest.LogCaptureFixture) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        with caplog.at_level(logging.WARNING):
            assert start_frame_tap(FrameThumbs(), "127.0.0.1", taken.getsockname()[1]) is None
    assert "frame tap port" in caplog.text


def test_every_frame_taken_is_found_whatever_the_thumbnail_thread_has_done() -> None:
    """The tap only copies (it runs on the encoding thread); the thumbnails are made
    later, or by the lookup: a burst past the waiting bound loses nothing, and each
    thumbnail is the frame's as it was when taken, not what the buffer holds later."""
    thumbs = FrameThumbs(keep=40)
    buffer = np.zeros((72, 128, 4), dtype=np.uint8)  # one reused buffer, as a ring slot
    for frame_id in range(40):
        buffer[:] = 0
        buffer[..., :3] = frame(frame_id)
        thumbs(frame_id, buffer)
    buffer[:] = 255
    assert [frame_id for frame_id, _ in thumbs.items()] == list(range(40))
    for frame_id in (0, 17, 39):
        got = thumbs.get(frame_id)
        assert got is not None
        np.testing.assert_array_equal(got, thumbnail(frame(frame_id)))


def test_the_thumbnail_thread_ends_when_idle_and_comes_back() -> None:
    thumbs = FrameThumbs(keep=4)
    thumbs.IDLE_EXIT_S = 0.05
    thumbs(1, frame(1))
    deadline = time.monotonic() + 5.0
    while thumbs._worker is not None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert thumbs._worker is None, "the thread stays after the frames stopped"
    thumbs(2, frame(2))
    assert [i for i, _ in thumbs.items()] == [1, 2]


def test_a_page_thumbnail_is_the_box_mean_and_bad_ones_are_refused() -> None:
    image = frame(3)
    sums = image.reshape(18, 4, 32, 4, 3).sum(axis=(1, 3), dtype=np.uint16)
    page = {"factor": THUMB, "rows": 18, "cols": 32, "sums": b64(sums.astype("<u2"))}
    np.testing.assert_allclose(page_thumbnail(page), thumbnail(image), atol=1e-4)
    with pytest.raises(ValueError, match="factor"):
        page_thumbnail({**page, "factor": 2})
    with pytest.raises(ValueError, match="sums"):
        page_thumbnail({**page, "rows": 17})


def b64(array: np.ndarray) -> str:
    return base64.b64encode(array.tobytes()).decode()


def test_frames_between_counts_the_tapped_frames_and_the_times_kept_are_bounded(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(FrameThumbs, "KEEP_TIMES", 5)
    thumbs = FrameThumbs()
    frame = np.zeros((8, 8, 4), dtype=np.uint8)
    t0 = time.monotonic()
    for frame_id in range(3):
        thumbs(frame_id, frame)
    t1 = time.monotonic()
    assert thumbs.frames_between(t0, t1 + 1e-6) == 3
    assert thumbs.frames_between(t1 + 1, t1 + 2) == 0
    for frame_id in range(3, 20):
        thumbs(frame_id, frame)
    assert len(thumbs.times) == 5  # a long session keeps the last frames' times only
    assert thumbs.frames_between(t0, time.monotonic() + 1e-6) == 5


def test_a_smaller_encoded_picture_is_compared_at_its_own_size() -> None:
    """The stream encoded below the display size: the page's thumbnail is smaller than
    the tap's; the comparison is made at the smaller size, either way round."""
    import cv2

    from server.serve.snapshots import psnr

    y, x = np.mgrid[0:720, 0:1280].astype(np.float32)
    frame = np.stack([128 + 60 * np.sin(x / 40), 128 + 60 * np.cos(y / 30), 0 * x + 90], -1)
    frame = frame.astype(np.uint8)
    shown = cv2.resize(frame, (426, 240), interpolation=cv2.INTER_AREA)
    same = psnr(thumbnail(shown), thumbnail(frame))
    assert same == psnr(thumbnail(frame), thumbnail(shown)) and same > 35.0
    other = np.roll(frame, 100, axis=1)
    assert psnr(thumbnail(shown), thumbnail(other)) < same - 10.0
