"""A log of refused CONNECT requests that a flood of them cannot fill the disk with.

At most `max_lines_per_s` lines per second; the rest are counted and summed up in
one "suppressed K refusals" line once the second is over.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable

log = logging.getLogger("server.quic.refusals")


class RefusalLog:
    def __init__(
        self,
        max_lines_per_s: int = 10,
        *,
        clock: Callable[[], float] = time.monotonic,
        logger: logging.Logger = log,
        what: str = "WebTransport session",
    ) -> None:
        self.what = what
        self.max_lines_per_s = max_lines_per_s
        self._clock = clock
        self._log = logger
        self._window_start = float("-inf")
        self._lines = 0
        self.suppressed = 0
        self.total = 0
        self._summary: asyncio.TimerHandle | None = None

    def refused(self, remote: str, status: int, reason: str) -> None:
        self.total += 1
        now = self._clock()
        if now - self._window_start >= 1.0:
            self.flush()
            self._window_start = now
            self._lines = 0
        if self._lines < self.max_lines_per_s:
            self._lines += 1
            self._log.warning("refused %s from %s: %d %s", self.what, remote, status, reason)
            return
        self.suppressed += 1
        if self._summary is None:
            try:
                loop = asyncio.get_running_loop()
            except RuntimeError:
                return  # no loop (unit tests): the next refusal or flush() reports it
            self._summary = loop.call_later(1.0, self.flush)

    def flush(self) -> None:
        """Write the "suppressed" line now, if any refusal went unlogged."""
        if self._summary is not None:
            self._summary.cancel()
            self._summary = None
        if self.suppressed:
            self._log.warning(
                "refused %d more %s attempts (log lines suppressed)", self.suppressed, self.what
            )
            self.suppressed = 0
