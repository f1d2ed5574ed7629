"""Whether the numba CPU kernels are compiled yet, so that ``backend="auto"`` may pick them.

A cold numba compile takes about a minute on 2 cores. ``./dev up`` starts it in the
background on a fresh machine and names, in ``UPCAST_KERNELS_MARKER``, the file it
touches once numba's cache is complete. Until that file exists, "auto" runs the torch
path of FSR 1, temporal and MPE (slower, same output within rounding) instead of
freezing the stream on a compile; an upscaler made after the file appears (a switch at
run time, a restarted worker) takes the kernels. Without the variable (tests, images
that compile at build time, plain ``upcast``) the kernels count as ready.
"""

from __future__ import annotations

import logging
import os

ENV_VAR = "UPCAST_KERNELS_MARKER"

log = logging.getLogger(__name__)
_told: set[str] = set()


def kernels_ready(method: str) -> bool:
    """True unless ``UPCAST_KERNELS_MARKER`` names a file that does not exist yet;
    the first refusal for each ``method`` is logged once per process."""
    marker = os.environ.get(ENV_VAR)
    if not marker or os.path.exists(marker):
        return True
    if method not in _told:
        _told.add(method)
        log.info(
            "%s runs on torch: the numba CPU kernels are still compiling in the background "
            "(%s appears when done; an upscaler chosen after that uses them)",
            method,
            marker,
        )
    return False
