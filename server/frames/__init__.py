"""The frame contract (G-buffers, sizes, flags), the shared-memory rings R and U with
their futex fences, the per-frame timing stamps and the frame-rate monitor that reads them.

May import: ``server.ops``. Everything that moves frames imports this; it imports no stage.
"""
