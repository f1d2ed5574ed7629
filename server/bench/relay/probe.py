"""A relay process's CPU and memory, read from /proc (any engine, no cooperation).

CPU is utime + stime of /proc/PID/stat, summed over all the process's threads (the
Rust relay's tokio workers included). ``CpuTrace`` samples it on a thread all along,
so a window that is known only afterwards (the load test reports its own) can be
read off by interpolation.
"""

from __future__ import annotations

import bisect
import threading
import time

from server.ops.process import cpu_seconds, rss_mb

TRACE_INTERVAL_S = 0.1


def cpu_percent_over(pid: int, seconds: float) -> float:
    """The process's CPU in % of one core over the next ``seconds`` (blocks)."""
    cpu0, t0 = cpu_seconds(pid), time.monotonic()
    time.sleep(seconds)
    return 100.0 * (cpu_seconds(pid) - cpu0) / (time.monotonic() - t0)


class CpuTrace:
    """(monotonic time, CPU seconds, RSS) of one process every ``interval_s``, on a thread."""

    def __init__(self, pid: int, interval_s: float = TRACE_INTERVAL_S) -> None:
        self.pid = pid
        self.interval_s = interval_s
        self.times: list[float] = []
        self.cpu_s: list[float] = []
        self.rss_mb: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="cpu-trace", daemon=True)

    def __enter__(self) -> CpuTrace:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        while True:
            try:
                cpu, rss = cpu_seconds(self.pid), rss_mb(self.pid)
            except (FileNotFoundError, ProcessLookupError):
                return  # the process is gone: the trace ends where it did
            self.times.append(time.monotonic())
            self.cpu_s.append(cpu)
            self.rss_mb.append(rss)
            if self._stop.wait(self.interval_s):
                return

    def at(self, t: float) -> float:
        """CPU seconds at monotonic time ``t``, interpolated between samples."""
        if len(self.times) < 2 or not self.times[0] <= t <= self.times[-1]:
            raise ValueError(f"time {t:.2f} is outside the CPU trace")
        i = max(1, bisect.bisect_left(self.times, t))
        t0, t1 = self.times[i - 1], self.times[i]
        c0, c1 = self.cpu_s[i - 1], self.cpu_s[i]
        return c0 + (c1 - c0) * (t - t0) / (t1 - t0) if t1 > t0 else c1

    def rss_at(self, t: float) -> float:
        """RSS (MB) of the last sample at or before monotonic time ``t``."""
        i = bisect.bisect_right(self.times, t)
        if i == 0:
            raise ValueError(f"time {t:.2f} is before the trace")
        return self.rss_mb[i - 1]

    def percent(self, start: float, end: float) -> float:
        """CPU in % of one core between two monotonic times."""
        return 100.0 * (self.at(end) - self.at(start)) / (end - start)
