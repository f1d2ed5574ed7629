"""Where ``upcast serve`` gets each session's publish token and its players' tokens."""

from __future__ import annotations

from collections.abc import Callable

from server.auth.keys import AuthKey
from server.auth.minting import session_tokens
from server.quic.moq_link import with_token as _with_token

TokenMinter = Callable[[str], str | None]


def no_token(broadcast: str) -> None:
    """An open relay (``--relay`` without ``--auth-key``): publish without a token."""
    return None


def publisher_minter(key: AuthKey) -> TokenMinter:
    """Each session's publisher token: ``root=<broadcast>``, put everything, get inputs."""
    return lambda broadcast: session_tokens(key, broadcast).publisher


def player_minter(key: AuthKey) -> TokenMinter:
    """The token in a session's watch URL: watch it and publish inputs to it."""
    return lambda broadcast: session_tokens(key, broadcast).player


def with_token(relay_url: str, token: str | None) -> str:
    """The relay URL carrying ``?jwt=<token>`` (browsers cannot set WebTransport headers;
    moq-relay takes the token the same way); unchanged without a token."""
    return relay_url if token is None else _with_token(relay_url, token)
