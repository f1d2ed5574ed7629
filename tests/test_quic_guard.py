"""The QUIC / HTTP/3 guard in front of the relay (server/quic/guard.py): what a peer may
send before it has a WebTransport session, over real QUIC against a real relay, and the
aioquic internals the guard reads (these tests fail if an aioquic upgrade moves them)."""

from __future__ import annotations

import asyncio
import functools
import ssl
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from importlib.metadata import version
from typing import Any

import pytest
from aioquic.asyncio.client import connect
from aioquic.asyncio.protocol import QuicConnectionProtocol
from aioquic.buffer import encode_uint_var
from aioquic.h3.connection import H3_ALPN, FrameType, H3Connection, H3Stream, StreamType
from aioquic.quic.configuration import QuicConfiguration
from aioquic.quic.events import ConnectionTerminated, QuicEvent

from server.quic.certs import CertBundle, generate_cert
from server.quic.guard import (
    Admission,
    ConnectionGuard,
    GuardLimits,
    check_connect_path,
)
from server.relay.relay import Relay
from tests.relay_harness import Publisher, Viewer, run_bounded, running_relay, until

PINNED_AIOQUIC = "1.7.2"
HUGE = (1 << 62) - 1


@pytest.fixture(scope="module")
def cert(tmp_path_factory: pytest.TempPathFactory) -> CertBundle:
    return generate_cert(directory=tmp_path_factory.mktemp("cert"))


run = functools.partial(run_bounded, timeout=60.0)


def refusals(relay: Relay, reason: str) -> float:
    value = relay.registry.get_sample_value("upcast_relay_guard_refusals_total", {"reason": reason})
    return value or 0.0


# --------------------------------------------------------------------- the pinned wrap


def test_aioquic_is_the_version_the_guard_was_written_against() -> None:
    """The guard reads aioquic's private HTTP/3 state: an upgrade must be a decision
    (re-check guard.py, connection.py and server.py, then move this pin)."""
    assert version("aioquic") == PINNED_AIOQUIC


def test_the_aioquic_internals_the_guard_reads_are_there() -> None:
    stream = H3Stream(0)
    for name in ("buffer", "frame_type", "frame_size", "stream_type", "session_id"):
        assert hasattr(stream, name), name
    # connection.py's _WtH3Connection notes the stream each packet was for through these.
    assert hasattr(H3Connection, "_receive_request_or_push_data")
    assert hasattr(H3Connection, "_receive_stream_data_uni")
    from aioquic.asyncio.server import QuicServer

    assert hasattr(QuicServer, "_connection_terminated")
    assert hasattr(QuicServer, "datagram_received")


# ----------------------------------------------------------------------- sans-IO units


def test_a_huge_declared_headers_frame_is_a_violation_at_once() -> None:
    guard = ConnectionGuard(GuardLimits(), now=0.0)
    stream = H3Stream(0)
    stream.frame_type, stream.frame_size, stream.buffer = FrameType.HEADERS, HUGE, b"x" * 1000
    violation = guard.after_stream_data(stream, 0, 1000, (), now=0.0)
    assert violation is not None and violation.reason == "h3_frame_too_large"


def test_a_huge_settings_frame_on_the_control_stream_is_a_violation() -> None:
    guard = ConnectionGuard(GuardLimits(), now=0.0)
    stream = H3Stream(2)
    stream.stream_type = StreamType.CONTROL
    stream.frame_type, stream.frame_size = FrameType.SETTINGS, 1 << 20
    violation = guard.after_stream_data(stream, 2, 100, (), now=0.0)
    assert violation is not None and violation.reason == "h3_frame_too_large"


def test_a_huge_unknown_frame_is_not_buffered_but_counted_until_the_limit() -> None:
    limits = GuardLimits(max_pre_connect_bytes=10_000)
    guard = ConnectionGuard(limits, now=0.0)
    stream = H3Stream(0)
    stream.frame_type, stream.frame_size = 0x21, HUGE  # reserved (grease) type: discarded
    for _ in range(9):
        assert guard.after_stream_data(stream, 0, 1000, (), now=0.0) is None
    violation = guard.after_stream_data(stream, 0, 1001, (), now=0.0)
    assert violation is not None and violation.reason == "h3_pre_connect_bytes"


def test_webtransport_payload_is_not_overhead() -> None:
    limits = GuardLimits(overhead_burst_bytes=1000, overhead_bytes_per_s=1)
    guard = ConnectionGuard(limits, now=0.0)
    stream = H3Stream(2)
    stream.stream_type, stream.session_id = StreamType.WEBTRANSPORT, 0
    for _ in range(100):
        assert guard.after_stream_data(stream, 2, 100_000, {0}, now=0.0) is None


def test_webtransport_streams_of_a_session_never_accepted_are_overhead() -> None:
    limits = GuardLimits(overhead_burst_bytes=1000, overhead_bytes_per_s=1)
    guard = ConnectionGuard(limits, now=0.0)
    stream = H3Stream(2)
    stream.stream_type, stream.session_id = StreamType.WEBTRANSPORT, 4
    violation = guard.after_stream_data(stream, 2, 100_000, {0}, now=0.0)
    assert violation is not None and violation.reason == "h3_overhead_rate"


def test_streams_without_payload_are_bounded_per_connection() -> None:
    guard = ConnectionGuard(GuardLimits(max_overhead_streams=10), now=0.0)
    for i in range(10):
        stream = H3Stream(4 * i + 2)
        stream.stream_type = 0x21  # a reserved (grease) type: discarded by aioquic
        assert guard.after_stream_data(stream, stream.stream_id, 1, (), now=0.0) is None
    eleventh = H3Stream(42)
    violation = guard.after_stream_data(eleventh, 42, 1, (), now=0.0)
    assert violation is not None and violation.reason == "h3_streams"


def test_overhead_beyond_its_rate_is_a_violation() -> None:
    limits = GuardLimits(overhead_burst_bytes=1000, overhead_bytes_per_s=100)
    guard = ConnectionGuard(limits, now=0.0)
    stream = H3Stream(0)
    assert guard.after_stream_data(stream, 0, 900, {0}, now=0.0) is None
    assert guard.after_stream_data(stream, 0, 150, {0}, now=0.5) is None
    violation = guard.after_stream_data(stream, 0, 500, {0}, now=0.6)
    assert violation is not None and violation.reason == "h3_overhead_rate"


def test_header_section_size_counts_names_values_and_overhead() -> None:
    guard = ConnectionGuard(GuardLimits(max_header_bytes=1000), now=0.0)
    assert guard.check_headers([(b"a", b"b" * 900)]) is None
    too_big = guard.check_headers([(b"a", b"b" * 500)] * 2)
    assert too_big is not None and too_big.reason == "h3_headers_too_large"


@pytest.mark.parametrize(
    "path",
    [
        "",
        "game",
        "/../..",
        "/a/../b",
        "/a/%2e%2e/b",
        "/a%00b",
        "/a\x00b",
        "/a b",
        "/" + "a" * 8192,
        "/%ff%fe",
        "/?" + "j" * 20_000,
    ],
)
def test_malformed_connect_paths_are_named(path: str) -> None:
    assert check_connect_path(path) is not None


@pytest.mark.parametrize(
    "path", ["/", "/game", "/anon/game-1?jwt=eyJ.abc.def", "/a/b%20c", "/room/.hidden"]
)
def test_ordinary_connect_paths_pass(path: str) -> None:
    assert check_connect_path(path) is None


def test_admission_per_source_live_count_and_rate() -> None:
    limits = GuardLimits(
        max_connections_per_source=3,
        new_connections_per_s_per_source=1.0,
        new_connections_burst_per_source=4.0,
    )
    admission = Admission(limits)
    conns = [object() for _ in range(3)]
    for conn in conns:
        assert admission.admit("10.0.0.1", 0.0) is None
        admission.started(conn, "10.0.0.1", 0.0)
    refused = admission.admit("10.0.0.1", 0.0)
    assert refused is not None and refused.reason == "source_connections"
    assert admission.admit("10.0.0.2", 0.0) is None  # another address is not affected
    admission.ended(conns[0])
    assert admission.admit("10.0.0.1", 0.0) is None  # the 4th token of the burst
    admission.started(object(), "10.0.0.1", 0.0)
    admission.ended(conns[1])
    rate = admission.admit("10.0.0.1", 0.0)  # burst spent: 5 taken (1 by 10.0.0.1's 4th)
    assert rate is not None and rate.reason == "source_connection_rate"
    assert admission.admit("10.0.0.1", 2.0) is None  # refilled


def test_admission_bounds_unauthenticated_connections_in_total() -> None:
    admission = Admission(GuardLimits(max_unauthenticated_connections=2))
    a, b = object(), object()
    admission.started(a, "10.0.0.1", 0.0)
    admission.started(b, "10.0.0.2", 0.0)
    refused = admission.admit("10.0.0.3", 0.0)
    assert refused is not None and refused.reason == "unauthenticated_connections"
    admission.authenticated(a)
    assert admission.admit("10.0.0.3", 0.0) is None


def test_admission_forgets_idle_sources_beyond_its_table() -> None:
    admission = Admission(GuardLimits(max_tracked_sources=100))
    for i in range(1000):
        assert admission.admit(f"10.0.{i // 256}.{i % 256}", 0.0) is None
    assert len(admission._sources) <= 100


# ------------------------------------------------------------------- over real QUIC


class RawPeer(QuicConnectionProtocol):
    """A QUIC client that writes raw bytes on HTTP/3 streams and notes when it is closed."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.terminated: ConnectionTerminated | None = None
        self.terminated_at: float | None = None

    def quic_event_received(self, event: QuicEvent) -> None:
        if isinstance(event, ConnectionTerminated) and self.terminated is None:
            self.terminated = event
            self.terminated_at = time.monotonic()

    def send(self, stream_id: int, data: bytes, end: bool = False) -> None:
        self._quic.send_stream_data(stream_id, data, end)
        self.transmit()

    def open_control_stream(self) -> int:
        stream_id = self._quic.get_next_available_stream_id(is_unidirectional=True)
        self.send(stream_id, encode_uint_var(StreamType.CONTROL))
        return stream_id


@asynccontextmanager
async def raw_peer(port: int) -> AsyncIterator[RawPeer]:
    config = QuicConfiguration(alpn_protocols=H3_ALPN, is_client=True)
    config.verify_mode = ssl.CERT_NONE
    async with connect(
        "127.0.0.1", port, configuration=config, create_protocol=RawPeer, wait_connected=True
    ) as peer:
        assert isinstance(peer, RawPeer)
        yield peer


async def flood_until_closed(peer: RawPeer, stream_id: int, head: bytes, seconds: float) -> int:
    """Send `head`, then 1 KiB chunks until the relay closes us or `seconds` pass;
    returns the bytes sent."""
    peer.send(stream_id, head)
    sent = len(head)
    deadline = time.monotonic() + seconds
    while peer.terminated is None and time.monotonic() < deadline:
        peer.send(stream_id, b"\x00" * 1024)
        sent += 1024
        await asyncio.sleep(0.002)
    return sent


@asynccontextmanager
async def watched_relay(cert: CertBundle, **config: Any) -> AsyncIterator[tuple[Relay, Viewer]]:
    """A relay with a publisher streaming at 50 fps and one viewer receiving it."""
    async with running_relay(cert, **config) as relay:
        publisher = Publisher()
        viewer = Viewer()
        await publisher.start(relay.port, cert)
        await until(lambda: "game" in relay.core.broadcasts)
        await viewer.connect(relay.port, cert)
        await viewer.subscribed()
        streaming = asyncio.create_task(publisher.stream(10_000, fps=50.0, group_every=10))
        await viewer.until_count(5)
        try:
            yield relay, viewer
        finally:
            streaming.cancel()
            viewer.close()
            publisher.close()


@pytest.mark.parametrize(
    ("name", "head", "reason"),
    [
        (
            "HEADERS frame of 2^62-1 bytes",
            encode_uint_var(FrameType.HEADERS) + encode_uint_var(HUGE),
            "h3_frame_too_large",
        ),
        (
            "unknown frame of 2^62-1 bytes",
            encode_uint_var(0x21) + encode_uint_var(HUGE),
            "h3_pre_connect_bytes",
        ),
        (
            "DATA before any HEADERS",
            encode_uint_var(FrameType.DATA) + encode_uint_var(HUGE),
            None,  # aioquic's own H3_FRAME_UNEXPECTED (0x105), at once
        ),
    ],
)
def test_request_stream_floods_are_closed_within_a_second_and_viewers_go_on(
    cert: CertBundle, name: str, head: bytes, reason: str | None
) -> None:
    async def main() -> None:
        async with watched_relay(cert) as (relay, viewer):
            before = len(viewer.frames)
            async with raw_peer(relay.port) as peer:
                started = time.monotonic()
                sent = await flood_until_closed(peer, 0, head, seconds=5.0)
                assert peer.terminated is not None, f"{name}: still open after {sent} B"
                assert peer.terminated_at is not None
                assert peer.terminated_at - started < 1.0, name
            if reason is None:
                assert peer.terminated.error_code == 0x105
            else:
                assert refusals(relay, reason) == 1
            await viewer.until_count(before + 10)  # the stream goes on

    run(main())


def test_control_stream_floods_are_closed(cert: CertBundle) -> None:
    async def main() -> None:
        async with running_relay(cert) as relay:
            async with raw_peer(relay.port) as peer:
                control = peer.open_control_stream()
                head = encode_uint_var(FrameType.SETTINGS) + encode_uint_var(HUGE)
                await flood_until_closed(peer, control, head, seconds=3.0)
                assert peer.terminated is not None
            assert refusals(relay, "h3_frame_too_large") == 1
            async with raw_peer(relay.port) as peer:
                control = peer.open_control_stream()
                empty_settings = encode_uint_var(FrameType.SETTINGS) + encode_uint_var(0)
                head = empty_settings + encode_uint_var(0x21) + encode_uint_var(HUGE)
                await flood_until_closed(peer, control, head, seconds=15.0)
                assert peer.terminated is not None
            assert refusals(relay, "h3_overhead_rate") == 1

    run(main())


def test_a_connection_without_a_connect_is_closed_at_the_deadline(cert: CertBundle) -> None:
    async def main() -> None:
        async with running_relay(cert, guard=GuardLimits(connect_deadline_s=0.5)) as relay:
            async with raw_peer(relay.port) as peer:
                peer.open_control_stream()
                await until(lambda: peer.terminated is not None, timeout=3.0)
            assert refusals(relay, "connect_deadline") == 1

    run(main())


def test_connections_over_the_per_source_limit_are_not_taken(cert: CertBundle) -> None:
    async def main() -> None:
        limits = GuardLimits(max_connections_per_source=3)
        async with running_relay(cert, guard=limits) as relay:
            async with (
                raw_peer(relay.port),
                raw_peer(relay.port),
                raw_peer(relay.port),
            ):
                with pytest.raises((ConnectionError, TimeoutError)):
                    async with asyncio.timeout(1.5), raw_peer(relay.port):
                        pass
                assert refusals(relay, "source_connections") >= 1
            # Closed ones free their place (after aioquic's draining period).
            await until(lambda: relay.quic_connections == 0, timeout=10.0)
            async with raw_peer(relay.port) as peer:
                assert peer.terminated is None

    run(main())
