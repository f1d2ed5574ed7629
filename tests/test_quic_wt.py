"""WebTransport server and client over loopback, in one asyncio loop."""

from __future__ import annotations

import asyncio
import socket
from collections.abc import Awaitable, Callable, Coroutine
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from server.quic import (
    CertBundle,
    CertificateHashError,
    Endpoints,
    WtConnectError,
    WtRequest,
    WtSession,
    connect,
    generate_cert,
    serve,
)
from server.quic.client import WtClientConnection

HOST = "localhost"


@pytest.fixture(scope="module")
def cert(tmp_path_factory: pytest.TempPathFactory) -> CertBundle:
    return generate_cert(directory=tmp_path_factory.mktemp("cert"))


@dataclass
class Recorder:
    """Client (or server) side handler: remembers everything it is told."""

    session: WtSession
    request: WtRequest
    data: dict[int, bytearray] = field(default_factory=dict)
    ended: set[int] = field(default_factory=set)
    resets: list[tuple[int, int]] = field(default_factory=list)
    datagrams: list[bytes] = field(default_factory=list)
    closed: list[str] = field(default_factory=list)
    changed: asyncio.Event = field(default_factory=asyncio.Event)

    def on_stream_data(self, stream_id: int, data: bytes, end_stream: bool) -> None:
        self.data.setdefault(stream_id, bytearray()).extend(data)
        if end_stream:
            self.ended.add(stream_id)
        self.changed.set()

    def on_stream_reset(self, stream_id: int, code: int) -> None:
        self.resets.append((stream_id, code))
        self.changed.set()

    def on_datagram(self, data: bytes) -> None:
        self.datagrams.append(data)
        self.changed.set()

    def on_closed(self, reason: str) -> None:
        self.closed.append(reason)
        self.changed.set()

    async def until(self, cond: Callable[[], bool], timeout: float = 5.0) -> None:
        async with asyncio.timeout(timeout):
            while not cond():
                self.changed.clear()
                await self.changed.wait()


class EchoHandler(Recorder):
    """Server side: echoes bidi streams on the same stream; a complete message
    `open-uni:X` / `open-bidi:X` makes the server open a stream carrying X;
    `flood:N` sends N bytes on a new server uni stream; `reset-me` resets."""

    def on_stream_data(self, stream_id: int, data: bytes, end_stream: bool) -> None:
        super().on_stream_data(stream_id, data, end_stream)
        is_uni = bool(stream_id & 2)
        if not is_uni and not bytes(self.data[stream_id]).startswith(b"cmd:"):
            self.session.send(stream_id, data, end_stream)
            return
        if not end_stream:
            return
        message = bytes(self.data[stream_id]).removeprefix(b"cmd:")
        if message.startswith(b"open-uni:"):
            sid = self.session.open_stream(True)
            self.session.send(sid, message[len(b"open-uni:") :], end_stream=True)
        elif message.startswith(b"open-bidi:"):
            sid = self.session.open_stream(False)
            self.session.send(sid, message[len(b"open-bidi:") :], end_stream=True)
        elif message.startswith(b"flood:"):
            sid = self.session.open_stream(True)
            self.session.send(sid, b"x" * int(message[len(b"flood:") :]))
            SERVER_STREAMS.append((self.session, sid))
        elif message == b"boom":
            raise RuntimeError("handler bug on purpose")
        elif is_uni:
            sid = self.session.open_stream(True)
            self.session.send(sid, message, end_stream=True)


SERVER_STREAMS: list[tuple[WtSession, int]] = []
SERVER_HANDLERS: list[EchoHandler] = []


def echo_factory(session: WtSession, request: WtRequest) -> EchoHandler:
    handler = EchoHandler(session, request)
    SERVER_HANDLERS.append(handler)
    return handler


def run(coro: Coroutine[Any, Any, None], timeout: float = 20.0) -> None:
    async def bounded() -> None:
        async with asyncio.timeout(timeout):
            await coro

    asyncio.run(bounded())


async def with_server(
    cert: CertBundle,
    body: Callable[[Endpoints], Awaitable[None]],
    **kwargs: Any,
) -> None:
    SERVER_STREAMS.clear()
    SERVER_HANDLERS.clear()
    endpoints = await serve(echo_factory, cert, host="::", port=0, **kwargs)
    try:
        await body(endpoints)
    finally:
        await endpoints.close()
    # Every session the server accepted was told it ended, exactly once.
    assert all(len(h.closed) == 1 for h in SERVER_HANDLERS), [h.closed for h in SERVER_HANDLERS]


async def open_client(
    port: int, cert: CertBundle, **kwargs: Any
) -> tuple[WtSession, str | None, Recorder]:
    holder: list[Recorder] = []

    def factory(session: WtSession, request: WtRequest) -> Recorder:
        holder.append(Recorder(session, request))
        return holder[0]

    kwargs.setdefault("cert_hash_hex", cert.sha256_hex)
    session, protocol = await connect(f"https://{HOST}:{port}/game", factory=factory, **kwargs)
    return session, protocol, holder[0]


def test_bidi_echo_and_negotiation(cert: CertBundle) -> None:
    async def body(ep: Endpoints) -> None:
        session, protocol, rec = await open_client(
            ep.port, cert, protocols=["moq-lite-04", "moq-lite-03"]
        )
        assert protocol == "moq-lite-03"
        assert rec.request.headers["wt-protocol"] == '"moq-lite-03"'
        sid = session.open_stream(False)
        session.send(sid, b"hello ")
        session.send(sid, b"world", end_stream=True)
        await rec.until(lambda: sid in rec.ended)
        assert bytes(rec.data[sid]) == b"hello world"
        server = SERVER_HANDLERS[0]
        assert server.request.path == "/game"
        assert server.request.protocol == "moq-lite-03"
        assert server.request.remote_address[0] in ("::1", "127.0.0.1")
        session.close(42, "done")
        assert rec.closed == ["closed locally: 42 done"]
        await server.until(lambda: bool(server.closed))
        assert server.closed == ["closed by peer: 42 done"]

    run(with_server(cert, body))


def test_server_opened_streams_reach_client(cert: CertBundle) -> None:
    async def body(ep: Endpoints) -> None:
        session, _, rec = await open_client(ep.port, cert)
        for command in (b"cmd:open-uni:U1", b"cmd:open-bidi:B1"):
            sid = session.open_stream(False)
            session.send(sid, command, end_stream=True)
        await rec.until(lambda: len(rec.ended) == 2)
        by_payload = {bytes(v): k for k, v in rec.data.items()}
        uni, bidi = by_payload[b"U1"], by_payload[b"B1"]
        assert uni & 3 == 3  # server-initiated unidirectional
        assert bidi & 3 == 1  # server-initiated bidirectional
        # A client uni stream is answered on a server uni stream.
        sid = session.open_stream(True)
        session.send(sid, b"cmd:via-uni", end_stream=True)
        await rec.until(lambda: b"via-uni" in [bytes(v) for v in rec.data.values()])
        session.close()

    run(with_server(cert, body))


def test_protocol_refused_unless_allowed(cert: CertBundle) -> None:
    async def body(ep: Endpoints) -> None:
        with pytest.raises(WtConnectError, match="status 400"):
            await open_client(ep.port, cert, protocols=["moqt-17"])
        # The server is still fine.
        session, protocol, _ = await open_client(ep.port, cert)
        assert protocol == "moq-lite-03"
        session.close()

    run(with_server(cert, body))

    async def lenient(ep: Endpoints) -> None:
        session, protocol, rec = await open_client(ep.port, cert, protocols=["moqt-17"])
        assert protocol is None
        assert "wt-protocol" not in rec.request.headers
        session.close()

    run(with_server(cert, lenient, allow_no_protocol=True))


def test_wrong_cert_hash_fails_clearly(cert: CertBundle) -> None:
    async def body(ep: Endpoints) -> None:
        with pytest.raises(CertificateHashError, match="expected 00"):
            await open_client(ep.port, cert, cert_hash_hex="00" * 32)
        with pytest.raises(WtConnectError, match="handshake"):
            # CA verification of a self-signed certificate fails in the handshake.
            await open_client(ep.port, cert, cert_hash_hex=None, verify=True)
        session, _, _ = await open_client(ep.port, cert, cert_hash_hex=None, verify=False)
        session.close()

    run(with_server(cert, body))


def test_http_url_fetches_hash(cert: CertBundle) -> None:
    async def body(ep: Endpoints) -> None:
        # localhost (::1 first) and IPv4: the "::" bind is dual stack on UDP and TCP.
        for host in ("localhost", "127.0.0.1", "[::1]"):
            session, protocol = await connect(
                f"http://{host}:{ep.port}/", factory=lambda s, r: Recorder(s, r)
            )
            assert protocol == "moq-lite-03"
            session.close()

    run(with_server(cert, body))


def test_connect_timeout_message() -> None:
    async def body() -> None:
        with socket.socket(socket.AF_INET6, socket.SOCK_DGRAM) as silent:
            silent.bind(("::1", 0))
            port = silent.getsockname()[1]
            with pytest.raises(WtConnectError, match=r"timed out after 0.5s during QUIC"):
                await connect(
                    f"https://[::1]:{port}/",
                    factory=lambda s, r: Recorder(s, r),
                    verify=False,
                    timeout=0.5,
                )

    run(body())


def test_write_after_peer_reset_and_stop_sending(cert: CertBundle) -> None:
    async def body(ep: Endpoints) -> None:
        session, _, rec = await open_client(ep.port, cert)
        sid = session.open_stream(False)
        session.send(sid, b"first")
        await rec.until(lambda: bytes(rec.data.get(sid, b"")) == b"first")
        server = SERVER_HANDLERS[0]
        # Client resets its side and asks the server to stop: the server learns both,
        # with the WebTransport codes (not the HTTP/3-mapped ones).
        session.reset_stream(sid, 7)
        session.stop_sending(sid, 9)
        await server.until(lambda: len(server.resets) == 2)
        assert sorted(server.resets) == [(sid, 7), (sid, 9)]
        # The server writes to the stream the client stopped: dropped, no exception.
        for _ in range(3):
            server.session.send(sid, b"late", end_stream=False)
        server.session.send(sid, b"", end_stream=True)
        session.send(sid, b"after my own reset")
        with pytest.raises(ValueError, match="not a stream of this"):
            session.send(4000 * 4 + 2, b"never opened")  # would be a bare QUIC stream
        # Session still usable.
        sid2 = session.open_stream(False)
        session.send(sid2, b"still", end_stream=True)
        await rec.until(lambda: sid2 in rec.ended)
        assert bytes(rec.data[sid2]) == b"still"
        session.close()

    run(with_server(cert, body))


def test_garbage_and_vanished_clients_do_not_kill_server(cert: CertBundle) -> None:
    async def body(ep: Endpoints) -> None:
        # Raw garbage datagrams, on IPv4 and IPv6.
        for family, host in ((socket.AF_INET, "127.0.0.1"), (socket.AF_INET6, "::1")):
            with socket.socket(family, socket.SOCK_DGRAM) as s:
                for size in (1, 20, 1200, 1500):
                    s.sendto(b"\xc3" + bytes(range(256)) * (size // 256 + 1), (host, ep.port))
        # A client that vanishes without closing.
        session, _, _ = await open_client(ep.port, cert)
        session.conn._transport.close()  # type: ignore[union-attr]
        # A handler that raises: only its session dies.
        session, _, rec = await open_client(ep.port, cert)
        sid = session.open_stream(False)
        session.send(sid, b"cmd:boom", end_stream=True)
        await rec.until(lambda: bool(rec.closed))
        # A plain HTTP/3 GET gets 404 and the connection survives.
        session, _, rec = await open_client(ep.port, cert)
        conn = session.conn
        get_id = conn.quic.get_next_available_stream_id()
        conn.h3.send_headers(
            get_id,
            [(b":method", b"GET"), (b":scheme", b"https"), (b":authority", b"x"), (b":path", b"/")],
            end_stream=True,
        )
        assert isinstance(conn, WtClientConnection)
        waiter: asyncio.Future[dict[str, str]] = asyncio.get_running_loop().create_future()
        conn.responses[get_id] = waiter
        conn.transmit()
        assert (await waiter)[":status"] == "404"
        # A second, normal client still gets its echo.
        sid = session.open_stream(False)
        session.send(sid, b"ping", end_stream=True)
        await rec.until(lambda: sid in rec.ended)
        assert bytes(rec.data[sid]) == b"ping"
        session.close()

    run(with_server(cert, body))


def test_buffered_bytes_follow_flow_control(cert: CertBundle) -> None:
    async def body(ep: Endpoints) -> None:
        session, _, rec = await open_client(ep.port, cert)
        conn = session.conn
        # Stall the client: drop every incoming datagram, so nothing gets acked.
        real_receive = conn.datagram_received
        stalled = True

        def maybe_receive(data: bytes | str, addr: Any) -> None:
            if not stalled:
                real_receive(data, addr)

        conn.datagram_received = maybe_receive  # type: ignore[method-assign]
        sid = session.open_stream(True)
        session.send(sid, b"cmd:flood:3000000", end_stream=True)
        server_handler: list[EchoHandler] = []
        async with asyncio.timeout(5):
            while not SERVER_STREAMS:
                await asyncio.sleep(0.01)
        server_session, server_sid = SERVER_STREAMS[0]
        server_handler = SERVER_HANDLERS
        await asyncio.sleep(0.3)
        stuck = server_session.buffered_bytes(server_sid)
        assert stuck >= 3_000_000  # nothing acknowledged
        assert server_session.total_buffered() >= stuck
        stalled = False
        # The client reads again: acks and flow-control credit drain the buffer.
        async with asyncio.timeout(10):
            while server_session.buffered_bytes(server_sid) > 0:
                await asyncio.sleep(0.05)
        await rec.until(lambda: sum(len(v) for v in rec.data.values()) >= 3_000_000, 10)
        assert server_handler
        session.close()

    run(with_server(cert, body), timeout=30)


def test_datagrams_both_ways(cert: CertBundle, tmp_path: Path) -> None:
    async def body(ep: Endpoints) -> None:
        session, _, rec = await open_client(ep.port, cert)
        session.send_datagram(b"dg-up")
        server = SERVER_HANDLERS[0]
        await server.until(lambda: server.datagrams == [b"dg-up"])
        server.session.send_datagram(b"dg-down")
        await rec.until(lambda: rec.datagrams == [b"dg-down"])
        session.close()

    run(with_server(cert, body))


def test_finished_streams_are_forgotten(cert: CertBundle, monkeypatch: pytest.MonkeyPatch) -> None:
    """aioquic never frees HTTP/3 state of WebTransport streams; the adapter does."""
    import server.quic.connection as connection_module

    monkeypatch.setattr(connection_module, "_PRUNE_AT", 8)

    async def body(ep: Endpoints) -> None:
        session, _, rec = await open_client(ep.port, cert)
        sids = []
        for i in range(40):
            sid = session.open_stream(False)
            session.send(sid, b"n%d" % i, end_stream=True)
            sids.append(sid)
        await rec.until(lambda: all(s in rec.ended for s in sids))
        await asyncio.sleep(0.2)  # let the last ACKs arrive
        conn = session.conn
        conn.prune_streams()
        assert len(conn._stream_owner) < 8
        assert len(session._streams) < 8
        assert len([s for s in conn.h3._stream if s in sids]) < 8
        assert session.total_buffered() == 0
        session.close()

    run(with_server(cert, body))
