"""Opt-in ``torch.compile`` (inductor; C++ on the CPU) of an upscaler's hot function.

Compiling costs tens of seconds the first time a geometry is seen; inductor's
on-disk cache (``TORCHINDUCTOR_CACHE_DIR``, default ``/tmp/torchinductor_$USER``)
makes a later start with the same code and sizes take seconds. The first call
of each geometry is timed and logged, and kept in ``warmup_s`` so the
evaluation can report it.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

import torch

log = logging.getLogger(__name__)


# One torch.compile wrapper per function for the whole process: dynamo keeps its
# compiled code per wrapper and gives up (runs eagerly, with only a warning) after
# a few entries per code object, so a wrapper per upscaler instance (the evaluation
# makes one per scene and scale) would silently stop compiling.
_SHARED: dict[Callable[..., Any], Callable[..., Any]] = {}


def _shared_compile(fn: Callable[..., Any]) -> Callable[..., Any]:
    compiled = _SHARED.get(fn)
    if compiled is None:
        compiled = _SHARED[fn] = torch.compile(fn, dynamic=False)
    return compiled


class CompiledFunction:
    """A pure tensor function compiled once per input geometry (static shapes)."""

    def __init__(self, fn: Callable[..., Any], what: str) -> None:
        self.what = what
        self._fn = _shared_compile(fn)
        self._seen: set[tuple[Any, ...]] = set()
        self.warmup_s: dict[str, float] = {}

    def __call__(self, *args: Any) -> Any:
        key = _geometry(args)
        if key in self._seen:
            return self._fn(*args)
        t0 = time.monotonic()
        out = self._fn(*args)
        took = time.monotonic() - t0
        self._seen.add(key)
        shapes = "x".join(str(d) for d in args[0].shape) if args else "?"
        self.warmup_s[shapes] = took
        log.info("compiled %s for %s in %.1f s (first call of this size)", self.what, shapes, took)
        return out


def _geometry(value: Any) -> Any:
    """What a static-shape compile specializes on: shapes, dtypes, devices, constants."""
    if isinstance(value, torch.Tensor):
        return (tuple(value.shape), value.dtype, value.device)
    if isinstance(value, tuple | list):
        return tuple(_geometry(v) for v in value)
    return value
