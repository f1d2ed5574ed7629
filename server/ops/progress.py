"""Progress lines of long runs (training, data rendering, benchmarks) on stderr.

One place for the elapsed/remaining arithmetic, so every long command reports
the same way and stdout stays for results.
"""

from __future__ import annotations

import sys
import time


def progress(text: str) -> None:
    """One progress line on stderr, flushed at once (the run may take minutes)."""
    print(text, file=sys.stderr, flush=True)


def elapsed_and_left(done: int, total: int, started: float) -> tuple[float, float]:
    """Seconds since ``started`` (``time.monotonic``) and the estimate of what is left
    after ``done`` of ``total`` equal steps."""
    elapsed = time.monotonic() - started
    return elapsed, elapsed / max(done, 1) * (total - done)
