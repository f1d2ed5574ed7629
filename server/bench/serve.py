"""``upcast bench serve``: N sessions of ``upcast serve``, one worker killed halfway.

Runs the real serve path (``upcast serve`` as a subprocess: one relay, one
process per session) and measures every session's frame rate twice: as the
session counts the frames it publishes (``/sessions``), and as a viewer on the
relay receives them (one moq-lite connection subscribed to every session's
``video`` track). After a warm-up, the first half of the measurement runs
undisturbed; then one session's worker is killed with SIGKILL and the second
half (which holds the whole worker restart) is measured the same way. The
report has per-session fps before and after, the longest gap a viewer saw
after the kill, and the others' after/before ratios.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import itertools
import json
import os
import signal
import subprocess
import sys
import time
import urllib.request
from collections import defaultdict
from pathlib import Path
from typing import Any

from server.media.catalog import VIDEO_TRACK
from server.moq.events import Event, FrameReceived
from server.ops.process import stop_child
from server.ops.report import BenchReport
from server.quic.moq_link import MoqLink, connect_moq
from server.session.broadcast import CATALOG_TRACK

ROOT = Path(__file__).resolve().parents[2]
UP_TIMEOUT_S = 240.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", type=Path, required=True, help="report path")
    parser.add_argument("--sessions", type=int, default=4)
    parser.add_argument("--render-size", default="640x360")
    parser.add_argument("--display-size", default="1280x720")
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--upscaler", default="bilinear")
    parser.add_argument("--duration", type=float, default=40.0, help="seconds measured in all")
    parser.add_argument("--warmup", type=float, default=8.0, help="seconds after all are up")
    parser.add_argument("--kill", type=int, default=2, help="whose worker is killed (1-based)")
    parser.add_argument("--port", type=int, default=4450, help="relay port (HTTP side: +1)")


class FrameCounter:
    """One viewer connection subscribed to every session's video track, following each
    session's catalog when the video moves to a new track (a new encoded size)."""

    def __init__(self) -> None:
        self.arrivals: dict[str, list[float]] = defaultdict(list)
        self._tracks: dict[int, str] = {}  # video subscription -> broadcast
        self._catalogs: dict[int, str] = {}  # catalog subscription -> broadcast
        self._video: dict[str, tuple[int, str]] = {}  # broadcast -> (subscription, track)

    def on_events(self, link: MoqLink, events: list[Event]) -> None:
        now = time.monotonic()
        for e in events:
            if not isinstance(e, FrameReceived):
                continue
            if e.subscription_id in self._tracks:
                self.arrivals[self._tracks[e.subscription_id]].append(now)
            elif e.subscription_id in self._catalogs:
                self._follow(link, self._catalogs[e.subscription_id], e.payload)

    def subscribe(self, link: MoqLink, broadcasts: list[str]) -> None:
        for b in broadcasts:
            self._catalogs[link.moq.subscribe(b, CATALOG_TRACK)] = b
            self._watch(link, b, VIDEO_TRACK)
        link.flush()

    def _watch(self, link: MoqLink, broadcast: str, track: str) -> None:
        old = self._video.get(broadcast)
        if old is not None:
            if old[1] == track:
                return
            self._tracks.pop(old[0], None)
            link.moq.unsubscribe(old[0])
        subscription = link.moq.subscribe(broadcast, track)
        self._tracks[subscription] = broadcast
        self._video[broadcast] = (subscription, track)

    def _follow(self, link: MoqLink, broadcast: str, catalog: bytes) -> None:
        with contextlib.suppress(ValueError, KeyError, TypeError, StopIteration):
            track = next(iter(json.loads(catalog)["video"]["renditions"]))
            self._watch(link, broadcast, str(track))
            link.flush()

    def rate(self, broadcast: str, start: float, end: float) -> float:
        n = sum(1 for t in self.arrivals[broadcast] if start <= t < end)
        return n / (end - start)

    def max_gap_ms(self, broadcast: str, start: float, end: float) -> float:
        times = [start] + [t for t in self.arrivals[broadcast] if start <= t < end] + [end]
        return max(b - a for a, b in itertools.pairwise(times)) * 1000.0


def _sessions(http_port: int) -> list[dict[str, Any]]:
    with urllib.request.urlopen(f"http://127.0.0.1:{http_port}/sessions", timeout=5) as r:
        rows: list[dict[str, Any]] = json.loads(r.read())["sessions"]
    return rows


async def _poll_sessions(http_port: int) -> list[dict[str, Any]]:
    return await asyncio.get_running_loop().run_in_executor(None, _sessions, http_port)


async def _wait_all_up(proc: subprocess.Popen[bytes], http_port: int) -> list[dict[str, Any]]:
    deadline = time.monotonic() + UP_TIMEOUT_S
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"upcast serve exited with {proc.returncode}")
        with contextlib.suppress(OSError, ValueError):
            rows = await _poll_sessions(http_port)
            if all(r["state"] == "up" and r["frames"] > 0 for r in rows):
                return rows
        await asyncio.sleep(0.5)
    raise TimeoutError(f"not every session was up after {UP_TIMEOUT_S:.0f} s")


async def watch_every_session(
    proc: subprocess.Popen[bytes], port: int, counter: FrameCounter | None = None
) -> tuple[list[str], FrameCounter, MoqLink]:
    """Once every session of ``upcast serve`` (relay on ``port``) is up: one viewer on
    the relay subscribed to each session's video track (``counter``, a new
    FrameCounter by default). The caller closes the link."""
    rows = await _wait_all_up(proc, port + 1)
    broadcasts = [r["broadcast"] for r in rows]
    counter = counter if counter is not None else FrameCounter()
    link = await connect_moq(f"http://127.0.0.1:{port}/", on_events=counter.on_events)
    counter.subscribe(link, broadcasts)
    return broadcasts, counter, link


async def _frames_at(http_port: int) -> tuple[float, dict[str, tuple[float, int]]]:
    """Now, and each session's (time counted, frames published)."""
    rows = await _poll_sessions(http_port)
    return time.monotonic(), {r["broadcast"]: (r["frames_at"], int(r["frames"])) for r in rows}


def _rate(a: tuple[float, int], b: tuple[float, int]) -> float:
    return (b[1] - a[1]) / (b[0] - a[0]) if b[0] > a[0] else 0.0


async def _measure(args: argparse.Namespace, report: BenchReport) -> None:
    http_port = args.port + 1
    cmd = [sys.executable, "-m", "server.cli", "serve", "--sessions", str(args.sessions)]
    cmd += ["--render-size", args.render_size, "--display-size", args.display_size]
    cmd += ["--fps", f"{args.fps:g}", "--upscaler", args.upscaler, "--port", str(args.port)]
    cmd += ["--admission", "admit"]  # N sessions, whatever the host: what is measured
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env)
    link: MoqLink | None = None
    try:
        broadcasts, counter, link = await watch_every_session(proc, args.port)
        await asyncio.sleep(args.warmup)
        half = args.duration / 2
        t0, f0 = await _frames_at(http_port)
        await asyncio.sleep(half)
        t1, f1 = await _frames_at(http_port)
        victim = next(r for r in await _poll_sessions(http_port) if r["index"] == args.kill)
        os.kill(int(victim["worker_pid"]), signal.SIGKILL)
        killed_at = time.monotonic()
        await asyncio.sleep(half)
        t2, f2 = await _frames_at(http_port)
        final = {r["broadcast"]: r for r in await _poll_sessions(http_port)}
        for b in broadcasts:
            before, after = _rate(f0[b], f1[b]), _rate(f1[b], f2[b])
            view_before, view_after = counter.rate(b, t0, t1), counter.rate(b, t1, t2)
            report.add_case(
                b,
                worker_killed=b == victim["broadcast"],
                target_fps=args.fps,
                session_fps_before=round(before, 2),
                session_fps_after=round(after, 2),
                viewer_fps_before=round(view_before, 2),
                viewer_fps_after=round(view_after, 2),
                viewer_max_gap_ms_after_kill=round(counter.max_gap_ms(b, killed_at, t2), 1),
                worker_restarts=final[b]["worker_restarts"],
                session_restarts=final[b]["restarts"],
            )
            if b != victim["broadcast"] and view_before > 0:
                report.add_ratio(
                    f"{b} viewer fps after/before", "after", "before", view_after / view_before
                )
    finally:
        if link is not None and not link.closed:
            link.wt.close(0, "bench over")
        stop_child(proc, 60)


def _summarize(report: BenchReport, target_fps: float) -> None:
    """Totals over all sessions, and what the figures mean on this machine."""
    cases = list(report.cases)
    others = [c for c in cases if not c["worker_killed"]]
    report.add_case(
        "all sessions",
        viewer_fps_total_before=round(sum(c["viewer_fps_before"] for c in cases), 2),
        viewer_fps_total_after=round(sum(c["viewer_fps_after"] for c in cases), 2),
        others_min_after_over_before=round(
            min(c["viewer_fps_after"] / c["viewer_fps_before"] for c in others), 3
        )
        if others and all(c["viewer_fps_before"] > 0 for c in others)
        else None,
    )
    held = min(c["viewer_fps_before"] for c in cases)
    if held < 0.9 * target_fps:
        report.notes.append(
            f"CPU-bound: every session renders, upscales and x264-encodes on the CPU, and "
            f"{len(cases)} of them share {os.cpu_count()} cores, so each held about "
            f"{held:.1f}-{max(c['viewer_fps_before'] for c in cases):.1f} of the "
            f"{target_fps:g} fps target before the kill. Whether the others kept their "
            "rate is judged against that 'before' rate, not against the target."
        )


def run(args: argparse.Namespace) -> int:
    if not 1 <= args.kill <= args.sessions:
        print(f"--kill must name a session in 1..{args.sessions}", file=sys.stderr)
        return 2
    report = BenchReport(
        "serve",
        {
            "sessions": args.sessions,
            "render_size": args.render_size,
            "display_size": args.display_size,
            "fps": args.fps,
            "upscaler": args.upscaler,
            "duration_s": args.duration,
            "warmup_s": args.warmup,
            "killed_worker_of_session": args.kill,
        },
    )
    report.notes.append(
        "session_fps: frames each session published (its own count, read from /sessions); "
        "viewer_fps: frames one moq-lite viewer on the relay received per session. 'before' is "
        "the first half of the measurement, 'after' the second half, which starts with a "
        "SIGKILL of one session's worker and holds its whole restart."
    )
    # Other work on the machine takes cores from the sessions: say how much there was.
    report.config["load_average_1m_at_start"] = round(os.getloadavg()[0], 2)
    try:
        asyncio.run(_measure(args, report))
        report.config["load_average_1m_at_end"] = round(os.getloadavg()[0], 2)
    except (RuntimeError, TimeoutError, OSError) as exc:
        print(f"upcast bench serve: {exc}", file=sys.stderr)
        return 1
    _summarize(report, args.fps)
    report.write(args.json)
    for case in report.cases:
        if "session_fps_before" not in case:
            continue
        print(
            f"{case['name']}: session {case['session_fps_before']:.1f} -> "
            f"{case['session_fps_after']:.1f} fps, viewer {case['viewer_fps_before']:.1f} -> "
            f"{case['viewer_fps_after']:.1f} fps"
            + ("  (worker killed)" if case["worker_killed"] else "")
        )
    print(f"wrote {args.json}")
    return 0
