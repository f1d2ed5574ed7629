"""Load-test settings and the timeline every viewer (in any process) follows.

The timeline is fixed before the first viewer connects, in ``time.monotonic()``
seconds (one system-wide clock on Linux, so worker processes share it): viewer
``i`` connects at ``start + i / ramp``, the measurement window opens ``warmup``
seconds after the last one was due and lasts ``duration``; links close a short
grace later (frames in flight at the window's end still match their timing
records). A fixed timeline needs no coordination between processes and makes
every run stop by itself.
"""

from __future__ import annotations

from dataclasses import dataclass
from urllib.parse import urlsplit

from server.ops.redact import redact_url

MAX_VIEWERS = 1000
MAX_DURATION_S = 3600.0
MAX_PROCESSES = 64
GRACE_S = 0.5


@dataclass(frozen=True)
class RelayAddress:
    scheme: str  # http (certificate hash fetched over TCP) or https (CA-verified or pinned)
    host: str
    port: int

    @property
    def authority(self) -> str:
        return f"[{self.host}]:{self.port}" if ":" in self.host else f"{self.host}:{self.port}"


def parse_relay_url(url: str) -> RelayAddress:
    """ValueError (with the expected form) unless ``url`` is http(s)://HOST:PORT/..."""
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as exc:
        raise ValueError(f"--relay {redact_url(url)!r}: {exc}") from None
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ValueError(f"--relay must look like http://localhost:4443/, got {redact_url(url)!r}")
    return RelayAddress(parts.scheme, parts.hostname, port or 443)


@dataclass(frozen=True)
class LoadConfig:
    relay_url: str
    viewers: int
    duration_s: float
    broadcast: str = "game"
    ramp_per_s: float = 20.0
    warmup_s: float = 2.0
    processes: int = 1
    connect_timeout_s: float = 10.0
    wait_broadcast_s: float = 15.0
    min_fps: float = 29.0
    max_p95_ms: float = 50.0
    cert_hash_hex: str | None = None
    token: str | None = None  # the viewers' relay token (?jwt=); None: anonymous viewers
    feedback: bool = False  # viewers publish <broadcast>/input/<id> and send feedback
    player: bool = False  # ... viewer 0 as the player
    rendition: str = "first"  # the video rendition watched (loadtest/viewer.py choose_rendition)

    def problem(self) -> str | None:
        """What is wrong with the settings, naming the option; None when usable."""
        try:
            parse_relay_url(self.relay_url)
        except ValueError as exc:
            return str(exc)
        if not 1 <= self.viewers <= MAX_VIEWERS:
            return f"--viewers must be 1..{MAX_VIEWERS}, got {self.viewers}"
        if not 0 < self.duration_s <= MAX_DURATION_S:
            return f"--duration must be in (0, {MAX_DURATION_S:g}] seconds, got {self.duration_s:g}"
        if not 0 < self.ramp_per_s <= 1000:
            return f"--ramp must be in (0, 1000] new viewers per second, got {self.ramp_per_s:g}"
        if not 0 <= self.warmup_s <= 60:
            return f"--warmup must be 0..60 seconds, got {self.warmup_s:g}"
        if not 1 <= self.processes <= MAX_PROCESSES:
            return f"--processes must be 1..{MAX_PROCESSES}, got {self.processes}"
        if self.processes > self.viewers:
            return f"--processes ({self.processes}) must not exceed --viewers ({self.viewers})"
        if not 0 < self.connect_timeout_s <= 120:
            return f"--connect-timeout must be in (0, 120] seconds, got {self.connect_timeout_s:g}"
        if self.min_fps < 0 or self.max_p95_ms <= 0:
            return "--min-fps must be >= 0 and --max-p95-ms positive"
        if not self.broadcast.strip("/"):
            return "--broadcast must not be empty"
        return None


@dataclass(frozen=True)
class RunPlan:
    start: float
    ramp_per_s: float
    window_start: float
    window_end: float
    stop: float

    def connect_at(self, index: int) -> float:
        return self.start + index / self.ramp_per_s

    @property
    def window(self) -> tuple[float, float]:
        return (self.window_start, self.window_end)


def make_plan(config: LoadConfig, start: float) -> RunPlan:
    last_due = start + (config.viewers - 1) / config.ramp_per_s
    window_start = last_due + config.warmup_s
    window_end = window_start + config.duration_s
    return RunPlan(start, config.ramp_per_s, window_start, window_end, window_end + GRACE_S)
