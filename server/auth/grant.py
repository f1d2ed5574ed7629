"""What a verified token (or an anonymous viewer) may do on the relay.

Paths match on whole segments, as moq-lite's broadcast paths do: a grant on
``game`` covers ``game`` and ``game/input/7`` but not ``gamez``.
"""

from __future__ import annotations

from dataclasses import dataclass

from server.moq.paths import join, normalize, strip_prefix

from .tokens import Claims


@dataclass(frozen=True, slots=True)
class Grant:
    publish: tuple[str, ...]
    """Path prefixes the holder may announce (publish) under."""
    subscribe: tuple[str, ...]
    """Path prefixes the holder may subscribe to (and be told about)."""
    who: str = "token"
    """For logs: "token", "anonymous" or "open relay"."""

    @classmethod
    def from_claims(cls, claims: Claims) -> Grant:
        root = normalize(claims.root)
        return cls(
            publish=tuple(join(root, normalize(s)) for s in claims.put),
            subscribe=tuple(join(root, normalize(s)) for s in claims.get),
        )

    @classmethod
    def everything(cls) -> Grant:
        """An open relay (``--no-auth``): anyone may do anything."""
        return cls(publish=("",), subscribe=("",), who="open relay")

    @classmethod
    def anonymous_viewer(cls) -> Grant:
        """``--public-viewers``: watch anything, publish nothing (inputs included)."""
        return cls(publish=(), subscribe=("",), who="anonymous")

    @property
    def publishes(self) -> bool:
        return bool(self.publish)

    def may_publish(self, path: str) -> bool:
        return _covered(self.publish, path)

    def may_subscribe(self, path: str) -> bool:
        return _covered(self.subscribe, path)


def _covered(prefixes: tuple[str, ...], path: str) -> bool:
    path = normalize(path)
    return any(strip_prefix(prefix, path) is not None for prefix in prefixes)
