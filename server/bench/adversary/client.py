"""A hostile QUIC/HTTP/3 client for the relay's adversarial tests and ``bench adversary``.

It speaks aioquic's QuicConnection like any client but lets its owner put arbitrary bytes
on any stream (request, control, QPACK, unknown uni types, WebTransport streams), with
aioquic's own H3Connection for the parts that must be valid (SETTINGS, a CONNECT) when
``h3=True``. With ``h3=False`` nothing HTTP/3 is sent unless the owner writes it: the
control stream and its SETTINGS are then the attacker's to forge.

Why not ``aioquic.asyncio.client.connect``: it always binds ``::`` and always sends
CONNECTION_CLOSE on exit. The attacker binds a chosen loopback source (``127.0.0.2`` by
default, so per-source limits on the relay separate it from the good viewers on
``127.0.0.1``) and can vanish without a CONNECTION_CLOSE. Loopback targets only.
"""

from __future__ import annotations

import asyncio
import ipaddress
import socket
import ssl
import time
from collections.abc import AsyncIterator, Callable, Sequence
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from typing import Any

from aioquic.asyncio.protocol import QuicConnectionProtocol
from aioquic.buffer import encode_uint_var
from aioquic.h3.connection import H3_ALPN, FrameType, H3Connection, H3Stream
from aioquic.h3.events import (
    DataReceived,
    H3Event,
    HeadersReceived,
    WebTransportStreamDataReceived,
)
from aioquic.quic.configuration import QuicConfiguration
from aioquic.quic.connection import QuicConnection
from aioquic.quic.events import (
    ConnectionTerminated,
    PingAcknowledged,
    ProtocolNegotiated,
    QuicEvent,
    StopSendingReceived,
    StreamReset,
)
from cryptography.hazmat.primitives import serialization

from server.quic.certs import der_sha256_hex

MAX_VARINT = (1 << 62) - 1
DEFAULT_SOURCE = "127.0.0.2"
# Stream types of RFC 9114 / 9204 / WebTransport, and one reserved ("grease") type that a
# receiver must ignore: 0x1f * N + 0x21.
UNI_CONTROL = 0x00
UNI_QPACK_ENCODER = 0x02
UNI_QPACK_DECODER = 0x03
UNI_WEBTRANSPORT = 0x54
GREASE_TYPE = 0x1F * 7 + 0x21
FRAME_DATA = 0x00
FRAME_HEADERS = 0x01
FRAME_SETTINGS = 0x04
FRAME_WEBTRANSPORT_STREAM = 0x41


class NotLoopbackError(ValueError):
    """The adversary refuses to attack anything but this machine."""


def varint(value: int) -> bytes:
    return encode_uint_var(value)


def frame(frame_type: int, payload: bytes) -> bytes:
    """A complete HTTP/3 frame."""
    return varint(frame_type) + varint(len(payload)) + payload


def frame_header(frame_type: int, declared_length: int) -> bytes:
    """Only the type and length of an HTTP/3 frame: the body is the attacker's business."""
    return varint(frame_type) + varint(declared_length)


def require_loopback(host: str) -> None:
    """Raise NotLoopbackError unless ``host`` names this machine."""
    if host == "localhost":
        return
    try:
        address = ipaddress.ip_address(host.strip("[]"))
    except ValueError:
        raise NotLoopbackError(f"{host!r} is not a loopback address") from None
    mapped = getattr(address, "ipv4_mapped", None)
    if not (address.is_loopback or (mapped is not None and mapped.is_loopback)):
        raise NotLoopbackError(f"{host!r} is not a loopback address")


class _AttackH3(H3Connection):
    """aioquic's H3Connection, plus the fix server/quic/connection.py applies: a bidi
    WebTransport stream we open stays WebTransport when the relay answers on it (aioquic
    would parse the answer as HTTP/3 frames and close our own connection)."""

    def create_webtransport_stream(self, session_id: int, is_unidirectional: bool = False) -> int:
        stream_id = super().create_webtransport_stream(session_id, is_unidirectional)
        if not is_unidirectional:
            stream = self._stream.get(stream_id)
            if stream is None:
                stream = self._stream[stream_id] = H3Stream(stream_id)
            stream.frame_type = FrameType.WEBTRANSPORT_STREAM
            stream.session_id = session_id
        return stream_id

    @property
    def control_stream_id(self) -> int:
        stream_id = self._local_control_stream_id
        assert stream_id is not None
        return stream_id

    @property
    def encoder_stream_id(self) -> int:
        stream_id = self._local_encoder_stream_id
        assert stream_id is not None
        return stream_id

    @property
    def decoder_stream_id(self) -> int:
        stream_id = self._local_decoder_stream_id
        assert stream_id is not None
        return stream_id


@dataclass
class CloseRecord:
    """How the relay ended this connection (monotonic time)."""

    at: float
    error_code: int
    reason: str
    by_peer: bool


@dataclass
class StreamAbort:
    at: float
    error_code: int
    stop_sending: bool


WtDataSink = Callable[[int, bytes, bool], None]

# A live relay acknowledges a PING within its max_ack_delay (25 ms) plus the loopback
# round trip; the margin is for a loaded 2-core machine.
PROBE_S = 0.5


class AttackConnection(QuicConnectionProtocol):
    """One attacker connection. Everything it saw from the relay is recorded."""

    def __init__(self, quic: QuicConnection, stream_handler: Any = None) -> None:
        super().__init__(quic, stream_handler)
        self.use_h3 = True
        self.h3_conn: _AttackH3 | None = None
        self.closed: CloseRecord | None = None
        self.aborts: dict[int, StreamAbort] = {}
        self.responses: dict[int, dict[str, str]] = {}
        self.capsules: dict[int, bytearray] = {}  # CONNECT stream -> bytes the relay sent
        self._wt_sink: WtDataSink | None = None
        # WebTransport data that overtook the CONNECT response (the relay's announce
        # interest does), kept until a session attaches.
        self._early_wt: list[tuple[int, bytes, bool]] = []
        self.bytes_sent = 0
        self.vanished = False
        self.deaf = False  # drop every datagram: a viewer that never reads
        self.changed = asyncio.Event()
        self._pings_acked: set[int] = set()
        self._next_ping = 1

    # -- state -------------------------------------------------------------------

    @property
    def quic(self) -> QuicConnection:
        return self._quic

    @property
    def h3(self) -> _AttackH3:
        if self.h3_conn is None:
            raise ConnectionError("no HTTP/3 layer (h3=False, or ALPN not negotiated)")
        return self.h3_conn

    @property
    def is_closed(self) -> bool:
        return self.closed is not None or self.vanished

    def buffered(self, stream_id: int) -> int:
        """Bytes queued on a stream and not yet acknowledged (aioquic's private sender)."""
        stream = self._quic._streams.get(stream_id)
        if stream is None:
            return 0
        return int(stream.sender._buffer_stop - stream.sender._buffer_start)

    # -- sending -----------------------------------------------------------------

    def open_bidi(self) -> int:
        return int(self._quic.get_next_available_stream_id(is_unidirectional=False))

    def open_uni(self, stream_type: int | None) -> int:
        """A new unidirectional stream; its type varint is written unless None."""
        stream_id = int(self._quic.get_next_available_stream_id(is_unidirectional=True))
        if stream_type is not None:
            self.send(stream_id, varint(stream_type))
        return stream_id

    def send(self, stream_id: int, data: bytes, end_stream: bool = False) -> bool:
        """Queue bytes (no flush); False once the connection or the stream is gone."""
        if self.is_closed:
            return False
        try:
            self._quic.send_stream_data(stream_id, data, end_stream)
        except (ValueError, RuntimeError, AssertionError):
            return False
        self.bytes_sent += len(data)
        return True

    def flush(self) -> None:
        if not self.vanished:
            self.transmit()

    def send_headers(
        self, stream_id: int, headers: list[tuple[bytes, bytes]], end_stream: bool = False
    ) -> None:
        """Well-formed HEADERS through aioquic's QPACK encoder (h3=True only)."""
        self.h3.send_headers(stream_id, headers, end_stream=end_stream)
        self.flush()

    def vanish(self) -> None:
        """Disappear like a closed laptop: no CONNECTION_CLOSE, no more datagrams."""
        if self.vanished:
            return
        self.vanished = True
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._transport is not None:
            self._transport.close()
        self.changed.set()

    async def relay_still_serving(self, timeout: float = PROBE_S) -> bool:
        """Whether the relay still runs this connection: it acknowledges a PING.

        Not closed is not the same thing: aioquic sends its CONNECTION_CLOSE once and
        ignores every later packet (RFC 9000 10.2 allows that), so when that one datagram
        is lost (a full socket buffer on a loaded machine) the relay has dropped the
        connection while we would wait for our idle timeout to learn it.
        """
        if self.is_closed:
            return False
        uid = self._next_ping
        self._next_ping += 1
        self._quic.send_ping(uid)
        self.flush()
        await self.until(lambda: uid in self._pings_acked or self.is_closed, timeout)
        return uid in self._pings_acked and not self.is_closed

    def close_politely(self) -> None:
        if not self.is_closed:
            self.close()

    # -- receiving ---------------------------------------------------------------

    def datagram_received(self, data: bytes | str, addr: Any) -> None:
        if self.deaf or self.vanished:
            return
        super().datagram_received(data, addr)

    def quic_event_received(self, event: QuicEvent) -> None:
        now = time.monotonic()
        if isinstance(event, ProtocolNegotiated):
            if self.use_h3 and self.h3_conn is None and event.alpn_protocol in H3_ALPN:
                self.h3_conn = _AttackH3(self._quic, enable_webtransport=True)
        elif isinstance(event, ConnectionTerminated):
            if self.closed is None:
                # aioquic reports our own close the same way; the reason tells them apart.
                self.closed = CloseRecord(now, event.error_code, event.reason_phrase, True)
        elif isinstance(event, PingAcknowledged):
            self._pings_acked.add(event.uid)
        elif isinstance(event, StreamReset):
            self.aborts.setdefault(event.stream_id, StreamAbort(now, event.error_code, False))
        elif isinstance(event, StopSendingReceived):
            self.aborts.setdefault(event.stream_id, StreamAbort(now, event.error_code, True))
        if self.h3_conn is not None:
            try:
                h3_events = self.h3_conn.handle_event(event)
            except Exception:  # our own parser choking on the relay's answer: not the test
                h3_events = []
            for h3_event in h3_events:
                self._h3_event(h3_event)
        self.changed.set()

    def _h3_event(self, event: H3Event) -> None:
        if isinstance(event, HeadersReceived):
            self.responses.setdefault(event.stream_id, _decode(event.headers))
        elif isinstance(event, DataReceived):
            self.capsules.setdefault(event.stream_id, bytearray()).extend(event.data)
        elif isinstance(event, WebTransportStreamDataReceived):
            if self._wt_sink is not None:
                self._wt_sink(event.stream_id, event.data, event.stream_ended)
            elif len(self._early_wt) < 64:
                self._early_wt.append((event.stream_id, event.data, event.stream_ended))

    def attach_wt(self, sink: WtDataSink) -> None:
        """Send WebTransport stream data (what arrived so far, then the rest) to ``sink``."""
        self._wt_sink = sink
        early, self._early_wt = self._early_wt, []
        for stream_id, data, ended in early:
            sink(stream_id, data, ended)

    async def until_closed(self, timeout: float) -> bool:
        return await self.until(lambda: self.is_closed, timeout)

    async def until(self, cond: Callable[[], bool], timeout: float) -> bool:
        """Wait for ``cond`` (checked on every event); False on timeout."""
        deadline = time.monotonic() + timeout
        while not cond():
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            self.changed.clear()
            try:
                async with asyncio.timeout(min(left, 0.05)):
                    await self.changed.wait()
            except TimeoutError:
                pass
        return True


async def count_still_served(conns: Sequence[AttackConnection]) -> int:
    """How many of ``conns`` the relay still serves (probed together, not in turn)."""
    open_ones = [c for c in conns if not c.is_closed]
    answers = await asyncio.gather(*(c.relay_still_serving() for c in open_ones))
    return sum(answers)


def _decode(raw: list[tuple[bytes, bytes]]) -> dict[str, str]:
    return {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in raw}


@dataclass(frozen=True)
class Target:
    """Where to attack: a relay on this machine."""

    host: str
    port: int
    cert_hash_hex: str | None = None
    source: str = DEFAULT_SOURCE
    authority: str = field(default="")

    def __post_init__(self) -> None:
        require_loopback(self.host)
        require_loopback(self.source)

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"https://{host}:{self.port}/"

    @property
    def host_port(self) -> str:
        return self.authority or (
            f"[{self.host}]:{self.port}" if ":" in self.host else f"{self.host}:{self.port}"
        )


def _bind(source: str) -> socket.socket:
    sock = socket.socket(socket.AF_INET6, socket.SOCK_DGRAM)
    try:
        sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 0)
        host = f"::ffff:{source}" if "." in source else source
        sock.bind((host, 0, 0, 0))
    except OSError:
        sock.close()
        raise
    return sock


async def open_attack(target: Target, *, h3: bool = True, timeout: float = 5.0) -> AttackConnection:
    """A QUIC connection to the relay, handshake done (and, with ``h3``, SETTINGS sent).

    The certificate is pinned by hash when the target names one (checked right after the
    handshake, as server/quic/client.py does), otherwise not verified at all.
    """
    loop = asyncio.get_running_loop()
    infos = await loop.getaddrinfo(target.host, target.port, type=socket.SOCK_DGRAM)
    addr: tuple[Any, ...] = infos[0][4]
    if len(addr) == 2:
        addr = ("::ffff:" + addr[0], addr[1], 0, 0)
    config = QuicConfiguration(
        alpn_protocols=H3_ALPN,
        is_client=True,
        max_datagram_frame_size=65536,
        server_name=target.host,
        idle_timeout=30.0,  # the relay, not the attacker, must be the one that gives up
    )
    config.verify_mode = ssl.CERT_NONE
    sock = _bind(target.source)
    quic = QuicConnection(configuration=config)
    _, protocol = await loop.create_datagram_endpoint(lambda: AttackConnection(quic), sock=sock)
    protocol.use_h3 = h3
    try:
        protocol.connect(addr)
        async with asyncio.timeout(timeout):
            await protocol.wait_connected()
        if target.cert_hash_hex is not None:
            peer = quic.tls._peer_certificate
            actual = der_sha256_hex(peer.public_bytes(serialization.Encoding.DER)) if peer else ""
            if actual != target.cert_hash_hex.strip().lower():
                raise ConnectionError(f"certificate hash {actual} is not the pinned one")
    except BaseException:
        protocol.vanish()
        raise
    return protocol


@asynccontextmanager
async def attack(target: Target, *, h3: bool = True) -> AsyncIterator[AttackConnection]:
    """``open_attack`` that always releases its socket (politely unless it vanished)."""
    conn = await open_attack(target, h3=h3)
    try:
        yield conn
    finally:
        if not conn.vanished:
            conn.close_politely()
            conn.transmit()
            if conn._transport is not None:
                conn._transport.close()
            if conn._timer is not None:
                conn._timer.cancel()
                conn._timer = None


def connect_headers(
    target: Target,
    path: str = "/",
    *,
    method: bytes = b"CONNECT",
    protocol: bytes | None = b"webtransport",
    offer: bytes | None = b'"moq-lite-03"',
) -> list[tuple[bytes, bytes]]:
    """The CONNECT of a WebTransport session (every part can be made wrong)."""
    headers = [
        (b":method", method),
        (b":scheme", b"https"),
        (b":authority", target.host_port.encode()),
        (b":path", path.encode("latin-1")),
    ]
    if protocol is not None:
        headers.append((b":protocol", protocol))
    headers.append((b"origin", f"https://{target.host_port}".encode()))
    if offer is not None:
        headers.append((b"wt-available-protocols", offer))
    return headers


async def request(
    conn: AttackConnection, headers: list[tuple[bytes, bytes]], timeout: float = 3.0
) -> tuple[int, str | None]:
    """Send one request on a new stream; (its stream, the response's :status or None)."""
    stream_id = conn.open_bidi()
    conn.send_headers(stream_id, headers)
    await conn.until(lambda: stream_id in conn.responses or conn.is_closed, timeout)
    status = conn.responses.get(stream_id, {}).get(":status")
    return stream_id, status


async def pump_bytes(
    conn: AttackConnection,
    stream_id: int,
    chunk: bytes,
    *,
    deadline: float,
    max_bytes: int,
    high_water: int = 256 * 1024,
    tick_s: float = 0.002,
    on_sent: Callable[[int], None] | None = None,
) -> int:
    """Keep ``stream_id`` fed with ``chunk`` until the deadline, ``max_bytes`` or the
    connection's end. Only tops up while less than ``high_water`` is queued, so the
    attacker's own memory stays bounded whatever the relay does with the bytes."""
    sent = 0
    while time.monotonic() < deadline and sent < max_bytes and not conn.is_closed:
        while conn.buffered(stream_id) < high_water and sent < max_bytes:
            if not conn.send(stream_id, chunk):
                return sent
            sent += len(chunk)
            if on_sent is not None:
                on_sent(sent)
        conn.flush()
        await asyncio.sleep(tick_s)
    return sent
