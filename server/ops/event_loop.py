"""The event loop every asyncio process of upcast runs on."""

from __future__ import annotations


def install_uvloop() -> None:
    """Use uvloop (libuv) when available: the relay, the session and the load test
    spend their time in the loop's I/O path. Plain asyncio works too, only slower."""
    try:
        import uvloop
    except ImportError:  # pragma: no cover - uvloop is a dependency
        return
    uvloop.install()
