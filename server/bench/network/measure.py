"""One profile of ``upcast bench network``: the stack, the emulated link, the page.

The stack runs as in the latency benchmark (LiveStack: relay process, game and
worker processes, the session on a thread of this process, a frame tap keeping
thumbnails of what was encoded). The emulator (server/net) listens on its own port
on loopback, in a process of its own (server/bench/network/link.py), and forwards
to the relay: UDP shaped, TCP passed through (the page
fetches the relay's certificate hash over TCP from the port it connects to). The
page itself is served by the relay directly; its ``port`` parameter makes it
connect to the emulator instead (``http://localhost:EMU/``: Chromium resolves
localhost to ::1, where the emulator listens too). Load-test viewers, if any,
connect to the emulator as well and share the link with the page. Spectator pages
(``--spectators``) each get an emulator of their own and join as the window opens
(server/bench/network/spectators.py).

Timeline: the page connects, plays ``warmup`` seconds, then the window of
``seconds`` opens; at its start the emulator's schedule restarts, so a profile's
steps (``drop``'s dip at 10 s) fall where their names say.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from typing import Any

from server.bench.latency import STAGES, LiveStack, StageCollector, percentiles
from server.bench.network.link import EmulatorProcess
from server.bench.network.page import (
    DRAW_WATCH,
    READ_DRAWS,
    PictureQuality,
    ShownFrames,
    counter_deltas,
)
from server.bench.network.series import SAMPLE_EVERY_S, RateSeries, capacity_bps
from server.bench.network.spectators import Spectators, published_frames
from server.bench.network.viewers import SpectatorViewers, viewers_summary
from server.bench.page_stats import read_latency, read_stats
from server.loadtest.plan import RunPlan
from server.loadtest.viewer import ViewerConfig
from server.net import resolve
from server.serve.snapshots import FrameThumbs
from server.stack.local import SessionConfig

CONNECT_TIMEOUT_S = 60.0
# Each received-PSNR snapshot reads the page's canvas back and sums it on the page's
# main thread, holding up the frames arriving meanwhile in every client stage: at one a
# second it lengthened lan's glass-to-glass p95 from 60.9 to 74.8 ms (20 s runs, one
# sitting); one every 3 s, 64.3, still ten pictures compared per 30 s profile.
SNAPSHOT_EVERY_S = 3.0
PROGRESS_EVERY_S = 2.0
VIEWER_LEAD_S = 1.5  # the viewers' worker gets the plan this long before they connect
LATE_RELEASE_NOTE_MS = 10.0  # emulator lateness (p99) past which the case says so


@dataclass(frozen=True)
class NetworkRun:
    profile: str
    seconds: float
    warmup_s: float
    viewers: int
    session: SessionConfig
    bitrate: int | None = None
    rate_control: bool = True
    intra_refresh: bool = True
    congestion_control: str | None = None  # the relay's QUIC sender; None: its default
    spectators: tuple[str, ...] = ()  # a spectator page per profile, each on its own link
    ladder: tuple[int, ...] = ()  # the session's rendition ladder (divisors); () none


def _stream_state(live: LiveStack, key: str) -> int | None:
    """A figure of the session's rate control from its stream state (what every timing
    record carries): ``bitrate`` is the rate chosen (bits per second of stream; while it
    thins the frame rate the encoder is told twice this), ``fps_divisor`` 1 or 2."""
    state = getattr(live.session, "stream_state", None)
    value = state.get(key) if isinstance(state, dict) else None
    return int(value) if isinstance(value, int | float) else None


def _bytes(stats: dict[str, Any]) -> int | None:
    value = stats.get("bytesReceived")
    return int(value) if isinstance(value, int | float) else None


def measure(run: NetworkRun, browser: Any) -> dict[str, Any]:
    schedule = resolve(run.profile)
    thumbs = FrameThumbs()
    name = run.profile
    with (
        LiveStack(
            run.session,
            frame_tap=thumbs,
            bitrate=run.bitrate,
            rate_control=run.rate_control,
            intra_refresh=run.intra_refresh,
            relay_args=()
            if run.congestion_control is None
            else ("--congestion-control", run.congestion_control),
            ladder=run.ladder,
        ) as live,
        EmulatorProcess(
            listen=("localhost", 0),
            upstream=("127.0.0.1", live.port),
            schedule=schedule,
            tcp_passthrough=True,
        ) as net,
        Spectators(run.spectators).start_links(live.port) as watchers,
    ):
        assert live.endpoint is not None and live.session is not None
        session = live.session
        spectators: SpectatorViewers | None = None
        # A context of its own per profile: closing it closes the page's TCP connections
        # through the emulator before the emulator stops.
        context = browser.new_context(viewport={"width": 1400, "height": 900})
        page = context.new_page()
        try:
            if run.viewers:
                config = ViewerConfig(
                    f"http://127.0.0.1:{net.port}/",
                    live.broadcast,
                    live.endpoint.cert_sha256,
                    10.0,
                    token=live.tokens.player,
                    feedback=True,
                )
                spectators = SpectatorViewers(config, run.viewers)
                spectators.start()
            page.add_init_script(DRAW_WATCH)
            page.on("console", lambda m: m.type == "error" and print("page:", m.text))
            page.goto(live.player_url(overlay="0", port=str(net.port)))
            page.wait_for_function(
                "() => window.upcast && window.upcast.stats().framesPresented > 0",
                timeout=CONNECT_TIMEOUT_S * 1000,
            )
            watchers.prepare(browser)
            t0 = time.monotonic() + run.warmup_s
            t_end = t0 + run.seconds
            if spectators is not None:
                start = time.monotonic() + VIEWER_LEAD_S
                spectators.begin(RunPlan(start, 20.0, t0, t_end, t_end + 0.5))
            collector = StageCollector.empty()
            while (left := t0 - time.monotonic()) > 0:
                page.wait_for_timeout(int(min(SAMPLE_EVERY_S, left) * 1000) + 1)
                collector.update(read_latency(page), keep=False)
            net.restart_schedule()
            shown = ShownFrames()
            shown.start(page.evaluate(READ_DRAWS)["draws"])
            first = read_stats(page)
            published0 = session.broadcast.stats.frames_published
            probe = session.rate.controller.probe
            probes0 = (probe.started, probe.succeeded)
            t0 = time.monotonic()
            t_end = t0 + run.seconds
            series = RateSeries(schedule, t0)
            quality = PictureQuality()
            next_snapshot = t0 + SNAPSHOT_EVERY_S / 2
            next_progress = t0 + PROGRESS_EVERY_S
            last = first
            next_sample = t0
            while True:
                # Samples on a fixed 0.5 s grid; the page reads fit between them.
                while (left := next_sample - time.monotonic()) > 0:
                    page.wait_for_timeout(int(left * 1000) + 1)
                now = time.monotonic()
                link = net.stats()
                series.sample(
                    now,
                    target_bps=_stream_state(live, "bitrate"),
                    step=int(link["step"]),
                    link_bytes=int(link["down"]["bytes_delivered"]),
                    page_bytes=_bytes(last),
                    frame_divisor=_stream_state(live, "fps_divisor"),
                )
                if now >= t_end:
                    break
                next_sample = min(max(next_sample + SAMPLE_EVERY_S, now), t_end)
                if run.spectators:
                    # They join after the window's first sample, so that it is on time.
                    if not watchers.joined:
                        watchers.join(live.port, live.broadcast, t0)
                    watchers.read(now, published_frames(session))
                live.check()
                last = read_stats(page)
                collector.update(last["latency"])
                shown.add(page.evaluate(READ_DRAWS)["draws"])
                if now >= next_snapshot:
                    quality.snapshot(page, thumbs)
                    next_snapshot += SNAPSHOT_EVERY_S
                if now >= next_progress:
                    next_progress += PROGRESS_EVERY_S
                    _progress(name, t0, run.seconds, series, shown)
            elapsed = time.monotonic() - t0
            published = session.broadcast.stats.frames_published - published0
            # Link probes (padded frames, server/session/link_probe.py) in the window.
            probes = {"started": probe.started - probes0[0], "proved": probe.succeeded - probes0[1]}
            tail = page.evaluate(READ_DRAWS)
            shown.add(tail["draws"])
            shown.finish(tail["now"])
            end = read_stats(page)
            link_end = net.stats()
            if run.spectators:
                watchers.finish(published_frames(session))
        finally:
            context.close()
        viewers = spectators.finish() if spectators is not None else []
    presented = end["framesPresented"] - first["framesPresented"]
    late = link_end["release_late_ms"].get("p99")
    notes = watchers.notes(LATE_RELEASE_NOTE_MS)
    if late is not None and late > LATE_RELEASE_NOTE_MS:
        notes.append(
            f"the emulator released packets late (p99 {late:.0f} ms after their due time):"
            " the machine was overloaded and the figures include that"
        )
    g2g = percentiles(collector.samples["total"])
    return {
        "name": name,
        "profile": schedule.description,
        "seconds": round(elapsed, 2),
        "frames_published": published,
        "frames_shown": presented,
        "frames_drawn": shown.shown,
        "server_fps": round(published / elapsed, 2),
        "page_fps": round(presented / elapsed, 2),
        "delivered_ratio": round(presented / published, 4) if published else None,
        "freezes": shown.summary(),
        "glass_to_glass": g2g,
        # Where the time goes (each stage's own p50 / p95; they do not add up at the p95).
        "stages": {stage: percentiles(collector.samples[stage]) for stage in STAGES},
        "median_ms": g2g["p50_ms"],
        "p95_ms": g2g["p95_ms"],
        "received_psnr_db": quality.summary(),
        "page_counters": counter_deltas(first, end),
        "bitrate_means": series.means(),
        "probes": probes,
        "series": series.as_dict(),
        "capacity_steps": [
            {"at_s": s.at_s, "capacity_bps": capacity_bps(schedule, i)}
            for i, s in enumerate(schedule.steps)
        ],
        "link": {k: link_end[k] for k in ("down", "up", "release_late_ms", "send_errors")},
        "viewers": viewers_summary(viewers) if run.viewers else None,
        **({"spectators": watchers.summary()} if run.spectators else {}),
        "notes": notes,
    }


def _mbit(value: float | int | None) -> str:
    return "-" if value is None else f"{value / 1e6:.2f}"


def _progress(name: str, t0: float, seconds: float, series: RateSeries, shown: ShownFrames) -> None:
    at = time.monotonic() - t0
    target = series.bitrate_target_bps[-1] if series.bitrate_target_bps else None
    capacity = series.capacity_bps[-1] if series.capacity_bps else None
    delivered = series.link_delivered_bps[-1] if series.link_delivered_bps else None
    print(
        f"  {name}: {at:5.1f}/{seconds:.0f} s, target {_mbit(target)} Mbit/s, capacity "
        f"{'unlimited' if capacity is None else _mbit(capacity)}, link {_mbit(delivered)},"
        f" shown {shown.shown / max(at, 1e-3):.1f} fps, {shown.freezes} freezes",
        file=sys.stderr,
        flush=True,
    )
