"""The upscaler worker process: ring R -> upscaler (``upscalers``) -> ring U, its
frame-generation prediction stage, its run-time control socket and its metrics.

May import: ``server.frames``, ``server.ops``, ``server.config_types``, ``upscalers``.
Never the game (it only knows the ring names) or the network layers.
"""
