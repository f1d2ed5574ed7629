"""Start the QUIC (WebTransport) and TCP (HTTP) listeners on one port number."""

from __future__ import annotations

import asyncio
import socket
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from .certs import CertBundle
from .connection import IDLE_TIMEOUT_S
from .guard import GuardLimits, GuardLog
from .http_side import HttpSide, Route, bind_tcp, serve_http
from .server import DEFAULT_PROTOCOLS, WtServer, bind_udp, serve_webtransport
from .session import Authorize, HandlerFactory


@dataclass
class Endpoints:
    wt: WtServer
    http: asyncio.Server
    http_side: HttpSide
    port: int

    async def close(self) -> None:
        self.wt.close()
        self.http.close()
        await self.http.wait_closed()


def bind_pair(host: str, port: int, attempts: int = 20) -> tuple[socket.socket, socket.socket]:
    """UDP and TCP sockets on the same port; with port 0 retry until the number the
    kernel picked for UDP is also free on TCP."""
    for _ in range(attempts if port == 0 else 1):
        udp = bind_udp(host, port)
        try:
            tcp = bind_tcp(host, udp.getsockname()[1])
        except OSError:
            udp.close()
            if port != 0:
                raise
            continue
        return udp, tcp
    raise OSError(f"no port free on both UDP and TCP for {host}")


async def serve(
    factory: HandlerFactory,
    cert: CertBundle,
    *,
    host: str = "::",
    port: int = 4443,
    protocols: Sequence[str] = DEFAULT_PROTOCOLS,
    allow_no_protocol: bool = False,
    web_root: str | Path | None = None,
    routes: Mapping[str, Route] | None = None,
    idle_timeout: float = IDLE_TIMEOUT_S,
    authorize: Authorize | None = None,
    guard_limits: GuardLimits | None = None,
    guard_log: GuardLog | None = None,
) -> Endpoints:
    """WebTransport on UDP and HTTP (hash, static files, routes) on TCP, one port."""
    udp, tcp = bind_pair(host, port)
    side = HttpSide(cert.sha256_hex, web_root=web_root, routes=routes)
    try:
        wt = await serve_webtransport(
            factory,
            cert,
            protocols=protocols,
            allow_no_protocol=allow_no_protocol,
            sock=udp,
            idle_timeout=idle_timeout,
            authorize=authorize,
            guard_limits=guard_limits,
            guard_log=guard_log,
        )
    except BaseException:
        udp.close()
        tcp.close()
        raise
    http = await serve_http(side, sock=tcp)
    return Endpoints(wt=wt, http=http, http_side=side, port=wt.port)
