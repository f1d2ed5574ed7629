"""Attacks from inside (or around) accepted WebTransport sessions: moq-lite lengths,
stream and subscription counts, viewers that never read, connect storms, vanishing
clients."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable

from server.bench.adversary.attack_types import MAX_CONNECTIONS, AttackContext, AttackResult
from server.bench.adversary.client import (
    FRAME_HEADERS,
    MAX_VARINT,
    AttackConnection,
    count_still_served,
    frame_header,
    open_attack,
)
from server.bench.adversary.moq import AttackSession, open_session
from server.moq.messages import StreamType
from server.moq.wire import encode_message, encode_varint

SESSION_CLOSE_WAIT_S = 1.0


async def _each_session(
    ctx: AttackContext,
    duration_s: float,
    name: str,
    attack: Callable[[AttackSession], Awaitable[None]],
    *,
    pause_s: float = 0.1,
) -> AttackResult:
    """Open a session, run ``attack`` on it, wait for the relay to close it; repeat."""
    result = AttackResult(name)
    deadline = time.monotonic() + duration_s
    conns: list[AttackConnection] = []
    try:
        while time.monotonic() < deadline and result.connections < MAX_CONNECTIONS:
            try:
                conn, session, status = await open_session(ctx.target)
            except (ConnectionError, OSError, TimeoutError):
                result.notes.append("a connection attempt failed (refused or timed out)")
                await asyncio.sleep(0.05)
                continue
            conns.append(conn)
            first = result.connections == 0
            result.connections += 1
            result.statuses.append(status or "none")
            if session is None:
                await asyncio.sleep(pause_s)
                continue
            if first:
                result.crossed_at = time.monotonic()
            await attack(session)
            result.bytes_sent += conn.bytes_sent
            # The full wait even near the deadline: a session attacked just before it
            # would otherwise be counted open when the relay was about to close it.
            await conn.until_closed(SESSION_CLOSE_WAIT_S)
            result.record_close(conn, first=first)
            if session.close_code is not None:
                result.session_closes.append(session.close_code)
            await asyncio.sleep(pause_s)
    finally:
        await result.finish(conns)
    return result


# -- oversized moq-lite lengths ----------------------------------------------------


async def _huge_message(session: AttackSession) -> None:
    stream_id = session.raw_stream(False)
    data = encode_varint(StreamType.SUBSCRIBE) + encode_varint(MAX_VARINT) + bytes(64)
    session.conn.send(stream_id, data)
    session.conn.flush()


async def _huge_string(session: AttackSession) -> None:
    stream_id = session.raw_stream(False)
    body = encode_varint(MAX_VARINT) + b"prefix"  # announce interest: string prefix
    session.conn.send(stream_id, encode_varint(StreamType.ANNOUNCE) + encode_message(body))
    session.conn.flush()


async def moq_message_length(ctx: AttackContext, duration_s: float) -> AttackResult:
    return await _each_session(ctx, duration_s, "moq_message_length", _huge_message)


async def moq_string_length(ctx: AttackContext, duration_s: float) -> AttackResult:
    return await _each_session(ctx, duration_s, "moq_string_length", _huge_string)


async def moq_frame_size(ctx: AttackContext, duration_s: float) -> AttackResult:
    """An attacker publisher, subscribed to by an attacker viewer, whose group's first
    frame claims 2^62 - 1 bytes (open relay only: a publish needs no token there)."""
    counter = iter(range(MAX_CONNECTIONS))
    watchers: list[AttackConnection] = []

    async def attack(session: AttackSession) -> None:
        broadcast = f"evil{next(counter)}"
        session.accept_subscribes = True
        session.moq.publish(broadcast)
        session.flush()
        await asyncio.sleep(0.2)  # the announce reaches the relay before the subscribe
        watcher_conn, watcher, _ = await open_session(ctx.target)
        watchers.append(watcher_conn)
        if watcher is None:
            return
        watcher.moq.subscribe(broadcast, "video")
        watcher.flush()
        if not await session.conn.until(lambda: bool(session.subscribe_requests), 2.0):
            return
        stream_id = session.moq.open_group(session.subscribe_requests[-1], 0)
        session.flush()
        if stream_id is not None:
            session.conn.send(stream_id, encode_varint(MAX_VARINT) + bytes(1200))
            session.conn.flush()

    try:
        return await _each_session(ctx, duration_s, "moq_frame_size", attack)
    finally:
        for conn in watchers:
            conn.vanish()


# -- counts: streams and subscriptions --------------------------------------------


async def _many_streams(session: AttackSession) -> None:
    """Thousands of WebTransport streams left open: probes (bidi) and unfinished group
    headers (uni)."""
    for i in range(3000):
        if session.conn.is_closed:
            return
        if i % 2:
            stream_id = session.raw_stream(False)
            session.conn.send(stream_id, encode_varint(StreamType.PROBE))
        else:
            stream_id = session.raw_stream(True)
            session.conn.send(stream_id, b"\x00")
        if i % 100 == 99:
            session.conn.flush()
            await asyncio.sleep(0.01)
    session.conn.flush()


async def _many_subscriptions(session: AttackSession) -> None:
    for i in range(3000):
        if session.conn.is_closed or session.moq.closed:
            return
        session.moq.subscribe("game", "video")
        if i % 100 == 99:
            session.flush()
            await asyncio.sleep(0.01)
    session.flush()


async def many_streams(ctx: AttackContext, duration_s: float) -> AttackResult:
    return await _each_session(ctx, duration_s, "many_streams", _many_streams)


async def many_subscriptions(ctx: AttackContext, duration_s: float) -> AttackResult:
    return await _each_session(ctx, duration_s, "many_subscriptions", _many_subscriptions)


async def many_request_streams(ctx: AttackContext, duration_s: float) -> AttackResult:
    """Thousands of HTTP/3 request streams, each with the start of a HEADERS frame that
    never completes: no CONNECT is ever accepted on the connection."""
    result = AttackResult("many_request_streams")
    conn = await open_attack(ctx.target)
    result.connections = 1
    result.crossed_at = time.monotonic()
    deadline = time.monotonic() + duration_s
    try:
        for i in range(5000):
            if conn.is_closed or time.monotonic() > deadline:
                break
            stream_id = conn.open_bidi()
            conn.send(stream_id, frame_header(FRAME_HEADERS, 100) + b"\x00\x00")
            if i % 100 == 99:
                conn.flush()
                await asyncio.sleep(0.01)
        conn.flush()
        await conn.until_closed(max(0.0, deadline - time.monotonic()))
        result.bytes_sent = conn.bytes_sent
        result.record_close(conn, first=True)
        result.open_at_end = await count_still_served([conn])
    finally:
        conn.vanish()
        result.ended = time.monotonic()
    return result


# -- viewers that never read -------------------------------------------------------

STALLED_VIEWERS = 8
RESUME_S = 2.0  # after a stall the relay's loss recovery has backed off: give it time


async def stalled_viewers(
    ctx: AttackContext, duration_s: float, *, count: int = STALLED_VIEWERS
) -> AttackResult:
    """Viewers that subscribe, get frames, then stop reading for the whole attack (no
    ACK, no flow-control credit back); at the end they read again, and must find their
    connection alive (a RESET_STREAM past their stream credit would kill it)."""
    result = AttackResult("stalled_viewers")
    deadline = time.monotonic() + duration_s
    opened = await asyncio.gather(
        *(open_session(ctx.target) for _ in range(count)), return_exceptions=True
    )
    sessions: list[AttackSession] = []
    for item in opened:
        if isinstance(item, BaseException):
            result.notes.append(f"a viewer could not connect: {item!r}")
            continue
        conn, session, status = item
        result.connections += 1
        result.statuses.append(status or "none")
        if session is None:
            conn.vanish()
            continue
        session.moq.subscribe(ctx.broadcast, "video")
        session.flush()
        sessions.append(session)
    try:
        for session in sessions:
            await session.conn.until(session.has_frames, 3.0)
        result.crossed_at = time.monotonic()
        for session in sessions:
            session.conn.deaf = True
        await asyncio.sleep(max(0.0, deadline - time.monotonic()))
        before = [s.frames for s in sessions]
        for session in sessions:
            session.conn.deaf = False
            session.conn.quic.send_ping(0)
            session.conn.flush()
        await asyncio.sleep(RESUME_S)
        for session, frames in zip(sessions, before, strict=True):
            result.record_close(session.conn, first=False)
            if session.frames == frames and not session.conn.is_closed:
                result.notes.append(f"a resumed viewer got no frame within {RESUME_S:g} s")
        result.open_at_end = await count_still_served([s.conn for s in sessions])
    finally:
        for session in sessions:
            session.conn.vanish()
        result.ended = time.monotonic()
    return result


# -- connection churn --------------------------------------------------------------

STORM_CONCURRENCY = 4


async def _subscribed_session(ctx: AttackContext, result: AttackResult) -> AttackConnection | None:
    """One more connection with a session that subscribes to the video (when the CONNECT
    is accepted), noted in `result`; None when the relay did not answer."""
    result.connections += 1
    try:
        conn, session, status = await open_session(ctx.target, timeout=2.0)
    except (ConnectionError, OSError, TimeoutError):
        result.statuses.append("no answer")
        return None
    result.statuses.append(status or "none")
    if session is not None:
        session.moq.subscribe(ctx.broadcast, "video")
        session.flush()
    return conn


async def connect_storm(ctx: AttackContext, duration_s: float) -> AttackResult:
    """Connect, CONNECT, subscribe, close politely; as fast as 4 loops can."""
    result = AttackResult("connect_storm")
    deadline = time.monotonic() + duration_s

    async def loop() -> None:
        while time.monotonic() < deadline and result.connections < MAX_CONNECTIONS:
            conn = await _subscribed_session(ctx, result)
            if conn is None:
                continue
            result.record_close(conn, first=False)
            conn.close_politely()
            conn.transmit()
            conn.vanish()  # the socket: CONNECTION_CLOSE already left

    await asyncio.gather(*(loop() for _ in range(STORM_CONCURRENCY)))
    result.ended = time.monotonic()
    return result


async def vanishing_clients(ctx: AttackContext, duration_s: float) -> AttackResult:
    """Sessions that subscribe and then vanish without CONNECTION_CLOSE, ~20 a second;
    the relay only learns of it from its idle timeout."""
    result = AttackResult("vanishing_clients")
    deadline = time.monotonic() + duration_s
    while time.monotonic() < deadline and result.connections < MAX_CONNECTIONS // 4:
        conn = await _subscribed_session(ctx, result)
        if conn is None:
            continue
        await asyncio.sleep(0.05)
        conn.vanish()
    result.ended = time.monotonic()
    return result
