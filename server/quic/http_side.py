"""Plain HTTP/1.1 on TCP, same port number as the QUIC server.

It serves what a browser needs before WebTransport: the certificate hash
(/certificate.sha256, how @moq/watch pins a self-signed certificate from an
http:// URL), the web client's static files, /healthz, and extra routes the
caller adds (metrics, JSON stats). Stdlib only: it is small and must not pull
a web framework into the relay.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import unquote, urlsplit

log = logging.getLogger(__name__)

MAX_HEAD = 16 * 1024  # request line + headers; larger requests get 431
HEAD_TIMEOUT = 10.0  # seconds to send a complete request head (slowloris bound)
WRITE_TIMEOUT = 30.0  # seconds for a client to take a response before we give up
MAX_REQUESTS_PER_CONNECTION = 100

CONTENT_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".mjs": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".map": "application/json; charset=utf-8",
    ".json": "application/json; charset=utf-8",
    ".wasm": "application/wasm",
    ".svg": "image/svg+xml",
    ".png": "image/png",
    ".ico": "image/x-icon",
    ".txt": "text/plain; charset=utf-8",
}

REASONS = {
    200: "OK",
    204: "No Content",
    400: "Bad Request",
    404: "Not Found",
    405: "Method Not Allowed",
    413: "Content Too Large",
    431: "Request Header Fields Too Large",
    500: "Internal Server Error",
}


@dataclass(frozen=True)
class HttpRequest:
    method: str
    path: str
    """Decoded path without the query string."""
    query: str
    headers: dict[str, str]
    """Lowercase names."""


Response = tuple[int, str, bytes]
"""(status, content type, body)."""
Route = Callable[[HttpRequest], Awaitable[Response]]


class HttpSide:
    """Request routing; independent of the socket so it is easy to test."""

    def __init__(
        self,
        cert_hash_hex: str | Callable[[], str],
        web_root: str | Path | None = None,
        routes: Mapping[str, Route] | None = None,
    ) -> None:
        # A callable lets the caller rotate the certificate without a restart.
        self._cert_hash = cert_hash_hex
        self._root = Path(web_root).resolve() if web_root is not None else None
        self.routes: dict[str, Route] = dict(routes or {})

    def cert_hash(self) -> str:
        value = self._cert_hash() if callable(self._cert_hash) else self._cert_hash
        return value.strip().lower()

    async def respond(self, request: HttpRequest) -> Response:
        path = request.path
        if path == "/certificate.sha256":
            return 200, "text/plain; charset=utf-8", self.cert_hash().encode("ascii")
        if path == "/healthz":
            return 200, "text/plain; charset=utf-8", b"ok"
        route = self.routes.get(path)
        if route is not None:
            return await route(request)
        return self._static(path)

    def _static(self, path: str) -> Response:
        not_found: Response = (404, "text/plain; charset=utf-8", b"not found")
        if self._root is None or "\x00" in path:
            return not_found
        rel = path.lstrip("/")
        # Refuse any '..' segment outright, then also check the resolved path
        # (symlinks) stays inside the root.
        if any(part == ".." for part in rel.replace("\\", "/").split("/")):
            return not_found
        target = (self._root / rel).resolve()
        if not target.is_relative_to(self._root):
            return not_found
        if target.is_dir():
            target = target / "index.html"
        if not target.is_file():
            return not_found
        content_type = CONTENT_TYPES.get(target.suffix.lower(), "application/octet-stream")
        return 200, content_type, target.read_bytes()

    async def handle_connection(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        try:
            await self._serve_connection(reader, writer)
        except asyncio.CancelledError:
            # Server shutdown with a connection open, wherever the handler was (reading
            # or closing): end quietly. Python 3.11's stream protocol logs a traceback
            # for a handler task that ends cancelled, so this one returns normally.
            writer.close()

    async def _serve_connection(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        try:
            for _ in range(MAX_REQUESTS_PER_CONNECTION):
                if not await self._one_request(reader, writer):
                    break
        except (ConnectionError, TimeoutError, asyncio.IncompleteReadError):
            pass  # client went away or was too slow: just drop the connection
        except Exception:
            log.exception("HTTP connection failed")
        finally:
            writer.close()
            with contextlib.suppress(Exception):
                await writer.wait_closed()

    async def _one_request(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> bool:
        """Serve one request; returns whether the connection may be reused."""
        try:
            async with asyncio.timeout(HEAD_TIMEOUT):
                head = await reader.readuntil(b"\r\n\r\n")
        except asyncio.LimitOverrunError:
            await self._write(writer, "GET", 431, "text/plain", b"request head too large", False)
            return False
        except asyncio.IncompleteReadError:
            return False
        lines = head.decode("latin-1").split("\r\n")
        parts = lines[0].split(" ")
        if len(parts) != 3 or not parts[2].startswith("HTTP/1."):
            await self._write(writer, "GET", 400, "text/plain", b"bad request", False)
            return False
        method, target, version = parts
        headers: dict[str, str] = {}
        for line in lines[1:]:
            name, sep, value = line.partition(":")
            if sep:
                headers[name.strip().lower()] = value.strip()
        keep_alive = (
            headers.get("connection", "").lower() != "close"
            if version == "HTTP/1.1"
            else headers.get("connection", "").lower() == "keep-alive"
        )
        if headers.get("content-length", "0") not in ("", "0") or "transfer-encoding" in headers:
            # Only GET/HEAD are served; a body we will not read poisons keep-alive.
            await self._write(writer, method, 413, "text/plain", b"no request bodies", False)
            return False
        if method == "OPTIONS":
            await self._write(writer, method, 204, "text/plain", b"", keep_alive)
            return keep_alive
        if method not in ("GET", "HEAD"):
            await self._write(writer, method, 405, "text/plain", b"method not allowed", False)
            return False
        url = urlsplit(target)
        request = HttpRequest(method, unquote(url.path), url.query, headers)
        try:
            status, content_type, body = await self.respond(request)
        except Exception:
            log.exception("HTTP route %s failed", request.path)
            status, content_type, body = 500, "text/plain", b"internal error"
        await self._write(writer, method, status, content_type, body, keep_alive)
        return keep_alive

    @staticmethod
    async def _write(
        writer: asyncio.StreamWriter,
        method: str,
        status: int,
        content_type: str,
        body: bytes,
        keep_alive: bool,
    ) -> None:
        head = [
            f"HTTP/1.1 {status} {REASONS.get(status, 'Unknown')}",
            f"Content-Type: {content_type}",
            f"Content-Length: {len(body)}",
            # Cross-origin pages (a web client on another port) fetch the hash and stats.
            "Access-Control-Allow-Origin: *",
            "Access-Control-Allow-Methods: GET, HEAD, OPTIONS",
            # The hash changes with every generated certificate; files change on rebuild.
            "Cache-Control: no-cache, no-store",
            f"Connection: {'keep-alive' if keep_alive else 'close'}",
        ]
        writer.write(("\r\n".join(head) + "\r\n\r\n").encode("latin-1"))
        if method != "HEAD":
            writer.write(body)
        async with asyncio.timeout(WRITE_TIMEOUT):
            await writer.drain()


def bind_tcp(host: str, port: int) -> socket.socket:
    """A listening TCP socket; "::" also accepts IPv4 (asyncio would set V6ONLY)."""
    family = socket.AF_INET6 if ":" in host or host == "" else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if family == socket.AF_INET6:
            sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 0)
            sock.bind((host or "::", port, 0, 0))
        else:
            sock.bind((host, port))
        sock.listen(128)
    except OSError:
        sock.close()
        raise
    sock.setblocking(False)
    return sock


async def serve_http(
    side: HttpSide,
    *,
    host: str = "::",
    port: int = 4443,
    sock: socket.socket | None = None,
) -> asyncio.Server:
    """Start serving `side` on TCP `host`:`port` (or an already bound `sock`)."""
    return await asyncio.start_server(
        side.handle_connection,
        sock=sock if sock is not None else bind_tcp(host, port),
        limit=MAX_HEAD,
    )
