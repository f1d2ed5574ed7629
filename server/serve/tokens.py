"""Where ``upcast serve`` gets each session's publish token, and how a token rides a URL."""

from __future__ import annotations

from collections.abc import Callable
from urllib.parse import quote

TokenMinter = Callable[[str], str | None]


def no_token(broadcast: str) -> None:
    """AUTH: the single place where serve mints a session's publish token.

    Returns None (publish without a token) until server/auth/ is wired here: the
    lead replaces this with a minter that signs, for ``broadcast``, a token with
    ``root=<broadcast>``, ``put=[""]`` and ``get=["input"]`` from ``--auth-key``."""
    return None


def with_token(relay_url: str, token: str | None) -> str:
    """The relay URL carrying ``?jwt=<token>`` (browsers cannot set WebTransport headers;
    moq-relay takes the token the same way)."""
    if token is None:
        return relay_url
    sep = "&" if "?" in relay_url else "?"
    return f"{relay_url}{sep}jwt={quote(token, safe='')}"
