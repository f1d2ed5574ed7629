"""``upcast loadtest`` measures a stream another MoQ publisher made: moq-rs's CMAF
importer (its own catalog, no timing track, and its own fragments: trun version 1,
flags 0x1/0x5 with sizes and durations left to tfhd defaults in moq-rs 0.5.1; 0x305
elsewhere) publishing FFmpeg's fragmented MP4 through our relay. fps, loss and
latency come out, with no bad fragments; without a timing track, loss and latency
are read on the media clock."""

from __future__ import annotations

import asyncio
import contextlib
import io
import os
import struct
import time
from collections.abc import Coroutine
from typing import Any

import av
import numpy as np
import pytest

from server.loadtest.plan import LoadConfig
from server.loadtest.results import summary, table
from server.loadtest.run import LoadResult, run_load
from server.loadtest.viewer_stats import ViewerStats
from server.media.cmaf import find_box, iter_boxes
from server.quic.certs import CertBundle, generate_cert
from server.relay.relay import Relay, RelayConfig

if os.environ.get("CI"):
    import moq
else:
    moq = pytest.importorskip("moq", reason="moq-rs not installed: pip install -e '.[dev]'")

FPS = 30


def test_media_clock_loss_and_delay_without_a_timing_track() -> None:
    stats = ViewerStats(0, window=(10.0, 20.0))
    wall = 1_700_000_000_000_000
    step = 33_333
    for n in range(30):
        if n in (7, 8):  # two frames never arrive
            continue
        late = 4_000 if n % 10 == 3 else 0  # some arrive 4 ms later than the rest
        stats.on_video(n * step, 100, 10.0 + n / FPS, wall + n * step + 20_000 + late, step)
    assert stats.lost == 2 and stats.published == 30
    delays = stats.media_delay_ms()
    assert len(delays) == 28 and min(delays) == 0.0 and max(delays) == pytest.approx(4.0)
    assert stats.summary()["media_delay_ms"]["count"] == 28


def _ffmpeg_fragments(seconds: float) -> tuple[bytes, list[bytes]]:
    buf = io.BytesIO()
    movflags = "frag_every_frame+empty_moov+default_base_moof"
    out = av.open(buf, "w", format="mp4", options={"movflags": movflags})
    stream = out.add_stream("libx264", rate=FPS)
    stream.width, stream.height, stream.pix_fmt = 320, 180, "yuv420p"
    stream.options = {"preset": "ultrafast", "tune": "zerolatency", "g": str(FPS)}
    for i in range(int(seconds * FPS)):
        img = np.zeros((180, 320, 3), np.uint8)
        img[:, (i * 3) % 320] = 255
        for packet in stream.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
            out.mux(packet)
    for packet in stream.encode(None):
        out.mux(packet)
    out.close()
    data = buf.getvalue()
    spans = list(iter_boxes(data))
    first = next(i for i, b in enumerate(spans) if b.kind == b"moof")
    fragments = [data[b.start : spans[i + 1].end] for i, b in enumerate(spans) if b.kind == b"moof"]
    return data[: spans[first].start], fragments


async def _publish_with_moq_rs(url: str, init: bytes, fragments: list[bytes]) -> None:
    """moq-rs publishes broadcast "rs" from the fMP4, one fragment per frame period."""
    async with moq.Client(url, tls_verify=False, websocket_enabled=False) as client:
        broadcast = client.create_broadcast("rs")
        producer = broadcast.publish_container(moq.ContainerFormat.FMP4, init)
        broadcast.announce()
        start = time.monotonic()
        for n, fragment in enumerate(fragments):
            await asyncio.sleep(max(0.0, start + n / FPS - time.monotonic()))
            producer.write(fragment)
        producer.finish()


def _run(coro: Coroutine[Any, Any, Any], timeout: float = 40.0) -> Any:
    async def bounded() -> Any:
        async with asyncio.timeout(timeout):
            return await coro

    return asyncio.run(bounded())


@pytest.fixture(scope="module")
def cert(tmp_path_factory: pytest.TempPathFactory) -> CertBundle:
    return generate_cert(directory=tmp_path_factory.mktemp("cert"))


def test_loadtest_measures_a_moq_rs_publisher(
    cert: CertBundle, monkeypatch: pytest.MonkeyPatch
) -> None:
    init, fragments = _ffmpeg_fragments(seconds=9.0)
    seen: list[bytes] = []
    _record_video(seen, monkeypatch)

    async def body() -> LoadResult:
        relay = Relay(RelayConfig(host="127.0.0.1", port=0), cert)
        await relay.start()
        url = f"https://127.0.0.1:{relay.port}/"
        publisher = asyncio.create_task(_publish_with_moq_rs(url, init, fragments))
        try:
            config = LoadConfig(
                f"http://127.0.0.1:{relay.port}/", viewers=2, duration_s=3.0,
                warmup_s=1.0, broadcast="rs", cert_hash_hex=cert.sha256_hex,
            )  # fmt: skip
            return await run_load(config, progress=False)
        finally:
            publisher.cancel()
            with contextlib.suppress(asyncio.CancelledError, moq.Error):
                await publisher
            await relay.close()

    result: LoadResult = _run(body())
    # What came through the relay is moq-rs's own layout (trun v1), not ours (v0, 0x701).
    assert seen, "no video frame recorded"
    words = set()
    for payload in seen:
        trun = find_box(payload, [b"moof", b"traf", b"trun"])
        words.add(struct.unpack_from(">I", payload, trun.payload_start)[0])
    print("trun version/flags seen:", sorted(hex(w) for w in words))
    assert 0x000701 not in words and all(w >> 24 == 1 for w in words), words
    for s in result.stats:
        assert s.connected and s.error is None and s.catalog, s.summary()
        assert s.bad_fragments == 0
        assert s.fps() == pytest.approx(FPS, abs=3.0), s.summary()
        assert s.lost == 0 and s.published >= 2.5 * FPS, s.summary()
        delays = s.media_delay_ms()
        assert len(delays) >= 2.5 * FPS and sorted(delays)[int(0.95 * len(delays))] < 100.0
    summ = summary(result)
    assert summ["media_delay_ms"]["count"] >= 5 * FPS
    assert summ["lost_total"] == 0
    assert "media-clock delay" in table(result)


def _record_video(seen: list[bytes], monkeypatch: pytest.MonkeyPatch) -> None:
    """Keep the video payloads the viewers parse (bounded)."""
    import server.loadtest.viewer as viewer

    original = viewer.parse_fragment

    def recording(data: bytes, *args: Any, **kwargs: Any) -> Any:
        if len(seen) < 400:
            seen.append(bytes(data))
        return original(data, *args, **kwargs)

    monkeypatch.setattr(viewer, "parse_fragment", recording)
