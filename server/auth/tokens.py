"""Sign and verify moq-token compatible JWTs (HS256).

Claims as moq-dev's moq-token defines them: ``root`` (a broadcast path prefix),
``put`` and ``get`` (path suffixes under ``root`` the holder may publish / subscribe
to; ``""`` is everything under root; moq-token writes a string or a list, both are
read), ``exp`` and ``iat`` (seconds since the epoch), ``cluster`` (relay-to-relay;
read and kept, not used here).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import jwt

from .keys import ALGORITHM, AuthKey

MAX_TOKEN_CHARS = 8192  # far above any real token; bounds the work a stranger can ask


class TokenError(ValueError):
    """A token that does not verify; ``reason`` is short and safe to log."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


@dataclass(frozen=True, slots=True)
class Claims:
    root: str
    put: tuple[str, ...] = ()
    get: tuple[str, ...] = ()
    exp: int | None = None
    iat: int | None = None
    cluster: bool = False

    @classmethod
    def for_(
        cls,
        root: str,
        *,
        put: tuple[str, ...] = (),
        get: tuple[str, ...] = (),
        expires_in_s: float | None = None,
        now: float | None = None,
    ) -> Claims:
        """Claims issued now, expiring ``expires_in_s`` later (None: never)."""
        issued = int(time.time() if now is None else now)
        exp = None if expires_in_s is None else issued + int(expires_in_s)
        return cls(root=root, put=put, get=get, exp=exp, iat=issued)

    def to_json(self) -> dict[str, object]:
        out: dict[str, object] = {"root": self.root}
        if self.put:
            out["put"] = list(self.put)
        if self.get:
            out["get"] = list(self.get)
        if self.cluster:
            out["cluster"] = True
        if self.exp is not None:
            out["exp"] = self.exp
        if self.iat is not None:
            out["iat"] = self.iat
        return out


def sign(key: AuthKey, claims: Claims) -> str:
    if not claims.put and not claims.get:
        raise ValueError("a token must grant put or get (moq-token refuses one without)")
    headers = {"kid": key.kid} if key.kid else None
    return jwt.encode(claims.to_json(), key.secret, algorithm=ALGORITHM, headers=headers)


def verify(key: AuthKey, token: str, *, now: float | None = None) -> Claims:
    """The token's claims, or TokenError (expired, bad signature, malformed, wrong alg)."""
    if len(token) > MAX_TOKEN_CHARS:
        raise TokenError("malformed: too long")
    try:
        header = jwt.get_unverified_header(token)
    except jwt.DecodeError:
        raise TokenError("malformed") from None
    # Checked before PyJWT sees the key: "none" and asymmetric algorithms (the classic
    # confusion attacks) never reach signature code.
    if header.get("alg") != ALGORITHM:
        raise TokenError(f"wrong algorithm {str(header.get('alg'))[:16]!r}")
    try:
        payload = jwt.decode(
            token,
            key.secret,
            algorithms=[ALGORITHM],
            options={"verify_exp": False, "verify_iat": False},
        )
    except jwt.InvalidSignatureError:
        raise TokenError("bad signature") from None
    except jwt.InvalidTokenError as exc:
        raise TokenError(f"malformed: {type(exc).__name__}") from None
    claims = _claims(payload)
    # Expiry checked here with an injectable clock (tests) rather than PyJWT's.
    if claims.exp is not None and claims.exp <= (time.time() if now is None else now):
        raise TokenError("expired")
    return claims


def _paths(payload: dict[str, object], name: str) -> tuple[str, ...]:
    value = payload.get(name)
    if value is None:
        return ()
    if isinstance(value, str):
        return (value,)
    if isinstance(value, list) and all(isinstance(v, str) for v in value):
        return tuple(value)
    raise TokenError(f"malformed: claim {name!r} must be a string or a list of strings")


def _int_claim(payload: dict[str, object], name: str) -> int | None:
    value = payload.get(name)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise TokenError(f"malformed: claim {name!r} must be a number")
    return int(value)


def _claims(payload: dict[str, object]) -> Claims:
    root = payload.get("root")
    if not isinstance(root, str):
        raise TokenError("malformed: claim 'root' (a string) is missing")
    put, get = _paths(payload, "put"), _paths(payload, "get")
    if not put and not get:
        raise TokenError("malformed: the token grants neither put nor get")
    return Claims(
        root=root,
        put=put,
        get=get,
        exp=_int_claim(payload, "exp"),
        iat=_int_claim(payload, "iat"),
        cluster=payload.get("cluster") is True,
    )
