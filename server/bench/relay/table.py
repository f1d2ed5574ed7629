"""The printed table of ``bench relay``: one row per engine and viewer count, as they
finish, then the upcast/moq-rs ratio of CPU per viewer for each viewer count."""

from __future__ import annotations

from typing import Any

HEAD = (
    f"{'engine':<7} {'viewers':>7} {'CPU %':>6} {'idle %':>6} {'%/viewer':>8}"
    f" {'fps min':>7} {'fps mean':>8} {'lost':>5} {'p50 ms':>6} {'p95 ms':>6} {'RSS MB':>6}"
    f"  kept up"
)


def _num(value: Any, width: int, digits: int = 1) -> str:
    return f"{value:{width}.{digits}f}" if isinstance(value, int | float) else f"{'-':>{width}}"


def header() -> str:
    return f"{HEAD}\n{'-' * len(HEAD)}"


def row(case: dict[str, Any]) -> str:
    if case.get("error"):
        return f"{case['engine']:<7} {case['viewers']:>7}  FAILED: {case['error']}"
    return (
        f"{case['engine']:<7} {case['viewers']:>7}"
        f" {_num(case['relay_cpu_percent'], 6)} {_num(case['relay_cpu_percent_idle'], 6)}"
        f" {_num(case['cpu_per_viewer_percent'], 8, 2)}"
        f" {_num(case['fps_min'], 7)} {_num(case['fps_mean'], 8)} {case['lost_frames']:>5}"
        f" {_num(case['median_ms'], 6)} {_num(case['p95_ms'], 6)} {_num(case['relay_rss_mb'], 6)}"
        f"  {'yes' if case['fps_held'] else 'NO'}"
    )


def ratio_line(viewers: int, what: str, ratio: float | None, ours: Any, theirs: Any) -> str:
    shown = f"{ratio:.1f}x" if ratio is not None else "-"
    return (
        f"{viewers:>3} viewers: {what} upcast/moq-rs = {shown}"
        f" ({_num(ours, 0, 2).strip()} % / {_num(theirs, 0, 2).strip()} % of a core)"
    )
