"""End to end: aioquic over a lossy, delaying user-space link on loopback.

The server sends 6 Mbit/s of video-like chunks (25 KB every 33 ms, one stream)
for 4 s through an 8 Mbit/s, 30 ms RTT, 1 % loss link; the client counts the bytes
of the chunks that arrive within ``DEADLINE_S`` of being sent. upcast-media must
carry >= 90 % of them and beat NewReno by a clear margin.
"""

from __future__ import annotations

import asyncio

import pytest

from server.bench.network.congestion import LinkSpec, measure
from server.quic.congestion_media import NAME

LINK = LinkSpec(rate_mbit=8.0, rtt_ms=30.0, loss=0.01)
DEADLINE_S = 0.5


@pytest.mark.timeout(60)
def test_media_controller_carries_video_through_a_lossy_link() -> None:
    async def both() -> dict[str, float]:
        figures = {}
        for algorithm in (NAME, "reno"):
            result = await measure(algorithm, LINK, seconds=4.0, rate_mbit=6.0, seed=7)
            figures[algorithm] = result.on_time_fraction(DEADLINE_S)
        return figures

    figures = asyncio.run(both())
    shown = ", ".join(f"{k}: {100 * v:.1f} % on time" for k, v in figures.items())
    assert figures[NAME] >= 0.90, shown
    assert figures[NAME] >= figures["reno"] + 0.25, shown
