"""The supervisor's HTTP side: ``GET /sessions`` (JSON), ``/metrics`` (Prometheus), ``/healthz``.

A dozen lines of asyncio instead of a web framework: three read-only GETs,
one request per connection, on the supervisor's own event loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections.abc import Iterable

from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.registry import Collector

from server.relay.process import RelayProcess
from server.serve.supervisor import Supervisor

log = logging.getLogger(__name__)

MAX_REQUEST_BYTES = 8192
READ_TIMEOUT_S = 5.0


class _SessionCollector(Collector):
    """Per-session gauges, read from the supervisor at scrape time."""

    def __init__(self, supervisor: Supervisor, relay: RelayProcess | None = None) -> None:
        self.supervisor = supervisor
        self.relay = relay  # the relay serve started (None: an external one)

    def collect(self) -> Iterable[GaugeMetricFamily]:
        rows = self.supervisor.snapshot()
        gauges = {
            "up": GaugeMetricFamily(
                "upcast_serve_session_up", "1 while the session publishes", labels=["broadcast"]
            ),
            "restarts": GaugeMetricFamily(
                "upcast_serve_session_restarts", "Session process restarts", labels=["broadcast"]
            ),
            "worker_restarts": GaugeMetricFamily(
                "upcast_serve_worker_restarts",
                "Worker restarts in the current session process",
                labels=["broadcast"],
            ),
            "fps": GaugeMetricFamily(
                "upcast_serve_session_fps", "Frames per second published", labels=["broadcast"]
            ),
        }
        for row in rows:
            labels = [str(row["broadcast"])]
            gauges["up"].add_metric(labels, 1.0 if row["state"] == "up" else 0.0)
            gauges["restarts"].add_metric(labels, float(row["restarts"]))
            gauges["worker_restarts"].add_metric(labels, float(row["worker_restarts"]))
            gauges["fps"].add_metric(labels, float(row["fps"]))
        yield from gauges.values()


class ServeHttp:
    def __init__(self, supervisor: Supervisor, relay: RelayProcess | None = None) -> None:
        self.supervisor = supervisor
        self.relay = relay  # the relay serve started (None: an external one)
        self.registry = CollectorRegistry()
        self.registry.register(_SessionCollector(supervisor))
        self._server: asyncio.Server | None = None

    async def start(self, host: str, port: int) -> int:
        """Listen; returns the bound port."""
        # asyncio binds "::" IPv6-only; None listens on every address of both families.
        bind = None if host in ("::", "") else host
        self._server = await asyncio.start_server(self._handle, bind, port)
        return int(self._server.sockets[0].getsockname()[1])

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()

    def respond(self, path: str) -> tuple[int, str, bytes]:
        """(status, content type, body) for a GET of ``path``."""
        path = path.split("?", 1)[0]
        if path == "/sessions":
            cpu = self.supervisor.cpu
            answer = {
                "relay": self._relay(),
                # Whether each session's CPU share is enforced (cgroups), and why not.
                "cpu_shares": {
                    "enforced": cpu is not None and cpu.available,
                    "reason": "off (--no-cpu-shares)" if cpu is None else cpu.reason,
                },
                "sessions": self.supervisor.snapshot(),
            }
            body = json.dumps(answer, indent=1).encode()
            return 200, "application/json", body
        if path == "/metrics":
            return 200, "text/plain; version=0.0.4", generate_latest(self.registry)
        if path == "/healthz":
            ok = self.supervisor.all_up()
            return (200 if ok else 503), "text/plain", b"ok\n" if ok else b"sessions down\n"
        return 404, "text/plain", b"not found\n"

    def _relay(self) -> dict[str, object]:
        relay = self.relay
        if relay is None:
            return {"url": self.supervisor.relay_url, "pid": None, "restarts": None}
        proc = relay.proc
        return {
            "url": self.supervisor.relay_url,
            "pid": None if proc is None else proc.pid,
            "restarts": relay.restarts,
        }

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            async with asyncio.timeout(READ_TIMEOUT_S):
                head = await reader.readuntil(b"\r\n\r\n")
            method, path, _ = head[:MAX_REQUEST_BYTES].decode("latin-1").split(" ", 2)
            if method != "GET":
                status, ctype, body = 405, "text/plain", b"GET only\n"
            else:
                status, ctype, body = self.respond(path)
            reason = {200: "OK", 404: "Not Found", 405: "Method Not Allowed"}.get(
                status, "Service Unavailable"
            )
            writer.write(
                f"HTTP/1.1 {status} {reason}\r\nContent-Type: {ctype}\r\n"
                f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n".encode()
                + body
            )
            await writer.drain()
        except (
            TimeoutError,
            ValueError,
            asyncio.IncompleteReadError,
            asyncio.LimitOverrunError,
            ConnectionError,
        ) as exc:
            log.debug("serve http: bad request: %s", exc)
        finally:
            writer.close()
            with contextlib.suppress(ConnectionError):
                await writer.wait_closed()
