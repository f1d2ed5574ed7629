"""Reading the player's ``window.upcast.stats()`` from a benchmark's headless page.

The benchmarks run the streaming session in their own process (``LiveStack``), so
whatever their main thread does in Python holds the GIL against the session's
encoding thread, and shows in the encode stage they measure. Playwright turns an
``evaluate`` result into Python objects node by node, in Python: ``stats()`` carries
up to 600 samples for each of 18 stages, about 11,000 numbers, and converting them
every half second (``upcast bench network``) held the GIL long enough to lengthen the
encode stage's p95 (lan, 20 s runs: 26.4 ms, 20.4 with the read below, 17.4 with the
page read every 2 s and no snapshots). As one JSON string the page serialises it and
Python's ``json`` parses it in C.
"""

from __future__ import annotations

import json
from typing import Any

_STATS = "() => JSON.stringify(window.upcast.stats())"
_LATENCY = "() => JSON.stringify(window.upcast.stats().latency)"


def read_stats(page: Any) -> dict[str, Any]:
    """The page's ``window.upcast.stats()``."""
    return _object(page.evaluate(_STATS))


def read_latency(page: Any) -> dict[str, Any]:
    """The page's ``window.upcast.stats().latency``: per stage, its recent samples."""
    return _object(page.evaluate(_LATENCY))


def _object(text: object) -> dict[str, Any]:
    value = json.loads(text) if isinstance(text, str) else None
    if not isinstance(value, dict):
        raise RuntimeError(f"the page's stats are not an object: {str(text)[:80]!r}")
    return value
