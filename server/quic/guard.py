"""Bounds on what a QUIC peer may send before and around its WebTransport CONNECT.

aioquic's HTTP/3 layer trusts the peer more than a public relay can:
- it buffers a HEADERS, PUSH_PROMISE, SETTINGS or MAX_PUSH_ID frame until the whole
  declared length has arrived, and copies the buffer again on every packet, so one
  HEADERS frame that claims 2^62-1 bytes costs a core for as long as its sender likes;
- it discards unknown frames and unknown stream types cheaply but without end;
- it keeps a connection that never completes a CONNECT until the idle timeout, and it
  creates connection state for every Initial packet, from any number of sources.

`ConnectionGuard` looks at the state aioquic keeps after each packet (it never parses
bytes itself) and names the first limit a connection crossed; `Admission` decides in
front of aioquic's QuicServer whether a new connection is taken at all. What they
read are aioquic internals of the pinned version (``H3Stream`` fields, ``H3Connection.
_stream``): tests/test_quic_guard.py fails if they stop being there.

Crossing a limit closes that one connection (H3_EXCESSIVE_LOAD) or drops the new
connection's Initial; each refusal is counted by reason and logged, rate-limited.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Callable, Container
from dataclasses import dataclass
from urllib.parse import unquote

from aioquic.h3.connection import FrameType, H3Stream, StreamType

from server.moq.limits import TokenBucket

from .refusals import RateLimitedLog

H3_EXCESSIVE_LOAD = 0x107
H3_REQUEST_REJECTED = 0x10B

# Frames aioquic holds whole before acting on them (RFC 9114 sections 7.2.2-7.2.7).
_BUFFERED_REQUEST_FRAMES = (FrameType.HEADERS, FrameType.PUSH_PROMISE)
_BUFFERED_CONTROL_FRAMES = (FrameType.SETTINGS, FrameType.MAX_PUSH_ID)

# Reasons, as counted and as the Prometheus label values of the relay.
FRAME_TOO_LARGE = "h3_frame_too_large"
HEADERS_TOO_LARGE = "h3_headers_too_large"
STREAM_BUFFER = "h3_stream_buffer"
STREAMS = "h3_streams"
PRE_CONNECT_BYTES = "h3_pre_connect_bytes"
OVERHEAD_RATE = "h3_overhead_rate"
CONNECT_DEADLINE = "connect_deadline"
SOURCE_CONNECTIONS = "source_connections"
UNAUTHENTICATED_CONNECTIONS = "unauthenticated_connections"
SOURCE_CONNECTION_RATE = "source_connection_rate"
BAD_PATH = "bad_path"
REASONS = (
    FRAME_TOO_LARGE,
    HEADERS_TOO_LARGE,
    STREAM_BUFFER,
    STREAMS,
    PRE_CONNECT_BYTES,
    OVERHEAD_RATE,
    CONNECT_DEADLINE,
    SOURCE_CONNECTIONS,
    UNAUTHENTICATED_CONNECTIONS,
    SOURCE_CONNECTION_RATE,
    BAD_PATH,
)

MAX_PATH_CHARS = 1024  # the URL path of a CONNECT, without its query
MAX_QUERY_CHARS = 16 * 1024  # room for a token of server.auth.tokens.MAX_TOKEN_CHARS


@dataclass(frozen=True, slots=True)
class GuardLimits:
    """Every bound a peer meets before it is a WebTransport session (all per connection
    unless named otherwise). The defaults leave a browser's CONNECT (a few hundred bytes
    of headers plus a token of up to 8 KiB) far inside them."""

    max_frame_bytes: int = 32 * 1024
    """Declared length of a HEADERS, PUSH_PROMISE, SETTINGS or MAX_PUSH_ID frame."""
    max_header_bytes: int = 64 * 1024
    """Decoded size of one header section (names + values + 32 per field, RFC 9114 4.2.2)."""
    max_stream_buffer_bytes: int = 48 * 1024
    """Bytes aioquic may hold for one HTTP/3 stream that is not WebTransport payload."""
    max_overhead_streams: int = 64
    """Streams over the connection's life that carry no WebTransport payload of an
    accepted session (a browser opens 4 or 5: control, QPACK, CONNECT, a grease one).
    aioquic keeps a record of each such stream until the connection ends."""
    max_pre_connect_bytes: int = 64 * 1024
    """Bytes on one request stream before a CONNECT on it is accepted."""
    overhead_bytes_per_s: int = 32 * 1024
    overhead_burst_bytes: int = 256 * 1024
    """Everything that is not WebTransport stream payload: control and QPACK streams,
    request and CONNECT streams (capsules), unknown stream types and frames."""
    connect_deadline_s: float = 5.0
    """A connection without an accepted CONNECT by then is closed."""
    max_connections_per_source: int = 128
    """Live connections from one IP address (NATs put many players behind one, and a
    load test runs its viewers from one)."""
    max_unauthenticated_connections: int = 512
    """Live connections, from all sources, that have no accepted CONNECT yet."""
    new_connections_per_s_per_source: float = 20.0
    """Each costs a TLS handshake (a few ms of CPU): a storm from one address must not
    take the relay's core from the viewers. A load test ramps at up to this rate."""
    new_connections_burst_per_source: float = 40.0
    max_tracked_sources: int = 65536
    """Sources whose connection rate is remembered (oldest forgotten first)."""

    def __post_init__(self) -> None:
        for name in self.__slots__:
            value = getattr(self, name)
            if value <= 0:
                raise ValueError(f"GuardLimits.{name} must be positive, got {value}")


@dataclass(frozen=True, slots=True)
class Violation:
    reason: str
    """One of REASONS."""
    detail: str
    """For the log: sizes and limits, never the peer's bytes."""


class GuardLog:
    """Counts refusals by reason, tells a listener (the relay's metrics), logs them
    rate-limited: shared by every connection of one server."""

    def __init__(
        self,
        on_refusal: Callable[[str], None] | None = None,
        log: RateLimitedLog | None = None,
    ) -> None:
        self.counts: dict[str, int] = dict.fromkeys(REASONS, 0)
        self.on_refusal = on_refusal
        self.log = log or RateLimitedLog(
            logger=logging.getLogger(__name__),
            summary="%d more QUIC connections closed or refused (log lines suppressed)",
        )

    def refused(self, remote: str, violation: Violation, code: int | None = None) -> None:
        """`code`: the HTTP/3 error code the connection was closed with; None for a new
        connection that was dropped before it existed."""
        self.counts[violation.reason] = self.counts.get(violation.reason, 0) + 1
        if self.on_refusal is not None:
            self.on_refusal(violation.reason)
        if code is None:
            self.log.warning(
                "dropped new QUIC connection from %s: %s: %s",
                remote,
                violation.reason,
                violation.detail,
            )
        else:
            self.log.warning(
                "closed QUIC connection from %s with %#x: %s: %s",
                remote,
                code,
                violation.reason,
                violation.detail,
            )


class ConnectionGuard:
    """The byte limits of one connection, checked after aioquic handled each packet."""

    def __init__(self, limits: GuardLimits, now: float) -> None:
        self.limits = limits
        self._overhead = TokenBucket(limits.overhead_bytes_per_s, limits.overhead_burst_bytes, now)
        self._pre_connect: dict[int, int] = {}
        self._overhead_streams: set[int] = set()

    def after_stream_data(
        self,
        stream: H3Stream | None,
        stream_id: int,
        size: int,
        sessions: Container[int],
        now: float,
    ) -> Violation | None:
        """Check one StreamDataReceived of `size` bytes once aioquic's HTTP/3 layer has
        handled it. `stream` is aioquic's record of the stream (None when aioquic ignored
        the data); `sessions`: the ids (CONNECT stream ids) of the accepted sessions."""
        if stream is not None and _is_webtransport(stream) and stream.session_id in sessions:
            return None  # payload: the session's own ingress limit applies
        if stream_id not in self._overhead_streams:
            self._overhead_streams.add(stream_id)
            if len(self._overhead_streams) > self.limits.max_overhead_streams:
                return Violation(
                    STREAMS,
                    f"more than {self.limits.max_overhead_streams} streams without"
                    " WebTransport payload of an accepted session",
                )
        if not self._overhead.take(size, now):
            return Violation(
                OVERHEAD_RATE,
                f"more than {self.limits.overhead_bytes_per_s} B/s of HTTP/3 overhead",
            )
        if stream_id % 4 == 0 and stream_id not in sessions:  # client-initiated bidi
            total = self._pre_connect.get(stream_id, 0) + size
            self._pre_connect[stream_id] = total
            if total > self.limits.max_pre_connect_bytes:
                return Violation(
                    PRE_CONNECT_BYTES,
                    f"{total} B on a request stream without an accepted CONNECT"
                    f" (limit {self.limits.max_pre_connect_bytes})",
                )
        return None if stream is None else self.check_stream(stream)

    def check_stream(self, stream: H3Stream) -> Violation | None:
        declared = stream.frame_size
        if declared is not None and declared > self.limits.max_frame_bytes:
            buffered = (
                stream.stream_type is None and stream.frame_type in _BUFFERED_REQUEST_FRAMES
            ) or (
                stream.stream_type == StreamType.CONTROL
                and stream.frame_type in _BUFFERED_CONTROL_FRAMES
            )
            if buffered:
                return Violation(
                    FRAME_TOO_LARGE,
                    f"frame type {stream.frame_type:#x} declares {declared} B"
                    f" (limit {self.limits.max_frame_bytes})",
                )
        if len(stream.buffer) > self.limits.max_stream_buffer_bytes:
            return Violation(
                STREAM_BUFFER,
                f"{len(stream.buffer)} B held for stream {stream.stream_id}"
                f" (limit {self.limits.max_stream_buffer_bytes})",
            )
        return None

    def check_headers(self, headers: list[tuple[bytes, bytes]]) -> Violation | None:
        size = sum(len(name) + len(value) + 32 for name, value in headers)
        if size > self.limits.max_header_bytes:
            return Violation(
                HEADERS_TOO_LARGE,
                f"header section of {size} B (limit {self.limits.max_header_bytes})",
            )
        return None

    def connect_accepted(self, stream_id: int) -> None:
        self._pre_connect.pop(stream_id, None)


def _is_webtransport(stream: H3Stream) -> bool:
    if stream.stream_type == StreamType.WEBTRANSPORT:
        return True  # unidirectional
    return stream.frame_type == FrameType.WEBTRANSPORT_STREAM and stream.session_id is not None


def check_connect_path(path: str) -> str | None:
    """Why a CONNECT ``:path`` is malformed, or None. Both the open and the token relay
    apply it before anything else reads the path."""
    if not path.startswith("/"):
        return "path does not start with '/'"
    route, _, query = path.partition("?")
    if len(route) > MAX_PATH_CHARS:
        return f"path longer than {MAX_PATH_CHARS} characters"
    if len(query) > MAX_QUERY_CHARS:
        return f"query longer than {MAX_QUERY_CHARS} characters"
    if any(ord(c) < 0x21 or ord(c) == 0x7F for c in path):
        return "control character or space in the path"
    try:
        decoded = unquote(route, errors="strict")
    except UnicodeDecodeError:
        return "percent-encoding that is not UTF-8"
    if any(ord(c) < 0x20 or ord(c) == 0x7F for c in decoded):
        return "encoded control character in the path"
    if any(segment in (".", "..") for segment in decoded.split("/")):
        return "'.' or '..' segment in the path"
    return None


@dataclass
class _Source:
    bucket: TokenBucket
    live: int = 0


class Admission:
    """Which new connections a server takes: per source address (live count and rate)
    and unauthenticated ones in total. Sans-IO: the server tells it about connections
    that start, authenticate and end; `admit` answers for a new connection's Initial."""

    def __init__(self, limits: GuardLimits) -> None:
        self.limits = limits
        self._sources: OrderedDict[str, _Source] = OrderedDict()
        self._unauthenticated: set[object] = set()
        self._source_of: dict[object, str] = {}

    @property
    def unauthenticated(self) -> int:
        return len(self._unauthenticated)

    def live(self, host: str) -> int:
        source = self._sources.get(host)
        return 0 if source is None else source.live

    def admit(self, host: str, now: float) -> Violation | None:
        limits = self.limits
        source = self._source(host, now)
        if source.live >= limits.max_connections_per_source:
            return Violation(
                SOURCE_CONNECTIONS,
                f"{source.live} connections open from this address"
                f" (limit {limits.max_connections_per_source})",
            )
        if len(self._unauthenticated) >= limits.max_unauthenticated_connections:
            return Violation(
                UNAUTHENTICATED_CONNECTIONS,
                f"{len(self._unauthenticated)} connections without a session"
                f" (limit {limits.max_unauthenticated_connections})",
            )
        if not source.bucket.take(1, now):
            return Violation(
                SOURCE_CONNECTION_RATE,
                f"more than {limits.new_connections_per_s_per_source:g} new connections/s"
                " from this address",
            )
        return None

    def started(self, connection: object, host: str, now: float) -> None:
        self._source(host, now).live += 1
        self._source_of[connection] = host
        self._unauthenticated.add(connection)

    def authenticated(self, connection: object) -> None:
        self._unauthenticated.discard(connection)

    def ended(self, connection: object) -> None:
        self._unauthenticated.discard(connection)
        host = self._source_of.pop(connection, None)
        source = None if host is None else self._sources.get(host)
        if source is not None:
            source.live = max(0, source.live - 1)

    def _source(self, host: str, now: float) -> _Source:
        source = self._sources.get(host)
        if source is None:
            bucket = TokenBucket(
                self.limits.new_connections_per_s_per_source,
                self.limits.new_connections_burst_per_source,
                now,
            )
            source = self._sources[host] = _Source(bucket)
            self._forget_oldest()
        else:
            self._sources.move_to_end(host)
        return source

    def _forget_oldest(self) -> None:
        """Bound the table (spoofed sources could fill it): forget the least recently
        seen sources that hold no live connection."""
        excess = len(self._sources) - self.limits.max_tracked_sources
        if excess <= 0:
            return
        for host in list(self._sources):
            if excess <= 0:
                break
            if self._sources[host].live == 0:
                del self._sources[host]
                excess -= 1
