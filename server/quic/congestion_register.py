"""Which congestion controller QUIC connections use: the registered names, the
process-wide default, and the check settings run on a configured name.

aioquic keeps its registry private (``_factories``) and offers no listing; its own
"reno" and "cubic" register when ``aioquic.quic.recovery`` is imported, ours when
``congestion_media`` is.
"""

from __future__ import annotations

import aioquic.quic.recovery  # noqa: F401  (registers "reno" and "cubic")
from aioquic.quic.congestion import base as aioquic_congestion

from server.quic import congestion_media

DEFAULT_ALGORITHM = congestion_media.NAME
_default = DEFAULT_ALGORITHM


def algorithm_names() -> tuple[str, ...]:
    """The registered names, the default first."""
    names = sorted(aioquic_congestion._factories)
    names.remove(DEFAULT_ALGORITHM)
    return (DEFAULT_ALGORITHM, *names)


def check_algorithm(name: str) -> str:
    """`name` if registered, else a ValueError that lists the allowed names."""
    if name not in aioquic_congestion._factories:
        allowed = ", ".join(algorithm_names())
        raise ValueError(f"unknown congestion control {name!r} (allowed: {allowed})")
    return name


def default_algorithm() -> str:
    """What a QuicConfiguration built in this process uses unless told otherwise."""
    return _default


def set_default_algorithm(name: str) -> None:
    """Choose the process-wide default (``upcast relay --congestion-control``)."""
    global _default
    _default = check_algorithm(name)
