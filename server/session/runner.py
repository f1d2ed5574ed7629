"""StreamingSession: ring U -> CMAF encoder -> moq-lite broadcast on a relay, inputs back.

One asyncio loop (uvloop in the CLI) runs the relay connection, the input
router and the monitor; encoding runs on the capture thread (capture.py), which
hands each fragment to the loop. The relay connection is retried with backoff:
a relay restart costs the viewers a reconnect, never the game a stall (the
capture thread keeps draining ring U and dropping frames nobody can receive).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
from prometheus_client import CollectorRegistry

from server.frames.frame import Size
from server.frames.monitor import FrameRateMonitor
from server.frames.ring import FrameRing
from server.game.sounds import GameSounds, SoundSource
from server.media.audio_encode import OpusEncoder
from server.media.catalog import (
    VIDEO_TRACK,
    AudioSection,
    audio_section,
    catalog_of,
    video_track_name,
)
from server.media.encode import EncodedConfig, EncoderConfig, VideoEncoder, encoded_size
from server.media.ladder import RenditionLadder, RungFrame
from server.moq.events import Event
from server.ops.redact import redact_url
from server.quic.client import WtConnectError
from server.quic.moq_link import MoqLink, connect_moq
from server.session.audio_capture import AudioCapture, CapturedAudio
from server.session.broadcast import GameBroadcast
from server.session.capture import CapturedFrame, CaptureThread
from server.session.gamepad_keys import GamepadKeyMap
from server.session.input_router import InputRouter
from server.session.ladder_metrics import LadderMetrics
from server.session.ladder_thread import LadderThread
from server.session.quality.adapter import SessionQuality, session_quality
from server.session.session_rate import SessionRate
from server.stream_config import DEFAULT_GOP_S

log = logging.getLogger(__name__)

RECONNECT_MIN_S = 0.25
RECONNECT_MAX_S = 5.0
MONITOR_INTERVAL_S = 2.0


@dataclass(frozen=True)
class StreamSettings:
    relay_url: str
    broadcast: str = "game"
    fps: float = 60.0
    bitrate: int | None = None  # bit/s; None: scaled from 6 Mbit/s at 720p60
    gop_seconds: float = 2.0
    cert_hash_hex: str | None = None  # pin the relay's certificate (else fetched over http)
    upscaler: str | None = None  # what the worker starts with (shown in the player)
    scale: float | None = None  # display / render size at start
    frame_generation: bool | None = None  # whether the game starts predicting every other frame
    cache_policy: str | None = None  # the layer-cache policy the worker starts with, if any
    token: str | None = None  # JWT for the relay (sent as ?jwt=); None: an open relay
    # "game": the built-in renderer; "x11": a captured application (colour only; raw input)
    source: str = "game"
    gamepad: GamepadKeyMap | None = None  # gamepad -> keys (None: the standard default)
    # Publish the game's sound (Opus, track ``audio``). Off here so library users opt
    # in; the commands (upcast up, serve, session) turn it on unless --no-audio.
    audio: bool = False
    # The bitrate follows the player's feedback (session_rate.py); off: fixed.
    rate_control: bool = True
    # Intra refresh sweeps instead of periodic IDRs (encode.py); a viewer that lost a
    # group asks for a keyframe, and one comes every SAFETY_IDR_S for those that cannot.
    intra_refresh: bool = True
    # Adaptive quality (server/session/quality): "auto" chooses upscaler, scale and frame
    # generation to hold ``fps``; needs the starting upscaler and scale (else fixed).
    quality: str = "fixed"
    quality_preference: str = "framerate"
    min_scale: float = 1.0
    max_scale: float = 4.0
    quality_methods: tuple[str, ...] = ()
    # The rendition ladder for spectators (server/media/ladder.py): rungs at the display
    # size / each divisor. Empty here so library users opt in; the commands default to
    # DEFAULT_DIVISORS unless --ladder off.
    ladder: tuple[int, ...] = ()
    ladder_gop_seconds: float = DEFAULT_GOP_S


def _ladder(settings: StreamSettings, display: Size) -> RenditionLadder | None:
    """The rendition ladder the settings ask for; None without one, or when its
    encoders cannot open (logged: the player's track goes on alone)."""
    if not settings.ladder:
        return None
    try:
        ladder = RenditionLadder(
            display, settings.fps, settings.ladder, gop_seconds=settings.ladder_gop_seconds
        )
    except (RuntimeError, ValueError, OSError):
        log.exception("no rendition ladder: streaming the player's track alone")
        return None
    if not ladder.rungs:
        return None
    sizes = ", ".join(f"{r.track} at {r.bitrate // 1000} kbit/s" for r in ladder.rungs)
    log.info("rendition ladder: %s, a group every %.1f s", sizes, settings.ladder_gop_seconds)
    return ladder


# Under intra refresh, an IDR this often anyway: a spectator the relay skipped (which
# cannot ask for a keyframe) waits at most this long for a group to join.
SAFETY_IDR_S = 10.0


class StreamingSession:
    def __init__(
        self,
        settings: StreamSettings,
        ring_u: FrameRing,
        display: Size,
        *,
        game_input: Path | None = None,
        worker_control: Path | None = None,
        registry: CollectorRegistry | None = None,
        on_upscaler_set: Callable[[str], None] | None = None,
        on_scale_request: Callable[[float], None] | None = None,
        frame_tap: Callable[[int, npt.NDArray[np.uint8]], None] | None = None,
        sound: SoundSource | None = None,
    ) -> None:
        """``sound``: what the audio track plays (default: the reference game's sounds)."""
        self.settings = settings
        self.display = display
        self._frame_tap = frame_tap
        self.ring_u = ring_u
        self.encoder = VideoEncoder(
            EncoderConfig(
                width=display.width,
                height=display.height,
                fps=settings.fps,
                bitrate=settings.bitrate,
                gop_seconds=settings.gop_seconds,
                intra_refresh=settings.intra_refresh,
            )
        )
        self.stream_state: dict[str, str | float | bool] = {}
        self.rate = SessionRate(
            self.encoder, self.stream_state, enabled=settings.rate_control, registry=registry
        )
        self.monitor = FrameRateMonitor("session", settings.fps, registry=registry)
        self.router = InputRouter(
            game_input=game_input,
            worker_control=worker_control,
            request_keyframe=self.encoder.request_keyframe,
            on_upscaler_set=self._upscaler_set,
            on_scale_request=self._scale_requested,
            on_frame_generation=self._frame_generation_set,
            on_cache_policy=self._cache_policy_set,
            on_encode_scale=self._encode_scale_set,
            on_frame_rate=self._frame_rate_set,
            max_frame_rate=settings.fps,
            color_only=settings.source != "game",
            gamepad_keys=settings.gamepad,
            on_message=self.rate.on_message,
        )
        self.quality: SessionQuality = session_quality(
            settings, display, self.router, self.monitor, self.stream_state, registry
        )
        self.router.on_control_outcome = self.quality.control_outcome
        self._on_upscaler_set = on_upscaler_set
        self._on_scale_request = on_scale_request
        self.sound: SoundSource = sound if sound is not None else GameSounds()
        self.audio_encoder: OpusEncoder | None = None
        audio: AudioSection | None = None
        if settings.audio:
            try:
                self.audio_encoder = OpusEncoder()
            except Exception:
                log.exception("no Opus encoder: streaming without audio")
            else:
                cfg = self.audio_encoder.config
                audio = audio_section(
                    sample_rate=cfg.sample_rate,
                    channels=cfg.channels,
                    bitrate=cfg.bitrate,
                    frame_ms=cfg.frame_us // 1000,
                )
        self._audio_section = audio
        self.audio: AudioCapture | None = None
        self.ladder = _ladder(settings, display)
        self._ladder_thread: LadderThread | None = None
        self._ladder_metrics: LadderMetrics | None = None
        self._registry = registry
        self.broadcast = GameBroadcast(
            settings.broadcast,
            self._catalog_json(self.encoder.encoded_config, VIDEO_TRACK),
            on_input=self.router.handle,
            on_keyframe_wanted=self.encoder.request_keyframe,
            on_input_ended=self._input_ended,
            audio=audio is not None,
            rung_tracks=self.ladder.tracks if self.ladder is not None else (),
            on_rung_keyframe_wanted=(
                self.ladder.request_keyframe if self.ladder is not None else None
            ),
            on_rungs_watched=self.ladder.set_wanted if self.ladder is not None else None,
        )
        if self.ladder is not None:
            self.ladder.set_wanted(frozenset())  # nobody watches a rung yet
        self.broadcast.stream_state = self.stream_state
        # The page disables what the source cannot do (a captured application: methods
        # that need depth and motion, scale changes, frame generation).
        self.broadcast.stream_state["source"] = settings.source
        if settings.upscaler is not None:
            self.broadcast.stream_state["upscaler"] = settings.upscaler
        if settings.scale is not None:
            self.broadcast.stream_state["scale"] = round(settings.scale, 3)
        if settings.frame_generation is not None:
            self.broadcast.stream_state["frame_generation"] = settings.frame_generation
        if settings.cache_policy is not None:
            self.broadcast.stream_state["cache_policy"] = settings.cache_policy
        self.broadcast.stream_state["encoded"] = f"{display.width}x{display.height}"
        self.broadcast.stream_state["frame_rate"] = settings.fps
        self.link: MoqLink | None = None
        self.connected = asyncio.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._capture: CaptureThread | None = None
        self._skipped_seen = 0

    def _catalog_json(self, config: EncodedConfig, track: str) -> bytes:
        """The catalog: the player's track ``track`` first, then the ladder's rungs."""
        cfg = self.encoder.config
        rungs = self.ladder.renditions() if self.ladder is not None else None
        catalog = catalog_of(config, cfg.fps, cfg.target_bitrate, track, self._audio_section, rungs)
        return catalog.to_json()

    def reconnect(self) -> None:
        """Drop the relay connection now (say, the relay was restarted): the relay loop
        connects again at once instead of waiting for the idle timeout."""
        link = self.link
        if link is not None and not link.closed:
            link.close(0, "reconnecting")

    def _click(self) -> None:
        if self.audio is not None:
            self.audio.click()

    def _upscaler_set(self, name: str) -> None:
        self._click()
        self.broadcast.stream_state["upscaler"] = name
        if self._on_upscaler_set is not None:
            self._on_upscaler_set(name)

    def _scale_requested(self, scale: float) -> None:
        self._click()
        self.broadcast.stream_state["scale"] = round(scale, 3)
        if self._on_scale_request is not None:
            self._on_scale_request(scale)

    def _frame_generation_set(self, on: bool) -> None:
        self._click()
        self.broadcast.stream_state["frame_generation"] = on

    def _encode_scale_set(self, scale: float) -> None:
        self._click()
        self.set_encode_scale(scale)

    def _frame_rate_set(self, fps: float) -> None:
        """The game renders at ``fps`` from its next frame: the monitor judges the rate
        and the stage budgets against it, and the rate control budgets its bits by it."""
        self._click()
        self.monitor.set_target_fps(fps)
        self.rate.set_source_fps(fps)
        self.broadcast.stream_state["frame_rate"] = round(fps, 3)

    def _cache_policy_set(self, policy: str | None) -> None:
        self._click()
        if policy is None:
            self.broadcast.stream_state.pop("cache_policy", None)
        else:
            self.broadcast.stream_state["cache_policy"] = policy

    # -- running ---------------------------------------------------------------------

    async def run(self, stop: asyncio.Event) -> None:
        self._loop = asyncio.get_running_loop()
        origin: int | None = None
        if self.audio_encoder is not None:
            # One origin for both media clocks: a sound and its frame share a pts.
            origin = time.monotonic_ns()
            self.audio = AudioCapture(
                self.sound, self.audio_encoder, self._from_audio_thread, origin_ns=origin
            )
            self.audio.start()
        if self.ladder is not None:
            self._ladder_thread = LadderThread(self.ladder, self._from_ladder_thread)
            if self._registry is not None:
                self._ladder_metrics = LadderMetrics(
                    self._registry, self.ladder, self._ladder_thread
                )
            self._ladder_thread.start()
        self._capture = CaptureThread(
            self.ring_u,
            self.encoder,
            self._from_capture_thread,
            frame_tap=self._frame_tap,
            pts_origin_ns=origin,
            keep_every=lambda: self.rate.frame_divisor,
            ladder_sink=self._ladder_thread.submit if self._ladder_thread is not None else None,
        )
        self._capture.start()
        tasks = [
            asyncio.create_task(self._relay_loop(stop), name="session-relay"),
            asyncio.create_task(self._tick_loop(stop), name="session-inputs"),
            asyncio.create_task(self._monitor_loop(stop), name="session-monitor"),
            asyncio.create_task(self.rate.run(stop), name="session-rate"),
            asyncio.create_task(self.quality.run(stop), name="session-quality"),
        ]
        if self.settings.intra_refresh:
            tasks.append(asyncio.create_task(self._safety_idr_loop(stop), name="session-idr"))
        try:
            await stop.wait()
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            self._capture.stop()
            if self._ladder_thread is not None:
                self._ladder_thread.stop()
            if self.audio is not None:
                self.audio.stop()
            if self.link is not None and not self.link.closed:
                self.link.close(0, "session ending")

    def _from_capture_thread(self, frame: CapturedFrame) -> None:
        if self.audio is not None:
            self.audio.frame(frame.meta)
        loop = self._loop
        if loop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(self._publish, frame)

    def _from_ladder_thread(self, frames: list[RungFrame], failed: list[str]) -> None:
        loop = self._loop
        if loop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(self._publish_rungs, frames, failed)

    def _publish_rungs(self, frames: list[RungFrame], failed: list[str]) -> None:
        for track in failed:
            config = self.encoder.encoded_config
            catalog = self._catalog_json(config, self.broadcast.video_track)
            self.broadcast.drop_rung(track, catalog)
        for frame in frames:
            self.broadcast.publish_rung(frame.track, frame.encoded)
        if self._ladder_metrics is not None:
            self._ladder_metrics.published(frames)
        link = self.link
        if link is not None and not link.closed:
            link.flush()

    def _from_audio_thread(self, captured: CapturedAudio) -> None:
        loop = self._loop
        if loop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(self._publish_audio, captured)

    def _publish_audio(self, captured: CapturedAudio) -> None:
        self.broadcast.publish_audio(captured)
        link = self.link
        if link is not None and not link.closed:
            link.flush()

    def _input_ended(self, source: str) -> None:
        self.router.forget(source)
        self.rate.forget(source)

    def set_encode_scale(self, scale: float) -> tuple[int, int]:
        """Encode at the display size / ``scale`` (>= 1) from the next frame on; returns
        the size (even, rounded down). The viewers follow through a new catalog and
        video track (see _publish); 1 returns to the display size."""
        width, height = encoded_size(self.display, scale)
        self.encoder.set_encoded_size(width, height)
        return width, height

    def _switch_video(self, config: EncodedConfig) -> None:
        track = video_track_name(config.generation)
        self.broadcast.switch_video(track, self._catalog_json(config, track))
        self.stream_state["encoded"] = f"{config.width}x{config.height}"
        log.info(
            "encoding at %dx%d (display %dx%d) on track %s",
            config.width,
            config.height,
            self.display.width,
            self.display.height,
            track,
        )

    def _publish(self, frame: CapturedFrame) -> None:
        if frame.encoded.new_config is not None:
            self._switch_video(frame.encoded.new_config)
        self.broadcast.publish_frame(frame.encoded, frame.meta)
        self.rate.frame_sent(frame.encoded)
        link = self.link
        if link is not None and not link.closed:
            link.flush()
        capture = self._capture
        skipped = 0
        if capture is not None:
            skipped = capture.stats.skipped - self._skipped_seen
            self._skipped_seen = capture.stats.skipped
        self.monitor.frame(frame.meta.stamps, dropped=skipped)
        self.quality.frame(frame.meta)

    def _on_events(self, link: MoqLink, events: list[Event]) -> None:
        self.broadcast.handle(events)

    async def _relay_loop(self, stop: asyncio.Event) -> None:
        delay = RECONNECT_MIN_S
        url = self.settings.relay_url
        shown = redact_url(url)  # a ?jwt= typed into --relay stays out of the log
        while not stop.is_set():
            try:
                link = await connect_moq(
                    url,
                    on_events=self._on_events,
                    cert_hash_hex=self.settings.cert_hash_hex,
                    token=self.settings.token,
                )
            except (WtConnectError, OSError, TimeoutError) as exc:
                log.warning("relay %s unreachable (%s); retrying in %.1f s", shown, exc, delay)
                await asyncio.sleep(delay)
                delay = min(RECONNECT_MAX_S, delay * 2)
                continue
            delay = RECONNECT_MIN_S
            self.link = link
            self.broadcast.attach(link.moq)
            link.pump()
            self.connected.set()
            log.info("publishing broadcast %r on %s", self.settings.broadcast, shown)
            reason = await link.wait_closed()
            self.connected.clear()
            self.broadcast.detach()
            self.link = None
            for source in list(self.router.held):
                self.router.forget(source)
            if not stop.is_set():
                log.warning("relay connection lost (%s); reconnecting", reason)

    async def _tick_loop(self, stop: asyncio.Event) -> None:
        period = 1.0 / self.settings.fps
        while not stop.is_set():
            await asyncio.sleep(period)
            self.router.tick()

    async def _safety_idr_loop(self, stop: asyncio.Event) -> None:
        while not stop.is_set():
            await asyncio.sleep(SAFETY_IDR_S)
            self.encoder.request_keyframe()

    async def _monitor_loop(self, stop: asyncio.Event) -> None:
        while not stop.is_set():
            await asyncio.sleep(MONITOR_INTERVAL_S)
            self.monitor.check_budgets()
            snap = self.monitor.snapshot()
            log.debug("session: %s", snap.as_dict())
