"""Cache policies: each answers "refresh now?" for a frame (``CachePolicy.decide``).

Names for configs and the benchmark are in ``registry``."""

from upscalers.cache.policies.base import CachePolicy
from upscalers.cache.policies.registry import available, make_policy

__all__ = ["CachePolicy", "available", "make_policy"]
