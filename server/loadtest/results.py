"""Load-test results: the verdict, the end-of-run table and the JSON report.

A viewer *held* when it stayed connected, got at least ``min_fps`` frames per
second over the window and its p95 publish -> receive latency was at most
``max_p95_ms`` (the issue's criterion). Summary latencies pool every viewer's
samples: a percentile of percentiles would hide the worst viewer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from server.ops.report import BenchReport

from .run import LoadResult
from .viewer_stats import ViewerStats, percentiles

TABLE_ROWS = 20


def latency_ms(stats: ViewerStats) -> list[float]:
    """publish -> receive; for a publisher without a timing track, the media-clock delay."""
    return stats.publish_to_receive_ms or stats.media_delay_ms()


def held(stats: ViewerStats, min_fps: float, max_p95_ms: float) -> bool:
    samples = latency_ms(stats)
    if not stats.connected or stats.disconnected or not samples:
        return False
    p95 = float(np.percentile(samples, 95))
    return stats.fps() >= min_fps and p95 <= max_p95_ms


def verdict(result: LoadResult) -> dict[str, Any]:
    cfg = result.config
    holding = [s.viewer for s in result.stats if held(s, cfg.min_fps, cfg.max_p95_ms)]
    return {
        "criterion": f"fps >= {cfg.min_fps:g} and p95 publish->receive <= {cfg.max_p95_ms:g} ms",
        "viewers": len(result.stats),
        "viewers_held": len(holding),
        "all_held": len(holding) == len(result.stats),
        "not_held": sorted(set(range(len(result.stats))) - set(holding)),
    }


def summary(result: LoadResult) -> dict[str, Any]:
    stats = result.stats
    fps = [s.fps() for s in stats]
    publish: list[float] = []
    render_end: list[float] = []
    media: list[float] = []
    for s in stats:
        publish.extend(s.publish_to_receive_ms)
        render_end.extend(s.render_end_to_receive_ms)
        media.extend(s.media_delay_ms())
    window_s = result.plan.window_end - result.plan.window_start
    published = max((s.published for s in stats), default=0)
    pooled = percentiles(publish)
    return {
        "viewers": len(stats),
        "connected": sum(1 for s in stats if s.connected),
        "failed": sum(1 for s in stats if s.error is not None),
        "fps_min": round(min(fps, default=0.0), 2),
        "fps_median": round(float(np.median(fps)) if fps else 0.0, 2),
        "publisher_fps": round(published / window_s, 2) if window_s > 0 else None,
        "lost_total": sum(s.lost for s in stats),
        "frames_total": sum(s.frames for s in stats),
        "mbit_s_total": round(sum(s.mbit_s() for s in stats), 2),
        "publish_to_receive_ms": pooled,
        "render_end_to_receive_ms": percentiles(render_end),
        "media_delay_ms": percentiles(media),
        # connect start -> first video frame (a group's first frame: a keyframe), the
        # join time a viewer sees, connection setup included
        "first_frame_ms": percentiles(
            [s.first_frame_ms for s in stats if s.first_frame_ms is not None]
        ),
        "median_ms": pooled.get("p50"),
        "p95_ms": pooled.get("p95"),
        "relay_cpu_percent": _round(result.relay_cpu_percent),
        "relay_cpu_unavailable": result.relay_cpu_error,
        "loadtest_cpu_percent": _round(result.loadtest_cpu_percent),
        "loadtest_worker_cpu_percent": [_round(c) for c in result.worker_cpu_percent],
        "window_s": round(window_s, 2),
    }


def _round(value: float | None) -> float | None:
    return None if value is None else round(value, 1)


def config_dict(result: LoadResult) -> dict[str, Any]:
    cfg = result.config
    plan = result.plan
    return {
        "relay": cfg.relay_url,
        "broadcast": cfg.broadcast,
        "rendition": cfg.rendition,
        "viewers": cfg.viewers,
        "duration_s": cfg.duration_s,
        "ramp_per_s": cfg.ramp_per_s,
        "warmup_s": cfg.warmup_s,
        "ramp_s": round(plan.window_start - plan.start - cfg.warmup_s, 2),
        "processes": result.processes,
        "viewer_mode": (
            "one process (one event loop)"
            if result.processes == 1
            else f"{result.processes} worker processes, one event loop each"
        ),
        "min_fps": cfg.min_fps,
        "max_p95_ms": cfg.max_p95_ms,
        "load_average_start": [round(x, 2) for x in result.load_average_start],
        "load_average_end": [round(x, 2) for x in result.load_average_end],
    }


@dataclass
class LoadReport(BenchReport):
    """BenchReport plus the verdict (and, for --find-max, the steps)."""

    verdict: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        out = super().to_dict()
        out["verdict"] = self.verdict
        return out


def build_report(result: LoadResult, extra_config: dict[str, Any] | None = None) -> LoadReport:
    report = LoadReport("loadtest", {**config_dict(result), **(extra_config or {})})
    cfg = result.config
    for s in result.stats:
        data = s.summary()
        pub = data["publish_to_receive_ms"]
        report.add_case(
            f"viewer {s.viewer}",
            **data,
            median_ms=pub.get("p50"),
            p95_ms=pub.get("p95"),
            held=held(s, cfg.min_fps, cfg.max_p95_ms),
        )
    report.add_case("summary", **summary(result))
    report.verdict = verdict(result)
    report.notes.extend(result.notes)
    report.notes.append(
        "latency = wall clock when the whole video frame arrived at the viewer minus the"
        " frame's publish (or render_end) stamp from its timing record, matched by pts_us"
    )
    return report


def _ms(p: dict[str, float | int], key: str) -> str:
    value = p.get(key)
    return f"{value:7.1f}" if isinstance(value, float) and math.isfinite(value) else "      -"


def table(result: LoadResult) -> str:
    cfg = result.config
    # "dly": the media-clock delay of a publisher without a timing track (summary line).
    kind = "pub" if _latency_name(summary(result)) == "publish->receive" else "dly"
    head = (
        f"{'viewer':>8} {'fps':>6} {'frames':>7} {'lost':>5} {'Mbit/s':>7}"
        f" {kind + ' p50':>7} {kind + ' p95':>7} {kind + ' p99':>7} {'rend p95':>8}  held"
    )
    lines = [head, "-" * len(head)]
    for s in result.stats[:TABLE_ROWS]:
        pub = percentiles(latency_ms(s))
        rend = percentiles(s.render_end_to_receive_ms)
        ok = "yes" if held(s, cfg.min_fps, cfg.max_p95_ms) else f"NO {s.error or ''}".rstrip()
        lines.append(
            f"{s.viewer:>8} {s.fps():6.1f} {s.frames:7d} {s.lost:5d} {s.mbit_s():7.2f}"
            f" {_ms(pub, 'p50')} {_ms(pub, 'p95')} {_ms(pub, 'p99')} {_ms(rend, 'p95'):>8}  {ok}"
        )
    if len(result.stats) > TABLE_ROWS:
        lines.append(f"{'...':>8} ({len(result.stats) - TABLE_ROWS} more viewers in the JSON)")
    summ = summary(result)
    pub = _latency(summ)
    rend = summ["render_end_to_receive_ms"]
    lines.append("-" * len(head))
    lines.append(
        f"{'all':>8} {summ['fps_min']:6.1f} {summ['frames_total']:7d} {summ['lost_total']:5d}"
        f" {summ['mbit_s_total']:7.2f} {_ms(pub, 'p50')} {_ms(pub, 'p95')} {_ms(pub, 'p99')}"
        f" {_ms(rend, 'p95'):>8}"
    )
    lines.extend(summary_lines(result))
    return "\n".join(lines)


def summary_lines(result: LoadResult) -> list[str]:
    """The run in two lines (below the table, and per step of --find-max), plus notes."""
    summ = summary(result)
    pub = _latency(summ)
    lines: list[str] = []
    relay_cpu = (
        f"{summ['relay_cpu_percent']:.0f}% of a core"
        if summ["relay_cpu_percent"] is not None
        else f"unavailable ({summ['relay_cpu_unavailable']})"
    )
    v = verdict(result)
    workers = ", ".join(f"{c:.0f}%" if c is not None else "?" for c in result.worker_cpu_percent)
    lines.append(
        f"fps min {summ['fps_min']:.1f} / median {summ['fps_median']:.1f}"
        f" (publisher {summ['publisher_fps']}); lost {summ['lost_total']};"
        f" {_latency_name(summ)} p50/p95/p99 {_ms(pub, 'p50').strip()}/{_ms(pub, 'p95').strip()}"
        f"/{_ms(pub, 'p99').strip()} ms;"
        f" relay CPU {relay_cpu}; load-test CPU {_cpu(summ['loadtest_cpu_percent'])}"
        f" ({config_dict(result)['viewer_mode']}: {workers})"
    )
    lines.append(
        f"verdict: {v['viewers_held']}/{v['viewers']} viewers held {v['criterion']};"
        f" load average {result.load_average_start[0]:.2f} -> {result.load_average_end[0]:.2f}"
    )
    lines.extend(f"note: {n}" for n in result.notes)
    return lines


def _latency(summ: dict[str, Any]) -> dict[str, float | int]:
    pub: dict[str, float | int] = summ["publish_to_receive_ms"]
    return pub if pub.get("count") else summ["media_delay_ms"]


def _latency_name(summ: dict[str, Any]) -> str:
    if summ["publish_to_receive_ms"].get("count") or not summ["media_delay_ms"].get("count"):
        return "publish->receive"
    return "no timing track: media-clock delay over the fastest frame"


def _cpu(value: float | None) -> str:
    return "?" if value is None else f"{value:.0f}%"
