"""A moq-lite session on an attacker's connection: well-formed when it has to be.

The sans-IO MoqSession (server/moq/session.py) runs over an AttackConnection's accepted
WebTransport session, so an attacker can subscribe, publish or stall like a real
viewer, and next to it write raw bytes on WebTransport streams of the same session.
"""

from __future__ import annotations

from aioquic.quic.connection import stream_is_unidirectional

from server.bench.adversary.client import (
    AttackConnection,
    Target,
    connect_headers,
    open_attack,
    request,
)
from server.moq import events as ev
from server.moq.session import MoqSession
from server.moq.transmit import CloseSession, ResetStream, SendData, StopSending
from server.quic import codes
from server.quic.connection import close_reason


class AttackSession:
    """MoqSession <-> AttackConnection. ``accept_subscribes`` answers the relay's
    SUBSCRIBEs (an attacker publisher); frames received are only counted."""

    def __init__(self, conn: AttackConnection, session_id: int) -> None:
        self.conn = conn
        self.session_id = session_id
        self.moq = MoqSession(is_client=True, open_stream=self.open_stream)
        self.frames = 0
        self.subscribe_requests: list[int] = []
        self.accept_subscribes = False
        conn.attach_wt(self._on_data)

    def open_stream(self, is_unidirectional: bool) -> int:
        return self.conn.h3.create_webtransport_stream(
            self.session_id, is_unidirectional=is_unidirectional
        )

    def has_frames(self) -> bool:
        return self.frames > 0

    @property
    def close_text(self) -> str | None:
        """The relay's CLOSE_WEBTRANSPORT_SESSION ("closed by peer: CODE REASON"), if any."""
        capsules = self.conn.capsules.get(self.session_id)
        return None if capsules is None else close_reason(bytes(capsules))

    @property
    def close_code(self) -> int | None:
        text = self.close_text
        if text is None:
            return None
        parts = text.removeprefix("closed by peer:").split()
        return int(parts[0]) if parts and parts[0].isdigit() else None

    def _on_data(self, stream_id: int, data: bytes, end_stream: bool) -> None:
        self.moq.receive(stream_id, data, end_stream)
        self.pump()

    def pump(self) -> None:
        for event in self.moq.take_events():
            if isinstance(event, ev.FrameReceived):
                self.frames += 1
            elif isinstance(event, ev.SubscribeRequested):
                self.subscribe_requests.append(event.request_id)
                if self.accept_subscribes:
                    self.moq.accept_subscribe(event.request_id)
        self.flush()

    def flush(self) -> None:
        for t in self.moq.take_transmit():
            if isinstance(t, SendData):
                self.conn.send(t.stream_id, t.data, t.end_stream)
            elif isinstance(t, ResetStream | StopSending):
                self._abort(t)
            elif isinstance(t, CloseSession):
                pass  # an attacker does not say goodbye
        self.conn.flush()

    def _abort(self, t: ResetStream | StopSending) -> None:
        code = codes.to_http_code(t.error_code)
        try:
            if isinstance(t, ResetStream):
                self.conn.quic.reset_stream(t.stream_id, code)
            elif not stream_is_unidirectional(t.stream_id) or t.stream_id & 1:
                self.conn.quic.stop_stream(t.stream_id, code)
        except (ValueError, AssertionError):
            pass

    def raw_stream(self, is_unidirectional: bool) -> int:
        """A WebTransport stream of this session that MoqSession knows nothing about."""
        return self.open_stream(is_unidirectional)


async def open_session(
    target: Target, path: str = "/", *, timeout: float = 5.0
) -> tuple[AttackConnection, AttackSession | None, str | None]:
    """Connect and CONNECT: (connection, session if accepted, the :status)."""
    conn = await open_attack(target, timeout=timeout)
    stream_id, status = await request(conn, connect_headers(target, path), timeout)
    if status != "200":
        return conn, None, status
    return conn, AttackSession(conn, stream_id), status
