"""``upcast eval``: quality evaluations of the upscalers (speed against error, tables, plots).

A tool: may import ``server.game``, ``server.frames``, ``server.ops``, ``server.bench`` and
``upscalers``; no stage imports it.
"""
