"""Tokens, key files and grants (server/auth), without a network."""

from __future__ import annotations

import base64
import json
import stat
import time
from pathlib import Path

import jwt
import pytest

from server.auth import (
    Authorizer,
    Claims,
    Grant,
    KeyFileError,
    TokenError,
    generate_key,
    load_key,
    sign,
    verify,
)
from server.auth.keys import AuthKey
from server.quic.refusals import RefusalLog
from server.quic.session import Refusal


@pytest.fixture
def key(tmp_path: Path) -> AuthKey:
    path = tmp_path / "relay.jwk"
    generate_key(path)
    return load_key(path)


def test_key_file_is_a_private_jwk(tmp_path: Path) -> None:
    path = tmp_path / "relay.jwk"
    generate_key(path)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    jwk = json.loads(path.read_text())
    assert jwk["kty"] == "oct" and jwk["alg"] == "HS256"
    assert len(base64.urlsafe_b64decode(jwk["k"] + "==")) == 32
    with pytest.raises(FileExistsError):
        generate_key(path)  # never overwrites a key in use


@pytest.mark.parametrize(
    ("content", "problem"),
    [
        (None, "does not exist"),
        ("{nope", "not JSON"),
        ("[]", "expected a JWK object"),
        ('{"kty": "RSA", "k": "x"}', "kty must be 'oct'"),
        ('{"kty": "oct", "alg": "HS512", "k": "x"}', "alg must be 'HS256'"),
        ('{"kty": "oct"}', "field 'k'"),
        ('{"kty": "oct", "k": "c2hvcnQ"}', "at least 32"),
    ],
)
def test_bad_key_file_names_file_and_problem(
    tmp_path: Path, content: str | None, problem: str
) -> None:
    path = tmp_path / "bad.jwk"
    if content is not None:
        path.write_text(content)
    with pytest.raises(KeyFileError) as info:
        load_key(path)
    assert str(path) in str(info.value) and problem in str(info.value)


def test_round_trip_keeps_every_claim(key: AuthKey) -> None:
    claims = Claims.for_("game", put=("",), get=("input",), expires_in_s=60)
    back = verify(key, sign(key, claims))
    assert back == claims
    assert back.exp is not None and back.iat is not None and back.exp - back.iat == 60


def test_string_put_and_get_are_read_as_one_path(key: AuthKey) -> None:
    # moq-token writes a single path as a plain string.
    token = jwt.encode({"root": "demo", "put": "bbb", "get": ""}, key.secret, algorithm="HS256")
    claims = verify(key, token)
    assert claims.put == ("bbb",) and claims.get == ("",)


def test_expired_token_is_refused(key: AuthKey) -> None:
    token = sign(key, Claims.for_("game", get=("",), expires_in_s=10, now=time.time() - 20))
    with pytest.raises(TokenError, match="expired"):
        verify(key, token)


def test_tampered_token_is_refused(key: AuthKey) -> None:
    token = sign(key, Claims.for_("game", get=("",)))
    header, _payload, signature = token.split(".")
    forged = base64.urlsafe_b64encode(json.dumps({"root": "", "put": [""]}).encode())
    with pytest.raises(TokenError, match="bad signature"):
        verify(key, f"{header}.{forged.decode().rstrip('=')}.{signature}")


def test_other_key_is_a_bad_signature(key: AuthKey, tmp_path: Path) -> None:
    generate_key(tmp_path / "other.jwk")
    other = load_key(tmp_path / "other.jwk")
    with pytest.raises(TokenError, match="bad signature"):
        verify(key, sign(other, Claims.for_("game", put=("",))))


def test_alg_none_and_other_algorithms_are_refused(key: AuthKey) -> None:
    unsigned = jwt.encode({"root": "", "put": [""]}, None, algorithm="none")
    with pytest.raises(TokenError, match="wrong algorithm 'none'"):
        verify(key, unsigned)
    hs512 = jwt.encode({"root": "", "put": [""]}, key.secret * 2, algorithm="HS512")
    with pytest.raises(TokenError, match="wrong algorithm 'HS512'"):
        verify(key, hs512)


@pytest.mark.parametrize("token", ["", "abc", "a.b.c", "x" * 10_000])
def test_malformed_tokens_are_refused(key: AuthKey, token: str) -> None:
    with pytest.raises(TokenError, match="malformed"):
        verify(key, token)


def test_token_granting_nothing_is_malformed(key: AuthKey) -> None:
    token = jwt.encode({"root": "game"}, key.secret, algorithm="HS256")
    with pytest.raises(TokenError, match="neither put nor get"):
        verify(key, token)
    with pytest.raises(ValueError, match="put or get"):
        sign(key, Claims("game"))


def test_grant_matches_whole_segments() -> None:
    grant = Grant.from_claims(Claims("game", put=("input",), get=("",)))
    assert grant.may_publish("game/input") and grant.may_publish("game/input/7")
    assert not grant.may_publish("game") and not grant.may_publish("game/inputs")
    assert grant.may_subscribe("game") and grant.may_subscribe("game/video")
    assert not grant.may_subscribe("gamez") and not grant.may_subscribe("other/game")
    assert grant.may_subscribe("/game//input/")  # paths normalized as @moq/lite does


def test_anonymous_and_open_grants() -> None:
    anon = Grant.anonymous_viewer()
    assert anon.may_subscribe("anything/at/all") and not anon.may_publish("game/input/1")
    assert Grant.everything().may_publish("x")


def test_authorizer_decisions(key: AuthKey) -> None:
    player = sign(key, Claims.for_("game", put=("input",), get=("",)))
    public = Authorizer(key, public_viewers=True)
    private = Authorizer(key, public_viewers=False)
    assert public.authorize("/") == Grant.anonymous_viewer()
    assert private.authorize("/") == Refusal(401, "missing token")
    grant = private.authorize(f"/?jwt={player}")
    assert isinstance(grant, Grant) and grant.may_publish("game/input/3")
    bad = private.authorize("/?jwt=abc")
    assert isinstance(bad, Refusal) and bad.status == 401 and "malformed" in bad.reason
    assert private.authorize(f"/?jwt={player}&jwt={player}") == Refusal(
        401, "malformed token: more than one jwt parameter"
    )
    outside = private.authorize(f"/other?jwt={player}")
    assert isinstance(outside, Refusal) and outside.status == 403
    assert isinstance(private.authorize(f"/game?jwt={player}"), Grant)
    assert Authorizer.open_relay().authorize("/") == Grant.everything()


def test_refusal_log_is_rate_limited(caplog: pytest.LogCaptureFixture) -> None:
    now = [100.0]
    refusals = RefusalLog(max_lines_per_s=5, clock=lambda: now[0])
    with caplog.at_level("WARNING", logger="server.quic.refusals"):
        for _ in range(1000):
            refusals.refused("10.0.0.1:5", 401, "missing token")
        now[0] += 1.5
        refusals.refused("10.0.0.1:5", 401, "missing token")
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 7  # 5 in the first second, the summary, 1 in the next
    assert "refused 995 more WebTransport session attempts" in lines[5]
    assert refusals.total == 1001
