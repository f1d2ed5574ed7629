"""After an outage a live stream comes back within the capped probe interval, not after
QUIC's doubled probe timeouts (server/quic/probe_backoff.py). Two aioquic connections,
sans-IO, on a simulated 15 ms path with virtual time."""

from __future__ import annotations

import ssl
from pathlib import Path

import pytest
from aioquic.quic.configuration import QuicConfiguration
from aioquic.quic.connection import QuicConnection
from aioquic.quic.events import HandshakeCompleted, StreamDataReceived

from server.quic import generate_cert
from server.quic.certs import CertBundle
from server.quic.probe_backoff import MAX_PROBE_INTERVAL_S, CappedProbeRecovery, cap_probe_backoff
from server.quic.server import server_configuration

ONE_WAY_S = 0.0075
TICK_S = 0.001
FRAME_S = 1 / 30
FRAME_BYTES = 4000
CLIENT_ADDR = ("127.0.0.1", 40000)
SERVER_ADDR = ("127.0.0.1", 4443)


@pytest.fixture(scope="module")
def cert(tmp_path_factory: pytest.TempPathFactory) -> CertBundle:
    return generate_cert(directory=tmp_path_factory.mktemp("cert"))


def _stream_through_outage(cert: CertBundle, capped: bool, start: float, end: float) -> float:
    """Seconds from the end of an outage (every datagram lost both ways in [start, end))
    to the first stream data the client receives after it, while the server sends a
    frame every FRAME_S."""
    server_config = server_configuration(cert, idle_timeout=60.0)
    client_config = QuicConfiguration(
        is_client=True,
        alpn_protocols=server_config.alpn_protocols,
        verify_mode=ssl.CERT_NONE,
        idle_timeout=60.0,
    )
    client = QuicConnection(configuration=client_config)
    server = QuicConnection(
        configuration=server_config,
        original_destination_connection_id=client._original_destination_connection_id,
    )
    if capped:
        cap_probe_backoff(client)
        cap_probe_backoff(server)
    now = 0.0
    client.connect(SERVER_ADDR, now=now)
    wire: list[tuple[float, QuicConnection, bytes, tuple[str, int]]] = []
    stream_id: int | None = None
    next_frame = 0.0
    heard: set[int] = {id(client)}  # a server has no path until its first datagram
    links = ((client, server, CLIENT_ADDR), (server, client, SERVER_ADDR))
    while now < end + 10.0:
        for sender, receiver, source in links:
            if id(sender) not in heard:
                continue
            for data, _ in sender.datagrams_to_send(now=now):
                if not start <= now < end:
                    wire.append((now + ONE_WAY_S, receiver, data, source))
        due = [w for w in wire if w[0] <= now]
        wire = [w for w in wire if w[0] > now]
        for _, receiver, data, source in due:
            receiver.receive_datagram(data, source, now=now)
            heard.add(id(receiver))
        for conn in (client, server):
            if id(conn) not in heard:
                continue
            timer = conn.get_timer()
            if timer is not None and timer <= now:
                conn.handle_timer(now=now)
        while (event := server.next_event()) is not None:
            if isinstance(event, HandshakeCompleted):
                stream_id = server.get_next_available_stream_id(is_unidirectional=True)
        while (event := client.next_event()) is not None:
            if isinstance(event, StreamDataReceived) and now >= end:
                return now - end
        if stream_id is not None and now >= next_frame:
            server.send_stream_data(stream_id, b"\x00" * FRAME_BYTES)
            next_frame += FRAME_S
        now += TICK_S
    raise AssertionError("the stream never came back")


def test_a_stream_is_back_within_the_probe_interval_after_seconds_of_loss(
    cert: CertBundle,
) -> None:
    """3.5 s of loss from 1.0 s: aioquic's doubled probe timeouts (0.09 s at first on
    this path) fire at 1.35, 1.43, 1.61, 1.95, 2.64 and 4.02 s, the next at 6.78; the
    link is back at 4.5 and the stream waits 2.3 s for it. Capped: 0.25 s."""
    capped = _stream_through_outage(cert, True, 1.0, 4.5)
    plain = _stream_through_outage(cert, False, 1.0, 4.5)
    assert capped <= MAX_PROBE_INTERVAL_S + 2 * ONE_WAY_S + 0.02, capped
    # aioquic's own doubling waits far longer on the same outage: the cap is what helps.
    assert plain > 2 * capped and plain > 1.0, (plain, capped)


def test_short_outages_and_the_handshake_keep_quics_own_timing(cert: CertBundle) -> None:
    """A lost packet or two (no backoff yet) recovers as fast with the cap as without."""
    capped = _stream_through_outage(cert, True, 1.0, 1.05)
    plain = _stream_through_outage(cert, False, 1.0, 1.05)
    assert capped == pytest.approx(plain, abs=0.01)


def test_capping_is_idempotent_and_logs_an_unknown_aioquic(
    cert: CertBundle, caplog: pytest.LogCaptureFixture, tmp_path: Path
) -> None:
    conn = QuicConnection(
        configuration=server_configuration(cert), original_destination_connection_id=bytes(8)
    )
    cap_probe_backoff(conn)
    cap_probe_backoff(conn)
    assert type(conn._loss) is CappedProbeRecovery
    conn._loss = None  # type: ignore[assignment]
    cap_probe_backoff(conn)
    assert "probe backoff not capped" in caplog.text
