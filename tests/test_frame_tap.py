"""The session's frame tap over HTTP (server/serve/frame_tap.py): what deploy/smoke.sh
compares a browser's canvas with when the session runs in a container."""

from __future__ import annotations

import io
import json
import logging
import socket
import urllib.error
import urllib.request
from collections.abc import Iterator

import numpy as np
import pytest

from server.bench.snapshots import THUMB, FrameThumbs, thumbnail
from server.serve.frame_tap import FrameTapServer, start_frame_tap


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
