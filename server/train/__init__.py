"""Training of the neural upscalers (``upcast train``): dataset and loop.

A tool: may import ``server.game``, ``server.frames``, ``server.ops`` and ``upscalers``;
no stage imports it.
"""
