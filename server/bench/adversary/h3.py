"""Attacks below WebTransport: HTTP/3 frames, QPACK and unidirectional stream types.

Every flood writes a header whose length field claims far more than any limit (or a
stream type the relay must ignore), then keeps the stream fed until the relay closes the
connection, reconnecting while the attack lasts (bounded in connections and bytes).
"""

from __future__ import annotations

import asyncio
import random
import time
from collections.abc import Callable

from server.bench.adversary.attack_types import (
    MAX_CONNECTIONS,
    MAX_FLOOD_BYTES,
    AttackContext,
    AttackResult,
)
from server.bench.adversary.client import (
    FRAME_HEADERS,
    FRAME_SETTINGS,
    GREASE_TYPE,
    MAX_VARINT,
    UNI_CONTROL,
    UNI_QPACK_DECODER,
    UNI_QPACK_ENCODER,
    AttackConnection,
    frame,
    frame_header,
    open_attack,
    pump_bytes,
)
from server.bench.adversary.moq import open_session

CHUNK = bytes(1200)
GREASE_FRAME = 0x1F * 5 + 0x21  # a reserved frame type: a receiver must skip it
CLOSE_WAIT_S = 1.5  # after the attack, how long the last connection may take to be closed

Prepare = Callable[[AttackConnection], int]
"""Opens the attacked stream, writes the offending preamble, returns the stream id."""


def _headers_flood(conn: AttackConnection) -> int:
    stream_id = conn.open_bidi()
    conn.send(stream_id, frame_header(FRAME_HEADERS, MAX_VARINT))
    return stream_id


def _unknown_frame_flood(conn: AttackConnection) -> int:
    stream_id = conn.open_bidi()
    conn.send(stream_id, frame_header(GREASE_FRAME, MAX_VARINT))
    return stream_id


def _settings_flood(conn: AttackConnection) -> int:
    """h3=False: the attacker's own control stream, whose first frame is a SETTINGS
    frame that never ends."""
    stream_id = conn.open_uni(UNI_CONTROL)
    conn.send(stream_id, frame_header(FRAME_SETTINGS, MAX_VARINT))
    return stream_id


def _control_unknown_flood(conn: AttackConnection) -> int:
    """After aioquic's valid SETTINGS: an unknown frame on the control stream that never
    ends."""
    stream_id = conn.h3.control_stream_id
    conn.send(stream_id, frame_header(GREASE_FRAME, MAX_VARINT))
    return stream_id


def _unknown_uni_flood(conn: AttackConnection) -> int:
    return conn.open_uni(GREASE_TYPE)


def _qpack_encoder_flood(conn: AttackConnection) -> int:
    """Valid but useless QPACK encoder instructions (Set Dynamic Table Capacity 0)."""
    return conn.h3.encoder_stream_id


async def flood(
    ctx: AttackContext,
    duration_s: float,
    name: str,
    prepare: Prepare,
    *,
    h3: bool = True,
    chunk: bytes = CHUNK,
) -> AttackResult:
    result = AttackResult(name)
    deadline = time.monotonic() + duration_s
    conns: list[AttackConnection] = []
    try:
        while time.monotonic() < deadline and result.connections < MAX_CONNECTIONS:
            try:
                conn = await open_attack(ctx.target, h3=h3)
            except (ConnectionError, OSError, TimeoutError):
                result.notes.append("a connection attempt failed (refused or timed out)")
                await asyncio.sleep(0.05)
                continue
            conns.append(conn)
            first = result.connections == 0
            result.connections += 1
            stream_id = prepare(conn)
            conn.flush()
            if first:
                result.crossed_at = time.monotonic()

                def log_sent(n: int) -> None:
                    result.sent_log.append((time.monotonic(), n))

            sent = await pump_bytes(
                conn,
                stream_id,
                chunk,
                deadline=deadline,
                max_bytes=MAX_FLOOD_BYTES,
                on_sent=log_sent if first else None,
            )
            result.bytes_sent += sent
            if not conn.is_closed:
                await conn.until_closed(max(0.0, deadline - time.monotonic()))
            result.record_close(conn, first=first)
        if conns and not conns[-1].is_closed:
            await conns[-1].until_closed(CLOSE_WAIT_S)
            result.record_close(conns[-1], first=len(conns) == 1)
    finally:
        await result.finish(conns)
    return result


async def headers_flood(ctx: AttackContext, duration_s: float) -> AttackResult:
    return await flood(ctx, duration_s, "headers_flood", _headers_flood)


async def unknown_frame_flood(ctx: AttackContext, duration_s: float) -> AttackResult:
    return await flood(ctx, duration_s, "unknown_frame_flood", _unknown_frame_flood)


async def settings_flood(ctx: AttackContext, duration_s: float) -> AttackResult:
    return await flood(ctx, duration_s, "settings_flood", _settings_flood, h3=False)


async def control_unknown_flood(ctx: AttackContext, duration_s: float) -> AttackResult:
    return await flood(ctx, duration_s, "control_unknown_flood", _control_unknown_flood)


async def unknown_uni_flood(ctx: AttackContext, duration_s: float) -> AttackResult:
    return await flood(ctx, duration_s, "unknown_uni_flood", _unknown_uni_flood)


async def qpack_encoder_flood(ctx: AttackContext, duration_s: float) -> AttackResult:
    return await flood(
        ctx, duration_s, "qpack_encoder_flood", _qpack_encoder_flood, chunk=b"\x20" * 1200
    )


# -- garbage: finite random bytes on one stream of each kind ------------------------

STREAM_KINDS = (
    "request",
    "control",
    "unknown_uni",
    "qpack_encoder",
    "qpack_decoder",
    "wt_uni",
    "wt_bidi",
)


async def send_garbage(ctx: AttackContext, kind: str, data: bytes) -> AttackConnection:
    """One connection that writes ``data`` on a stream of ``kind`` (a WebTransport kind
    inside an accepted session) and flushes. The caller closes or watches it."""
    if kind in ("wt_uni", "wt_bidi"):
        conn, session, status = await open_session(ctx.target)
        if session is None:
            raise ConnectionError(f"CONNECT refused: {status}")
        stream_id = session.raw_stream(kind == "wt_uni")
    else:
        conn = await open_attack(ctx.target)
        if kind == "request":
            stream_id = conn.open_bidi()
        elif kind == "control":
            stream_id = conn.h3.control_stream_id
        elif kind == "unknown_uni":
            stream_id = conn.open_uni(GREASE_TYPE)
        elif kind == "qpack_encoder":
            stream_id = conn.h3.encoder_stream_id
        elif kind == "qpack_decoder":
            stream_id = conn.h3.decoder_stream_id
        else:
            raise ValueError(f"unknown stream kind {kind!r}; one of {STREAM_KINDS}")
    conn.send(stream_id, data)
    conn.flush()
    return conn


async def garbage_streams(ctx: AttackContext, duration_s: float) -> AttackResult:
    """Random bytes (seeded) on every stream kind in turn, one connection each."""
    result = AttackResult("garbage_streams")
    rng = random.Random(1234)
    deadline = time.monotonic() + duration_s
    conns: list[AttackConnection] = []
    try:
        while time.monotonic() < deadline and result.connections < MAX_CONNECTIONS:
            kind = STREAM_KINDS[result.connections % len(STREAM_KINDS)]
            data = rng.randbytes(rng.randint(1, 2000))
            try:
                conn = await send_garbage(ctx, kind, data)
            except (ConnectionError, OSError, TimeoutError):
                result.notes.append("a connection attempt failed (refused or timed out)")
                await asyncio.sleep(0.05)
                continue
            conns.append(conn)
            result.connections += 1
            result.bytes_sent += len(data)
            await asyncio.sleep(0.05)
        await asyncio.sleep(0.3)
        for conn in conns:
            result.record_close(conn, first=False)
    finally:
        await result.finish(conns)
    return result


# -- QPACK: a header block whose string length claims 2^62 ------------------------

# Required Insert Count 0, Base 0, then a literal field line with a literal name
# (0b0010_0NNN, N=7: the name length continues) whose length never ends sensibly.
HUGE_QPACK_STRING = b"\x00\x00" + b"\x27" + b"\xff" * 8 + b"\x7f" + b"name"


async def qpack_string_length(ctx: AttackContext, duration_s: float) -> AttackResult:
    """HEADERS frames of honest length whose QPACK string length is absurd, one per
    connection; each must be refused (aioquic closes with QPACK_DECOMPRESSION_FAILED)."""
    result = AttackResult("qpack_string_length")
    deadline = time.monotonic() + duration_s
    conns: list[AttackConnection] = []
    try:
        while time.monotonic() < deadline and result.connections < MAX_CONNECTIONS:
            conn = await open_attack(ctx.target)
            conns.append(conn)
            first = result.connections == 0
            result.connections += 1
            stream_id = conn.open_bidi()
            conn.send(stream_id, frame(FRAME_HEADERS, HUGE_QPACK_STRING))
            conn.flush()
            if first:
                result.crossed_at = time.monotonic()
            # The full wait even near the deadline (see adversary_sessions._each_session).
            await conn.until_closed(1.0)
            result.bytes_sent += conn.bytes_sent
            result.record_close(conn, first=first)
            await asyncio.sleep(0.1)
    finally:
        await result.finish(conns)
    return result


__all__ = [
    "STREAM_KINDS",
    "UNI_QPACK_DECODER",
    "UNI_QPACK_ENCODER",
    "control_unknown_flood",
    "flood",
    "garbage_streams",
    "headers_flood",
    "qpack_encoder_flood",
    "qpack_string_length",
    "send_garbage",
    "settings_flood",
    "unknown_frame_flood",
    "unknown_uni_flood",
]
