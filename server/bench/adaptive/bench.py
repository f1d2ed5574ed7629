"""``upcast bench adaptive``: adaptive quality against fixed settings, 1 to N sessions,
with a CPU hog taking a core for the middle third of each run.

Each case runs the real serve path (``upcast serve`` as a subprocess: one relay, one
process per session) with ``--quality auto`` or with one fixed setting, on the same
scene, seed and schedule, one after the other. One moq-lite viewer on the relay counts
every session's video frames; ``/sessions`` is read every second for the setting each
session runs. Per session the report has:

- the frame rate the viewer received, per one-second bin: mean, minimum, the share of
  bins at 90 % of the target or more, and the mean before, during and after the hog;
- the frame rate the session chose (adaptive quality lowers it when nothing cheaper
  holds the target): its mean, and the share of bins at 90 % of it or more;
- how long after the hog started the rate was back at 90 % (two bins in a row), and
  how long after it ended the setting stepped up again;
- the settings it ran and for how long, the switches (each is one log line of the
  session, counted from serve's log), and the picture the speed-against-error table
  expects of them, weighted by time (the table's figure, a model);
- the picture the viewer saw, measured: PSNR and SSIM of the decoded stream against
  the game's ground truth at display size, sampled on a game-time grid with a missing
  frame scored as the older one still on screen, over the whole window and per
  segment of the scene schedule; and how long frames took from render to the viewer
  (server/bench/adaptive/picture.py). The stream is kept compressed during the case
  and decoded and scored after serve has stopped, so scoring takes no CPU from the
  sessions measured.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import functools
import itertools
import os
import re
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from server.bench.adaptive.picture import (
    DecodeCounts,
    GroundTruth,
    RecordedStream,
    StreamRecorder,
    decode_times_us,
    decoded_frames,
    game_time_grid,
    percentile,
    render_to_receive_ms,
    score_stream,
)
from server.bench.serve import ROOT, _poll_sessions, watch_every_session
from server.game.render.scenes import SCHEDULE_SEGMENTS, scene_segments
from server.ops.process import stop_child
from server.ops.report import BenchReport
from server.quic.moq_link import MoqLink
from server.session.quality.figures import load_figures
from server.session.quality.model import QualityModel, Setting

HOLD = 0.9
QUALITY_LINE = re.compile(
    r"\[(?P<broadcast>[^\]]+)\] server\.session\.quality\.adapter: "
    r"quality (?P<dir>up|down|back|goal):"
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", type=Path, required=True, help="report path")
    parser.add_argument("--sessions", default="1,2,4", help="session counts, comma-separated")
    parser.add_argument(
        "--fixed",
        default="fitted",
        help="fixed settings to compare, comma-separated METHOD@SCALE (display / render);"
        " 'fitted' is the machine-fitted default start (bilinear at the fitted render size)",
    )
    parser.add_argument("--display-size", default="1280x720")
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument(
        "--duration", type=float, default=60.0,
        help="seconds measured per case (default: one whole cycle of the schedule scene)",
    )  # fmt: skip
    parser.add_argument("--warmup", type=float, default=8.0, help="seconds after all are up")
    parser.add_argument(
        "--hog", action=argparse.BooleanOptionalAction, default=True,
        help="a busy loop takes one core for the middle third of each case (default: on)",
    )  # fmt: skip
    parser.add_argument("--port", type=int, default=4470, help="relay port (HTTP side: +1)")
    parser.add_argument(
        "--scene",
        default="schedule",
        help="the game's scene (default: schedule, 12 s each of still, slow pan, fast yaw"
        " with cuts, moving objects and thin detail)",
    )
    parser.add_argument(
        "--picture-every",
        type=float,
        default=0.5,
        help="seconds of game time between scored samples of the decoded picture"
        " (0: do not score the picture)",
    )
    parser.add_argument(
        "--truth-supersample", type=int, default=3,
        help="subsamples per axis of the ground truth (as upcast eval's)",
    )  # fmt: skip
    parser.add_argument(
        "--admission",
        choices=("admit", "refuse", "queue"),
        default="admit",
        help="upcast serve's admission (admit: every session runs, the default here)",
    )


@dataclass(frozen=True)
class Case:
    sessions: int
    mode: str  # "auto" or "fixed"
    setting: Setting | None  # the fixed one; None: the fitted start

    @property
    def name(self) -> str:
        what = "auto" if self.mode == "auto" else (
            "fixed fitted" if self.setting is None else f"fixed {self.setting.describe()}"
        )  # fmt: skip
        return f"{self.sessions} sessions, {what}"


def _size_for(display: str, scale: float) -> str:
    w, h = (int(v) for v in display.lower().split("x"))
    return f"{max(2, round(w / scale / 2) * 2)}x{max(2, round(h / scale / 2) * 2)}"


def _parse_fixed(text: str) -> list[Setting | None]:
    out: list[Setting | None] = []
    for item in (t.strip() for t in text.split(",") if t.strip()):
        if item == "fitted":
            out.append(None)
            continue
        method, _, scale = item.partition("@")
        out.append(Setting(method, float(scale)))
    return out


def _bins(arrivals: list[float], start: float, end: float) -> list[float]:
    n = max(1, int(end - start))
    counts = [0] * n
    for t in arrivals:
        if t < start:
            continue  # int() rounds toward zero: -0.5 s would land in the first bin
        i = int(t - start)
        if i < n:
            counts[i] += 1
    return [float(c) for c in counts]


def _back_at(bins: list[float], start_bin: int, target: float) -> float | None:
    """Seconds from ``start_bin`` until two bins in a row hold 90 % of the target."""
    for i in range(start_bin, len(bins) - 1):
        if bins[i] >= HOLD * target and bins[i + 1] >= HOLD * target:
            return float(i - start_bin)
    return None


def _stepped_up_after(
    timeline: list[tuple[float, Setting]], at: float, model: QualityModel
) -> float | None:
    """Seconds from ``at`` until a poll shows a setting above the one running at ``at``
    (a higher frame rate, or the same rate and a better expected picture)."""
    before = [s for t, s in timeline if t <= at]
    if not before:
        return None
    base = before[-1]
    base_q = model.expected_psnr(base, "unknown")
    for t, s in timeline:
        if t <= at:
            continue
        if s.rate > base.rate + 1e-6 or (
            abs(s.rate - base.rate) < 1e-6 and model.expected_psnr(s, "unknown") > base_q + 0.05
        ):
            return round(t - at, 1)
    return None


def _mean(values: list[float]) -> float:
    return sum(values) / len(values) if values else 0.0


async def _run_case(
    case: Case, args: argparse.Namespace, report: BenchReport, truth: GroundTruth
) -> None:
    cmd = [sys.executable, "-m", "server.cli", "serve", "--sessions", str(case.sessions)]
    cmd += ["--display-size", args.display_size, "--fps", f"{args.fps:g}"]
    cmd += ["--port", str(args.port), "--quality", case.mode, "--scene", args.scene]
    # Every session runs, even where admission would refuse one: the bench measures how
    # N sessions share the host (admission is measured by its own test).
    cmd += ["--admission", args.admission]
    if case.setting is not None:
        cmd += ["--upscaler", case.setting.method]
        cmd += ["--render-size", _size_for(args.display_size, case.setting.scale)]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    recorder = StreamRecorder()
    with tempfile.NamedTemporaryFile(prefix="upcast-bench-adaptive-", suffix=".log") as log_file:
        window, rows = await _run_serve(cmd, env, log_file, case, args, report, recorder)
    if args.picture_every > 0:
        # After serve has stopped: decoding and the ground truth take the idle host.
        for broadcast, row in rows.items():
            stream = recorder.streams.get(broadcast)
            if stream is not None:
                row.update(_viewed_picture(stream, window, truth, args))


async def _run_serve(
    cmd: list[str],
    env: dict[str, str],
    log_file: IO[bytes],
    case: Case,
    args: argparse.Namespace,
    report: BenchReport,
    recorder: StreamRecorder,
) -> tuple[tuple[float, float], dict[str, dict[str, object]]]:
    """Runs one case; the measured window (monotonic) and each session's report row."""
    http_port = args.port + 1
    rows: dict[str, dict[str, object]] = {}
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stderr=log_file, stdout=subprocess.DEVNULL)
    link: MoqLink | None = None
    hog: subprocess.Popen[bytes] | None = None
    timeline: dict[str, list[tuple[float, Setting]]] = {}
    published: dict[str, list[tuple[float, int]]] = {}  # (counted at, frames) per poll
    try:
        broadcasts, counter, link = await watch_every_session(proc, args.port, recorder)
        await asyncio.sleep(args.warmup)
        start = time.monotonic()
        third = args.duration / 3
        hog_at = (start + third, start + 2 * third) if args.hog else None
        while (now := time.monotonic()) < start + args.duration:
            if hog_at is not None and hog is None and now >= hog_at[0]:
                hog = subprocess.Popen([sys.executable, "-c", "while True: pass"])
            if hog is not None and hog_at is not None and now >= hog_at[1] and hog.poll() is None:
                stop_child(hog, 1)
            with contextlib.suppress(OSError, ValueError):
                for r in await _poll_sessions(http_port):
                    published.setdefault(r["broadcast"], []).append(
                        (float(r["frames_at"] or 0.0), int(r["frames"]))
                    )
                    frame_rate = r.get("frame_rate")
                    setting = Setting(
                        str(r["upscaler"]),
                        float(r["scale"]),
                        bool(r.get("frame_generation")),
                        _encode_scale(args.display_size, r.get("encoded")),
                        float(frame_rate) / args.fps
                        if isinstance(frame_rate, int | float) and frame_rate > 0
                        else 1.0,
                    )
                    timeline.setdefault(r["broadcast"], []).append((now - start, setting))
            await asyncio.sleep(1.0)
        end = start + args.duration
        recorder.stop()
        log_file.flush()
        changes = _changes(Path(log_file.name).read_text(errors="replace"))
        model = QualityModel(load_figures(), _pixels(args.display_size))
        for b in broadcasts:
            # From the second second: the first holds the viewer's catch-up after the
            # warm-up (a burst above the target that would flatter every case).
            bins = _bins(counter.arrivals[b], start, end)[1:]
            case_row = _add_session(
                report, case, b, bins, timeline.get(b, []), changes.get(b, []), model, args
            )
            rows[b] = case_row
            counts = published.get(b, [])
            if len(counts) >= 2 and counts[-1][0] > counts[0][0]:
                rate = (counts[-1][1] - counts[0][1]) / (counts[-1][0] - counts[0][0])
                case_row["session_published_fps"] = round(rate, 2)
                # Between polls (about a second apart): whether a gap at the viewer is
                # the session's (nothing published) or the delivery's.
                case_row["per_poll_published_fps"] = [
                    round((b1 - a1) / (b0 - a0), 1)
                    for (a0, a1), (b0, b1) in itertools.pairwise(counts)
                    if b0 > a0
                ]
    finally:
        if hog is not None and hog.poll() is None:
            stop_child(hog, 1)
        if link is not None and not link.closed:
            link.wt.close(0, "bench over")
        stop_child(proc, 60)
    # From the second second, as the frame-rate bins.
    return (start + 1.0, end), rows


def _viewed_picture(
    stream: RecordedStream,
    window: tuple[float, float],
    truth: GroundTruth,
    args: argparse.Namespace,
) -> dict[str, object]:
    """The decoded picture's PSNR and SSIM against the ground truth over the game time
    the measured window showed (see server/bench/adaptive/picture.py)."""
    shown = [
        stream.frames[pts][0]
        for (at, _, _), pts in zip(stream.fragments, decode_times_us(stream), strict=True)
        if at >= window[0] and pts is not None and pts in stream.frames
    ]
    latency = render_to_receive_ms(stream)
    out: dict[str, object] = {
        "render_to_receive_ms_p50": percentile(latency, 0.5),
        "render_to_receive_ms_p95": percentile(latency, 0.95),
    }
    if not shown:
        return {**out, "viewed_psnr_db": None, "viewed_ssim": None, "viewed_samples": 0}
    # The game time the window's frames showed: game time is not wall time (a game that
    # cannot keep its rate renders every tick late, and its world runs slow), so the
    # span is the received frames', and a sample between two of them is scored against
    # the older one still on screen.
    first, last = shown[0], max(shown)
    out["game_seconds_per_second"] = round((last - first) / 1e6 / (window[1] - window[0]), 3)
    grid = game_time_grid(first, last, args.picture_every, 0.5 / args.fps)
    counts = DecodeCounts()
    score = score_stream(decoded_frames(stream, counts), grid, truth)
    out.update(
        viewed_psnr_db=score.mean_psnr(),
        viewed_ssim=score.mean_ssim(),
        viewed_samples=len(score.psnr_db),
        shown_age_ms_p50=percentile(score.shown_age_ms, 0.5),
        shown_age_ms_p95=percentile(score.shown_age_ms, 0.95),
        decoded_frames=counts.decoded,
        undecodable=counts.undecodable,
        decoded_without_game_time=counts.without_game_time,
    )
    segment_of = scene_segments(args.scene)
    if segment_of is not None:
        segment: Callable[[float], str] = segment_of
        out["viewed_psnr_db_by_segment"] = {
            name: score.mean_psnr(functools.partial(_in_segment, segment, name))
            for name in SCHEDULE_SEGMENTS
        }
    return out


def _in_segment(segment: Callable[[float], str], name: str, game_us: int) -> bool:
    return segment(game_us / 1e6) == name


def _rate_at(timeline: list[tuple[float, Setting]], t: float) -> float:
    """The frame-rate fraction of the last poll at or before ``t`` (1 before any)."""
    rate = 1.0
    for at, setting in timeline:
        if at > t:
            break
        rate = setting.rate
    return rate


def _encode_scale(display: str, encoded: object) -> float:
    """display / encoded width, on the encoded-size ladder (1 when not reported)."""
    if not isinstance(encoded, str) or "x" not in encoded:
        return 1.0
    try:
        width = int(encoded.lower().split("x")[0])
        scale = int(display.lower().split("x")[0]) / width
    except (ValueError, ZeroDivisionError):
        return 1.0
    return min(_encode_ladder(), key=lambda e: abs(e - scale))


@functools.cache
def _encode_ladder() -> tuple[float, ...]:
    return tuple(QualityModel(load_figures(), 1).encode_scales())


def _pixels(size: str) -> int:
    w, h = (int(v) for v in size.lower().split("x"))
    return w * h


def _changes(log_text: str) -> dict[str, list[str]]:
    """Each session's quality log lines (one per change, with its reason)."""
    out: dict[str, list[str]] = {}
    for line in log_text.splitlines():
        m = QUALITY_LINE.search(line)
        if m:
            out.setdefault(m["broadcast"], []).append(line[m.start("dir") - len("quality ") :])
    return out


def _add_session(
    report: BenchReport,
    case: Case,
    broadcast: str,
    bins: list[float],
    timeline: list[tuple[float, Setting]],
    changes: list[str],
    model: QualityModel,
    args: argparse.Namespace,
) -> dict[str, object]:
    target = args.fps
    n = len(bins)
    third = n // 3
    expected = [
        model.expected_psnr(s, "unknown") for _, s in timeline if s.method in model.figures.methods
    ]
    seconds: dict[str, int] = {}
    for _, s in timeline:
        label = s.describe(target)
        seconds[label] = seconds.get(label, 0) + 1
    # The rate the session ran at in each bin (the last poll before it): a session that
    # lowered its frame rate is held to that rate by this figure, to the target by the other.
    chosen = [_rate_at(timeline, i + 1.5) * target for i in range(n)]
    return report.add_case(
        f"{case.name}: {broadcast}",
        sessions=case.sessions,
        mode=case.mode,
        fixed=None if case.setting is None else case.setting.describe(),
        target_fps=target,
        viewer_fps_mean=round(_mean(bins), 2),
        viewer_fps_min=min(bins) if bins else 0.0,
        share_of_seconds_at_90pct=round(sum(b >= HOLD * target for b in bins) / max(1, n), 3),
        frame_rate_mean=round(_mean(chosen), 2),
        share_of_seconds_at_90pct_of_its_rate=round(
            sum(b >= HOLD * c for b, c in zip(bins, chosen, strict=True)) / max(1, n), 3
        ),
        viewer_fps_before_hog=round(_mean(bins[:third]), 2),
        viewer_fps_during_hog=round(_mean(bins[third : 2 * third]), 2),
        viewer_fps_after_hog=round(_mean(bins[2 * third :]), 2),
        seconds_to_90pct_after_hog_start=_back_at(bins, third, target) if args.hog else None,
        # The timeline counts from the window's start; the bins from its second second.
        seconds_to_step_up_after_hog_end=(
            _stepped_up_after(timeline, 2 * args.duration / 3, model)
            if args.hog and case.mode == "auto"
            else None
        ),
        switches=len(changes),
        changes=changes,
        settings_seconds=seconds,
        expected_psnr_db_table=round(_mean(expected), 2) if expected else None,
        per_second_fps=bins,
    )


def run(args: argparse.Namespace) -> int:
    try:
        counts = [int(v) for v in args.sessions.split(",") if v.strip()]
        fixed = _parse_fixed(args.fixed)
    except ValueError as exc:
        print(f"upcast bench adaptive: {exc}", file=sys.stderr)
        return 2
    cases = [Case(n, "auto", None) for n in counts]
    cases += [Case(n, "fixed", s) for n in counts for s in fixed]
    report = BenchReport(
        "adaptive",
        {
            "sessions": counts,
            "fixed": [None if s is None else s.describe() for s in fixed],
            "display_size": args.display_size,
            "fps": args.fps,
            "duration_s": args.duration,
            "warmup_s": args.warmup,
            "hog": "one busy-loop process for the middle third" if args.hog else None,
            "scene": args.scene,
            "picture_every_s": args.picture_every,
            "truth_supersample": args.truth_supersample,
            "load_average_1m_at_start": round(os.getloadavg()[0], 2),
        },
    )
    report.notes.append(
        "viewer fps: frames one moq-lite viewer on the relay received per session per "
        "second. expected_psnr_db_table: the speed-against-error table's PSNR (against the "
        "game's ground truth, mean over its scenes) for the settings the session ran, "
        "weighted by time; a model figure, not a measurement of the decoded stream."
    )
    report.notes.append(
        "viewed_psnr_db / viewed_ssim: the decoded stream as the bench's viewer received "
        "it, against the game's ground truth at display size (supersampled) at game-time "
        "instants every picture_every_s; at each instant the frame on screen is the last "
        "received whose game time is not after it, so a lost, skipped or never-rendered "
        "frame is scored as the older picture still shown (shown_age_ms: how old), over the "
        "game time the window's frames span. A game that cannot keep its rate renders every "
        "tick late and its world runs slow: game_seconds_per_second says how slow. "
        "render_to_receive_ms: wall time a frame reached the viewer minus when its render "
        "started (one machine, one clock)."
    )
    width, height = (int(v) for v in args.display_size.lower().split("x"))
    truth = GroundTruth(args.scene, (width, height), ss=args.truth_supersample)
    started = time.monotonic()
    for i, case in enumerate(cases, 1):
        print(
            f"[{i}/{len(cases)}] {case.name} ({time.monotonic() - started:.0f} s so far)",
            flush=True,
        )
        try:
            asyncio.run(_run_case(case, args, report, truth))
        except (RuntimeError, TimeoutError, OSError) as exc:
            print(f"upcast bench adaptive: {case.name}: {exc}", file=sys.stderr)
            return 1
        for c in report.cases[-case.sessions :]:
            print(
                f"  {c['name']}: {c['viewer_fps_mean']:.1f} fps (min {c['viewer_fps_min']:.0f}, "
                f"{c['share_of_seconds_at_90pct']:.0%} of seconds at 90 %; ran at "
                f"{c['frame_rate_mean']:.1f} fps, {c['share_of_seconds_at_90pct_of_its_rate']:.0%} "
                f"of seconds at 90 % of that; published "
                f"{c.get('session_published_fps', '-')}), expected "
                f"{c['expected_psnr_db_table']} dB, viewed {c.get('viewed_psnr_db')} dB "
                f"SSIM {c.get('viewed_ssim')}, {c['switches']} switches"
            )
    report.config["run_s"] = round(time.monotonic() - started, 1)
    report.config["ground_truth_render_s"] = round(truth.render_s, 1)
    report.write(args.json)
    print(f"wrote {args.json} in {time.monotonic() - started:.0f} s")
    return 0
