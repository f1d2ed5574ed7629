"""ReFrame layer caching: reuse the deep branches of an encoder-decoder across frames.

- ``points``: the contract a network follows to be cacheable (its cache configs).
- ``layer_cache``: ``LayerCache`` swaps those branches for wrappers that keep or
  reuse their outputs, without touching the network's ``forward``.
- ``policies``: every policy answers "refresh now?" (``CachePolicy.decide``).
- ``cached_upscaler``: ``CachedUpscaler`` runs a neural upscaler with both.
"""
