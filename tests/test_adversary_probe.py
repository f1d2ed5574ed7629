"""The adversary's "does the relay still serve this connection" probe.

``bench adversary`` and the relay's adversarial tests report an attacker the relay left
open as a failure. aioquic sends its CONNECTION_CLOSE once and then ignores the peer, so
"our side saw no close" is not "the relay kept it": when that one datagram is lost the
relay has let go while we would wait for our idle timeout (a flaky CI failure came from
exactly that). The probe asks the relay with a PING instead.
"""

from __future__ import annotations

import asyncio

import pytest

from server.bench.adversary.client import MAX_VARINT, Target, count_still_served
from server.bench.adversary.moq import open_session
from server.moq.messages import StreamType
from server.moq.wire import encode_varint
from server.quic.certs import CertBundle, generate_cert
from tests.relay_harness import run_bounded, running_relay


@pytest.fixture(scope="module")
def cert(tmp_path_factory: pytest.TempPathFactory) -> CertBundle:
    return generate_cert(directory=tmp_path_factory.mktemp("cert"))


def test_a_live_session_answers_the_probe(cert: CertBundle) -> None:
    async def main() -> None:
        async with running_relay(cert) as relay:
            target = Target("127.0.0.1", relay.port, cert.sha256_hex)
            conn, session, status = await open_session(target)
            try:
                assert status == "200" and session is not None
                assert await conn.relay_still_serving()
                assert await count_still_served([conn]) == 1
            finally:
                conn.vanish()

    run_bounded(main())


def test_a_close_we_never_heard_still_counts_as_closed(cert: CertBundle) -> None:
    """The relay closes the session while we drop every datagram (its one
    CONNECTION_CLOSE included): our connection still looks open, the probe says no."""

    async def main() -> None:
        async with running_relay(cert) as relay:
            target = Target("127.0.0.1", relay.port, cert.sha256_hex)
            conn, session, _ = await open_session(target)
            try:
                assert session is not None
                conn.deaf = True
                # A moq-lite message claiming 2^62 - 1 bytes: the relay closes the session.
                stream_id = session.raw_stream(False)
                huge = encode_varint(StreamType.SUBSCRIBE) + encode_varint(MAX_VARINT)
                conn.send(stream_id, huge + bytes(64))
                conn.flush()
                await asyncio.sleep(0.5)
                conn.deaf = False
                assert not conn.is_closed  # what the old check looked at
                assert not await conn.relay_still_serving()
                assert await count_still_served([conn]) == 0
            finally:
                conn.vanish()

    run_bounded(main())
