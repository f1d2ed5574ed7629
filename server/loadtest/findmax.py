"""``--find-max``: the largest viewer count at which every viewer holds the criterion.

Steps up a fixed ladder with short runs; at the first failing count it bisects
between the last passing and the failing count (a ladder alone would answer
"30" when the truth is 45). It stops at the first failure of the ladder: more
viewers on the same relay do not do better, and each step costs a ramp.
"""

from __future__ import annotations

import asyncio
import dataclasses
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

from .plan import LoadConfig
from .results import LoadReport, config_dict, summary, verdict
from .run import LoadResult

LADDER = (10, 20, 30, 50, 75, 100, 150, 200, 300, 500, 750, 1000)
MAX_REFINE_STEPS = 3
PAUSE_S = 1.0  # the relay tears the previous step's sessions down


def ladder(max_viewers: int) -> list[int]:
    return [n for n in LADDER if n < max_viewers] + [max_viewers]


def _close_enough(low: int, high: int) -> bool:
    return high - low <= max(2, low // 10)


@dataclass
class FindMaxResult:
    steps: list[tuple[int, bool, LoadResult]] = field(default_factory=list)

    @property
    def largest_held(self) -> int:
        return max((n for n, ok, _ in self.steps if ok), default=0)

    @property
    def smallest_failed(self) -> int | None:
        return min((n for n, ok, _ in self.steps if not ok), default=None)


Runner = Callable[[LoadConfig, str], Awaitable[LoadResult]]


async def find_max(
    config: LoadConfig,
    step_duration_s: float,
    run: Runner,
    on_step: Callable[[int, bool, LoadResult], None] | None = None,
) -> FindMaxResult:
    """``run(config, label)`` runs one step; ``config.viewers`` is the upper bound."""
    found = FindMaxResult()

    async def step(viewers: int) -> bool:
        if found.steps:
            await asyncio.sleep(PAUSE_S)
        processes = min(config.processes, viewers)
        cfg = dataclasses.replace(
            config, viewers=viewers, duration_s=step_duration_s, processes=processes
        )
        result = await run(cfg, f"[{viewers} viewers]")
        ok = bool(verdict(result)["all_held"])
        found.steps.append((viewers, ok, result))
        if on_step is not None:
            on_step(viewers, ok, result)
        return ok

    low = 0
    high: int | None = None
    for viewers in ladder(config.viewers):
        if await step(viewers):
            low = viewers
        else:
            high = viewers
            break
    for _ in range(MAX_REFINE_STEPS):
        if high is None or _close_enough(low, high):
            break
        middle = (low + high) // 2 if low else max(1, high // 2)
        if middle in (low, high):
            break
        if await step(middle):
            low = middle
        else:
            high = middle
    return found


def step_row(viewers: int, ok: bool, result: LoadResult) -> dict[str, Any]:
    s = summary(result)
    v = verdict(result)
    return {
        "viewers": viewers,
        "all_held": ok,
        "viewers_held": v["viewers_held"],
        **{k: s[k] for k in ("fps_min", "fps_median", "publisher_fps", "lost_total")},
        "median_ms": s["median_ms"],
        "p95_ms": s["p95_ms"],
        "publish_to_receive_ms": s["publish_to_receive_ms"],
        "render_end_to_receive_ms": s["render_end_to_receive_ms"],
        "relay_cpu_percent": s["relay_cpu_percent"],
        "loadtest_cpu_percent": s["loadtest_cpu_percent"],
        "mbit_s_total": s["mbit_s_total"],
    }


def build_findmax_report(
    config: LoadConfig, step_duration_s: float, found: FindMaxResult
) -> LoadReport:
    base: dict[str, Any] = {}
    if found.steps:
        base = config_dict(found.steps[-1][2])
        # Per-step values; each step's case has its own count.
        for key in ("viewers", "ramp_s", "load_average_start", "load_average_end"):
            base.pop(key, None)
        base["load_average_start"] = [round(x, 2) for x in found.steps[0][2].load_average_start]
        base["load_average_end"] = [round(x, 2) for x in found.steps[-1][2].load_average_end]
    base.update(
        {
            "mode": "find-max",
            "max_viewers": config.viewers,
            "step_duration_s": step_duration_s,
            "ladder": ladder(config.viewers),
        }
    )
    report = LoadReport("loadtest-find-max", base)
    for viewers, ok, result in found.steps:
        report.add_case(f"{viewers} viewers", **step_row(viewers, ok, result))
    report.verdict = {
        "criterion": (
            f"every viewer fps >= {config.min_fps:g} and"
            f" p95 publish->receive <= {config.max_p95_ms:g} ms"
        ),
        "largest_viewer_count_held": found.largest_held,
        "smallest_viewer_count_failed": found.smallest_failed,
        "upper_bound_tried": config.viewers,
    }
    for _, _, result in found.steps:
        report.notes.extend(n for n in result.notes if n not in report.notes)
    return report


def findmax_table(found: FindMaxResult) -> str:
    head = (
        f"{'viewers':>8} {'held':>9} {'fps min':>7} {'fps med':>7} {'lost':>5}"
        f" {'pub p50':>7} {'pub p95':>7} {'pub p99':>7} {'relay CPU':>9} {'lt CPU':>6}"
    )
    lines = [head, "-" * len(head)]
    for viewers, _ok, result in sorted(found.steps, key=lambda s: s[0]):
        row = step_row(viewers, _ok, result)
        pub = row["publish_to_receive_ms"]
        lines.append(
            f"{viewers:>8} {row['viewers_held']:>4}/{viewers:<4} {row['fps_min']:7.1f}"
            f" {row['fps_median']:7.1f} {row['lost_total']:5d}"
            f" {_f(pub.get('p50'))} {_f(pub.get('p95'))} {_f(pub.get('p99'))}"
            f" {_pct(row['relay_cpu_percent']):>9} {_pct(row['loadtest_cpu_percent']):>6}"
        )
    largest = found.largest_held
    lines.append(f"largest viewer count with every viewer held: {largest or 'none'}")
    return "\n".join(lines)


def _f(value: object) -> str:
    return f"{value:7.1f}" if isinstance(value, float) else "      -"


def _pct(value: float | None) -> str:
    return "?" if value is None else f"{value:.0f}%"
