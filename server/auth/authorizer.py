"""Turn a WebTransport CONNECT's ``?jwt=`` into a Grant or a refusal, before the relay
allocates anything for the session.

The token travels in the URL (as with moq-relay) because browsers cannot set headers
on a WebTransport CONNECT. 401: no token where one is needed, or one that does not
verify; 403: a valid token used on a URL path outside its root.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from urllib.parse import parse_qs, urlsplit

from server.moq.paths import normalize, strip_prefix
from server.quic.session import Refusal

from .grant import Grant
from .keys import AuthKey
from .tokens import MAX_TOKEN_CHARS, TokenError, verify

MAX_QUERY_CHARS = 2 * MAX_TOKEN_CHARS


@dataclass(frozen=True)
class Authorizer:
    key: AuthKey | None
    """None: an open relay (``--no-auth``), every session may do anything."""
    public_viewers: bool = True
    """Sessions without a token may subscribe (never publish)."""

    @classmethod
    def open_relay(cls) -> Authorizer:
        return cls(key=None)

    def authorize(
        self, request_path: str, headers: Mapping[str, str] | None = None
    ) -> Grant | Refusal:
        if self.key is None:
            return Grant.everything()
        parts = urlsplit(request_path)
        if len(parts.query) > MAX_QUERY_CHARS:
            return Refusal(401, "malformed token: query too long")
        tokens = parse_qs(parts.query).get("jwt", [])
        if len(tokens) > 1:
            return Refusal(401, "malformed token: more than one jwt parameter")
        if not tokens:
            if self.public_viewers:
                return Grant.anonymous_viewer()
            return Refusal(401, "missing token")
        try:
            claims = verify(self.key, tokens[0])
        except TokenError as exc:
            return Refusal(401, f"invalid token: {exc.reason}")
        path = normalize(parts.path)
        root = normalize(claims.root)
        if strip_prefix(root, path) is None and strip_prefix(path, root) is None:
            return Refusal(403, "URL path is outside the token's root")
        return Grant.from_claims(claims)
