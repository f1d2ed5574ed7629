"""A synthetic publisher: a real game broadcast without the game, to load the relay alone.

``python -m server.loadtest.synthetic --relay http://localhost:4443/ --size 1280x720
--fps 30 --duration 60`` publishes broadcast ``game`` through GameBroadcast (the
same catalog, video and timing tracks as a session) from a scrolling textured
pattern, so a load test measures the relay without the game and the upscaler
worker taking the CPU.

Frames (``--encode``):
- ``loop`` (default): one GOP is encoded once with VideoEncoder at start; then
  its access units are looped, each rebuilt into a fresh CMAF fragment with
  ``media_fragment`` (new sequence number and decode time, so tfdt = pts_us
  keeps increasing). Every loop starts at the IDR, so the stream stays
  decodable; a keyframe request restarts the loop. Costs microseconds a frame.
- ``live``: every frame is encoded as it is published (about 7 ms a frame at
  720p on one core, on an executor thread: x264 drops the GIL).

Every frame's ``render_*``/``encode_*`` stamps are taken when it is produced and
``publish`` by GameBroadcast right before the bytes go to QUIC: real wall-clock
times, so publish -> receive means the same as with a game.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import signal
import sys
import time
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from server.frames.frame import Camera, FrameMeta, Size
from server.frames.timing import Stage, stamp
from server.media.catalog import catalog_for
from server.media.cmaf import media_fragment
from server.media.cmaf_read import parse_fragment
from server.media.encode import EncodedFrame, EncoderConfig, VideoEncoder
from server.moq.events import Event
from server.ops.event_loop import install_uvloop
from server.ops.logging_setup import install_redaction
from server.ops.redact import redact_url
from server.quic.client import WtConnectError
from server.quic.moq_link import MoqLink, connect_moq
from server.session.broadcast import GameBroadcast

log = logging.getLogger("upcast.synthetic")

SCROLL_PX = 4  # per frame: motion the encoder has to code, like a panning camera
PERIOD_PX = 320  # the texture repeats horizontally every this many pixels
RECONNECT_S = 0.5
MAX_DURATION_S = 4 * 3600.0
KEYFRAME_MIN_INTERVAL_S = 0.25  # as VideoEncoder: a storm of requests costs one IDR
DEFAULT_SIZE = Size(1280, 720)


@dataclass(frozen=True)
class SyntheticSettings:
    relay_url: str
    size: Size = DEFAULT_SIZE
    fps: float = 30.0
    bitrate: int | None = None  # bit/s; None: VideoEncoder's default for size and fps
    gop_seconds: float = 2.0
    broadcast: str = "game"
    encode: str = "loop"  # "loop" or "live"
    cert_hash_hex: str | None = None
    token: str | None = None  # publish token for the relay (?jwt=)

    def problem(self) -> str | None:
        if not self.relay_url.startswith(("http://", "https://")):
            return f"--relay must be an http(s):// URL, got {redact_url(self.relay_url)!r}"
        if self.size.width % 2 or self.size.height % 2 or min(self.size) < 16:
            return f"--size must be even and at least 16x16, got {self.size}"
        if not 0 < self.fps <= 240:
            return f"--fps must be in (0, 240], got {self.fps:g}"
        if self.encode not in ("loop", "live"):
            return f"--encode must be loop or live, got {self.encode!r}"
        return None


def texture(size: Size, seed: int = 7) -> npt.NDArray[np.uint8]:
    """(H, W + PERIOD_PX, 3): coloured bands, blocks and noise, periodic in x, so a
    frame is a (free) strided view at a moving offset."""
    rng = np.random.default_rng(seed)
    h = size.height
    x = np.arange(PERIOD_PX, dtype=np.float32)
    y = np.arange(h, dtype=np.float32)[:, None]
    tile = np.empty((h, PERIOD_PX, 3), dtype=np.float32)
    for c, phase in enumerate((0.0, 2.1, 4.2)):
        tile[..., c] = 128 + 60 * np.sin(2 * np.pi * x / PERIOD_PX * 3 + phase + y / 40.0)
    blocks = rng.integers(0, 2, size=(h // 16 + 1, PERIOD_PX // 16, 1)).astype(np.float32)
    tile += 50 * np.repeat(np.repeat(blocks, 16, axis=0), 16, axis=1)[:h]
    tile += rng.normal(0, 12, size=tile.shape).astype(np.float32)
    tile = np.clip(tile, 0, 255).astype(np.uint8)
    reps = -(-(size.width + PERIOD_PX) // PERIOD_PX)
    return np.ascontiguousarray(np.tile(tile, (1, reps, 1))[:, : size.width + PERIOD_PX])


def frame_view(tex: npt.NDArray[np.uint8], width: int, index: int) -> npt.NDArray[np.uint8]:
    offset = (index * SCROLL_PX) % PERIOD_PX
    return tex[:, offset : offset + width]


class FrameSource:
    """Produces the next EncodedFrame for a given pts; keyframes on request."""

    def __init__(self, settings: SyntheticSettings) -> None:
        self.settings = settings
        self.encoder = VideoEncoder(
            EncoderConfig(
                width=settings.size.width,
                height=settings.size.height,
                fps=settings.fps,
                bitrate=settings.bitrate,
                gop_seconds=settings.gop_seconds,
            )
        )
        self.texture = texture(settings.size)
        self.catalog_json = catalog_for(self.encoder).to_json()
        self._loop: list[tuple[bytes, bool]] = []
        self._position = 0
        self._sequence = 0
        self._keyframe_wanted = False
        self._last_keyframe_s = -1e9
        if settings.encode == "loop":
            self._loop = self._encode_gop()

    def _encode_gop(self) -> list[tuple[bytes, bool]]:
        cfg = self.encoder.config
        out: list[tuple[bytes, bool]] = []
        for i in range(cfg.gop_frames):
            view = frame_view(self.texture, cfg.width, i)
            encoded = self.encoder.encode(view, frame_id=i, pts_us=i * cfg.frame_duration_us)
            info = parse_fragment(encoded.fragment)
            out.append((info.sample, info.keyframe))
        if not out[0][1]:
            raise RuntimeError("the first frame of the GOP is not a keyframe")
        return out

    def want_keyframe(self) -> None:
        self._keyframe_wanted = True
        self.encoder.request_keyframe()

    def next(self, frame_id: int, pts_us: int) -> EncodedFrame:
        if not self._loop:
            view = frame_view(self.texture, self.settings.size.width, frame_id)
            return self.encoder.encode(view, frame_id=frame_id, pts_us=pts_us)
        start = time.perf_counter()
        now = time.monotonic()
        if self._keyframe_wanted and now - self._last_keyframe_s >= KEYFRAME_MIN_INTERVAL_S:
            self._position = 0
            self._keyframe_wanted = False
        if self._position >= len(self._loop):
            self._position = 0
        sample, keyframe = self._loop[self._position]
        self._position += 1
        if keyframe:
            self._last_keyframe_s = now
            self._keyframe_wanted = False
        self._sequence += 1
        duration = self.encoder.config.frame_duration_us
        fragment = media_fragment(self._sequence, pts_us, duration, sample, keyframe)
        ms = (time.perf_counter() - start) * 1000.0
        return EncodedFrame(frame_id, pts_us, keyframe, fragment, ms, 0.0, 0.0)


@dataclass
class PublisherStats:
    frames: int = 0
    late: int = 0  # ticks skipped because we were more than a frame behind
    connects: int = 0
    started: float = 0.0

    def fps(self) -> float:
        span = time.monotonic() - self.started
        return self.frames / span if span > 0 else 0.0


class SyntheticPublisher:
    def __init__(self, settings: SyntheticSettings) -> None:
        self.settings = settings
        self.source = FrameSource(settings)
        self.broadcast = GameBroadcast(
            settings.broadcast,
            self.source.catalog_json,
            on_input=lambda path, payload: None,
            on_keyframe_wanted=self.source.want_keyframe,
        )
        self.link: MoqLink | None = None
        self.stats = PublisherStats()
        self.connected = asyncio.Event()

    def _on_events(self, link: MoqLink, events: list[Event]) -> None:
        self.broadcast.handle(events)

    async def _relay_loop(self, stop: asyncio.Event) -> None:
        while not stop.is_set():
            try:
                link = await connect_moq(
                    self.settings.relay_url,
                    on_events=self._on_events,
                    cert_hash_hex=self.settings.cert_hash_hex,
                    timeout=5.0,
                    token=self.settings.token,
                )
            except (WtConnectError, ConnectionError, OSError, TimeoutError) as exc:
                log.warning("relay unreachable (%s); retrying", exc)
                await asyncio.sleep(RECONNECT_S)
                continue
            self.stats.connects += 1
            self.link = link
            self.broadcast.attach(link.moq)
            link.pump()
            self.connected.set()
            reason = await link.wait_closed()
            self.connected.clear()
            self.broadcast.detach()
            self.link = None
            if not stop.is_set():
                log.warning("relay connection lost (%s); reconnecting", reason)

    async def run(self, stop: asyncio.Event) -> PublisherStats:
        relay = asyncio.create_task(self._relay_loop(stop))
        loop = asyncio.get_running_loop()
        live = self.settings.encode == "live"
        period = 1.0 / self.settings.fps
        duration_us = self.source.encoder.config.frame_duration_us
        self.stats.started = start = time.monotonic()
        tick = 0
        try:
            while not stop.is_set():
                due = start + tick * period
                delay = due - time.monotonic()
                if delay > 0:
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(stop.wait(), delay)
                    continue
                if -delay > period:  # behind by more than a frame: skip, do not burst
                    skipped = int(-delay / period)
                    tick += skipped
                    self.stats.late += skipped
                meta = FrameMeta(frame_id=tick, camera=Camera.identity())
                stamp(meta.stamps, Stage.RENDER_START)
                stamp(meta.stamps, Stage.RENDER_END)  # the "render" is a view of the texture
                stamp(meta.stamps, Stage.ENCODE_START)
                pts_us = tick * duration_us
                if live:
                    encoded = await loop.run_in_executor(None, self.source.next, tick, pts_us)
                else:
                    encoded = self.source.next(tick, pts_us)
                stamp(meta.stamps, Stage.ENCODE_END)
                self.broadcast.publish_frame(encoded, meta)
                link = self.link
                if link is not None and not link.closed:
                    link.flush()
                self.stats.frames += 1
                tick += 1
        finally:
            relay.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await relay
            if self.link is not None and not self.link.closed:
                # wt.close, not MoqLink.close: that one logs a normal close as a warning.
                self.link.wt.close(0, "synthetic publisher done")
        return self.stats


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--relay", required=True, help="relay URL, e.g. http://localhost:4443/")
    parser.add_argument("--broadcast", default="game", help="broadcast name (default: game)")
    parser.add_argument("--size", default="1280x720", help="frame size WIDTHxHEIGHT")
    parser.add_argument("--fps", type=float, default=30.0, help="frames per second")
    parser.add_argument(
        "--bitrate-kbps", type=int, default=None, help="default: scaled 6 Mbit/s at 720p60"
    )
    parser.add_argument("--gop", type=float, default=2.0, help="seconds between keyframes")
    parser.add_argument(
        "--encode", choices=("loop", "live"), default="loop", help="see the module doc"
    )
    parser.add_argument("--cert-hash", default=None, help="pin this certificate SHA-256 (hex)")
    parser.add_argument("--duration", type=float, required=True, help="stop after SECONDS")
    parser.add_argument("--token", default=None, help="publish token (upcast token sign ...)")


def settings_from(args: argparse.Namespace) -> SyntheticSettings:
    """ValueError naming the option when an argument is unusable."""
    size = Size.parse(args.size)
    if not 0 < args.duration <= MAX_DURATION_S:
        raise ValueError(f"--duration must be in (0, {MAX_DURATION_S:g}], got {args.duration:g}")
    if args.bitrate_kbps is not None and args.bitrate_kbps < 10:
        raise ValueError(f"--bitrate-kbps must be at least 10, got {args.bitrate_kbps}")
    if args.gop <= 0:
        raise ValueError(f"--gop must be positive, got {args.gop:g}")
    settings = SyntheticSettings(
        relay_url=args.relay,
        size=size,
        fps=args.fps,
        bitrate=None if args.bitrate_kbps is None else args.bitrate_kbps * 1000,
        gop_seconds=args.gop,
        broadcast=args.broadcast,
        encode=args.encode,
        cert_hash_hex=args.cert_hash,
        token=args.token,
    )
    problem = settings.problem()
    if problem is not None:
        raise ValueError(problem)
    return settings


async def _main(settings: SyntheticSettings, duration_s: float) -> int:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    loop.call_later(duration_s, stop.set)
    publisher = SyntheticPublisher(settings)
    stats = await publisher.run(stop)
    print(
        f"synthetic publisher: {stats.frames} frames at {stats.fps():.1f} fps"
        f" ({stats.late} late ticks skipped, {stats.connects} relay connection(s))",
        file=sys.stderr,
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m server.loadtest.synthetic",
        description="publish a synthetic game broadcast to a relay (for load tests)",
    )
    add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        settings = settings_from(args)
    except ValueError as exc:
        print(f"synthetic publisher: {exc}", file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    install_redaction()
    install_uvloop()
    return asyncio.run(_main(settings, args.duration))


if __name__ == "__main__":
    sys.exit(main())
