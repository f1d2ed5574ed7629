"""The shared secret tokens are signed with, stored as a JWK (RFC 7517) JSON file.

The format is moq-token's (``{"kty":"oct","alg":"HS256","k":"<base64url>"}``), so one
key file serves this relay and moq-dev's ``moq-relay`` alike. The file is a secret:
it is written with mode 0600 and never logged.
"""

from __future__ import annotations

import base64
import json
import os
import secrets
from dataclasses import dataclass
from pathlib import Path

ALGORITHM = "HS256"
KEY_BYTES = 32  # HS256's own output size: a shorter secret weakens the MAC
MAX_KEY_FILE_BYTES = 64 * 1024


class KeyFileError(ValueError):
    """A key file that is missing or malformed; the message names the file."""


@dataclass(frozen=True, slots=True)
class AuthKey:
    secret: bytes
    kid: str | None = None

    def __repr__(self) -> str:  # never print the secret by accident
        return f"AuthKey(kid={self.kid!r}, {len(self.secret)} bytes)"


def _b64url_encode(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode("ascii")


def _b64url_decode(text: str) -> bytes:
    return base64.urlsafe_b64decode(text + "=" * (-len(text) % 4))


def generate_key(path: Path | str) -> None:
    """Write a fresh random HS256 JWK to ``path`` (mode 0600; an existing file is kept
    as it is and refused: overwriting a key would invalidate every token in use)."""
    path = Path(path)
    jwk = {
        "kty": "oct",
        "alg": ALGORITHM,
        "key_ops": ["sign", "verify"],
        "k": _b64url_encode(secrets.token_bytes(KEY_BYTES)),
    }
    # O_EXCL: never follow someone's symlink or truncate an existing key.
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        json.dump(jwk, f)
        f.write("\n")


def load_key(path: Path | str) -> AuthKey:
    """Read a JWK key file; KeyFileError names the file and what is wrong with it."""
    path = Path(path)
    try:
        with path.open("rb") as f:
            raw = f.read(MAX_KEY_FILE_BYTES + 1)
    except FileNotFoundError:
        raise KeyFileError(f"key file {path}: does not exist") from None
    except OSError as exc:
        raise KeyFileError(f"key file {path}: cannot read it ({exc.strerror or exc})") from None
    if len(raw) > MAX_KEY_FILE_BYTES:
        raise KeyFileError(f"key file {path}: larger than {MAX_KEY_FILE_BYTES} bytes")
    try:
        jwk = json.loads(raw)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise KeyFileError(f"key file {path}: not JSON ({exc})") from None
    if not isinstance(jwk, dict):
        raise KeyFileError(f"key file {path}: expected a JWK object, got {type(jwk).__name__}")
    return _parse_jwk(jwk, path)


def _parse_jwk(jwk: dict[str, object], path: Path) -> AuthKey:
    if jwk.get("kty") != "oct":
        raise KeyFileError(
            f"key file {path}: kty must be 'oct' (a shared secret), got {jwk.get('kty')!r}"
        )
    alg = jwk.get("alg", ALGORITHM)
    if alg != ALGORITHM:
        raise KeyFileError(f"key file {path}: alg must be {ALGORITHM!r}, got {alg!r}")
    k = jwk.get("k")
    if not isinstance(k, str) or not k:
        raise KeyFileError(f"key file {path}: field 'k' (the base64url secret) is missing")
    try:
        secret = _b64url_decode(k)
    except (ValueError, TypeError):
        raise KeyFileError(f"key file {path}: field 'k' is not base64url") from None
    if len(secret) < KEY_BYTES:
        raise KeyFileError(
            f"key file {path}: secret is {len(secret)} bytes, at least {KEY_BYTES} needed"
        )
    kid = jwk.get("kid")
    return AuthKey(secret, kid if isinstance(kid, str) else None)
