"""What the load test asks the relay over HTTP (same port number, TCP).

``/metrics`` gives ``process_cpu_seconds_total`` (Prometheus process collector):
two samples give the relay's CPU share over the window. ``/stats`` lists the
broadcasts, so the load test can wait for the publisher instead of measuring
an empty relay. Both are optional: another relay (or an old one) may lack
them, and the report then says "unavailable" instead of failing.
"""

from __future__ import annotations

import json
import re
import time
from dataclasses import dataclass

from server.quic.http_fetch import http_get

from .plan import RelayAddress

_CPU_LINE = re.compile(
    r"^process_cpu_seconds_total(?:\{[^}]*\})?\s+([0-9.eE+-]+)\s*$", re.MULTILINE
)
PROBE_TIMEOUT_S = 3.0


@dataclass(frozen=True)
class CpuSample:
    at: float  # time.monotonic() when the answer came
    cpu_s: float | None
    error: str | None = None


def parse_cpu_seconds(text: str) -> float | None:
    match = _CPU_LINE.search(text)
    return float(match.group(1)) if match else None


async def sample_relay_cpu(relay: RelayAddress) -> CpuSample:
    try:
        status, body = await http_get(relay.host, relay.port, "/metrics", timeout=PROBE_TIMEOUT_S)
    except (OSError, TimeoutError, ConnectionError) as exc:
        return CpuSample(
            time.monotonic(), None, f"GET /metrics failed: {exc or type(exc).__name__}"
        )
    if status != 200:
        return CpuSample(time.monotonic(), None, f"GET /metrics gave status {status}")
    cpu = parse_cpu_seconds(body.decode("utf-8", "replace"))
    if cpu is None:
        return CpuSample(time.monotonic(), None, "no process_cpu_seconds_total in /metrics")
    return CpuSample(time.monotonic(), cpu)


def cpu_percent(first: CpuSample | None, last: CpuSample | None) -> float | None:
    """Share of one core (100 = one core busy) between two samples."""
    if first is None or last is None or first.cpu_s is None or last.cpu_s is None:
        return None
    wall = last.at - first.at
    return 100.0 * (last.cpu_s - first.cpu_s) / wall if wall > 0 else None


async def relay_broadcasts(relay: RelayAddress) -> list[str] | None:
    """Broadcast paths the relay knows, or None if it has no usable /stats."""
    try:
        status, body = await http_get(relay.host, relay.port, "/stats", timeout=PROBE_TIMEOUT_S)
        if status != 200:
            return None
        found = json.loads(body).get("broadcasts")
    except (OSError, TimeoutError, ConnectionError, ValueError, AttributeError):
        return None
    if not isinstance(found, list):
        return None
    return [str(b) for b in found]
