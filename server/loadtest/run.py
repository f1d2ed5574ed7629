"""One load-test run: reach the relay, ramp the viewers, measure one window, collect.

The coordinator fetches the relay's certificate hash once (N viewers pin it;
N fetches would be N needless TCP connections during the ramp), waits for the
broadcast to exist, then runs the viewers in this process or in worker
processes along one RunPlan. The relay's CPU is sampled over HTTP at the
window's start and end, so it covers exactly the measured interval.
"""

from __future__ import annotations

import asyncio
import os
import resource
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TextIO

from server.ops.redact import redact_url
from server.quic.http_fetch import fetch_cert_hash

from .plan import LoadConfig, RelayAddress, RunPlan, make_plan, parse_relay_url
from .progress import ProgressBoard
from .relay_probe import CpuSample, cpu_percent, relay_broadcasts, sample_relay_cpu
from .viewer import Snapshot, ViewerConfig, WorkerResult, run_viewers
from .viewer_stats import ViewerStats
from .workers import WorkerPool

START_DELAY_S = 0.2  # plan start after setup: the loop is idle when the first viewer is due
RESULT_SLACK_S = 15.0  # workers closing and pickling their results


class LoadTestError(Exception):
    """The run could not start or collect its results (the message is for the user)."""


@dataclass
class LoadResult:
    config: LoadConfig
    plan: RunPlan
    stats: list[ViewerStats]
    processes: int
    worker_cpu_percent: list[float | None]
    loadtest_cpu_percent: float | None
    relay_cpu_first: CpuSample | None
    relay_cpu_last: CpuSample | None
    load_average_start: tuple[float, float, float]
    load_average_end: tuple[float, float, float]
    notes: list[str] = field(default_factory=list)

    @property
    def relay_cpu_percent(self) -> float | None:
        return cpu_percent(self.relay_cpu_first, self.relay_cpu_last)

    @property
    def relay_cpu_error(self) -> str | None:
        for sample in (self.relay_cpu_first, self.relay_cpu_last):
            if sample is not None and sample.error is not None:
                return sample.error
        return None if self.relay_cpu_percent is not None else "not sampled"


async def _cert_hash(relay: RelayAddress, config: LoadConfig) -> str | None:
    if config.cert_hash_hex is not None or relay.scheme != "http":
        return config.cert_hash_hex
    try:
        return await fetch_cert_hash(
            relay.host, relay.port, timeout=min(config.connect_timeout_s, 5.0)
        )
    except (ConnectionError, OSError, TimeoutError) as exc:
        raise LoadTestError(
            f"relay {redact_url(config.relay_url)} unreachable: {exc or type(exc).__name__}"
        ) from None


async def _wait_broadcast(relay: RelayAddress, config: LoadConfig) -> str | None:
    """Wait for the broadcast on the relay's /stats; a note when /stats cannot tell."""
    want = config.broadcast.strip("/")
    deadline = time.monotonic() + config.wait_broadcast_s
    while True:
        found = await relay_broadcasts(relay)
        if found is None:
            return "relay has no /stats: did not check that the broadcast exists"
        if want in (b.strip("/") for b in found):
            return None
        if time.monotonic() > deadline:
            raise LoadTestError(
                f"no broadcast {want!r} on the relay after {config.wait_broadcast_s:g}s"
                f" (it has {found or 'none'}); start a publisher (upcast up, or"
                " --synthetic-publisher)"
            )
        await asyncio.sleep(0.25)


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


async def _sample_window(
    relay: RelayAddress, plan: RunPlan
) -> tuple[CpuSample, CpuSample, float, float]:
    """Relay CPU samples at the window's edges, and this process's CPU and wall between."""
    await asyncio.sleep(max(0.0, plan.window_start - time.monotonic()))
    first = await sample_relay_cpu(relay)
    cpu0, wall0 = _cpu_seconds(), time.monotonic()
    await asyncio.sleep(max(0.0, plan.window_end - time.monotonic()))
    last = await sample_relay_cpu(relay)
    return first, last, _cpu_seconds() - cpu0, time.monotonic() - wall0


async def run_load(
    config: LoadConfig,
    *,
    progress: bool = True,
    label: str = "",
    stream: TextIO | None = None,
) -> LoadResult:
    problem = config.problem()
    if problem is not None:
        raise ValueError(problem)
    relay = parse_relay_url(config.relay_url)
    cert = await _cert_hash(relay, config)
    notes: list[str] = []
    note = await _wait_broadcast(relay, config)
    if note is not None:
        notes.append(note)
    viewer_config = ViewerConfig(
        config.relay_url,
        config.broadcast,
        cert,
        config.connect_timeout_s,
        config.token,
        feedback=config.feedback,
        player=config.player,
        rendition=config.rendition,
    )
    board: ProgressBoard | None = None

    def sink(snap: Snapshot) -> None:
        if board is not None:
            board.update(snap)

    pool: WorkerPool | None = None
    load_start = os.getloadavg()
    try:
        if config.processes == 1:
            plan = make_plan(config, time.monotonic() + START_DELAY_S)
            work: asyncio.Task[list[WorkerResult | None]] = asyncio.create_task(
                _single(viewer_config, plan, config.viewers, sink)
            )
        else:
            pool = WorkerPool(viewer_config, config.viewers, config.processes)
            pool.start()
            try:
                await pool.ready()
            except RuntimeError as exc:
                raise LoadTestError(str(exc)) from None
            plan = make_plan(config, time.monotonic() + START_DELAY_S)
            pool.send_plan(plan)
            deadline = plan.stop + config.connect_timeout_s + RESULT_SLACK_S
            work = asyncio.create_task(pool.results(deadline, sink))
        if progress:
            board = ProgressBoard(plan, config.viewers, label=label, stream=stream)
        sampling = asyncio.create_task(_sample_window(relay, plan))
        while not work.done():
            if board is not None:
                board.tick()
            await asyncio.wait({work}, timeout=1.0)
        results = work.result()
        first, last, own_cpu_s, own_wall_s = await sampling
    finally:
        if board is not None:
            board.finish()
        if pool is not None:
            pool.stop()
    return _collect(config, plan, results, first, last, own_cpu_s, own_wall_s, load_start, notes)


async def _single(
    config: ViewerConfig, plan: RunPlan, viewers: int, sink: Callable[[Snapshot], None]
) -> list[WorkerResult | None]:
    return [await run_viewers(config, plan, range(viewers), sink)]


def _collect(
    config: LoadConfig,
    plan: RunPlan,
    results: list[WorkerResult | None],
    first: CpuSample,
    last: CpuSample,
    own_cpu_s: float,
    own_wall_s: float,
    load_start: tuple[float, float, float],
    notes: list[str],
) -> LoadResult:
    stats: list[ViewerStats] = []
    worker_cpu: list[float | None] = []
    total_cpu_s = own_cpu_s if config.processes > 1 else 0.0  # the parent's share
    for k, result in enumerate(results):
        if result is None:
            notes.append(f"worker process {k} gave no result (died or too late)")
            worker_cpu.append(None)
            continue
        stats.extend(result.stats)
        share = None
        if result.cpu_s is not None and result.window_wall_s > 0:
            share = 100.0 * result.cpu_s / result.window_wall_s
            total_cpu_s += result.cpu_s
        worker_cpu.append(share)
    seen = {s.viewer for s in stats}
    for missing in sorted(set(range(config.viewers)) - seen):
        stats.append(ViewerStats(missing, window=plan.window, error="worker process lost"))
    stats.sort(key=lambda s: s.viewer)
    loadtest_cpu = 100.0 * total_cpu_s / own_wall_s if own_wall_s > 0 else None
    busiest = max((c for c in worker_cpu if c is not None), default=0.0)
    if busiest >= 85.0:
        notes.append(
            f"a load-test process used {busiest:.0f}% of a core: the viewers may be the"
            " bottleneck, not the relay (try --processes)"
        )
    return LoadResult(
        config=config,
        plan=plan,
        stats=stats,
        processes=config.processes,
        worker_cpu_percent=worker_cpu,
        loadtest_cpu_percent=loadtest_cpu,
        relay_cpu_first=first,
        relay_cpu_last=last,
        load_average_start=load_start,
        load_average_end=os.getloadavg(),
        notes=notes,
    )
