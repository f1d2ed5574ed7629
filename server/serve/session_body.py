"""One game session's body, shared by ``upcast up`` and each session of ``upcast serve``.

Starts the session's rings, game and worker (LocalStack), streams ring U to the
relay (StreamingSession, in this process) with its ``status`` track, and
watches it: a dead worker is restarted by the stack, a dead game ends the
session with RuntimeError (``upcast serve`` then restarts the whole session).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from server.serve.frame_tap import FrameTapServer
    from server.serve.status_reporter import StatusReporter
    from server.session.pulse_monitor import PulseMonitor
    from server.session.runner import StreamingSession
    from server.stack.local import LocalStack, SessionConfig
    from server.stream_config import StreamConfig

log = logging.getLogger(__name__)

CHECK_INTERVAL_S = 0.5
CONNECT_TIMEOUT_S = 30.0


class SessionFailed(RuntimeError):
    """The session could not start or stopped on its own; the message says why."""


@dataclass(frozen=True)
class SessionPlan:
    config: SessionConfig
    stream: StreamConfig  # broadcast, bitrate, keyframe interval
    relay_url: str  # where to publish
    token: str | None = None  # the publisher's JWT (None: an open relay)
    # The session's Prometheus port; the game's and the worker's are the next two
    # (one block of three per session). 0 = all off.
    metrics_port: int = 0
    cert_hash_hex: str | None = None  # pin the relay's certificate instead of fetching it
    duration_s: float | None = None  # stop after this long (None: until stop is set)
    # Thumbnails of the encoded frames by id over HTTP (server/serve/frame_tap.py);
    # 0 = off, the default: a debugging and testing aid.
    frame_tap_port: int = 0
    frame_tap_host: str = "127.0.0.1"


@dataclass
class LiveSession:
    """What callers see of a running session (in the on_up / on_tick callbacks)."""

    plan: SessionPlan
    stack: LocalStack
    session: StreamingSession
    status: StatusReporter
    metrics_port: int  # 0 when off or the port was taken


async def run_game_session(
    plan: SessionPlan,
    stop: asyncio.Event,
    *,
    on_up: Callable[[LiveSession], None],
    on_tick: Callable[[LiveSession], None] | None = None,
) -> None:
    """Run until ``stop``, the duration, or a failure (raises SessionFailed / RuntimeError
    / TimeoutError with a message for a person)."""
    from prometheus_client import CollectorRegistry, start_http_server

    from server.frames.frame import Size
    from server.serve.frame_tap import start_frame_tap
    from server.serve.snapshots import FrameThumbs
    from server.serve.status_reporter import StatusReporter
    from server.session.pulse_monitor import PulseMonitor
    from server.session.runner import StreamingSession, StreamSettings
    from server.stack.local import LocalStack
    from upscalers import registry as upscaler_registry

    loop = asyncio.get_running_loop()
    config, stream = plan.config, plan.stream
    ports = (plan.metrics_port + 1, plan.metrics_port + 2) if plan.metrics_port else (0, 0)
    stack = LocalStack(config, metrics_ports=ports, app_sound=stream.audio)
    session_task: asyncio.Task[None] | None = None
    sound: PulseMonitor | None = None
    thumbs = FrameThumbs() if plan.frame_tap_port else None
    tap: FrameTapServer | None = None
    try:
        await loop.run_in_executor(None, stack.start)
        await loop.run_in_executor(None, stack.wait_ready)
        assert stack.ring_u is not None
        registry = CollectorRegistry()
        metrics_port = plan.metrics_port
        if metrics_port:
            try:
                start_http_server(metrics_port, registry=registry)
            except OSError as exc:
                log.warning("session metrics port %d unavailable: %s", metrics_port, exc)
                metrics_port = 0
        settings = StreamSettings(
            relay_url=plan.relay_url,
            token=plan.token,
            broadcast=stream.broadcast,
            fps=config.fps,
            bitrate=stream.bitrate_bps,
            gop_seconds=stream.gop_seconds,
            cert_hash_hex=plan.cert_hash_hex,
            audio=stream.audio,
            rate_control=stream.rate_control,
            intra_refresh=stream.intra_refresh,
            ladder=tuple(stream.ladder),
            upscaler=config.upscaler,
            source=config.source,
            gamepad=config.gamepad,
            scale=config.scale,
            frame_generation=config.frame_generation,
            quality=stream.quality,
            quality_preference=stream.quality_preference,
            min_scale=stream.min_scale,
            max_scale=stream.max_scale,
            quality_methods=tuple(stream.quality_methods),
            cache_policy=upscaler_registry.cache_policy_at_start(
                config.upscaler, config.cache_policy
            ),
        )
        if stream.audio and config.source == "x11":
            # The application's own sound, from its session's PulseAudio sink.
            sound = PulseMonitor(stack.pulse_dir / "native")
        session = StreamingSession(
            settings,
            stack.ring_u,
            Size.parse(config.display_size),
            game_input=stack.input_path,
            worker_control=stack.control_path,
            registry=registry,
            on_upscaler_set=stack.remember_upscaler,
            sound=sound,
            frame_tap=thumbs,
        )
        if thumbs is not None:
            tap = start_frame_tap(thumbs, plan.frame_tap_host, plan.frame_tap_port)
        status = StatusReporter(session)
        session_task = asyncio.create_task(session.run(stop), name="session")
        try:
            async with asyncio.timeout(CONNECT_TIMEOUT_S):
                await session.connected.wait()
        except TimeoutError:
            raise SessionFailed("the session could not publish to the relay") from None
        live = LiveSession(plan, stack, session, status, metrics_port)
        status.publish()
        on_up(live)
        deadline = None if plan.duration_s is None else time.monotonic() + plan.duration_s
        while not stop.is_set():
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(CHECK_INTERVAL_S):
                    await stop.wait()
            stack.check_children()
            status.tick()
            if on_tick is not None:
                on_tick(live)
            if session_task.done():
                session_task.result()  # surfaces the error
                break
            if deadline is not None and time.monotonic() >= deadline:
                log.info("duration of %.0f s reached: stopping", plan.duration_s)
                break
    finally:
        stop.set()
        if session_task is not None:
            with contextlib.suppress(Exception):
                await session_task
        if sound is not None:
            sound.close()
        if tap is not None:
            tap.close()
        stack.stop()
