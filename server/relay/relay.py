"""The relay process: WebTransport endpoints + RelayCore + metrics, on one port number.

UDP carries QUIC (moq-lite-03 over WebTransport) for publishers, browsers and
load-test viewers; TCP on the same number serves the certificate hash, the web
client, ``/metrics`` (Prometheus) and ``/stats`` (JSON). Every connection is a
MoqLink whose received bytes go to the shared RelayCore; whatever connections
the core touched are flushed right away, so a frame from the publisher is on
the viewers' streams before the next datagram is read.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    generate_latest,
)
from prometheus_client.process_collector import ProcessCollector

from server.auth import Authorizer, Grant
from server.frames.monitor import FrameRateMonitor
from server.media.catalog import is_video_track
from server.moq.errors import ErrorCode
from server.moq.limits import IngressLimits, MoqLimits, TokenBucket
from server.moq.relay_core import ConnId, ConnStats, RelayCore
from server.quic.certs import CertBundle
from server.quic.endpoints import Endpoints, serve
from server.quic.guard import REASONS, GuardLimits, GuardLog
from server.quic.http_side import HttpRequest, Response
from server.quic.moq_link import MoqLink
from server.quic.refusals import RefusalLog
from server.quic.session import Refusal, WtRequest, WtSession

log = logging.getLogger(__name__)

POLL_INTERVAL_S = 0.05
MAX_MONITORED_BROADCASTS = 256
RELAY_STAGE_BUDGET_MS = 5.0  # receive one frame -> written to every viewer's stream
STATS_INTERVAL_S = 1.0


@dataclass
class RelayConfig:
    host: str = "::"
    port: int = 4443
    web_root: Path | None = None
    max_backlog_bytes: int = 2 * 1024 * 1024
    # A viewer that asked for no max_latency still skips ahead past this lag: a
    # cloud-gaming picture half a second old is worth less than the next keyframe.
    default_max_latency_ms: int = 500
    max_connections: int = 1000
    limits: MoqLimits = field(default_factory=MoqLimits)
    ingress: IngressLimits = field(default_factory=IngressLimits)
    # What a peer may send and open before it has a session (server/quic/guard.py).
    guard: GuardLimits = field(default_factory=GuardLimits)
    # Library default: open (tests, benchmarks). `upcast relay` makes the choice
    # explicit: --auth-key or --no-auth.
    authorizer: Authorizer = field(default_factory=Authorizer.open_relay)


def refusal_label(refusal: Refusal) -> str:
    """A Prometheus label with few values: the reason's kind, never its details."""
    if refusal.status == 403:
        return "forbidden_path"
    if refusal.reason == "missing token":
        return "missing_token"
    if refusal.reason.endswith("expired"):
        return "expired_token"
    return "invalid_token"


def close_label(code: int) -> str:
    """A Prometheus label for a moq-lite close code: its name, few values."""
    try:
        return ErrorCode(code).name.lower()
    except ValueError:
        return "other"


class RelayMetrics:
    def __init__(self, registry: CollectorRegistry) -> None:
        self.connections = Gauge("upcast_relay_connections", "Open sessions", registry=registry)
        self.accepted = Counter("upcast_relay_sessions", "Sessions accepted", registry=registry)
        self.refused = Counter(
            "upcast_relay_sessions_refused", "Sessions refused (limit)", registry=registry
        )
        self.unauthorized = Counter(
            "upcast_relay_sessions_unauthorized",
            "Sessions refused or closed for lack of rights (missing/invalid token, a"
            " publish outside the token's put)",
            ["reason"],
            registry=registry,
        )
        self.sessions_closed = Counter(
            "upcast_relay_sessions_closed",
            "Sessions the relay closed for what the peer sent: a moq-lite protocol"
            " violation, a limit (upload rate, message or frame size, streams,"
            " subscriptions), a publish outside the token",
            ["reason"],
            registry=registry,
        )
        self.requests_denied = Counter(
            "upcast_relay_requests_unauthorized",
            "Subscribe requests refused by the token's get",
            registry=registry,
        )
        self.frames_in = Counter(
            "upcast_relay_frames_in", "Frames from publishers", registry=registry
        )
        self.frames_out = Counter("upcast_relay_frames_out", "Frames to viewers", registry=registry)
        self.bytes_out = Counter(
            "upcast_relay_bytes_out", "Payload bytes to viewers", registry=registry
        )
        self.skipped = Counter(
            "upcast_relay_groups_skipped", "Groups a slow viewer skipped", registry=registry
        )
        self.subscribes_refused = Counter(
            "upcast_relay_subscribes_refused",
            "Subscribes refused because the session already holds two of that track",
            registry=registry,
        )
        self.viewers = Gauge(
            "upcast_relay_viewers",
            "Subscribers per track",
            ["broadcast", "track"],
            registry=registry,
        )
        self.guard_refusals = Counter(
            "upcast_relay_guard_refusals",
            "QUIC connections closed or refused before (or around) their WebTransport"
            " session: an HTTP/3 frame, header section or stream buffer over its limit,"
            " too many overhead bytes, no CONNECT in time, too many or too fast connections,"
            " a malformed CONNECT path",
            ["reason"],
            registry=registry,
        )
        for reason in REASONS:
            self.guard_refusals.labels(reason)  # every reason shows, at 0, from the start
        self.handle = Histogram(
            "upcast_relay_handle_seconds",
            "Time to act on one burst of input (relay_in -> relay_out on the viewers' streams)",
            buckets=(0.0001, 0.0002, 0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05),
            registry=registry,
        )


class Relay:
    """Owns the endpoints, the links and the fan-out core."""

    def __init__(self, config: RelayConfig, cert: CertBundle) -> None:
        self.config = config
        self.cert = cert
        self.registry = CollectorRegistry()
        ProcessCollector(registry=self.registry)  # process_cpu_seconds_total for the load test
        self.metrics = RelayMetrics(self.registry)
        self.guard_log = GuardLog(
            on_refusal=lambda reason: self.metrics.guard_refusals.labels(reason).inc()
        )
        self.core = RelayCore(
            self._buffered,
            max_backlog_bytes=config.max_backlog_bytes,
            default_max_latency_s=config.default_max_latency_ms / 1000 or None,
            on_frame=self._on_frame,
            on_denied=self._on_denied,
        )
        # In-session denials (a publish or subscribe outside the token) share one
        # rate-limited log, as refused CONNECTs do in the QUIC server.
        self.denial_log = RefusalLog(what="moq request")
        # One monitor per broadcast's video track: its fps and jitter as the relay
        # receives it, and the time to fan each frame out ("relay" stage).
        self.monitors: dict[str, FrameRateMonitor] = {}
        self._viewer_labels: set[tuple[str, str]] = set()
        self.links: dict[int, MoqLink] = {}
        self._ids = itertools.count(1)
        self._endpoints: Endpoints | None = None
        self._tasks: list[asyncio.Task[None]] = []
        # Per session: its live ConnStats (the core mutates it; it outlives the core's
        # record, so a session's last frames still count after the core dropped it) and
        # the totals already added to the Prometheus counters.
        self._conn_stats: dict[int, ConnStats] = {}
        self._counted: dict[int, tuple[int, int, int, int, int]] = {}
        self.started = time.monotonic()

    @property
    def port(self) -> int:
        assert self._endpoints is not None, "relay not started"
        return self._endpoints.port

    @property
    def quic_connections(self) -> int:
        """QUIC connections the server holds state for (refused and draining included)."""
        return 0 if self._endpoints is None else self._endpoints.wt.connection_count()

    @property
    def quic_connections_serving(self) -> int:
        """QUIC connections not yet closing (refused and draining ones left out)."""
        return 0 if self._endpoints is None else self._endpoints.wt.serving_count()

    async def start(self) -> None:
        routes = {"/metrics": self._metrics_route, "/stats": self._stats_route}
        self._endpoints = await serve(
            self._accept,
            self.cert,
            host=self.config.host,
            port=self.config.port,
            web_root=self.config.web_root,
            routes=routes,
            authorize=self._authorize,
            guard_limits=self.config.guard,
            guard_log=self.guard_log,
        )
        self._tasks.append(asyncio.create_task(self._poll_loop(), name="relay-poll"))
        self._tasks.append(asyncio.create_task(self._stats_loop(), name="relay-stats"))
        log.info(
            "relay listening on %s port %d (QUIC/UDP and HTTP/TCP)", self.config.host, self.port
        )

    async def close(self) -> None:
        for task in self._tasks:
            task.cancel()
        for link in list(self.links.values()):
            link.close(0, "relay shutting down")
        if self._endpoints is not None:
            await self._endpoints.close()

    # -- connections --------------------------------------------------------------

    def _authorize(self, path: str, headers: dict[str, str]) -> Grant | Refusal:
        """Runs in the QUIC server before the CONNECT is answered (and logged there)."""
        decision = self.config.authorizer.authorize(path, headers)
        if isinstance(decision, Refusal):
            self.metrics.unauthorized.labels(refusal_label(decision)).inc()
        return decision

    def _on_denied(self, conn_id: ConnId, action: str, path: str) -> None:
        link = self.links.get(conn_id)  # type: ignore[call-overload]
        remote = link.remote if link is not None else "?"
        self.denial_log.refused(remote, 403, f"{action} {path[:200]!r} not allowed by token")
        if action == "publish":
            self.metrics.unauthorized.labels(f"{action}_denied").inc()
        else:
            self.metrics.requests_denied.inc()

    def _ingress_bucket(self, grant: Grant) -> TokenBucket:
        limits = self.config.ingress
        if grant.publishes:
            rate, burst = limits.publisher_bytes_per_s, limits.publisher_burst_bytes
        else:
            rate, burst = limits.viewer_bytes_per_s, limits.viewer_burst_bytes
        return TokenBucket(rate, burst, time.monotonic())

    def _accept(self, wt: WtSession, request: WtRequest) -> MoqLink:
        conn_id = next(self._ids)
        # No grant only when the server runs without the hook (never from start()).
        grant = request.grant if isinstance(request.grant, Grant) else Grant.everything()
        link = MoqLink(
            wt,
            request,
            on_closed=lambda link, reason: self._closed(conn_id, reason),
            limits=self.config.limits,
            after_input=lambda link: self._handle(conn_id),
            ingress=self._ingress_bucket(grant),
        )
        if len(self.links) >= self.config.max_connections:
            self.metrics.refused.inc()
            log.warning("relay: refusing %s: %d sessions open", link.remote, len(self.links))
            asyncio.get_running_loop().call_soon(wt.close, 0x100, "too many sessions")
            return link
        self.links[conn_id] = link
        self.metrics.accepted.inc()
        self.metrics.connections.set(len(self.links))
        # The path without its query: the token is a secret and stays out of logs.
        log.info(
            "relay: session %d from %s (%s, %s)",
            conn_id,
            link.remote,
            request.path.split("?", 1)[0],
            grant.who,
        )
        self._flush(self.core.add_connection(conn_id, link.moq, grant))
        stats = self.core.stats(conn_id)
        if stats is not None:
            self._conn_stats[conn_id] = stats
        return link

    def _closed(self, conn_id: int, reason: str) -> None:
        link = self.links.pop(conn_id, None)
        if link is None:
            return
        stats = self.core.stats(conn_id)
        log.info("relay: session %d from %s closed (%s); %s", conn_id, link.remote, reason, stats)
        if link.local_close_code:
            self.metrics.sessions_closed.labels(close_label(link.local_close_code)).inc()
        self.metrics.connections.set(len(self.links))
        self._flush(self.core.remove_connection(conn_id))
        self._count(conn_id)  # its last frames since the previous update
        self._conn_stats.pop(conn_id, None)
        self._counted.pop(conn_id, None)

    def _handle(self, conn_id: int) -> None:
        t0 = time.perf_counter()
        touched = self.core.handle(conn_id)
        self._flush(touched)
        self.metrics.handle.observe(time.perf_counter() - t0)
        link = self.links.get(conn_id)
        if link is not None and link.moq.closed:
            # A protocol error closed this one session; the others go on.
            self._closed(conn_id, "protocol error")

    def _flush(self, touched: set[ConnId]) -> None:
        for conn_id in touched:
            link = self.links.get(conn_id)  # type: ignore[call-overload]
            if link is not None:
                link.flush()

    def _buffered(self, conn_id: ConnId, stream_id: int) -> int:
        link = self.links.get(conn_id)  # type: ignore[call-overload]
        return 0 if link is None else link.wt.buffered_bytes(stream_id)

    def _on_frame(self, track: tuple[str, str], size: int, fanout_s: float) -> None:
        broadcast, name = track
        if not is_video_track(name):  # "video", or "video.N" after an encoded-size change
            return
        monitor = self.monitors.get(broadcast)
        if monitor is None:
            if len(self.monitors) >= MAX_MONITORED_BROADCASTS:
                return
            monitor = self.monitors[broadcast] = FrameRateMonitor(
                f"relay/{broadcast}",
                None,
                registry=self.registry,
                budgets_ms={"relay": RELAY_STAGE_BUDGET_MS},
            )
        monitor.frame()
        monitor.record_stage("relay", fanout_s * 1000.0)

    # -- timers -------------------------------------------------------------------

    async def _poll_loop(self) -> None:
        while True:
            await asyncio.sleep(POLL_INTERVAL_S)
            try:
                self._flush(self.core.poll())
            except Exception:
                log.exception("relay poll failed")

    async def _stats_loop(self) -> None:
        while True:
            await asyncio.sleep(STATS_INTERVAL_S)
            self._update_counters()
            for broadcast, monitor in list(self.monitors.items()):
                monitor.check_budgets()
                if broadcast not in self.core.broadcasts:
                    del self.monitors[broadcast]  # gone: stop reporting it

    def _count(self, conn_id: int) -> None:
        """Add what one session did since it was last counted (counters only grow; a
        global sum over open sessions would lose the others' progress whenever one
        closes)."""
        s = self._conn_stats.get(conn_id)
        if s is None:
            return
        now = (s.frames_in, s.frames_out, s.bytes_out, s.groups_skipped, s.subscribes_refused)
        before = self._counted.get(conn_id, (0, 0, 0, 0, 0))
        m = self.metrics
        counters = (m.frames_in, m.frames_out, m.bytes_out, m.skipped, m.subscribes_refused)
        for counter, value, counted in zip(counters, now, before, strict=True):
            if value > counted:
                counter.inc(value - counted)
        self._counted[conn_id] = now

    def _update_counters(self) -> None:
        for conn_id in list(self._conn_stats):
            self._count(conn_id)
        counts = self.core.viewer_counts()
        # A track that ended reads 0 rather than keeping its last count.
        for key in self._viewer_labels - counts.keys():
            self.metrics.viewers.labels(*key).set(0)
        for key, count in counts.items():
            self.metrics.viewers.labels(*key).set(count)
        self._viewer_labels = set(counts)

    def snapshot(self) -> dict[str, object]:
        return {
            "uptime_s": round(time.monotonic() - self.started, 1),
            "sessions": len(self.links),
            "broadcasts": sorted(self.core.broadcasts),
            "monitor": {b: m.snapshot().as_dict() for b, m in self.monitors.items()},
            "viewers": {f"{b}/{t}": n for (b, t), n in self.core.viewer_counts().items()},
            "per_session": {
                str(cid): asdict(s) if (s := self.core.stats(cid)) is not None else None
                for cid in self.links
            },
        }

    async def _metrics_route(self, request: HttpRequest) -> Response:
        self._update_counters()
        return 200, CONTENT_TYPE_LATEST, generate_latest(self.registry)

    async def _stats_route(self, request: HttpRequest) -> Response:
        return 200, "application/json", json.dumps(self.snapshot()).encode()
