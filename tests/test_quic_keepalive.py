"""Keepalive and idle timeout: a quiet live session stays up, a vanished peer is noticed."""

from __future__ import annotations

import asyncio

import pytest

from server.quic import CertBundle, Endpoints, client, connection, generate_cert, serve
from tests.test_quic_wt import HOST, Recorder, echo_factory, run

IDLE_S = 1.0


@pytest.fixture(scope="module")
def cert(tmp_path_factory: pytest.TempPathFactory) -> CertBundle:
    return generate_cert(directory=tmp_path_factory.mktemp("cert"))


@pytest.fixture(autouse=True)
def fast_keepalive(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(connection, "KEEPALIVE_S", 0.25)
    monkeypatch.setattr(client, "IDLE_TIMEOUT_S", IDLE_S)


async def _client(port: int, cert: CertBundle) -> Recorder:
    holder: list[Recorder] = []

    def factory(session: object, request: object) -> Recorder:
        holder.append(Recorder(session, request))  # type: ignore[arg-type]
        return holder[0]

    await client.connect(
        f"https://{HOST}:{port}/game", factory=factory, cert_hash_hex=cert.sha256_hex
    )
    return holder[0]


def test_quiet_session_outlives_the_idle_timeout(cert: CertBundle) -> None:
    async def body() -> None:
        ep: Endpoints = await serve(echo_factory, cert, host="::", port=0, idle_timeout=IDLE_S)
        try:
            rec = await _client(ep.port, cert)
            await asyncio.sleep(3 * IDLE_S)  # nothing sent by either side but PINGs
            assert not rec.closed, rec.closed
            rec.session.close()
        finally:
            await ep.close()

    run(body())


def test_vanished_server_is_noticed_within_the_idle_timeout(cert: CertBundle) -> None:
    async def body() -> None:
        ep: Endpoints = await serve(echo_factory, cert, host="::", port=0, idle_timeout=IDLE_S)
        rec = await _client(ep.port, cert)
        # The relay process is killed: no CONNECTION_CLOSE, its socket just goes away.
        ep.wt._transport.close()  # type: ignore[attr-defined]
        t0 = asyncio.get_running_loop().time()
        await rec.until(lambda: bool(rec.closed), timeout=5 * IDLE_S)
        assert asyncio.get_running_loop().time() - t0 < 3 * IDLE_S
        ep.http.close()

    run(body())
