"""The two tokens a process that owns a relay and a session mints for itself.

``upcast up`` (and ``upcast serve``) sign them with the relay's key: the session's
publisher token publishes the broadcast and reads its viewers' inputs; the player
token watches it and publishes inputs (``<broadcast>/input/<id>``) only.
"""

from __future__ import annotations

from dataclasses import dataclass

from .keys import AuthKey
from .tokens import Claims, sign

PLAYER_TOKEN_LIFETIME_S = 30 * 24 * 3600  # a link someone shares is not valid forever
INPUT_SUFFIX = "input"


@dataclass(frozen=True)
class SessionTokens:
    publisher: str
    player: str


def session_tokens(key: AuthKey, broadcast: str) -> SessionTokens:
    # The publisher's token never leaves the process (no expiry: it reconnects for
    # as long as it runs); the player's ends up in URLs, so it expires.
    publisher = Claims.for_(broadcast, put=("",), get=(INPUT_SUFFIX,))
    player = Claims.for_(
        broadcast, put=(INPUT_SUFFIX,), get=("",), expires_in_s=PLAYER_TOKEN_LIFETIME_S
    )
    return SessionTokens(publisher=sign(key, publisher), player=sign(key, player))
