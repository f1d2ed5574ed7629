"""Warning logs that a flood (of refused CONNECTs, of protocol-error closes) cannot
fill the disk with.

At most `max_lines_per_s` lines per second; the rest are counted and summed up in
one "suppressed K" line once the second is over. `RateLimitedLog` is the general
form; `RefusalLog` words its lines for refused requests.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable

log = logging.getLogger("server.quic.refusals")


class RateLimitedLog:
    """``warning(msg, *args)`` as a Logger has it, but at most ``max_lines_per_s``
    lines a second; ``summary % count`` reports the lines left out."""

    def __init__(
        self,
        max_lines_per_s: int = 10,
        *,
        clock: Callable[[], float] = time.monotonic,
        logger: logging.Logger = log,
        summary: str = "%d more warnings (log lines suppressed)",
    ) -> None:
        self.summary = summary
        self.max_lines_per_s = max_lines_per_s
        self._clock = clock
        self._log = logger
        self._window_start = float("-inf")
        self._lines = 0
        self.suppressed = 0
        self.total = 0
        self._summary: asyncio.TimerHandle | None = None
        self._summary_loop: asyncio.AbstractEventLoop | None = None

    def warning(self, msg: str, *args: object) -> bool:
        """Log the line unless this second's quota is spent; True if it was logged."""
        self.total += 1
        now = self._clock()
        if now - self._window_start >= 1.0:
            self.flush()
            self._window_start = now
            self._lines = 0
        if self._lines < self.max_lines_per_s:
            self._lines += 1
            self._log.warning(msg, *args)
            return True
        self.suppressed += 1
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:
            return False  # no loop (unit tests): the next line or flush() reports it
        # A process-wide log outlives event loops (asyncio.run per test): a timer on
        # a loop that has ended would never fire, so the summary is rescheduled.
        if self._summary is None or self._summary_loop is not loop:
            self._summary = loop.call_later(1.0, self.flush)
            self._summary_loop = loop
        return False

    def flush(self) -> None:
        """Write the "suppressed" line now, if any line went unlogged."""
        if self._summary is not None:
            self._summary.cancel()
            self._summary = None
        if self.suppressed:
            self._log.warning(self.summary, self.suppressed)
            self.suppressed = 0


class RefusalLog(RateLimitedLog):
    """Refused CONNECTs (or moq requests), one server-wide limit."""

    def __init__(
        self,
        max_lines_per_s: int = 10,
        *,
        clock: Callable[[], float] = time.monotonic,
        logger: logging.Logger = log,
        what: str = "WebTransport session",
    ) -> None:
        # `what` is code-given, never request data: it may go into the format string.
        summary = "refused %d more " + what.replace("%", "%%") + " attempts (log lines suppressed)"
        super().__init__(max_lines_per_s, clock=clock, logger=logger, summary=summary)
        self.what = what

    def refused(self, remote: str, status: int, reason: str) -> None:
        self.warning("refused %s from %s: %d %s", self.what, remote, status, reason)
