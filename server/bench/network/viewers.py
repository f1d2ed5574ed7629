"""Load-test viewers next to the page on the emulated link, for ``upcast bench network``.

They run in a worker process of their own (server/loadtest/workers.py), so their
packets do not compete with the session and the emulator for this process's GIL,
and they count what reaches them as the browser does (frames lost, groups skipped,
freezes) and send feedback as spectators. The benchmark's thread drives Playwright's
sync API, so the pool's coroutines run on a helper thread with an event loop of its own.
"""

from __future__ import annotations

import asyncio
import threading
from typing import Any

from server.loadtest.plan import RunPlan
from server.loadtest.viewer import ViewerConfig, WorkerResult
from server.loadtest.viewer_stats import ViewerStats
from server.loadtest.workers import WorkerPool

RESULT_SLACK_S = 20.0


class SpectatorViewers:
    def __init__(self, config: ViewerConfig, count: int) -> None:
        self.count = count
        self._pool = WorkerPool(config, count, 1)
        self._ready: threading.Thread | None = None
        self._collect: threading.Thread | None = None
        self._error: BaseException | None = None
        self._results: list[WorkerResult | None] = []

    def start(self) -> None:
        """Spawn the worker (a second or two to import); ``begin`` gives it the plan."""
        self._pool.start()
        self._ready = self._thread(self._pool.ready())

    def begin(self, plan: RunPlan) -> None:
        assert self._ready is not None
        self._ready.join()
        if self._error is not None:
            raise RuntimeError(f"load-test viewers did not start: {self._error}")
        self._pool.send_plan(plan)
        deadline = plan.stop + RESULT_SLACK_S
        self._collect = self._thread(self._gather(deadline))

    async def _gather(self, deadline: float) -> None:
        self._results = await self._pool.results(deadline, lambda _snapshot: None)

    def finish(self) -> list[ViewerStats]:
        """The viewers' stats once they closed (empty when the worker gave none)."""
        try:
            if self._collect is not None:
                self._collect.join()
        finally:
            self._pool.stop()
        return [s for r in self._results if r is not None for s in r.stats]

    def _thread(self, coro: Any) -> threading.Thread:
        def run() -> None:
            try:
                asyncio.run(coro)
            except BaseException as exc:  # reported by begin()
                self._error = exc

        thread = threading.Thread(target=run, name="bench-viewers", daemon=True)
        thread.start()
        return thread


def viewers_summary(stats: list[ViewerStats]) -> dict[str, Any]:
    """Per viewer (fps, lost, delivery counters) and the worst of them."""
    per = [s.summary() for s in stats]
    connected = [s for s in stats if s.connected and s.error is None]
    return {
        "count": len(stats),
        "connected": len(connected),
        "min_fps": round(min((s.fps() for s in connected), default=0.0), 2),
        "max_lost": max((s.delivery_window.lost for s in connected), default=0),
        "max_freezes": max((s.delivery_window.freezes for s in connected), default=0),
        "viewers": per,
    }
