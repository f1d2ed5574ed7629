"""Binds the rate controller to a live session: viewers' messages in, encoder bitrate out.

The controller (rate_control.py) is pure logic; this runs it every
``UPDATE_INTERVAL_S`` on the session's loop, hands the encoder each new rate
(the encoding thread applies it before its next frame), and puts the rate and
why in the session's ``stream_state``, which rides in every timing record: the
page's overlay and ``upcast bench network`` read it from there.

When the bitrate alone cannot hold the frame rate (fewer than ``MIN_BITS_PER_PIXEL``
bits per pixel and frame: blocks and smears), the session encodes every other
frame instead (``frame_divisor`` 2), at twice the bits per frame, and goes back
to every frame once the rate gives ``RESTORE_FACTOR`` times that floor. x264
budgets bits per frame at the configured frame rate, so at divisor 2 the encoder
is told twice the rate to spend the same bits per second.

While the controller probes the link (link_probe.py) the encoder pads every frame
to the probe's rate over the frame interval (H.264 filler data), and each frame
sent tells the controller whether it was padded.
"""

from __future__ import annotations

import asyncio
import logging
import time

from prometheus_client import CollectorRegistry

from server.media.encode import MIN_BITRATE, EncodedFrame, VideoEncoder
from server.session.rate_control import RateController
from server.session.rate_metrics import RateMetrics
from server.session.viewer_input import FeedbackMessage, ViewerMessage

log = logging.getLogger(__name__)

UPDATE_INTERVAL_S = 0.1
MIN_BITS_PER_PIXEL = 0.035  # x264 ultrafast below this: visibly blocky at any size
RESTORE_FACTOR = 1.6  # hysteresis: full frame rate again at 1.6x the floor
MIN_THINNED_FPS = 20.0  # never halve a stream below 10 fps


class SessionRate:
    def __init__(
        self,
        encoder: VideoEncoder,
        stream_state: dict[str, str | float | bool],
        *,
        enabled: bool = True,
        registry: CollectorRegistry | None = None,
    ) -> None:
        """``enabled=False``: the configured bitrate stays whatever viewers report."""
        self.encoder = encoder
        self.enabled = enabled
        ceiling = encoder.config.target_bitrate
        self.controller = RateController(ceiling, min(MIN_BITRATE, ceiling))
        self._state = stream_state
        self.frame_divisor = 1
        cfg = encoder.config
        # The rate frames arrive at: the configured one until the game's frame rate is
        # lowered (set_source_fps).
        self.source_fps = cfg.fps
        self._bits_floor = MIN_BITS_PER_PIXEL * cfg.width * cfg.height * cfg.fps
        self._rate = cfg.target_bitrate
        self._metrics = RateMetrics.for_registry(registry) if registry is not None else None
        self._publish_state()

    def frame_sent(self, encoded: EncodedFrame) -> None:
        self.controller.frame_sent(
            encoded.pts_us, len(encoded.fragment), time.monotonic(), encoded.padded_to
        )

    def on_message(self, source: str, message: ViewerMessage) -> None:
        now = time.monotonic()
        if isinstance(message, FeedbackMessage):
            self.controller.feedback(source, message, now)
        else:
            self.controller.input_seen(source, now)

    def forget(self, source: str) -> None:
        self.controller.forget(source)

    def set_source_fps(self, fps: float) -> None:
        """Frames now arrive at ``fps`` (the game's frame rate changed): the bits-per-pixel
        floor and the bits each frame may take follow it."""
        if not fps > 0:
            raise ValueError(f"fps must be positive, got {fps}")
        self.source_fps = fps
        cfg = self.encoder.config
        self._bits_floor = MIN_BITS_PER_PIXEL * cfg.width * cfg.height * fps
        if self.enabled:
            self.encoder.set_bitrate(self._encoder_rate())

    def _encoder_rate(self) -> int:
        """What the encoder is told: x264 budgets bits per frame at its configured rate,
        so a stream sent at a fraction of it is told the rate over that fraction to spend
        the chosen bits per second (the encoder's ceiling still caps it)."""
        sent_fps = self.source_fps / self.frame_divisor
        return round(self._rate * self.encoder.config.fps / sent_fps)

    def step(self, now_s: float) -> None:
        rate = self.controller.update(now_s)
        self._pad(now_s)
        if rate is not None and self.enabled:
            self._rate = rate
            divisor = self._divisor_for(rate)
            if divisor != self.frame_divisor:
                log.info(
                    "frame rate %s: %.2f Mbit/s cannot hold %.0f fps",
                    "halved" if divisor > 1 else "restored",
                    rate / 1e6,
                    self.source_fps,
                )
                self.frame_divisor = divisor
            self.encoder.set_bitrate(self._encoder_rate())
            if self._metrics is not None:
                self._metrics.changes.inc()
            state = self.controller.state
            log.info(
                "bitrate %.2f Mbit/s (%s, %d player%s)",
                rate / 1e6,
                state.reason,
                state.players,
                "" if state.players == 1 else "s",
            )
        self._publish_state()

    def _pad(self, now_s: float) -> None:
        padding = self.controller.padding_bps(now_s) if self.enabled else 0.0
        fps = self.source_fps / self.frame_divisor
        self.encoder.pad_frames_to(int(padding / 8 / fps))

    def _divisor_for(self, rate: float) -> int:
        if self.source_fps < MIN_THINNED_FPS:
            return 1
        if self.frame_divisor == 1:
            return 2 if rate < self._bits_floor else 1
        return 1 if rate >= self._bits_floor * RESTORE_FACTOR else 2

    async def run(self, stop: asyncio.Event) -> None:
        while not stop.is_set():
            await asyncio.sleep(UPDATE_INTERVAL_S)
            self.step(time.monotonic())

    def _publish_state(self) -> None:
        state = self.controller.state
        if self._metrics is not None:
            self._metrics.update(self._rate, state, self.frame_divisor)
        self._state["bitrate"] = self._rate
        self._state["fps_divisor"] = self.frame_divisor
        self._state["rate_reason"] = state.reason if self.enabled else "fixed"
        self._state["probe_bps"] = round(state.probe_bps)
        if state.delivered_bps is not None:
            self._state["received_bps"] = round(state.delivered_bps)
        if state.queue_ms is not None:
            self._state["queue_ms"] = round(state.queue_ms, 1)
