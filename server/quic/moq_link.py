"""MoqLink: a sans-IO MoqSession bound to one WebTransport session.

The glue between server/moq (bytes in, events and transmits out) and
server/quic (aioquic). It feeds every received byte into the session, then
drains the session: events go to the owner's callback (which may issue more
commands), transmits go onto the wire. Nothing here knows what a relay, a
publisher or a viewer is; they are all owners of links.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

from server.moq.errors import ErrorCode
from server.moq.events import Event
from server.moq.limits import MoqLimits, TokenBucket
from server.moq.session import MoqSession
from server.moq.transmit import CloseSession, ResetStream, SendData, StopSending
from server.quic.client import connect
from server.quic.refusals import RateLimitedLog
from server.quic.session import WtRequest, WtSession

log = logging.getLogger(__name__)
# Protocol-error closes and over-rate peers, one process-wide limit: under attack
# every hostile session ends this way, and one WARNING each filled the disk.
warnings_log = RateLimitedLog(
    logger=log, summary="%d more moq session warnings (log lines suppressed)"
)

EventSink = Callable[["MoqLink", list[Event]], None]
# A pump that keeps producing events this many times in a row is a bug in an owner.
MAX_PUMP_ROUNDS = 64


class MoqLink:
    """The WtSessionHandler of a moq-lite session (either side)."""

    def __init__(
        self,
        wt: WtSession,
        request: WtRequest | None = None,
        *,
        on_events: EventSink | None = None,
        on_closed: Callable[[MoqLink, str], None] | None = None,
        limits: MoqLimits | None = None,
        after_input: Callable[[MoqLink], None] | None = None,
        ingress: TokenBucket | None = None,
    ) -> None:
        """``after_input`` replaces the default ``pump`` after received bytes: the
        relay drives many links from one RelayCore, which takes the events itself.
        ``ingress`` bounds the bytes per second the peer may send: past it the session
        is closed (LIMIT_EXCEEDED) before the bytes are parsed."""
        self.wt = wt
        self.request = request
        self.moq = MoqSession(
            is_client=wt.is_client,
            open_stream=wt.open_stream,
            can_open_stream=wt.can_open_stream,
            limits=limits,
        )
        self.on_events = on_events
        self.on_closed_callback = on_closed
        self.closed_reason: str | None = None
        # The code of the close this side sent (None: the peer closed, or still open).
        self.local_close_code: int | None = None
        self._closed = asyncio.Event()
        self._after_input = after_input or MoqLink.pump
        self._ingress = ingress

    @property
    def closed(self) -> bool:
        return self.closed_reason is not None

    @property
    def remote(self) -> str:
        host, port = self.wt.remote_address
        return f"{host}:{port}"

    # -- WtSessionHandler ------------------------------------------------------

    def on_stream_data(self, stream_id: int, data: bytes, end_stream: bool) -> None:
        if self._ingress is not None and not self._ingress.take(len(data), time.monotonic()):
            if not self.moq.closed:
                warnings_log.warning(
                    "moq session %s: receive rate over its limit; closing", self.remote
                )
                self.close(ErrorCode.LIMIT_EXCEEDED, "receive rate over limit")
            return
        self.moq.receive(stream_id, data, end_stream)
        self._after_input(self)

    def on_stream_reset(self, stream_id: int, code: int) -> None:
        self.moq.stream_reset(stream_id, code)
        self._after_input(self)

    def on_closed(self, reason: str) -> None:
        if self.closed_reason is not None:
            return
        self.closed_reason = reason or "closed"
        self._closed.set()
        if self.on_closed_callback is not None:
            self.on_closed_callback(self, self.closed_reason)

    # -- draining ----------------------------------------------------------------

    def pump(self) -> None:
        """Hand pending events to the owner (repeatedly: its commands may raise more),
        then put every pending transmit on the wire."""
        for _ in range(MAX_PUMP_ROUNDS):
            events = self.moq.take_events()
            if not events or self.on_events is None:
                break
            self.on_events(self, events)
        self.flush()

    def flush(self) -> None:
        for t in self.moq.take_transmit():
            if isinstance(t, SendData):
                self.wt.send(t.stream_id, t.data, t.end_stream)
            elif isinstance(t, ResetStream):
                self.wt.reset_stream(t.stream_id, t.error_code)
            elif isinstance(t, StopSending):
                self.wt.stop_sending(t.stream_id, t.error_code)
            elif isinstance(t, CloseSession):
                # A clean close (code 0) is routine; a protocol error is worth a warning.
                # UNAUTHORIZED was logged, rate-limited, by whoever refused: a flood of
                # refused sessions must not write one line each here.
                level = logging.WARNING
                if t.error_code == 0:
                    level = logging.INFO
                elif t.error_code == ErrorCode.UNAUTHORIZED:
                    level = logging.DEBUG
                line = ("moq session %s closed: %s (code %d)", self.remote, t.reason, t.error_code)
                if level == logging.WARNING:
                    warnings_log.warning(*line)
                else:
                    log.log(level, *line)
                if self.local_close_code is None:
                    self.local_close_code = t.error_code
                self.wt.close(t.error_code, t.reason)

    def close(self, code: int = 0, reason: str = "") -> None:
        self.moq.close(code, reason)
        self.flush()
        self.wt.close(code, reason)

    async def wait_closed(self) -> str:
        await self._closed.wait()
        return self.closed_reason or "closed"


async def connect_moq(
    url: str,
    *,
    on_events: EventSink | None = None,
    on_closed: Callable[[MoqLink, str], None] | None = None,
    cert_hash_hex: str | None = None,
    verify: bool = True,
    limits: MoqLimits | None = None,
    timeout: float = 10.0,
    token: str | None = None,
) -> MoqLink:
    """Open a moq-lite-03 session to a relay over WebTransport.

    An ``http://`` URL fetches the relay's certificate hash from the same port
    over TCP and pins it, as the browser player does. ``token`` (a JWT) is added to
    the URL as ``?jwt=``, where moq-relay and our relay read it.
    """
    if token is not None:
        url = with_token(url, token)
    links: list[MoqLink] = []

    def factory(wt: WtSession, request: WtRequest) -> MoqLink:
        link = MoqLink(wt, request, on_events=on_events, on_closed=on_closed, limits=limits)
        links.append(link)
        return link

    await connect(
        url,
        factory=factory,
        cert_hash_hex=cert_hash_hex,
        verify=verify,
        timeout=timeout,
    )
    return links[0]


def with_token(url: str, token: str) -> str:
    """``url`` with ``jwt=<token>`` in its query (replacing one already there)."""
    parts = urlsplit(url)
    query = [(k, v) for k, v in parse_qsl(parts.query, keep_blank_values=True) if k != "jwt"]
    query.append(("jwt", token))
    return urlunsplit(parts._replace(query=urlencode(query)))
