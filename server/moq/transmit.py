"""What a sans-IO session asks its transport adapter to do (see the contract in the docs)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class SendData:
    stream_id: int
    data: bytes
    end_stream: bool = False


@dataclass(frozen=True, slots=True)
class ResetStream:
    """Abandon our sending side of a stream (RESET_STREAM)."""

    stream_id: int
    error_code: int


@dataclass(frozen=True, slots=True)
class StopSending:
    """Ask the peer to stop sending on a stream (STOP_SENDING)."""

    stream_id: int
    error_code: int


@dataclass(frozen=True, slots=True)
class CloseSession:
    """Close this WebTransport session (not the whole QUIC connection's other sessions)."""

    error_code: int
    reason: str


Transmit = SendData | ResetStream | StopSending | CloseSession


def is_unidirectional(stream_id: int) -> bool:
    """QUIC stream id bit 1 (RFC 9000 section 2.1)."""
    return bool(stream_id & 0x2)


def is_client_initiated(stream_id: int) -> bool:
    """QUIC stream id bit 0 is set for server-initiated streams."""
    return not stream_id & 0x1
