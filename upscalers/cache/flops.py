"""FLOPs of a network's full and cached forward, counted by torch's FlopCounterMode.

Counting the two forwards (rather than summing per-submodule counts) needs no
knowledge of the network: whatever the cached path still runs is counted, and
the difference is exactly what a cached frame eliminates. FlopCounterMode
counts the matrix products and convolutions (the "Enc-Dec FLOPs" of ReFrame's
Table 1), not element-wise work.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch.utils.flop_counter import FlopCounterMode

from upscalers.cache.layer_cache import CacheMode, LayerCache


@dataclass(frozen=True)
class PathFlops:
    full: int
    cached: int

    @property
    def eliminated_share(self) -> float:
        """Share of a full forward's FLOPs a cached frame does not run."""
        return 0.0 if self.full == 0 else 1.0 - self.cached / self.full


def count_flops(forward: Callable[[], object]) -> int:
    with FlopCounterMode(display=False) as counter:
        forward()
    return int(counter.get_total_flops())


def path_flops(
    cache: LayerCache, run: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor
) -> PathFlops:
    """FLOPs of ``run(x)`` with everything computed, then with the cache reused.

    The cache's current contents are kept aside and put back, so measuring
    changes nothing for the frames that follow."""
    saved = cache.snapshot()
    try:
        with cache.using(CacheMode.REFRESH):
            full = count_flops(lambda: run(x))
        with cache.using(CacheMode.REUSE):
            cached = count_flops(lambda: run(x))
    finally:
        cache.put_back(saved)
    return PathFlops(full, cached)
