"""The player end to end against an in-page moq-lite publisher (no relay).

client_web/dist/test/loopback.html runs a small "game server" in the page: a
WebCodecs H.264 encoder whose frames @moq/hang packs as CMAF, published with
@moq/lite as broadcast ``game`` (catalog.json, video, timing) over a fake
WebTransport pair wired to the real player bundle, and a subscriber for the
player's ``game/input/<id>`` broadcast. It checks decode + present, the frame id
hooks against the painted colour, inputs, input-to-photon, reconnect and
re-announce. Build first: ``cd client_web && npm ci && npm run build``.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from tests.browser.conftest import DIST
from tests.chromium import browser_marks

pytestmark = browser_marks(DIST / "test" / "loopback.html")

PRESENTED_AT_LEAST = "n => window.upcast && window.upcast.stats().framesPresented >= n"


@pytest.fixture
def page(web_root: str, browser: Any) -> Iterator[Any]:
    # A fresh page per test: each test gets its own player and in-page publisher.
    page = browser.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    try:
        page.goto(f"{web_root}/test/loopback.html?jwt=loopback")  # a token: inputs on
        page.wait_for_function(PRESENTED_AT_LEAST, arg=10, timeout=15_000)
        yield page
        assert errors == []
        assert page.evaluate("() => window.loopback.errors") == []
    finally:
        page.close()


def _stats(page: Any) -> dict[str, Any]:
    return page.evaluate("() => window.upcast.stats()")  # type: ignore[no-any-return]


def test_frames_are_decoded_presented_and_timed(page: Any) -> None:
    page.wait_for_function(PRESENTED_AT_LEAST, arg=30, timeout=10_000)
    stats = _stats(page)
    assert stats["connected"] and stats["subscribed"]
    assert stats["codec"] == "avc1.42E01F"
    assert (stats["width"], stats["height"]) == (320, 180)
    assert stats["fps"] >= 10
    assert stats["framesDecoded"] >= stats["framesPresented"] >= 30
    assert stats["lastPresentedFrameId"] is not None
    for stage in ("render", "encode", "publish", "network", "decode", "present", "total"):
        assert stats["latency"][stage]["n"] > 0, stage
        assert stats["latency"][stage]["p50"] >= 0, stage
    assert stats["errors"] == []


def test_snapshot_shows_the_frame_it_names(page: Any) -> None:
    # Each harness frame is one flat colour: the snapshot's centre pixel must be the
    # colour painted for the frame id the snapshot reports (H.264 rounding allowed).
    result = page.evaluate(
        """async () => {
            for (let i = 0; i < 50; i++) {
                const snap = window.upcast.snapshot();
                if (snap.frameId !== null) {
                    const img = new Image();
                    img.src = snap.dataUrl;
                    await img.decode();
                    const c = new OffscreenCanvas(img.width, img.height).getContext('2d');
                    c.drawImage(img, 0, 0);
                    const px = c.getImageData(img.width >> 1, img.height >> 1, 1, 1).data;
                    return {frameId: snap.frameId, pixel: [px[0], px[1], px[2]],
                            painted: window.loopback.colors[snap.frameId]};
                }
                await new Promise(r => setTimeout(r, 20));
            }
            return null;
        }"""
    )
    assert result is not None
    diffs = [abs(a - b) for a, b in zip(result["pixel"], result["painted"], strict=True)]
    assert max(diffs) <= 24, result


def test_inputs_reach_the_game_and_input_to_photon_is_measured(page: Any) -> None:
    page.wait_for_function("() => window.upcast.stats().inputSubscribers > 0", timeout=5_000)
    page.click("#screen")
    page.keyboard.down("w")
    page.wait_for_function("() => window.upcast.stats().inputToPhoton.samples.length > 0")
    page.keyboard.up("w")
    box = page.locator("#screen").bounding_box()
    page.mouse.move(box["x"] + 50, box["y"] + 50)
    page.mouse.down()
    page.mouse.move(box["x"] + 90, box["y"] + 60, steps=4)
    page.mouse.up()
    assert page.is_disabled("#cache-policy")  # easu_rcas has no layer cache
    page.select_option("#upscaler", "unet_cached")
    page.select_option("#cache-policy", "budget")
    page.select_option("#upscaler", "lanczos2")
    assert page.is_disabled("#cache-policy")
    page.select_option("#scale", "3")
    page.click("#keyframe")
    page.wait_for_function("() => window.loopback.inputs.some(m => m.type === 'keyframe')")
    inputs = page.evaluate("() => window.loopback.inputs")
    kinds = [(m["type"], m.get("down"), m.get("upscaler"), m.get("scale")) for m in inputs]
    assert ("keys", ["w"], None, None) in kinds
    assert ("keys", [], None, None) in kinds
    assert ("control", None, "lanczos2", None) in kinds
    assert {"type": "control", "cache_policy": "budget"} in [
        {k: m[k] for k in ("type", "cache_policy") if k in m} for m in inputs
    ]
    assert ("control", None, None, 3) in kinds
    looks = [m for m in inputs if m["type"] == "look"]
    assert looks and sum(m["dx"] for m in looks) == pytest.approx(40)
    seqs = [m["seq"] for m in inputs]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    assert all(isinstance(m["sent_ms"], float | int) for m in inputs)
    photon = _stats(page)["inputToPhoton"]["samples"]
    assert 0 < photon[0] < 2000


def test_reconnects_after_the_connection_drops(page: Any) -> None:
    before = _stats(page)["framesPresented"]
    page.evaluate("() => window.loopback.dropConnection()")
    page.wait_for_function("() => window.loopback.connections >= 2", timeout=10_000)
    page.wait_for_function(PRESENTED_AT_LEAST, arg=before + 15, timeout=10_000)
    stats = _stats(page)
    assert stats["subscribed"]


def test_resubscribes_when_the_broadcast_comes_back(page: Any) -> None:
    page.evaluate("() => window.loopback.setLive(false)")
    page.wait_for_function(
        "() => window.upcast.stats().status.startsWith('waiting for broadcast')", timeout=5_000
    )
    stalled = _stats(page)["framesPresented"]
    page.evaluate("() => window.loopback.setLive(true)")
    page.wait_for_function(PRESENTED_AT_LEAST, arg=stalled + 15, timeout=10_000)
    assert _stats(page)["subscribed"]
