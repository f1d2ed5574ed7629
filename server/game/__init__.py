"""The reference game: the game loop that renders into ring R, player input applied to
the camera, its Prometheus metrics, and ``render/`` (scenes, G-buffers, ground truth).

May import: ``server.frames``, ``server.ops``. Never the worker, the media or network layers.
"""
