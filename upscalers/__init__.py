"""Upscalers: one interface (``base.Upscaler``), one registry, and the API for users.

One package per family: ``spatial`` (resamplers and OpenCV's baselines), ``fsr1``,
``temporal``, ``neural``, ``cache`` (layer caching), ``framegen`` (frame prediction),
each with its torch reference, CPU kernels and params; ``kernels`` compiles and warms
them. At the top: the interface, the registry, the host, the API, sanitizing.

``upscale_image`` and ``upscale_sequence`` live in ``upscalers/api.py`` and are
imported on first use: importing this package must not pull torch, because the
relay's base install imports ``upscalers.names`` (standard library only).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

__all__ = ["upscale_image", "upscale_sequence"]

if TYPE_CHECKING:
    # mypy sees the real signatures; the module-level __getattr__ below, which it does
    # not see, gives the same names at run time without importing torch up front.
    from upscalers.api import upscale_image, upscale_sequence
else:

    def __getattr__(name: str) -> object:
        if name in __all__:
            from upscalers import api

            return getattr(api, name)
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
