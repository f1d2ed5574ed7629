"""Secrets (``?jwt=`` tokens, keys, passwords) never reach a log line or an error message."""

from __future__ import annotations

import asyncio
import io
import json
import logging
import socket
import sys
from typing import Any
from urllib.parse import urlencode

import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from server.auth.keys import AuthKey
from server.auth.tokens import Claims, sign
from server.ops.logging_setup import JsonLineFormatter, RedactingFilter, install_redaction
from server.ops.redact import REDACTED, redact_text, redact_url
from server.quic import CertBundle, WtConnectError, WtRequest, WtSession, connect, generate_cert
from server.quic import serve as serve_wt
from server.quic.session import Refusal

SECRET = "SECRETtoken123"
JWT = sign(AuthKey(b"k" * 32), Claims.for_("game", put=("",)))


# -- redact_url ------------------------------------------------------------------


def test_url_query_secrets_are_masked_and_the_rest_kept() -> None:
    url = f"https://relay.example:4443/game?x=1&jwt={SECRET}&Access-Token={SECRET}#top"
    shown = redact_url(url)
    assert SECRET not in shown
    assert shown == (
        f"https://relay.example:4443/game?x=1&jwt={REDACTED}&Access-Token={REDACTED}#top"
    )


def test_url_without_secrets_is_unchanged() -> None:
    for url in ("http://localhost:4443/", "https://h/a/b?keyframe=3&x=%20y", "not a url"):
        assert redact_url(url) == url


def test_url_userinfo_password_is_masked() -> None:
    assert redact_url(f"https://alice:{SECRET}@h:1/p") == f"https://alice:{REDACTED}@h:1/p"


def test_url_with_a_bad_port_is_still_masked() -> None:
    # urlsplit raises on the port only when asked; the text pass still applies.
    shown = redact_url(f"https://h:99999999/?jwt={SECRET}")
    assert SECRET not in shown


@given(
    value=st.text(alphabet=st.characters(codec="utf-8"), min_size=6, max_size=40),
    name=st.sampled_from(["jwt", "token", "key", "secret", "password", "access_token", "API-KEY"]),
    before=st.booleans(),
)
def test_any_secret_value_in_a_query_never_appears(value: str, name: str, before: bool) -> None:
    assume(value.strip() and REDACTED not in value and value not in "https://relay:4443/g")
    pairs = [("x", "1"), (name, value)] if before else [(name, value), ("x", "1")]
    url = "https://relay:4443/g?" + urlencode(pairs)
    shown = redact_url(url)
    assert value not in shown
    assert urlencode({"v": value})[2:] not in shown  # nor its percent-encoded form


# -- redact_text -----------------------------------------------------------------


def test_text_masks_jwts_and_parameters_anywhere() -> None:
    text = (
        f"connect to https://h/g?jwt={SECRET}&x=2 failed; bare token {JWT}; "
        f"'token={SECRET}' and https://bob:{SECRET}@h/"
    )
    shown = redact_text(text)
    assert SECRET not in shown and JWT not in shown
    assert "x=2" in shown and "bob:" in shown
    assert shown.count(REDACTED) == 4


def test_text_masks_dict_and_json_entries_and_a_jwk() -> None:
    headers = {":path": "/g", "authorization": f"Bearer {SECRET}", "origin": "o"}
    jwk = {"kty": "oct", "alg": "HS256", "k": SECRET}
    for text in (str(headers), json.dumps(headers), str(jwk), json.dumps(jwk)):
        shown = redact_text(text)
        assert SECRET not in shown and REDACTED in shown
        assert "/g" in shown or "HS256" in shown


def test_text_leaves_lookalikes_alone() -> None:
    for text in (
        "keyframe=3 monkey=4",
        "a=b",
        "user@example.com",
        "no secrets here",
        "{'kty': 'oct', 'path': '/g'} it's: 'fine'",
    ):
        assert redact_text(text) == text


# -- the logging filter ------------------------------------------------------------


def logged(formatter: logging.Formatter, fn: Any) -> str:
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(formatter)
    logger = logging.getLogger("upcast.test.redact")
    logger.propagate = False
    logger.setLevel(logging.DEBUG)
    logger.addHandler(handler)
    install_redaction(logger)
    install_redaction(logger)  # idempotent: one filter per handler
    try:
        assert sum(isinstance(f, RedactingFilter) for f in handler.filters) == 1
        fn(logger)
    finally:
        logger.removeHandler(handler)
    return stream.getvalue()


@pytest.mark.parametrize("formatter", [logging.Formatter(), JsonLineFormatter()])
def test_filter_masks_messages_args_and_tracebacks(formatter: logging.Formatter) -> None:
    def calls(log: logging.Logger) -> None:
        log.warning("relay %s unreachable", f"http://h:1/?jwt={SECRET}")
        log.info(f"bare {JWT} in an f-string")
        log.debug("plain %d line", 7, extra={"relay_url": f"https://h/?jwt={SECRET}"})
        try:
            raise ConnectionError(f"CONNECT to https://h/?token={SECRET} refused")
        except ConnectionError:
            log.exception("connect failed")

    out = logged(formatter, calls)
    assert SECRET not in out and JWT not in out
    assert "plain 7 line" in out and "ConnectionError" in out
    if isinstance(formatter, JsonLineFormatter):
        lines = [json.loads(line) for line in out.splitlines()]
        assert len(lines) == 4 and REDACTED in lines[3]["exc"]


def test_filter_keeps_a_bad_format_for_the_handler_to_report() -> None:
    record = logging.makeLogRecord({"msg": "%d items", "args": ("x",)})
    assert RedactingFilter().filter(record) is True
    assert record.args == ("x",)


# -- WtConnectError messages --------------------------------------------------------


def _recorder(session: WtSession, request: WtRequest) -> object:
    return object()


def test_connect_error_to_a_closed_port_hides_the_token() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]  # closed once the with-block ends

    async def body() -> None:
        with pytest.raises(WtConnectError) as caught:
            await connect(
                f"https://127.0.0.1:{port}/game?jwt={SECRET}",
                factory=_recorder,  # type: ignore[arg-type]
                verify=False,
                timeout=0.5,
            )
        message = str(caught.value)
        assert SECRET not in message and f"jwt={REDACTED}" in message

    asyncio.run(body())


@pytest.fixture(scope="module")
def cert(tmp_path_factory: pytest.TempPathFactory) -> CertBundle:
    return generate_cert(directory=tmp_path_factory.mktemp("cert"))


def test_refused_connect_error_hides_the_token(cert: CertBundle) -> None:
    async def body() -> None:
        endpoints = await serve_wt(
            _recorder,  # type: ignore[arg-type]
            cert,
            host="127.0.0.1",
            port=0,
            authorize=lambda path, headers: Refusal(401, "invalid token"),
        )
        try:
            with pytest.raises(WtConnectError, match="status 401") as caught:
                await connect(
                    f"https://127.0.0.1:{endpoints.port}/game?jwt={JWT}",
                    factory=_recorder,  # type: ignore[arg-type]
                    cert_hash_hex=cert.sha256_hex,
                    timeout=5.0,
                )
            assert JWT not in str(caught.value)
        finally:
            await endpoints.close()

    asyncio.run(body())


def test_bad_url_error_hides_the_token() -> None:
    with pytest.raises(ValueError, match="not an http") as caught:
        asyncio.run(connect(f"ftp://h/?jwt={SECRET}", factory=_recorder))  # type: ignore[arg-type]
    assert SECRET not in str(caught.value)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__, "-q"]))
