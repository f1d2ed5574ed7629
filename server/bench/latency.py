"""``upcast bench latency``: the latency budget from render_end to client_present.

The whole stack runs as ``upcast up`` runs it (relay process, game and worker
processes, the streaming session in this process on its own event loop) and a
headless Chromium plays the stream from the relay over loopback. The page joins
the server's timing track with its own receive/decode/present stamps; this
benchmark reads those per-frame samples from ``window.upcast.stats()`` and
reports p50/p95 of every stage, plus the encoder's mux delay in frames
(fragments the encoder still holds back: 0 when every frame leaves at once).

:class:`LiveStack` is also what the end-to-end tests (tests/e2e/) start.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlencode

import numpy as np
import numpy.typing as npt

from server.auth import generate_key, load_key
from server.auth.minting import session_tokens
from server.bench.page_stats import read_latency, read_stats
from server.frames.frame import Size
from server.game.sounds import SoundSource
from server.ops.browser_paths import CHROMIUM, CHROMIUM_ARGS, WEB_ROOT
from server.ops.report import BenchReport
from server.relay.process import RelayEndpoint, RelayProcess
from server.session.runner import StreamingSession, StreamSettings
from server.stack.local import LocalStack, SessionConfig

log = logging.getLogger(__name__)

# Stages of the budget, in pipeline order (names of client_web/src/stats.ts); "render"
# comes before render_end and is reported for context, outside "total".
STAGES = (
    "render",
    "ring_r_handoff",
    "upscale",
    "ring_u_handoff",
    "encode",
    "publish",
    "network",
    "decode",
    "present",
    "total",
)
CONNECT_TIMEOUT_S = 30.0

FrameTap = Callable[[int, npt.NDArray[np.uint8]], None]


class LiveStack:
    """Relay process + game/worker processes + the streaming session on a thread.

    The session runs on an event loop of its own thread, so a synchronous caller
    (a test, Playwright's sync API) can drive a browser meanwhile."""

    def __init__(
        self,
        config: SessionConfig,
        *,
        port: int = 0,
        web_root: Path = WEB_ROOT,
        broadcast: str = "game",
        bitrate: int | None = None,
        frame_tap: FrameTap | None = None,
        audio: bool = False,
        sound: SoundSource | None = None,
        rate_control: bool = True,
        intra_refresh: bool = True,
        relay_args: tuple[str, ...] = (),
        ladder: tuple[int, ...] = (),
    ) -> None:
        """``audio``: publish sound too; ``sound``: what it plays (default: the game's).
        ``rate_control``, ``intra_refresh``, ``ladder``: the session's (StreamSettings;
        no rendition ladder by default, as there); ``relay_args``: more ``upcast relay``
        options."""
        self.config = config
        self._audio = audio
        self._sound = sound
        self._owned_sound: Any = None  # a PulseMonitor this stack made (source x11)
        self.broadcast = broadcast
        # A relay that checks tokens, as upcast up runs it: the session publishes with
        # its publisher token, the page sends inputs with the player's.
        self._key_dir = tempfile.TemporaryDirectory(prefix="upcast-livestack-key-")
        key_path = Path(self._key_dir.name) / "relay.jwk"
        generate_key(key_path)
        self.tokens = session_tokens(load_key(key_path), broadcast)
        self.relay = RelayProcess("::", port, web_root, auth_key=key_path, extra_args=relay_args)
        self._rate_control = rate_control
        self._intra_refresh = intra_refresh
        self._ladder = ladder
        self.stack = LocalStack(config, app_sound=audio)
        self.endpoint: RelayEndpoint | None = None
        self.session: StreamingSession | None = None
        self._bitrate = bitrate
        self._frame_tap = frame_tap
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._ready = threading.Event()

    @property
    def port(self) -> int:
        assert self.endpoint is not None
        return self.endpoint.port

    def player_url(self, **query: str) -> str:
        """The player page the relay serves (a secure context: localhost)."""
        params = {"broadcast": self.broadcast, "jwt": self.tokens.player, **query}
        return f"http://localhost:{self.port}/?" + urlencode(params)

    def start(self, timeout_s: float = CONNECT_TIMEOUT_S) -> LiveStack:
        try:
            self.endpoint = self.relay.start()
            self.stack.start()
            self.stack.wait_ready()
            self._thread = threading.Thread(target=self._run, name="live-session", daemon=True)
            self._thread.start()
            deadline = time.monotonic() + timeout_s
            while not self._ready.wait(0.1):
                if self._error is not None:
                    raise RuntimeError("streaming session failed") from self._error
                self.stack.check_children()
                if time.monotonic() > deadline:
                    raise TimeoutError(f"the session did not publish in {timeout_s:.0f} s")
        except BaseException:
            self.stop()
            raise
        return self

    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as exc:  # surfaced by start() / check()
            self._error = exc
            log.exception("streaming session failed")

    async def _main(self) -> None:
        assert self.endpoint is not None and self.stack.ring_u is not None
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        settings = StreamSettings(
            relay_url=f"http://127.0.0.1:{self.endpoint.port}/",
            token=self.tokens.publisher,
            broadcast=self.broadcast,
            fps=self.config.fps,
            bitrate=self._bitrate,
            cert_hash_hex=self.endpoint.cert_sha256,
            frame_generation=self.config.frame_generation,
            source=self.config.source,
            gamepad=self.config.gamepad,
            audio=self._audio,
            rate_control=self._rate_control,
            intra_refresh=self._intra_refresh,
            ladder=self._ladder,
        )
        if self._sound is None and self._audio and self.config.source == "x11":
            from server.session.pulse_monitor import PulseMonitor

            self._sound = self._owned_sound = PulseMonitor(self.stack.pulse_dir / "native")
        self.session = StreamingSession(
            settings,
            self.stack.ring_u,
            Size.parse(self.config.display_size),
            game_input=self.stack.input_path,
            worker_control=self.stack.control_path,
            on_upscaler_set=self.stack.remember_upscaler,
            frame_tap=self._frame_tap,
            sound=self._sound,
        )
        task = asyncio.create_task(self.session.run(self._stop))
        await self.session.connected.wait()
        self._ready.set()
        await task

    def check(self) -> None:
        """Raise if the session thread failed or the game died."""
        if self._error is not None:
            raise RuntimeError("streaming session failed") from self._error
        self.stack.check_children()

    def stop(self) -> None:
        loop, stop = self._loop, self._stop
        if loop is not None and stop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):  # the loop closed meanwhile
                loop.call_soon_threadsafe(stop.set)
        if self._thread is not None:
            self._thread.join(10.0)
        if self._owned_sound is not None:
            self._owned_sound.close()
        self.stack.stop()
        self.relay.stop()
        self._key_dir.cleanup()

    def __enter__(self) -> LiveStack:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


# -- reading the page's latency windows ---------------------------------------------------


def new_samples(previous: list[float], current: list[float]) -> list[float]:
    """The samples ``current`` (a bounded window, oldest first) added since ``previous``.

    The page keeps the last N samples of each stage; two reads overlap where the
    tail of the first equals the head of the second (float ms with microsecond
    resolution: a false overlap of many samples is practically impossible). The
    overlap ends with ``previous``'s last sample, so only the places where that
    value occurs in ``current`` are tried, with numpy: this runs on the benchmark's
    main thread, beside the session's encoder, for 18 stages every read."""
    if not previous:
        return list(current)
    old = np.asarray(previous, dtype=np.float64)
    new = np.asarray(current, dtype=np.float64)
    # The longest overlap first: the shortest shift of ``previous``.
    for end in np.flatnonzero(new == old[-1])[::-1]:
        length = int(end) + 1
        if length <= old.size and np.array_equal(new[:length], old[old.size - length :]):
            return list(current[length:])
    return list(current)


@dataclass
class StageCollector:
    """Accumulates each stage's samples across reads of ``stats().latency``."""

    last: dict[str, list[float]]
    samples: dict[str, list[float]]

    @classmethod
    def empty(cls) -> StageCollector:
        return cls({s: [] for s in STAGES}, {s: [] for s in STAGES})

    def update(self, latency: dict[str, Any], *, keep: bool = True) -> None:
        for stage in STAGES:
            current = [float(x) for x in latency.get(stage, {}).get("samples", [])]
            added = new_samples(self.last[stage], current)
            if keep:
                self.samples[stage].extend(added)
            self.last[stage] = current


def percentiles(samples: list[float]) -> dict[str, float | int | None]:
    if not samples:
        return {"count": 0, "p50_ms": None, "p95_ms": None}
    arr = np.asarray(samples, dtype=np.float64)
    return {
        "count": int(arr.size),
        "p50_ms": round(float(np.percentile(arr, 50)), 3),
        "p95_ms": round(float(np.percentile(arr, 95)), 3),
        "median_ms": round(float(np.median(arr)), 3),
        "mean_ms": round(float(arr.mean()), 3),
    }


# -- the benchmark ----------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", type=Path, required=True, help="report path")
    parser.add_argument("--fps", default="30,60", help="frame rates to measure, comma-separated")
    parser.add_argument("--seconds", type=float, default=20.0, help="seconds measured per rate")
    parser.add_argument("--warmup", type=float, default=4.0, help="seconds before measuring")
    parser.add_argument("--scene", default="default")
    parser.add_argument("--render-size", default="640x360")
    parser.add_argument("--display-size", default="1280x720")
    parser.add_argument("--upscaler", default="bilinear")
    parser.add_argument("--poll", type=float, default=2.0, help="seconds between page reads")


def _measure(args: argparse.Namespace, fps: float, browser: Any) -> dict[str, Any]:
    config = SessionConfig(
        scene=args.scene,
        render_size=args.render_size,
        display_size=args.display_size,
        fps=fps,
        upscaler=args.upscaler,
    )
    with LiveStack(config) as live:
        page = browser.new_page(viewport={"width": 1400, "height": 900})
        try:
            page.goto(live.player_url(overlay="0"))
            page.wait_for_function(
                "() => window.upcast && window.upcast.stats().framesPresented > 0",
                timeout=CONNECT_TIMEOUT_S * 1000,
            )
            collector = StageCollector.empty()
            warm_end = time.monotonic() + args.warmup
            while time.monotonic() < warm_end:
                time.sleep(min(args.poll, max(0.0, warm_end - time.monotonic())))
                collector.update(read_latency(page), keep=False)
            session = live.session
            assert session is not None
            start_stats = read_stats(page)
            server_frames0 = session.broadcast.stats.frames_published
            t0 = time.monotonic()
            end = t0 + args.seconds
            while time.monotonic() < end:
                time.sleep(min(args.poll, max(0.0, end - time.monotonic())))
                live.check()
                collector.update(read_latency(page))
                print(
                    f"  {fps:g} fps: {time.monotonic() - t0:5.1f}/{args.seconds:.0f} s, "
                    f"{len(collector.samples['total'])} frames timed",
                    file=sys.stderr,
                )
            elapsed = time.monotonic() - t0
            stats = read_stats(page)
            server_frames = session.broadcast.stats.frames_published - server_frames0
            encoder = session.encoder
        finally:
            page.close()
    presented = stats["framesPresented"] - start_stats["framesPresented"]
    return {
        "name": f"{args.display_size}@{fps:g}",
        "fps_target": fps,
        "seconds": round(elapsed, 2),
        "server_fps": round(server_frames / elapsed, 2),
        "page_fps": round(presented / elapsed, 2),
        "page_dropped": stats["dropped"] - start_stats["dropped"],
        "groups_skipped": stats["groupsSkipped"] - start_stats["groupsSkipped"],
        "version": stats.get("version"),
        "codec": stats.get("codec"),
        # x264 zerolatency + our own CMAF boxing: one fragment per frame, none held back.
        "mux_delay_frames": encoder.frames_in - encoder.fragments_out,
        "encoder_frames_in": encoder.frames_in,
        "encoder_fragments_out": encoder.fragments_out,
        "stages": {stage: percentiles(collector.samples[stage]) for stage in STAGES},
        "median_ms": percentiles(collector.samples["total"])["median_ms"],
        "p95_ms": percentiles(collector.samples["total"])["p95_ms"],
    }


def _print_table(cases: list[dict[str, Any]]) -> None:
    header = f"{'stage':16}" + "".join(f"{c['name']:>24}" for c in cases)
    print(header)
    print(f"{'':16}" + "".join(f"{'p50 / p95 ms':>24}" for _ in cases))
    for stage in STAGES:
        row = f"{stage:16}"
        for case in cases:
            s = case["stages"][stage]
            cell = "-" if s["count"] == 0 else f"{s['p50_ms']:.2f} / {s['p95_ms']:.2f}"
            row += f"{cell:>24}"
        print(row)
    for key in ("server_fps", "page_fps", "mux_delay_frames"):
        print(f"{key:16}" + "".join(f"{c[key]!s:>24}" for c in cases))


def run(args: argparse.Namespace) -> int:
    if not CHROMIUM.exists():
        print("upcast bench latency: needs /usr/bin/chromium", file=sys.stderr)
        return 2
    if not (WEB_ROOT / "index.html").is_file():
        print("upcast bench latency: build client_web first (npm run build)", file=sys.stderr)
        return 2
    try:
        rates = [float(x) for x in args.fps.split(",") if x.strip()]
    except ValueError:
        print(f"upcast bench latency: bad --fps {args.fps!r}", file=sys.stderr)
        return 2
    from playwright.sync_api import sync_playwright

    load_before = _loadavg()
    report = BenchReport(
        "latency",
        {
            "scene": args.scene,
            "render_size": args.render_size,
            "display_size": args.display_size,
            "upscaler": args.upscaler,
            "fps": rates,
            "seconds": args.seconds,
            "warmup": args.warmup,
            "transport": "loopback, relay process, headless Chromium (WebTransport)",
        },
    )
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=list(CHROMIUM_ARGS))
        try:
            for fps in rates:
                case = _measure(args, fps, browser)
                report.add_case(**case)
        finally:
            browser.close()
    report.notes.append(
        "stages from the page's stats().latency: server spans from the timing track, "
        "network = client receive - publish, total = client present - render_end "
        "(wall clocks of one machine)"
    )
    report.notes.append(f"load average before {load_before}, after {_loadavg()}")
    report.write(args.json)
    _print_table(report.cases)
    print(f"wrote {args.json}")
    return 0


def _loadavg() -> list[float]:
    try:
        with open("/proc/loadavg", encoding="utf-8") as f:
            return [float(x) for x in f.read().split()[:3]]
    except OSError:
        return []
