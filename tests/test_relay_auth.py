"""Tokens against a real relay over QUIC: who may publish, watch and send inputs, and
what a flood of refused attempts leaves behind (nothing)."""

from __future__ import annotations

import asyncio
import functools
import gc
import logging
import time
import tracemalloc
from pathlib import Path
from typing import Any

import pytest
from aioquic.quic.connection import QuicConnection

from server.auth import Authorizer, Claims, generate_key, load_key, sign
from server.auth.keys import AuthKey
from server.auth.minting import session_tokens
from server.moq import events as ev
from server.moq.errors import ErrorCode
from server.moq.limits import IngressLimits
from server.quic.certs import CertBundle, generate_cert
from server.quic.client import WtConnectError
from server.quic.guard import GuardLimits
from server.relay.relay import Relay
from tests.relay_harness import Peer, Publisher, Viewer, run_bounded, running_relay, until


@pytest.fixture(scope="module")
def cert(tmp_path_factory: pytest.TempPathFactory) -> CertBundle:
    return generate_cert(directory=tmp_path_factory.mktemp("cert"))


@pytest.fixture(scope="module")
def key(tmp_path_factory: pytest.TempPathFactory) -> AuthKey:
    path = tmp_path_factory.mktemp("key") / "relay.jwk"
    generate_key(path)
    return load_key(path)


run = functools.partial(run_bounded, timeout=30.0)


def unauthorized(relay: Relay, reason: str) -> float:
    value = relay.registry.get_sample_value(
        "upcast_relay_sessions_unauthorized_total", {"reason": reason}
    )
    return value or 0.0


async def closed(peer: Peer) -> str:
    await peer.until(lambda: peer.moq_link.closed)
    return peer.moq_link.closed_reason or ""


def test_publish_without_or_with_bad_token_gets_401(cert: CertBundle, key: AuthKey) -> None:
    async def main() -> None:
        async with running_relay(cert, authorizer=Authorizer(key, public_viewers=False)) as relay:
            with pytest.raises(WtConnectError, match="status 401"):
                await Publisher().start(relay.port, cert)
            with pytest.raises(WtConnectError, match="status 401"):
                await Publisher().start(relay.port, cert, token="not.a.token")
            expired = sign(key, Claims.for_("game", put=("",), expires_in_s=1, now=time.time() - 5))
            with pytest.raises(WtConnectError, match="status 401"):
                await Publisher().start(relay.port, cert, token=expired)
            assert unauthorized(relay, "missing_token") == 1
            assert unauthorized(relay, "invalid_token") == 1
            assert unauthorized(relay, "expired_token") == 1
            assert not relay.links and not relay.core.broadcasts

    run(main())


def test_token_on_a_path_outside_its_root_gets_403(cert: CertBundle, key: AuthKey) -> None:
    async def main() -> None:
        async with running_relay(cert, authorizer=Authorizer(key)) as relay:
            token = session_tokens(key, "game").publisher
            link_url = f"https://localhost:{relay.port}/other"
            from server.quic.moq_link import connect_moq

            with pytest.raises(WtConnectError, match="status 403"):
                await connect_moq(link_url, cert_hash_hex=cert.sha256_hex, token=token)
            assert unauthorized(relay, "forbidden_path") == 1

    run(main())


def test_publisher_token_streams_and_player_token_watches(cert: CertBundle, key: AuthKey) -> None:
    async def main() -> None:
        tokens = session_tokens(key, "game")
        async with running_relay(cert, authorizer=Authorizer(key, public_viewers=False)) as relay:
            publisher = Publisher()
            await publisher.start(relay.port, cert, tokens.publisher)
            await until(lambda: "game" in relay.core.broadcasts)
            viewer = Viewer()
            await viewer.connect(relay.port, cert, tokens.player)
            await viewer.subscribed()
            publisher.send_frame(500, new_group=True)
            await viewer.until_count(1)

    run(main())


def test_viewer_token_that_announces_the_broadcast_is_closed(
    cert: CertBundle, key: AuthKey, caplog: pytest.LogCaptureFixture
) -> None:
    async def main() -> None:
        tokens = session_tokens(key, "game")
        async with running_relay(cert, authorizer=Authorizer(key)) as relay:
            publisher = Publisher()
            await publisher.start(relay.port, cert, tokens.publisher)
            await until(lambda: "game" in relay.core.broadcasts)
            owner = relay.core.broadcasts["game"]
            intruder = Publisher()  # a player's token: put only on game/input
            await intruder.start(relay.port, cert, tokens.player)
            reason = await closed(intruder)
            assert f"{int(ErrorCode.UNAUTHORIZED)} not allowed to publish" in reason
            assert relay.core.broadcasts == {"game": owner}  # not taken over
            assert unauthorized(relay, "publish_denied") == 1
            await until(lambda: len(relay.links) == 1)

    caplog.set_level(logging.WARNING)
    run(main())
    assert any("publish 'game' not allowed by token" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("public_viewers", [True, False])
def test_anonymous_viewer_watches_only_when_viewers_are_public(
    cert: CertBundle, key: AuthKey, public_viewers: bool
) -> None:
    async def main() -> None:
        tokens = session_tokens(key, "game")
        authorizer = Authorizer(key, public_viewers=public_viewers)
        async with running_relay(cert, authorizer=authorizer) as relay:
            publisher = Publisher()
            await publisher.start(relay.port, cert, tokens.publisher)
            await until(lambda: "game" in relay.core.broadcasts)
            viewer = Viewer()
            if not public_viewers:
                with pytest.raises(WtConnectError, match="status 401"):
                    await viewer.connect(relay.port, cert)
                return
            await viewer.connect(relay.port, cert)
            await viewer.subscribed()
            for i in range(5):
                publisher.send_frame(800, new_group=i == 0)
            await viewer.until_count(5)

    run(main())


def test_input_needs_put_on_broadcast_input(cert: CertBundle, key: AuthKey) -> None:
    async def main() -> None:
        tokens = session_tokens(key, "game")
        async with running_relay(cert, authorizer=Authorizer(key)) as relay:
            publisher = Publisher()
            await publisher.start(relay.port, cert, tokens.publisher)
            await until(lambda: "game" in relay.core.broadcasts)
            anonymous = Publisher("game/input/anon")
            await anonymous.start(relay.port, cert)
            await closed(anonymous)
            assert "game/input/anon" not in relay.core.broadcasts
            other = sign(key, Claims.for_("other", put=("input",), get=("",)))
            stranger = Publisher("game/input/stranger")
            await stranger.start(relay.port, cert, other)
            await closed(stranger)
            player = Publisher("game/input/player")
            await player.start(relay.port, cert, tokens.player)
            await until(lambda: "game/input/player" in relay.core.broadcasts)
            assert not player.moq_link.closed
            assert unauthorized(relay, "publish_denied") == 2

    run(main())


def test_subscribe_outside_get_is_refused_and_unannounced(cert: CertBundle, key: AuthKey) -> None:
    async def main() -> None:
        tokens = session_tokens(key, "game")
        other = sign(key, Claims.for_("other", get=("",)))
        async with running_relay(cert, authorizer=Authorizer(key)) as relay:
            publisher = Publisher()
            await publisher.start(relay.port, cert, tokens.publisher)
            await until(lambda: "game" in relay.core.broadcasts)
            viewer = Viewer()
            await viewer.connect(relay.port, cert, other)
            viewer.request_announces("")
            subscription = viewer.subscribe("game", "video")
            await viewer.until(lambda: viewer.subscription_ended(subscription))
            refused = viewer.closed_subscription(subscription)
            assert refused is not None and not refused.accepted
            assert refused.error_code == ErrorCode.UNAUTHORIZED
            assert not [e for e in viewer.of(ev.AnnounceReceived) if e.path == "game"]
            assert not viewer.moq_link.closed  # one request refused, the session goes on
            assert publisher.subscribe_count == 0  # nothing was asked upstream

    run(main())


def test_upload_over_the_viewer_rate_closes_that_session(cert: CertBundle, key: AuthKey) -> None:
    async def main() -> None:
        limits = IngressLimits(viewer_bytes_per_s=1024, viewer_burst_bytes=4096)
        async with running_relay(cert, authorizer=Authorizer(key), ingress=limits) as relay:
            publisher = Publisher()
            await publisher.start(relay.port, cert, session_tokens(key, "game").publisher)
            publisher.moq_link.moq.request_announces("p" * 8000)  # the same 8 KB, within its bound
            publisher.moq_link.flush()
            viewer = Viewer()
            await viewer.connect(relay.port, cert)
            viewer.request_announces("x" * 8000)  # a valid message, twice the burst
            reason = await closed(viewer)
            assert f"{int(ErrorCode.LIMIT_EXCEEDED)} receive rate over limit" in reason
            await until(lambda: len(relay.links) == 1)
            assert not publisher.moq_link.closed  # publishers have their own, larger bound

    run(main())


def live_quic_connections() -> int:
    """QuicConnection objects alive in this process, both sides (after a collection)."""
    gc.collect()
    return sum(1 for o in gc.get_objects() if isinstance(o, QuicConnection))


async def settled(relay: Relay, elsewhere: int) -> None:
    """Wait until only the publisher's connection is left: in the relay's tables and as
    objects (a closed connection lives on until its keepalive timer has fired once).
    ``elsewhere``: QuicConnection objects alive before this relay started (earlier tests
    in the same process may still hold some)."""
    try:
        await until(lambda: relay_tables(relay)["quic_connections"] == 1, timeout=15)
        await until(lambda: live_quic_connections() == elsewhere + 2, timeout=15, step=0.5)
    except TimeoutError:
        raise AssertionError(
            f"not settled: {relay_tables(relay)}, {live_quic_connections()} QuicConnection"
        ) from None


def relay_tables(relay: Relay) -> dict[str, int]:
    """Every per-connection table of the relay, the core and the QUIC server."""
    core = relay.core
    return {
        "links": len(relay.links),
        # Entries of sessions that are gone (live ones appear at the first stats tick).
        "conn_stats_of_closed": len(relay._conn_stats.keys() - relay.links.keys()),
        "counted_of_closed": len(relay._counted.keys() - relay.links.keys()),
        "core_conns": len(core._conns),
        "owners": len(core._owners),
        "tracks": len(core._tracks),
        "quic_connections": relay.quic_connections,
    }


async def refused_connects(relay: Relay, cert: CertBundle, count: int, token: str | None) -> int:
    refused = 0
    gate = asyncio.Semaphore(16)

    async def one() -> None:
        nonlocal refused
        async with gate:
            try:
                await Publisher().start(relay.port, cert, token)
            except WtConnectError as exc:
                assert "status 401" in str(exc)
                refused += 1

    await asyncio.gather(*(one() for _ in range(count)))
    return refused


async def forbidden_announces(relay: Relay, cert: CertBundle, count: int, token: str) -> None:
    gate = asyncio.Semaphore(8)

    async def one(i: int) -> None:
        async with gate:
            intruder = Publisher(f"game/forbidden/{i}")
            await intruder.start(relay.port, cert, token)
            await closed(intruder)

    await asyncio.gather(*(one(i) for i in range(count)))


def test_many_refused_attempts_cost_no_lasting_memory(
    cert: CertBundle, key: AuthKey, caplog: pytest.LogCaptureFixture
) -> None:
    """300 CONNECTs without a valid token and 50 sessions whose token forbids what they
    announce: all refused, all counted, log lines rate-limited, and afterwards every
    per-connection table is back to its size before and traced memory did not grow."""
    attempts, announces = 300, 50
    player = session_tokens(key, "game").player
    found: dict[str, Any] = {}

    async def main() -> None:
        elsewhere = live_quic_connections()
        authorizer = Authorizer(key, public_viewers=False)
        # This flood is about what refused sessions leave behind, not about how fast one
        # address may connect: admission (tests/test_quic_guard.py) is set out of the way.
        fast = GuardLimits(
            new_connections_per_s_per_source=1e6, new_connections_burst_per_source=1e6
        )
        async with running_relay(cert, authorizer=authorizer, guard=fast) as relay:
            publisher = Publisher()
            await publisher.start(relay.port, cert, session_tokens(key, "game").publisher)
            await until(lambda: "game" in relay.core.broadcasts)
            # Warm up every code path once (imports, caches), then measure.
            await refused_connects(relay, cert, 5, None)
            await forbidden_announces(relay, cert, 5, player)
            await settled(relay, elsewhere)
            before = relay_tables(relay)
            start = tracemalloc.take_snapshot()
            t0 = time.monotonic()
            refused = await refused_connects(relay, cert, attempts // 2, None)
            refused += await refused_connects(relay, cert, attempts // 2, "bad.token.here")
            await forbidden_announces(relay, cert, announces, player)
            found["elapsed"] = time.monotonic() - t0
            await settled(relay, elsewhere)
            end = tracemalloc.take_snapshot()
            found["refused"] = refused
            found["tables"] = (before, relay_tables(relay))
            found["grown"] = grown_bytes(start, end)
            found["missing"] = unauthorized(relay, "missing_token")
            found["invalid"] = unauthorized(relay, "invalid_token")
            found["denied"] = unauthorized(relay, "publish_denied")
            assert relay.core.broadcasts.keys() == {"game"}
            assert not publisher.moq_link.closed

    caplog.set_level(logging.WARNING)
    tracemalloc.start(1)
    try:
        run(main(), timeout=240)
    finally:
        tracemalloc.stop()
    print(f"\nrefused-attempt flood: {found}")
    assert found["refused"] == attempts
    assert (found["missing"], found["invalid"]) == (attempts // 2 + 5, attempts // 2)
    assert found["denied"] == announces + 5
    before, after = found["tables"]
    assert after == before
    # One QUIC connection holds ~30 kB: 350 leaked would be 10 MB. What may remain is
    # the size of the server's connection-id dict after its peak (dicts never shrink).
    assert found["grown"] < 256 * 1024, found["grown"]
    lines = [r.getMessage() for r in caplog.records if "refused" in r.getMessage()]
    one_line_each = [m for m in lines if m.startswith("refused WebTransport session from")]
    summaries = [m for m in lines if "(log lines suppressed)" in m]
    assert one_line_each and summaries
    budget = 10 * (int(found["elapsed"]) + 2)  # 10 lines/s per log, plus partial seconds
    assert len(one_line_each) <= budget < attempts


def grown_bytes(start: tracemalloc.Snapshot, end: tracemalloc.Snapshot) -> int:
    """Growth of memory allocated by the relay, the QUIC stack and the auth code."""
    keep = [
        tracemalloc.Filter(True, f"*{Path('server')}/*"),
        tracemalloc.Filter(True, "*/aioquic/*"),
        tracemalloc.Filter(True, "*/jwt/*"),
    ]
    diff = end.filter_traces(keep).compare_to(start.filter_traces(keep), "filename")
    return sum(stat.size_diff for stat in diff)
