"""Attacks on the CONNECT itself: never finished, wrong, or carrying a bad token."""

from __future__ import annotations

import asyncio
import base64
import json
import secrets
import time
from urllib.parse import quote

from server.auth.keys import AuthKey
from server.auth.tokens import Claims, sign
from server.bench.adversary.attack_types import MAX_CONNECTIONS, AttackContext, AttackResult
from server.bench.adversary.client import (
    FRAME_HEADERS,
    AttackConnection,
    connect_headers,
    frame_header,
    open_attack,
    request,
)
from server.bench.adversary.moq import open_session

SLOW_CONNECTIONS = 16


async def slow_connect(ctx: AttackContext, duration_s: float) -> AttackResult:
    """Connections that never get a CONNECT accepted: half open a request stream and
    send the first bytes of its HEADERS frame, half send nothing at all after the
    handshake. Watched for ``duration_s`` after the last one is open: the relay must
    close every one."""
    result = AttackResult("slow_connect")
    conns: list[AttackConnection] = []
    try:
        for i in range(SLOW_CONNECTIONS):
            try:
                conn = await open_attack(ctx.target)
            except (ConnectionError, OSError, TimeoutError):
                result.notes.append("a connection attempt failed (refused or timed out)")
                continue
            conns.append(conn)
            result.connections += 1
            if i % 2 == 0:
                stream_id = conn.open_bidi()
                conn.send(stream_id, frame_header(FRAME_HEADERS, 300) + b"\x00\x00\xd1")
                conn.flush()
        result.crossed_at = time.monotonic()  # the connect deadline runs from here (about)
        # From here, not from the first handshake: sixteen handshakes took more than a
        # second on a loaded machine, and the last connections' deadlines then fell
        # after the watch had ended (a CI run saw no close at all).
        deadline = result.crossed_at + duration_s
        while time.monotonic() < deadline and not all(c.is_closed for c in conns):
            await asyncio.sleep(0.05)
        for conn in conns:
            result.record_close(conn, first=False)
        closes = [c.closed.at for c in conns if c.closed is not None]
        result.closed_at = max(closes) if len(closes) == len(conns) and closes else None
    finally:
        await result.finish(conns)
    return result


BAD_PATHS = ("game", "/../..", "/game/%00", "/%2e%2e/x", "/" + "a" * 8192)


async def wrong_connects(ctx: AttackContext, duration_s: float) -> AttackResult:
    """GET, CONNECT without :protocol, and CONNECTs whose :path is not a path (no leading
    slash, dot segments, NUL, 8 KiB); a new connection for each round."""
    result = AttackResult("wrong_connects")
    deadline = time.monotonic() + duration_s
    t = ctx.target
    requests = [
        connect_headers(t, "/", method=b"GET", protocol=None, offer=None),
        connect_headers(t, "/", protocol=None),
        *(connect_headers(t, path) for path in BAD_PATHS),
    ]
    conns: list[AttackConnection] = []
    try:
        while time.monotonic() < deadline and result.connections < MAX_CONNECTIONS:
            try:
                conn = await open_attack(t)
            except (ConnectionError, OSError, TimeoutError):
                result.notes.append("a connection attempt failed (refused or timed out)")
                await asyncio.sleep(0.05)
                continue
            conns.append(conn)
            result.connections += 1
            for headers in requests:
                if conn.is_closed:
                    break
                _, status = await request(conn, headers, timeout=1.0)
                result.statuses.append(status or "none")
            result.record_close(conn, first=False)
            await asyncio.sleep(0.1)
    finally:
        await result.finish(conns)
    return result


def _b64(data: dict[str, object]) -> str:
    raw = json.dumps(data, separators=(",", ":")).encode()
    return base64.urlsafe_b64encode(raw).rstrip(b"=").decode()


def bad_tokens(key: AuthKey, broadcast: str) -> dict[str, str]:
    """The tokens a stranger would try, by name."""
    now = time.time()
    claims = Claims.for_(broadcast, put=("",), get=("",))
    unsigned = _b64(claims.to_json())
    return {
        "expired": sign(key, Claims.for_(broadcast, put=("",), expires_in_s=1, now=now - 60)),
        "wrong_key": sign(AuthKey(secrets.token_bytes(32)), claims),
        "alg_none": f"{_b64({'alg': 'none', 'typ': 'JWT'})}.{unsigned}.",
        "wrong_path": sign(key, Claims.for_("someone-else", put=("",), get=("",))),
    }


async def bad_token_attempts(ctx: AttackContext, duration_s: float) -> AttackResult:
    """Each bad token on its own connection, then a subscribe-only token that publishes
    the broadcast; rounds until the attack ends."""
    if ctx.auth_key is None:
        raise ValueError("bad_tokens needs an auth relay (AttackContext.auth_key)")
    result = AttackResult("bad_tokens")
    deadline = time.monotonic() + duration_s
    tokens = bad_tokens(ctx.auth_key, ctx.broadcast)
    watch_only = sign(ctx.auth_key, Claims.for_(ctx.broadcast, get=("",), expires_in_s=600))
    conns: list[AttackConnection] = []
    try:
        while time.monotonic() < deadline and result.connections < MAX_CONNECTIONS:
            for token in tokens.values():
                conn, _, status = await open_session(
                    ctx.target, f"/{ctx.broadcast}?jwt={quote(token)}"
                )
                conns.append(conn)
                result.connections += 1
                result.statuses.append(status or "none")
                await conn.until_closed(0.5)
                result.record_close(conn, first=False)
            conn, session, status = await open_session(ctx.target, f"/?jwt={quote(watch_only)}")
            conns.append(conn)
            result.connections += 1
            result.statuses.append(status or "none")
            if session is not None:
                session.moq.publish(ctx.broadcast)
                session.flush()
                await conn.until_closed(1.0)
                result.record_close(conn, first=False)
                if session.close_code is not None:
                    result.session_closes.append(session.close_code)
            await asyncio.sleep(0.1)
    finally:
        await result.finish(conns)
    return result
