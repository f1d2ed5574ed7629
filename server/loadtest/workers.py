"""Spread viewers over worker processes (``--processes K``).

One Python process is one core: with many viewers, decrypting QUIC in the
load-test process can be the bottleneck instead of the relay. Each worker
process runs its own event loop (uvloop) with viewers ``k, k+K, k+2K, ...``
(interleaved, so the ramp stays spread over all processes), follows the same
RunPlan, sends Snapshots over a queue and its WorkerResult over its pipe.

Workers are started with ``spawn``: a fork of a process that has run an event
loop (the parent fetched the certificate hash with one) is not safe.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing as mp
import queue as queue_module
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import Any

from server.ops.event_loop import install_uvloop
from server.ops.logging_setup import install_redaction

from .plan import RunPlan
from .viewer import Snapshot, ViewerConfig, WorkerResult, run_viewers

log = logging.getLogger(__name__)

READY_TIMEOUT_S = 60.0
POLL_S = 0.05


def _worker_main(
    worker: int, config: ViewerConfig, indices: list[int], conn: Connection, queue: Any
) -> None:
    logging.basicConfig(level=logging.WARNING)
    install_redaction()
    logging.getLogger("quic").setLevel(logging.WARNING)
    install_uvloop()
    try:
        conn.send("ready")
        if not conn.poll(READY_TIMEOUT_S):
            return
        plan: RunPlan = conn.recv()
        result = asyncio.run(run_viewers(config, plan, indices, queue.put, worker=worker))
        conn.send(result)
    except (KeyboardInterrupt, BrokenPipeError, EOFError):
        pass


class WorkerPool:
    def __init__(self, config: ViewerConfig, viewers: int, processes: int) -> None:
        self.groups = [list(range(k, viewers, processes)) for k in range(processes)]
        self._ctx = mp.get_context("spawn")
        self.queue: Any = self._ctx.Queue()
        self._config = config
        self._procs: list[BaseProcess] = []
        self._conns: list[Connection] = []

    def start(self) -> None:
        for worker, indices in enumerate(self.groups):
            parent, child = self._ctx.Pipe()
            proc = self._ctx.Process(
                target=_worker_main,
                args=(worker, self._config, indices, child, self.queue),
                name=f"loadtest-worker-{worker}",
                daemon=True,
            )
            proc.start()
            child.close()
            self._procs.append(proc)
            self._conns.append(parent)

    async def ready(self, timeout: float = READY_TIMEOUT_S) -> None:
        deadline = time.monotonic() + timeout
        waiting = set(range(len(self._conns)))
        while waiting:
            for k in list(waiting):
                if self._conns[k].poll(0):
                    if self._conns[k].recv() != "ready":
                        raise RuntimeError(f"load-test worker {k} did not start")
                    waiting.discard(k)
                elif not self._procs[k].is_alive():
                    raise RuntimeError(f"load-test worker {k} exited while starting")
            if time.monotonic() > deadline:
                raise RuntimeError(f"load-test workers not ready after {timeout:g}s")
            await asyncio.sleep(POLL_S)

    def send_plan(self, plan: RunPlan) -> None:
        for conn in self._conns:
            conn.send(plan)

    def drain(self, sink: Callable[[Snapshot], None]) -> None:
        while True:
            try:
                sink(self.queue.get_nowait())
            except queue_module.Empty:
                return

    async def results(
        self, deadline: float, sink: Callable[[Snapshot], None]
    ) -> list[WorkerResult | None]:
        """Each worker's result; None for one that died or missed ``deadline`` (monotonic)."""
        found: list[WorkerResult | None] = [None] * len(self._conns)
        pending = set(range(len(self._conns)))
        while pending and time.monotonic() < deadline:
            self.drain(sink)
            for k in list(pending):
                conn = self._conns[k]
                try:
                    if conn.poll(0):
                        found[k] = conn.recv()
                        pending.discard(k)
                    elif not self._procs[k].is_alive():
                        pending.discard(k)
                except (EOFError, OSError):
                    pending.discard(k)
            await asyncio.sleep(POLL_S)
        self.drain(sink)
        return found

    def stop(self) -> None:
        for proc in self._procs:
            proc.join(2.0)
            if proc.is_alive():
                log.warning("load-test worker %s did not exit; terminating it", proc.name)
                proc.terminate()
                proc.join(2.0)
        for conn in self._conns:
            conn.close()
        self.queue.close()
