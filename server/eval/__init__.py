"""``upcast eval``: quality evaluations of the upscalers (speed against error, tables, plots).

A tool: may import ``server.game``, ``server.frames``, ``server.ops`` (its report writer
among them) and ``upscalers``; no stage imports it.
"""
